"""The capture's time: the slave's pan at each exposure (PanLookup, over the motor's history and, with the sim
motor behind a rendering source, the capture's replica of that motor), what a motor state may claim before it
moves that history (motor_state_implausible, remember), and the exposure times of each pair (ExposureClock).
Split from services/pipeline/capture.py (issue #34); what each does and why: docs/SERVICE.md, "The camera's time"."""

from __future__ import annotations

import logging
import math
import threading
import time

from vergence.wire.messages import MessageError, MotorState
from vergence.motors.simulated import Replica
from vergence.head.timing import PanHistory, Stamper

log = logging.getLogger("vergence.capture")
FUTURE_S = 0.05  # a motor history whose newest state is this far ahead of our clock is forgotten
SETTLE_S = 0.025  # the longest a rendering source waits for the motor's report of its exposure's instant


def motor_state_implausible(st: MotorState, motor, now_ns: int, max_skew_s: float) -> str | None:
    """Why a motor_state is not believed (it moves the pan every frame carries, hence the commands): a pan
    outside the motor's soft limits of our settings, or a time further than max_skew_s from our clock."""
    lo, hi = motor.min_rad, motor.max_rad
    if not lo - 1e-3 <= st.pan_rad <= hi + 1e-3:
        return f"pan {st.pan_rad:.4g} rad outside the motor limits [{lo:.4g}, {hi:.4g}]"
    if abs(st.t_ns - now_ns) > max_skew_s * 1e9:
        return f"state from {(st.t_ns - now_ns) / 1e9:+.3g} s off our clock"
    return None


def remember(history: PanHistory, st: MotorState, now_ns: int) -> bool:
    """A plausible motor state into the history (True); MessageError when it is not newer than the newest. A newest
    state from more than FUTURE_S in our future (a forgery within max_skew_s, or a clock that jumped) is
    forgotten rather than left to refuse every true state until then. The state of a motor that is disconnected or
    absent says a pan it does not know (its goal: an actuator started before its ROS 2 joint's first state said 0
    while the joint stood at -4.8 deg, and every frame carried 0): left out (False)."""
    if st.status in ("disconnected", "absent"):
        return False
    t = st.t_ns / 1e9
    if history.add(t, st.pan_rad):
        return True
    if not (history.t and history.t[-1] > now_ns / 1e9 + FUTURE_S):
        raise MessageError("motor state not newer than the last one")
    history.clear()
    history.add(t, st.pan_rad)
    return True


class PanLookup:
    """The slave's pan for one frame, from the motor's history (the zenoh callback adds to it meanwhile): a
    source that renders (the simulator) asks it at its exposure times, and the frame then carries the same
    pan. With the sim motor behind a rendering source, the pan comes from the capture's replica of that
    motor (vergence.motors.simulated.Replica) while it is trusted: exact at any instant up to now, once the
    motor has counted the commands seen (ready). Before any motor state the pan is not known: the source renders
    at its start pan and the frame is stale (it commands nothing: the motor may be anywhere, as one started at
    [actuator.motor] start_deg is); a source whose images do not follow the motor always has its start pan."""

    def __init__(self, history: PanHistory, lock: threading.Condition, source, replica: Replica | None = None):
        self.history, self.lock, self.source = history, lock, source
        self.replica = replica
        self.seen: dict[int, float | None] = {}
        self.guessed: set[int] = set()  # instants whose pan the history extrapolated past its newest state
        self.exact: set[int] = set()  # instants whose pan is the replica's shaft
        self.waited = False  # ready() waited for the motor to count a command

    def settle(self, t_ns: int, timeout: float = SETTLE_S) -> None:
        """Wait (at most timeout) until the motor has reported its pan at or after t_ns: a source that renders
        the slave (the simulator) then never renders a pan the history has to guess (extrapolated past its
        newest state, a step of the motor shows some 15 ms late). No wait with a trusted replica (it knows
        the shaft up to now), without a history, or (longer) for a motor that stopped reporting."""
        end = time.monotonic() + timeout
        while True:
            with self.lock:
                if self.replica is not None and self.replica.trusted:
                    return
                if not len(self.history) or self.history.t[-1] * 1e9 >= t_ns:
                    return
            if time.monotonic() >= end:
                return
            time.sleep(0.0005)

    def ready(self) -> None:
        """Before a rendering source picks its exposure: with a trusted replica, wait until the motor has
        counted every command seen (at most Replica.ANSWER_NS from its arrival), so that the replica holds
        every goal written before the exposure."""
        rep = self.replica
        if rep is None:
            return
        with self.lock:
            while rep.trusted and (since := rep.unanswered(time.monotonic_ns())) is not None:
                self.waited = True
                self.lock.wait((since + rep.ANSWER_NS - time.monotonic_ns()) / 1e9 + 1e-4)

    def ahead_ns(self) -> int:
        """How far past now the pan is known for a source to render ahead: with a trusted replica, half the sim
        motor's latency (a goal takes effect that long after its write; the other half for a command's trip here,
        which ready() has waited for), else 0: a history knows nothing after its newest state."""
        rep = self.replica
        with self.lock:
            return rep.m.latency_ns // 2 if rep is not None and rep.trusted else 0

    def _at(self, t_ns: int) -> float | None:
        if t_ns not in self.seen:
            with self.lock:
                pan = self.replica.at(t_ns) if self.replica is not None else None
                if pan is not None:
                    self.exact.add(t_ns)
                elif len(self.history):  # (before any motor state the pan is not known)
                    pan = self.history.at(t_ns / 1e9)
                    if t_ns / 1e9 > self.history.t[-1]:
                        self.guessed.add(t_ns)
                self.seen[t_ns] = pan
        return self.seen[t_ns]

    def __call__(self, t_ns: int) -> float:
        """The pan to render the slave at (where the history cannot tell, its newest: the frame is stale; before its
        oldest state, that one: the motor was there, and a camera's image can be older than the motor's first report
        the capture heard: rendered at the newest, a late camera's first frames showed a move before it was made)."""
        pan = self._at(t_ns)
        if pan is None:
            with self.lock:
                h = self.history
                pan = h.pan[0] if len(h) and t_ns / 1e9 < h.t[0] else h.newest()
        return pan if pan is not None else self.source.start_pan_rad

    def frame(self, t_slave_ns: int) -> tuple[float, bool, bool]:
        """(the frame's pan, stale, guessed): the pan at the slave's exposure, whether the history could not tell,
        and whether it told it past its newest state (extrapolated at the motor's last rate: a turn since is not in
        it; vergence.head.scenery reads no verdict on such a pan). From the replica's shaft, the encoder's reading
        of it (the sim source's encoder(): with encoder_noise=, each frame's pan one noisy reading)."""
        if not self.source.follows_pan:
            return self.source.start_pan_rad, False, False
        pan = self._at(t_slave_ns)
        if pan is None:
            return self(t_slave_ns), True, False
        if t_slave_ns in self.exact:  # the shaft itself: what the encoder reads of it
            pan = getattr(self.source, "encoder", float)(pan)
        return pan, False, t_slave_ns in self.guessed


