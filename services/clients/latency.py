"""`vergence latency [--amplitude DEG] [--hold-s S] [--wait S]`: measure the camera's latency on the running head.

With the rig running on a still, textured scene (the master fixed), it holds the reducer's commands
(messages.Hold on vergence/<rig>/hold, renewed every 0.5 s), steps the slave through a known motion about
its present pan (+-amplitude and half of it, each step held hold-s; within +-1 degree and the motor's soft
limits) with its own messages.Command, records the decisions (vergence/<rig>/decision) and the motor's states
(vergence/<rig>/motor_state), and finds the instant at which the measured offsets follow the motor best
(vergence.head.latency.fit_latency). It prints the slave camera's exposure-to-read latency with its uncertainty and
the settings line to put in the TOML ([camera] latency_s), then puts the slave back and releases the hold.
Exit 1 when no rig answers, 2 when the scene or the motor does not allow the measurement (it says why).
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import threading
import time

from vergence.wire import keys
from vergence.config import load
from vergence.choices import Fault
from vergence.head.follows import ADVICE
from vergence.head.latency import LatencyError, fit_latency, motion_plan
from vergence.wire.messages import Command, Hold, MessageError, MotorState, Decision

from services.runtime import session
from services.runtime.args import number
from services.runtime.node import Node

log = logging.getLogger("vergence.latency")

RENEW_S = 0.5  # the hold is renewed this often, each for twice as long


def configure(p: argparse.ArgumentParser) -> None:
    session.add_options(p)
    p.add_argument("--amplitude", type=number(0, 1, lo_open=True), default=0.5, metavar="DEG",
                   help="the steps' size about the present pan, degrees (default 0.5, at most 1)")
    p.add_argument("--hold-s", type=number(0, 60, lo_open=True), default=0.4, metavar="S",
                   help="how long each step is held (default 0.4)")
    p.add_argument("--wait", type=number(0, 3600, lo_open=True), default=5.0, metavar="S",
                   help="how long to wait for the rig's decisions and motor states (default 5)")


class Recorder:
    """The decisions and motor states as they come (zenoh callback threads); malformed ones are skipped."""

    def __init__(self):
        self.lock = threading.Lock()
        self.decisions: list[Decision] = []
        self.states: list[MotorState] = []
        self.sent: list[int] = []  # when each of our commands was sent (ns)

    def on_decision(self, sample) -> None:
        self._keep(sample, Decision, self.decisions)

    def on_state(self, sample) -> None:
        self._keep(sample, MotorState, self.states)

    def _keep(self, sample, cls, into: list) -> None:
        try:
            msg = cls.from_bytes(sample.payload.to_bytes())
        except MessageError:
            return
        with self.lock:
            into.append(msg)

    def snapshot(self) -> tuple[list[Decision], list[MotorState]]:
        with self.lock:
            return list(self.decisions), list(self.states)


def _wait(cond, seconds: float) -> bool:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.05)
    return cond()


class Mover:
    """Holds the reducer and commands the slave: each command as fresh as the newest decision's frame, so the
    actuator's stale check (a command older than the last) takes it."""

    def __init__(self, s, rig: str, rec: Recorder):
        self.s, self.rig, self.rec = s, rig, rec
        self.next_renew = 0.0

    def renew(self, release: bool = False) -> None:
        now = time.time_ns()
        until = now if release else now + round(2 * RENEW_S * 1e9)
        self.s.put(keys.hold(self.rig), Hold(until_ns=until, t_ns=now, source="vergence latency").to_bytes())

    def command(self, pan: float) -> None:
        decisions, _ = self.rec.snapshot()
        t = max([d.t_capture_ns for d in decisions] + [time.time_ns() - 10**9]) + 1
        self.rec.sent.append(time.time_ns())
        self.s.put(keys.command(self.rig), Command(rig=self.rig, frame=-1, t_capture_ns=t, pan_rad=pan,
                                                   correction_rad=0.0, direction=0, magnitude_px=0.0,
                                                   confidence=1.0, t_sent_ns=time.time_ns()).to_bytes())

    def run(self, plan: list[tuple[float, float]], hold_s: float) -> None:
        t0 = time.monotonic()
        for at, pan in plan + [(plan[-1][0] + hold_s, plan[-1][1])]:
            while time.monotonic() - t0 < at:
                if time.monotonic() >= self.next_renew:
                    self.renew()
                    self.next_renew = time.monotonic() + RENEW_S
                time.sleep(0.01)
            self.command(pan)


