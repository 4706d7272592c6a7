"""`vergence reducer`: gathers the shards of each frame, decides, publishes the profile and the command.

Subscribes to vergence/<rig>/frame and vergence/<rig>/correlation/*; vergence.pipeline.Gatherer assembles
each frame by the plan the frame carries, drops (and counts) a frame whose shards miss the deadline
([reducer] deadline_ms), and reduces a complete one with vergence.match.decide_scores and the controller.
Publishes messages.Profile on vergence/<rig>/profile and, when the controller moves the slave,
messages.Command on vergence/<rig>/command; never from an incomplete profile. Counters go out as JSON on
vergence/<rig>/status/reducer/<id> every second and at exit. The profile is only encoded and published while
someone subscribes to it. Each decision carries the fovea centre (x, y) it was made for and the fixated
point's depth (vergence.depth, with the [rig] table's baseline, gimbal and master). Every SUMMARY_S seconds
with frames, one log line says what the loop is doing (summary()).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import threading
import time

import zenoh

from vergence import depth, kernel, pipeline
from vergence.config import load
from vergence.messages import Frame, MessageError, Partial

from . import session

log = logging.getLogger("vergence.reducer")
STATUS_S = 1.0
SUMMARY_S = 5.0
EXPIRE_S = 0.05  # the longest sleep between deadline checks (frames also expire as messages arrive)


def configure(p: argparse.ArgumentParser) -> None:
    session.add_options(p)
    p.add_argument("--deadline-ms", type=float, default=None, help="drop a frame whose shards are not all in "
                                                                   "by then (default: settings, 50)")


def warm_up(settings) -> None:
    """Decide once on a synthetic textured frame (left-right check included), so the first real frame
    does not pay for loading the compiled kernels."""
    import numpy as np

    kernel.warm_up()
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (64, 128), np.uint8)
    p = dataclasses.replace(settings.network, window=15, vsearch=min(settings.network.vsearch, 2))
    g = pipeline.Gatherer(p, settings.control)
    f = pipeline.make_frame(img, img, rig="warm", frame=0, pan_rad=0.0, focal_px=100.0, params=p,
                            plan=[["w", 0, 128 - 15 + 1]])
    g.add_frame(f)
    g.add_partial(pipeline.compute_partial(f, "w"))


def summary(seconds: float, frames: int, lost: int, commands: int, last: pipeline.Result) -> str:
    """The reducer's periodic log line: what came through in the last `seconds`, and the latest decision."""
    d, f = last.decision, last.frame
    return (f"last {seconds:.0f} s: frames {frames} decided, {lost} dropped, commands {commands}; frame {f.frame}: "
            f"offset {d.offset_px:+.2f} px, {'confident' if d.confident else 'abstains'} (margin {d.confidence:.2f}, "
            f"w {f.window}), slave pan at capture {math.degrees(f.pan_rad):+.3f} deg")