class ExposureClock:
    """The exposure times of the pairs read (vergence.head.timing.Stamper: the source's own where believable, else
    the read time less [camera] latency_s), and what the status says of them: the latency (read minus the
    master's exposure) and the skew (slave minus master) over the last period, the stamps not believed per
    reason (logged once each); a warning, once, when the skew is over half a frame."""

    def __init__(self, timing, frame_s: float):
        self.stamper = Stamper(timing)
        self.frame_s = frame_s
        self.latency: list[int] = []
        self.skew: list[int] = []
        self.logged: set[str] = set()

    def stamp(self, t_read_ns: int, claimed) -> tuple[int, int]:
        tm, ts, why = self.stamper.stamp(t_read_ns, claimed)
        if why is not None and why not in self.logged:
            self.logged.add(why)
            log.warning("the source's exposure stamps %s are not believed (%s); this frame and any other such is "
                        "stamped at its read time less [camera] latency_s (%.3f s)", claimed, {
                            "future": "after the read", "old": "more than a second before the read",
                            "backwards": "not after the previous frame's"}[why], self.stamper.timing.latency_s)
        self.latency.append(t_read_ns - tm)
        self.skew.append(ts - tm)
        del self.latency[:-256], self.skew[:-256]
        return tm, ts

    def fields(self) -> dict:
        out: dict = {"stamps_rejected": dict(self.stamper.rejected)}
        if self.latency:
            lat, skew = sorted(self.latency), sorted(self.skew)
            out["latency_ms"] = round(lat[len(lat) // 2] / 1e6, 2)
            out["skew_ms"] = round(skew[len(skew) // 2] / 1e6, 2)
            if self.frame_s and abs(out["skew_ms"]) > 500 * self.frame_s and "skew" not in self.logged:
                self.logged.add("skew")
                log.warning("the slave is exposed %.1f ms after the master, over half a frame: trigger both cameras "
                            "together, or the decisions measure a moving target at two instants", out["skew_ms"])
            self.latency.clear()
            self.skew.clear()
        return out


class Pacer:
    """The capture's schedule at one period (s): wait() returns when the next read is due, and how many reads of
    the schedule were given up. A read late by up to BUFFER periods (the process descheduled, a slow render) is
    made up at once; later than that, the reads between are given up (`periods_missed` in the status), and the
    schedule goes on from there. One: the workers' rings hold two frames and the reducer gathers up to three in
    order, and a larger buffer measured no better at 250 Hz under load (docs/PERFORMANCE.md)."""

    BUFFER = 1

    def __init__(self, period: float, clock=time.monotonic):
        self.period, self.clock = period, clock
        self.next_t = clock()

    def wait(self, stop: threading.Event) -> int:
        """Sleep until the next read is due (or the stop); the reads given up since the last call."""
        delay = self.next_t - self.clock()
        if delay > 0:
            stop.wait(delay)
        due = self.next_t + self.period
        floor = self.clock() - self.BUFFER * self.period
        missed = max(0, math.ceil((floor - due) / self.period - 1e-9))
        self.next_t = due + missed * self.period
        return missed