def record(node: Node, rec: Recorder, rig: str, amplitude_deg: float, hold_s: float, wait: float,
           planner=motion_plan, name: str = "latency", ready=None, subscribe: bool = True):
    """In the node's block: the rig's decisions and motor states while the slave steps through the plan
    (planner(p0, lo, hi, amplitude rad, hold_s)), as (decisions, states, t_start); or the exit code: 1 when the rig
    does not answer, 2 when ready() (called once the rig answers) says why not to move (it prints why)."""
    if subscribe:  # (a second record in the same node reuses the first's subscriptions)
        node.subscriber(keys.decision(rig), rec.on_decision)
        node.subscriber(keys.motor_state(rig), rec.on_state)
    mover = Mover(node.session, rig, rec)
    try:
        if not _wait(lambda: all(rec.snapshot()), wait):
            d, m = rec.snapshot()
            print(f"vergence {name}: no {'decisions' if not d else 'motor states'} on rig {rig!r} within "
                  f"{wait:g} s: start the rig first (vergence up), with a still textured scene", file=sys.stderr)
            return 1
        if ready is not None and not ready():
            return 2
        state = rec.snapshot()[1][-1]
        p0 = state.pan_rad
        plan = planner(p0, state.min_rad, state.max_rad, math.radians(amplitude_deg), hold_s)
        room = max(p for _, p in plan) - min(p for _, p in plan)
        if room < math.radians(0.2):
            print(f"vergence {name}: the motor's limits ({math.degrees(state.min_rad):+.2f}, "
                  f"{math.degrees(state.max_rad):+.2f} deg) leave {math.degrees(room):.2f} deg to step about its pan "
                  f"{math.degrees(p0):+.2f}: move the slave off the limit (or widen [actuator.motor] min_deg, "
                  "max_deg) and try again", file=sys.stderr)
            return 2
        print(f"holding the reducer, stepping the slave +-{amplitude_deg:g} deg about {math.degrees(p0):+.2f} "
              f"deg for {len(plan) * hold_s:.1f} s ...", file=sys.stderr)
        t_start = time.time_ns()
        mover.renew()
        mover.run(plan, hold_s)
        decisions, states = rec.snapshot()
        node.health.count("commands", len(plan) + 1)
    finally:
        mover.renew(release=True)
    return decisions, states, t_start


def main(rig: str, conf, amplitude_deg: float, hold_s: float, wait: float) -> int:
    if not (0 < amplitude_deg <= 1.0) or not (0.1 <= hold_s <= 5.0) or not wait > 0:
        print("vergence latency: --amplitude must be in (0, 1] degrees, --hold-s in [0.1, 5] s, --wait > 0",
              file=sys.stderr)
        return 2
    rec = Recorder()
    try:
        with Node("latency", rig, conf, session.Stop(install=False), log=log, timeout=wait, quiet=True) as node:
            got = record(node, rec, rig, amplitude_deg, hold_s, wait)
    except ConnectionError as e:
        print(f"vergence latency: {e}", file=sys.stderr)
        return 1
    if isinstance(got, int):
        return got
    decisions, states, t_start = got
    used = [(d.t_capture_ns + d.skew_ns, d.t_read_ns or d.t_capture_ns, d.offset_px) for d in decisions
            if d.confident and d.t_capture_ns >= t_start]
    try:
        fit = fit_latency(used, [(m.t_ns, m.pan_rad) for m in states if m.t_ns >= t_start - 10**9])
    except LatencyError as e:
        print(f"vergence latency: {e}", file=sys.stderr)
        if e.slope is not None:  # the motor moved, the image did not follow: the loop's check has a name for that
            print(f"vergence latency: or {ADVICE[Fault.SLAVE_FROZEN]}", file=sys.stderr)
        return 2
    print(report(fit))
    return 0


def report(fit) -> str:
    ms = 1e3
    lines = [f"exposure to read: {fit.latency_s * ms:.1f} +- {fit.sigma_s * ms:.1f} ms (the slave camera; {fit.n} "
             f"decisions, r2 {fit.r2:.3f}, {abs(fit.slope):.0f} px/rad)"]
    if abs(fit.delta_s) * ms >= max(2.0, 2 * fit.sigma_s * ms):
        lines.append(f"the frames were stamped {fit.stamped_s * ms:.1f} ms before their read, "
                     f"{fit.delta_s * ms:.1f} ms late. Where the source does not stamp its images, put in the "
                     "settings:")
    else:
        lines.append(f"the frames' stamps are right (within {abs(fit.delta_s) * ms:.1f} ms); the settings line, "
                     "for a source that does not stamp its images:")
    lines.append(f"[camera]\nlatency_s = {max(0.0, fit.latency_s):.4f}")
    lines.append("(the skew between the cameras cannot be told with a fixed master on a still scene)")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    rig = args.rig or load(args.config).rig
    return main(rig, session.config_from_args(args), args.amplitude, args.hold_s, args.wait)
