"""`vergence worker [--name ID]`: computes layer 4 for its shard of each frame.

Subscribes to vergence/<rig>/frame with a RingChannel(1): a slow worker always works on the newest frame and
never builds a queue. For each frame whose plan names it, publishes messages.Partial on
vergence/<rig>/correlation/<id>. Membership is its liveliness token vergence/<rig>/alive/worker/<id>, declared
once the kernel is warm; the capture plans shards from these tokens. Counters go out as JSON on
vergence/<rig>/status/worker/<id> every second and at exit.
"""

from __future__ import annotations

import argparse
import json
import logging
import threading
import time

import numpy as np
import zenoh

from vergence import kernel, pipeline
from vergence.config import load
from vergence.match import Params
from vergence.messages import Frame, MessageError

from . import session

log = logging.getLogger("vergence.worker")
STATUS_S = 1.0


def configure(p: argparse.ArgumentParser) -> None:
    session.add_options(p)
    p.add_argument("--name", default=None, help="worker id prefix (default: the host name); -<pid> is appended")


def warm_up(params: Params) -> None:
    """Run the kernel once on a small synthetic frame, so the first real frame is not late."""
    kernel.warm_up()
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (64, 96), np.uint8)
    p = Params(window=15, vsearch=min(params.vsearch, 2), circular=params.circular, support=params.support)
    f = pipeline.make_frame(img, img, rig="warm", frame=0, pan_rad=0.0, focal_px=80.0, params=p,
                            plan=[["w", 0, 96 - 15 + 1]])
    pipeline.compute_partial(f, "w")


def main(rig: str, conf: zenoh.Config, stop: session.Stop, name: str | None = None,
         params: Params | None = None) -> int:
    warm_up(params or Params())
    alive = session.alive_key(rig, "worker", name)
    wid = alive.rsplit("/", 1)[1]
    health = pipeline.Health("worker", wid, log)
    frame_key = f"vergence/{rig}/frame"
    with session.open_session(conf) as s:
        sub = s.declare_subscriber(frame_key, zenoh.handlers.RingChannel(1))
        pub = s.declare_publisher(f"vergence/{rig}/correlation/{wid}", express=True)
        status_pub = s.declare_publisher(f"vergence/{rig}/status/worker/{wid}")
        busy_ns = [0]

        def loop():
            while True:
                sample = sub.recv()
                if stop.is_set():
                    return
                t0 = time.perf_counter_ns()
                try:
                    frame = Frame.from_bytes(sample.payload.to_bytes())
                except MessageError as e:
                    health.reject("frame", e)
                    continue
                try:
                    part = pipeline.compute_partial(frame, wid)
                except Exception as e:  # a frame that validates but cannot be computed: never fatal
                    health.reject("frame", e)
                    continue
                if part is None:
                    health.count("not_in_plan")
                    continue
                pub.put(part.to_bytes())
                health.count("partials")
                busy_ns[0] += time.perf_counter_ns() - t0

        th = threading.Thread(target=loop, name="worker-loop", daemon=True)
        th.start()
        token = s.liveliness().declare_token(alive)  # only now: the subscriber is up and the kernel warm
        log.info("worker %s on %s", wid, frame_key)
        try:
            while not stop.wait(STATUS_S) and th.is_alive():
                status_pub.put(json.dumps(health.status(busy_s=busy_ns[0] / 1e9)))
        finally:
            token.undeclare()
            stop.set()
            # wake the loop thread: a local, empty sample on its own subscription
            s.put(frame_key, b"", allowed_destination=zenoh.Locality.SESSION_LOCAL)
            th.join(5.0)
            status_pub.put(json.dumps(health.status(busy_s=busy_ns[0] / 1e9, exiting=True)))
            log.info("worker %s exits: %s bad %s", wid, health.counters, health.bad)
    return 0


def run(args: argparse.Namespace) -> int:
    settings = load(args.config)
    stop = session.Stop()
    return main(args.rig or settings.rig, session.config_from_args(args), stop, args.name, settings.network)
