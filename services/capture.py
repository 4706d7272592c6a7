"""`vergence capture --source SPEC [--rate HZ] [--frames N]`: reads stereo frames and publishes them.

Publishes on vergence/<rig>/frame a messages.Frame per image pair: only what layer 1 needs (the master fovea
and the slave band with their Sobel margins, the master band for the left-right check), the slave pan at
capture time (the latest messages.MotorState on vergence/<rig>/motor/state; the source's start pan before
any), and the shard plan made from the workers' liveliness tokens vergence/<rig>/alive/worker/* at that
moment. With no worker alive, frames are counted (no_workers) and not published. A downscaled
messages.Preview goes on vergence/<rig>/preview at [capture] preview_hz. With [network] max_window > 0 the
window grows by 8 px while the decisions (vergence/<rig>/decision) are not confident (the dynamic window).
Counters go out as JSON on vergence/<rig>/status/capture/<id> every second and at exit.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
import threading
import time

import cv2
import zenoh

from vergence import pipeline, retina
from vergence.config import load
from vergence.messages import MessageError, MotorState, Preview, Verdict
from vergence.sources import SourceError, open_source

from . import session
from .match import point_arg

log = logging.getLogger("vergence.capture")
STATUS_S = 1.0


def configure(p: argparse.ArgumentParser) -> None:
    session.add_options(p)
    p.add_argument("--source", default=None, metavar="SPEC",
                   help="files:LEFT,RIGHT | video:LEFT,RIGHT | camera:0,1 | sim[:key=value:...] "
                        "(default: settings, sim)")
    p.add_argument("--rate", type=float, default=None, metavar="HZ",
                   help="frames per second, 0 = as fast as possible (default: settings, 30)")
    p.add_argument("--frames", type=int, default=0, metavar="N", help="exit after publishing N frames (0: never)")
    p.add_argument("--at", type=point_arg, default=None, metavar="X,Y", help="fovea centre (default: image centre)")
    p.add_argument("--focal", type=float, default=None, help="focal length in pixels (default: the source's)")


class Membership:
    """The live workers, from liveliness tokens (history included); the plan is recomputed on change."""

    def __init__(self):
        self.lock = threading.Lock()
        self.workers: set[str] = set()
        self.changes = 0

    def on_sample(self, sample) -> None:
        wid = str(sample.key_expr).rsplit("/", 1)[1]
        with self.lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self.workers.add(wid)
            else:
                self.workers.discard(wid)
            self.changes += 1
        log.info("workers: %s", sorted(self.workers))

    def snapshot(self) -> tuple[int, list[str]]:
        with self.lock:
            return self.changes, sorted(self.workers)


def main(settings, conf: zenoh.Config, stop: session.Stop, *, frames: int = 0,
         at: tuple[int, int] | None = None) -> int:
    rig, cs, params = settings.rig, settings.capture, settings.network
    try:
        source = open_source(cs.source, cs.master)
    except SourceError as e:
        print(f"vergence capture: {e}", file=sys.stderr)
        return 2
    wd, ht = source.size
    focal = cs.focal_px or source.focal_px or 0.8 * wd
    x, y = at if at is not None else (wd // 2, ht // 2)
    try:
        retina.check_point((ht, wd), x, y, params.window, params.vsearch)
    except retina.BorderError as e:
        print(f"vergence capture: {e}", file=sys.stderr)
        source.close()
        return 2
    alive = session.alive_key(rig, "capture")
    cid = alive.rsplit("/", 1)[1]
    health = pipeline.Health("capture", cid, log)
    windows = pipeline.WindowControl(params)
    members = Membership()
    pan = [source.start_pan_rad]

    def on_motor(sample):
        try:
            pan[0] = MotorState.from_bytes(sample.payload.to_bytes()).pan_rad
            health.count("motor_states")
        except MessageError as e:
            health.reject("motor_state", e)

    def on_decision(sample):
        try:
            v = Verdict.from_bytes(sample.payload.to_bytes())
        except MessageError as e:
            health.reject("decision", e)
            return
        windows.update(v.window, v.confident)

    period = 1.0 / cs.rate_hz if cs.rate_hz > 0 else 0.0
    preview_period = 1.0 / cs.preview_hz if cs.preview_hz > 0 else 0.0
    pw = min(cs.preview_width, wd) if cs.preview_width > 0 else wd
    ph = max(1, round(ht * pw / wd))
    with session.open_session(conf) as s:
        pub_frame = s.declare_publisher(f"vergence/{rig}/frame", express=True)
        pub_preview = s.declare_publisher(f"vergence/{rig}/preview")
        pub_status = s.declare_publisher(f"vergence/{rig}/status/capture/{cid}")
        subs = [s.declare_subscriber(f"vergence/{rig}/motor/state", on_motor),
                s.liveliness().declare_subscriber(f"vergence/{rig}/alive/worker/*", members.on_sample, history=True)]
        if params.max_window:
            subs.append(s.declare_subscriber(f"vergence/{rig}/decision", on_decision))
        token = s.liveliness().declare_token(alive)
        log.info("capture %s: %s (%d x %d, f=%.1f px) at %s Hz on vergence/%s/frame", cid, cs.source, wd, ht,
                 focal, cs.rate_hz or "max", rig)
        plan_key, plan = None, []
        fid = 0
        published = 0
        next_t = time.monotonic()
        next_preview = next_t
        next_status = next_t + STATUS_S
        try:
            while not stop.is_set() and (frames <= 0 or published < frames):
                if period:
                    delay = next_t - time.monotonic()
                    if delay > 0:
                        stop.wait(delay)
                        if stop.is_set():
                            break
                    # keep the schedule, but never try to catch up more than one period late
                    next_t = max(next_t + period, time.monotonic() - period)
                p_now = pan[0]
                try:
                    master, slave = source.read(p_now)
                except SourceError as e:
                    print(f"vergence capture: {e}", file=sys.stderr)
                    return 2
                t_ns = time.time_ns()
                w = windows.window
                changes, ids = members.snapshot()
                if (changes, w) != plan_key:
                    plan_key = (changes, w)
                    plan = pipeline.plan_shards(ids, wd - w + 1)
                fid += 1
                health.count("frames")
                if plan and not pub_frame.matching_status.matching:
                    # workers are alive but the router has not yet told this session about their
                    # subscriptions (just after start): a frame now would go nowhere
                    health.count("unrouted")
                elif plan:
                    try:
                        frame = pipeline.make_frame(master, slave, rig=rig, frame=fid, pan_rad=p_now, focal_px=focal,
                                                    params=params, plan=plan, at=(x, y), window=w,
                                                    t_capture_ns=t_ns)
                    except retina.BorderError:  # a grown window that no longer fits: back to the base one
                        windows.window = params.window
                        continue
                    frame.truth_pan_rad = source.truth_pan_rad  # the simulator's ground truth, else None
                    pub_frame.put(frame.to_bytes())
                    published += 1
                    health.count("published")
                else:
                    health.count("no_workers")
                now = time.monotonic()
                if preview_period and now >= next_preview:
                    next_preview = now + preview_period
                    m = cv2.resize(master, (pw, ph), interpolation=cv2.INTER_AREA)
                    sl = cv2.resize(slave, (pw, ph), interpolation=cv2.INTER_AREA)
                    pub_preview.put(Preview(rig=rig, frame=fid, t_capture_ns=t_ns, width=pw, height=ph, scale=pw / wd,
                                            master=m.tobytes(), slave=sl.tobytes(), pan_rad=p_now,
                                            truth_pan_rad=source.truth_pan_rad).to_bytes())
                if now >= next_status:
                    next_status = now + STATUS_S
                    pub_status.put(json.dumps(health.status(window=windows.window, workers=len(plan))))
        finally:
            for sub in subs:  # no callback may still run while the session closes
                sub.undeclare()
            token.undeclare()
            pub_status.put(json.dumps(health.status(window=windows.window, workers=len(plan), exiting=True)))
            source.close()
            log.info("capture %s exits: %s bad %s", cid, health.counters, health.bad)
    return 0


def settings_from_args(args: argparse.Namespace):
    st = load(args.config)
    cs = st.capture
    changes = {k: v for k, v in (("source", args.source), ("rate_hz", args.rate), ("focal_px", args.focal))
               if v is not None}
    cs = dataclasses.replace(cs, **changes)
    return dataclasses.replace(st, capture=cs, **({"rig": args.rig} if args.rig else {}))


def run(args: argparse.Namespace) -> int:
    settings = settings_from_args(args)
    stop = session.Stop()
    return main(settings, session.config_from_args(args), stop, frames=args.frames, at=args.at)