def main(settings, conf: zenoh.Config, stop: session.Stop, deadline_ms: float | None = None) -> int:
    rig = settings.rig
    warm_up(settings)
    deadline = (deadline_ms if deadline_ms is not None else settings.reducer.deadline_ms) / 1000.0
    gatherer = pipeline.Gatherer(settings.network, settings.control, deadline)
    alive = session.alive_key(rig, "reducer")
    rid = alive.rsplit("/", 1)[1]
    health = pipeline.Health("reducer", rid, log)
    prefix = f"vergence/{rig}/correlation/"
    lock = threading.Lock()  # zenoh may run the two subscribers' callbacks on different threads
    with session.open_session(conf) as s:
        pub_decision = s.declare_publisher(f"vergence/{rig}/decision", express=True)
        pub_profile = s.declare_publisher(f"vergence/{rig}/profile", express=True)
        pub_command = s.declare_publisher(f"vergence/{rig}/command", express=True)
        pub_status = s.declare_publisher(f"vergence/{rig}/status/reducer/{rid}")

        last: list[pipeline.Result] = []
        geo = settings.geometry

        def publish(results) -> None:
            if results:
                last[:] = results[-1:]
            for r in results:
                if r.command is not None:  # the command first: the actuator waits for it
                    pub_command.put(r.command.to_bytes())
                    health.count("commands")
                where = depth.decision_fields(r.frame, r.decision, r.scores, geo.baseline_m, geo.gimbal,
                                              geo.master or settings.capture.master)
                pub_decision.put(dataclasses.replace(r.verdict, **where).to_bytes())
                if pub_profile.matching_status.matching:  # up to 65 KB at 640 px: only encoded when wanted
                    pub_profile.put(dataclasses.replace(r.profile, **where).to_bytes())
                health.count("profiles")

        def on_frame(sample) -> None:
            try:
                frame = Frame.from_bytes(sample.payload.to_bytes())
            except MessageError as e:
                with lock:
                    health.reject("frame", e)
                return
            with lock:
                try:
                    publish(gatherer.add_frame(frame))
                except Exception as e:  # a frame that validates but cannot be decided on: never fatal
                    health.reject("frame", e)

        def on_partial(sample) -> None:
            key = str(sample.key_expr)
            try:
                part = Partial.from_bytes(sample.payload.to_bytes())
                if key[len(prefix):] != part.worker:
                    raise MessageError(f"partial from worker {part.worker!r} on key {key}")
            except MessageError as e:
                with lock:
                    health.reject("partial", e)
                return
            with lock:
                try:
                    publish(gatherer.add_partial(part))
                except Exception as e:  # never fatal
                    health.reject("partial", e)

        # Messages are handled in zenoh's callback threads (no hand-over to another thread: one wake-up
        # less per message); this thread only expires deadlines and publishes the status.
        subs = [s.declare_subscriber(f"vergence/{rig}/frame", on_frame),
                s.declare_subscriber(prefix + "*", on_partial)]
        token = s.liveliness().declare_token(alive)
        log.info("reducer %s on vergence/%s/{frame,correlation/*}, deadline %.0f ms", rid, rig, deadline * 1e3)

        def status(**extra) -> bytes:
            with lock:
                return json.dumps(health.status(gatherer=dict(gatherer.counters), pending=len(gatherer.pending),
                                                **extra)).encode()

        next_status = time.monotonic() + STATUS_S
        next_summary, seen = time.monotonic() + SUMMARY_S, (0, 0, 0)
        sleep = EXPIRE_S
        try:
            while not stop.wait(sleep):
                with lock:
                    gatherer.expire()
                    due = gatherer.next_deadline()
                now = time.monotonic()
                # wake at the next deadline (every 5 ms before: 200 wake-ups a second for nothing)
                sleep = EXPIRE_S if due is None else min(EXPIRE_S, max(0.001, due - now))
                if now >= next_status:
                    pub_status.put(status())
                    next_status = now + STATUS_S
                if now >= next_summary:
                    with lock:
                        c = gatherer.counters
                        counts = (c["complete"], c["dropped"] + c["superseded"], health.counters.get("commands", 0))
                        if counts[0] > seen[0]:
                            log.info("%s", summary(SUMMARY_S, *(a - b for a, b in zip(counts, seen)), last[0]))
                    seen, next_summary = counts, now + SUMMARY_S
        finally:
            # no callback may still run while the session closes (it can hang the exit otherwise)
            for sub in subs:
                sub.undeclare()
            token.undeclare()
            pub_status.put(status(exiting=True))
            log.info("reducer %s exits: %s gatherer %s bad %s", rid, health.counters, gatherer.counters, health.bad)
    return 0


def settings_from_args(args: argparse.Namespace):
    st = load(args.config)
    return dataclasses.replace(st, **({"rig": args.rig} if args.rig else {}))


def run(args: argparse.Namespace) -> int:
    settings = settings_from_args(args)
    stop = session.Stop()
    return main(settings, session.config_from_args(args), stop, args.deadline_ms)
