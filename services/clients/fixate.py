"""`vergence fixate X,Y [--rig R] [--wait S]`: ask the running capture to move its fovea to master pixel (X, Y).

Puts one messages.Fixate on vergence/<rig>/fixate. With --wait S (default 2), waits up to S seconds for the
first decision (vergence/<rig>/decision) made for the new point and prints it (x, y, offset, converged,
depth); exit 2 with the capture's reason when its status says it refused this request (the point where the fovea
does not fit: status field fixate_rejection, matched by the request's t_ns); exit 1 when nothing came (no
capture running). --wait 0 only sends. The wait counts from the start, the router's included: exit 1 with one
line when no router answers within it (within session.CLIENT_WAIT_S with --wait 0)."""

from __future__ import annotations

import argparse
import logging
import math
import sys
import threading
import time

from vergence.wire import keys
from vergence.config import load
from vergence.wire.messages import Fixate, MessageError, Decision
from vergence.wire.status import decode_status

from services.runtime import session
from services.runtime.args import master_point, number
from services.runtime.node import Node

log = logging.getLogger("vergence.fixate")


def configure(p: argparse.ArgumentParser) -> None:
    session.add_options(p)
    p.add_argument("point", type=master_point, metavar="X,Y", help="the new fovea centre in master pixels")
    p.add_argument("--source", default="vergence fixate", help="who asks (free text, logged by the capture)")
    p.add_argument("--wait", type=number(0, 3600, note="0: only send"), default=2.0, metavar="S",
                   help="wait up to S seconds (the router's answer included) for the first decision at the new "
                        f"point (0: only send, after at most {session.CLIENT_WAIT_S:g} s for a router)")


def describe(v: Decision) -> str:
    depth = (f"depth {v.depth_m:.4f} m +- {v.depth_sigma_m:.4f}" if math.isfinite(v.depth_m) else "no depth")
    return (f"frame {v.frame} at ({v.x}, {v.y}): offset {v.offset_px:+.2f} px, "
            f"{'converged' if v.converged else 'confident' if v.confident else 'abstains'}, {depth}")


def refusal(payload: bytes, t_ns: int) -> str | None:
    """A capture status's reason for refusing the request sent at t_ns, or None (another request's, none, or
    not a status we can read: a peer's message is a claim, so anything malformed is only ignored)."""
    try:
        r = decode_status(payload).fixate_rejection()
    except MessageError:
        return None
    return r[1] if r is not None and r[0] == t_ns else None


class Answer:
    """The first answer to the request sent at t_ns (zenoh callback threads): a decision at the target, or the
    capture's refusal in its status."""

    def __init__(self, target: tuple[int, int], t_ns: int):
        self.target, self.t_ns = target, t_ns
        self.got: list[Decision] = []
        self.refused: list[str] = []
        self.seen = threading.Event()

    def on_decision(self, sample) -> None:
        try:
            v = Decision.from_bytes(sample.payload.to_bytes())
        except MessageError:
            return
        if (v.x, v.y) == self.target and not self.seen.is_set():
            self.got.append(v)
            self.seen.set()

    def on_status(self, sample) -> None:
        why = refusal(sample.payload.to_bytes(), self.t_ns)
        if why is not None and not self.seen.is_set():
            self.refused.append(why)
            self.seen.set()


def main(rig: str, conf, x: float, y: float, source: str, wait: float) -> int:
    target = (int(round(x)), int(round(y)))
    t_ns = time.time_ns()
    answer = Answer(target, t_ns)
    got, refused, seen = answer.got, answer.refused, answer.seen
    t_start = time.monotonic()
    router_wait = wait if wait > 0 else session.CLIENT_WAIT_S
    with Node("fixate", rig, conf, session.Stop(install=False), log=log, timeout=router_wait, quiet=True) as node:
        if wait > 0:
            node.subscriber(keys.decision(rig), answer.on_decision)
            node.subscriber(keys.status(rig, "capture", "*"), answer.on_status)
        t0 = time.monotonic()
        node.session.put(keys.fixate(rig), Fixate(x=x, y=y, t_ns=t_ns, source=source).to_bytes())
        node.health.count("sent")
        if wait <= 0:
            print(f"fixate ({x:g}, {y:g}) sent on {keys.fixate(rig)}")
            return 0
        if not seen.wait(max(0.0, t_start + wait - time.monotonic())):
            print(f"vergence fixate: no decision at ({target[0]}, {target[1]}) within {wait:g} s (is a "
                  "capture running on this rig?)", file=sys.stderr)
            return 1
        if refused:
            print(f"vergence fixate: the capture refused {refused[0]}; the fovea stays where it was",
                  file=sys.stderr)
            return 2
        print(f"{describe(got[0])}  ({(time.monotonic() - t0) * 1e3:.0f} ms after the request)")
        return 0

def run(args: argparse.Namespace) -> int:
    rig = args.rig or load(args.config).rig
    return main(rig, session.config_from_args(args), *args.point, args.source, args.wait)
