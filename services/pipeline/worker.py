"""`vergence worker [--name ID]`: computes layer 4 for its shard of each frame.

Subscribes to vergence/<rig>/frame with a RingChannel(RING = 2), oldest first: a stall of a frame period (the
process descheduled while two frames came) loses no frame, and a slow worker works at most one frame behind and
never builds a queue; the frames its ring replaced before it took them are counted (`skipped`, from the gaps in
the frame ids). Frames beyond [limits] max_frame_bytes / max_frame_ops, or captured further than
[limits] max_skew_s from this host's clock, are counted as bad and not computed. For each frame whose plan
names it, publishes messages.Correlation on
vergence/<rig>/correlation/<id>. Membership is its liveliness token vergence/<rig>/alive/worker/<id>, declared
once the kernel is warm; the capture plans shards from these tokens. Counters go out as JSON on
vergence/<rig>/status/worker/<id> every second and at exit.
"""

from __future__ import annotations

import argparse
import logging
import time

import zenoh

from vergence.wire import keys
from vergence.config import LimitSettings, load
from vergence.stages.frames import check_frame
from vergence.wire.messages import MessageError
from vergence.network.params import Params
from vergence.stages.shards import compute_correlation

from services.runtime import session
from services.runtime.node import Node
from services.runtime.warm import warm_up

log = logging.getLogger("vergence.worker")
RING = 2  # frames held for the loop's thread (1: a stall of a period skipped a frame in a quarter of 250 Hz runs)


def configure(p: argparse.ArgumentParser) -> None:
    session.add_options(p)
    p.add_argument("--name", default=None, help="worker id prefix (default: the host name); -<pid> is appended")


class Gaps:
    """Frames the ring replaced before the worker took them, from the gaps in the frame ids (a jump
    back or a jump beyond `window` is a new capture or a forged id: not counted)."""

    def __init__(self, window: int = 1000):
        self.last = -1
        self.window = window

    def seen(self, fid: int) -> int:
        gap = fid - self.last - 1 if self.last >= 0 else 0
        self.last = fid
        return gap if 0 < gap <= self.window else 0


class Worker:
    """One worker's loop (a thread of its Node): the oldest frame its ring holds, checked, its shard computed and
    published."""

    def __init__(self, node: Node, limits: LimitSettings):
        self.node, self.health, self.limits = node, node.health, limits
        self.gaps = Gaps(limits.frame_window)
        self.busy_ns = 0
        self.sub = node.ring(keys.frame(node.rig), RING)
        self.pub = node.publisher(keys.correlation(node.rig, node.ident), express=True)

    def loop(self) -> None:
        health = self.health
        for sample in self.node.samples(self.sub):
            t0 = time.perf_counter_ns()
            try:
                frame = check_frame(sample.payload.to_bytes(), self.limits, time.time_ns())
            except MessageError as e:
                health.reject("frame", e)
                continue
            skipped = self.gaps.seen(frame.frame)
            if skipped:
                health.count("skipped", skipped)
            try:
                part = compute_correlation(frame, self.node.ident)
            except Exception as e:  # a frame that validates but cannot be computed: never fatal
                health.reject("frame", e)
                continue
            if part is None:
                health.count("not_in_plan")
                continue
            self.pub.put(part.to_bytes())
            health.count("correlations")
            self.busy_ns += time.perf_counter_ns() - t0


def main(rig: str, conf: zenoh.Config, stop: session.Stop, name: str | None = None,
         params: Params | None = None, limits: LimitSettings | None = None) -> int:
    limits = limits or LimitSettings()
    warm_up(params or Params())
    workers: list[Worker] = []
    with Node("worker", rig, conf, stop, name=name, log=log,
              fields=lambda: {"busy_s": workers[0].busy_ns / 1e9 if workers else 0.0}) as node:
        worker = Worker(node, limits)
        workers.append(worker)
        node.thread(worker.loop, name="worker-loop")
        node.ready()  # only now: the subscriber is up and the kernel warm
        log.info("worker %s on %s", node.ident, keys.frame(rig))
        node.run_status()
    return 0


def run(args: argparse.Namespace) -> int:
    settings = load(args.config)
    stop = session.Stop()
    return main(args.rig or settings.rig, session.config_from_args(args), stop, args.name, settings.network,
                settings.limits)
