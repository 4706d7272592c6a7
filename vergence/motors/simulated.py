"""A simulated pan motor that behaves like a servo: latency, top speed, acceleration, a first-order final
approach, whole ticks, hard limits; and its replica in another process.

A goal written at time t reaches the motor at t + latency_s (quantised to a whole tick when `quantise`).
The shaft then heads for it at the speed v* = min(|e| / tau, max_speed, sqrt(2 a |e|)) (e: the distance
left; the last term brakes in time), its speed changing by at most max_accel_deg_s2. The state is
integrated in fixed 0.25 ms steps on a grid of the clock's own (whole multiples of the step in integer
nanoseconds), so positions depend neither on how often the motor is polled nor on when it started; a motor
at rest on its goal skips ahead. read_position() is the present position as the encoder reports it (a whole
tick when quantising), at the instant position_ns (right after a goal is written: the write's instant), and
`shaft` the exact angle the camera is at. The hard limits are the soft limits plus one degree: the safety
layer never lets a goal past the soft ones anyway.

The clock is the wall clock by default (time.time_ns), the clock of the motor states' t_ns: a Replica in
another process (the capture's, for the simulator that renders the slave) then integrates on the same grid
from the same goals at the same instants, and knows the shaft without waiting for the motor's reports.

It lies as a real motor does when told (issue #35; `vergence actuator --faults`, which `vergence up` gives the sim
source's stall= and encoder_noise=): stall (T0, T1) s, it stops where it is at T0 and takes no goal until T1 (the
encoder tells the truth: it does not move); noise_deg, each reading off by Gaussian noise of that deviation. Their
times count from the exposure of the first frame the motor is commanded for (Driver.first_exposure).
"""

from __future__ import annotations

import bisect
import math
import random
import time
from collections import deque
from collections.abc import Callable

from .base import Driver, MotorSettings

__all__ = ["SimMotor", "Replica", "H"]

H_NS = 250_000  # the integration step, ns
H = H_NS / 1e9  # and in seconds


WRITE_READ_NS = 5_000_000  # a read this soon after a goal's write reports the write's instant


def _ceil_step(ns: int) -> int:
    """The first grid step at or after ns."""
    return -(-ns // H_NS)


class SimMotor(Driver):
    """clock: seconds (a test's, or `vergence sim`'s virtual time; exact to the nanosecond below 10^5 s), or
    clock_ns: integer nanoseconds (default: the wall clock, time.time_ns)."""

    name = "sim"

    def __init__(self, settings: MotorSettings | None = None, clock: Callable[[], float] | None = None,
                 clock_ns: Callable[[], int] = time.time_ns, stall: tuple[float, float] | None = None,
                 noise_deg: float = 0.0, seed: int = 0):
        super().__init__(settings or MotorSettings())
        s = self.settings
        self.clock_ns = clock_ns if clock is None else (lambda: round(clock() * 1e9))
        self.tick_rad = 2 * math.pi / s.ticks_per_rev
        # the shaft at the grid step self.k (at self.k * H_NS ns), in the motor's own sense (MotorLoop gives it
        # direction x (pan - offset)): start_deg is the pan it starts at, on the nearest tick (a pan offset by a
        # fraction of a tick would leave it between two, where no model of it that reads the encoder can put it)
        self.pan = self._quantise(s.to_motor(math.radians(s.start_deg)))
        self.vel = 0.0
        self.goal = self.pan
        self.pending: deque[tuple[int, float]] = deque()  # (the step it reaches the motor at, goal)
        self.k = self.clock_ns() // H_NS
        self.latency_ns = round(s.latency_s * 1e9)
        self.position_ns: int | None = None  # the instant of the latest read_position
        self._written: int | None = None  # the instant of a goal written since the latest read
        self.torque = False
        self.hard = tuple(sorted(s.to_motor(x) for x in (s.min_rad - math.radians(1), s.max_rad + math.radians(1))))
        self.vmax = math.radians(s.max_speed_deg_s) or math.inf
        self.amax = math.radians(s.max_accel_deg_s2) or math.inf
        self.stall, self.noise_rad, self.rng = stall, math.radians(noise_deg), random.Random(seed)
        self.stall_ns: tuple[int, int] | None = None  # the stall's instants, once the first exposure is known
        self.stop_k: int | None = None  # the grid step the stall stops the shaft at, until it is reached

    def _quantise(self, pan: float) -> float:
        return self.settings.whole_ticks(pan)

    def _step(self, h: float) -> None:
        e = self.goal - self.pan
        tau = self.settings.tau_s
        v = abs(e) / tau if tau > 0 else math.inf
        v = min(v, self.vmax, math.sqrt(2 * self.amax * abs(e)) if math.isfinite(self.amax) else math.inf)
        if math.isinf(v):  # no time constant, speed or acceleration limit: there at once
            self.pan, self.vel = self.goal, 0.0
            return
        want = math.copysign(v, e)
        dv = want - self.vel
        lim = self.amax * h
        if tau > 0 and v == abs(e) / tau and abs(dv) <= lim and abs(e) / tau * math.exp(-h / tau) <= self.vmax:
            # the first-order approach, integrated exactly over the step
            e *= math.exp(-h / tau)
            self.pan, self.vel = self.goal - e, e / tau
            return
        self.vel = want if abs(dv) <= lim else self.vel + math.copysign(lim, dv)
        move = self.vel * h
        if tau <= 0 and abs(move) >= abs(e):  # a pure speed limit: stop on the goal
            self.pan, self.vel = self.goal, 0.0
        else:
            self.pan += move
        if not self.hard[0] <= self.pan <= self.hard[1]:
            self.pan = min(self.hard[1], max(self.hard[0], self.pan))
            self.vel = 0.0

    def _advance(self, now_ns: int | None = None) -> None:
        """The state integrated up to the last grid step at or before now_ns (default: the clock's now)."""
        end = (self.clock_ns() if now_ns is None else now_ns) // H_NS
        while self.k < end:
            while self.pending and self.pending[0][0] <= self.k:  # every goal due by now: the newest wins
                self.goal = self.pending.popleft()[1]
            if self.stop_k is not None and self.stop_k <= self.k:  # a stall: it stops where it is
                self.goal, self.stop_k = self.pan, None
                self.pending.clear()
            if not self.torque:
                self.vel = 0.0
            elif self.pan == self.goal and self.vel == 0.0:
                pass
            elif abs(self.goal - self.pan) < 1e-12 and abs(self.vel) < 1e-9:
                self.pan, self.vel = self.goal, 0.0
            else:
                self._step(H)
                self.k += 1
                continue
            # at rest: skip to the next pending goal (or to now), on the grid
            nxt = min(self.pending[0][0] if self.pending else end, end if self.stop_k is None else self.stop_k)
            self.k += max(1, min(nxt, end) - self.k)

    def _at(self, ns: int) -> float:
        """The shaft at ns, from the state at the grid step (at or, by less than a step, after ns)."""
        return self.pan + self.vel * max(0.0, (ns - self.k * H_NS) / 1e9)

    @property
    def shaft(self) -> float:
        """The exact shaft angle now (between grid steps: extrapolated at the present speed)."""
        now = self.clock_ns()
        self._advance(now)
        return self._at(now)

    def open(self) -> float:
        self._advance()
        self.torque = True
        return self.read_position()

    def close(self, torque_off: bool = True) -> None:
        self._advance()
        if torque_off:
            self.torque = False

    def describe(self) -> str:
        lies = ([f"stalled {self.stall[0]:g}-{self.stall[1]:g} s from the first commanded frame"] if self.stall else []
                ) + ([f"encoder noise {math.degrees(self.noise_rad):g} deg"] if self.noise_rad else [])
        return f"sim ({', '.join(lies)}, as --faults says)" if lies else "sim"

    def first_exposure(self, t_ns: int) -> None:
        if self.stall is not None and self.stall_ns is None:
            self.stall_ns = (t_ns + round(self.stall[0] * 1e9), t_ns + round(self.stall[1] * 1e9))
            self.stop_k = max(_ceil_step(self.stall_ns[0]), self.k)

    def write_goal(self, pan_rad: float) -> None:
        now = self.clock_ns()
        self._advance(now)
        goal = self._quantise(pan_rad)
        self._written = now
        if self.stall_ns is not None and self.stall_ns[0] <= now + self.latency_ns < self.stall_ns[1]:
            return  # stalled when it would take it: it takes none
        if self.latency_ns <= 0:
            self.goal = goal
        else:
            self.pending.append((_ceil_step(now + self.latency_ns), goal))

    def read_position(self) -> float:
        """The encoder's reading now, or right after a goal was written (within WRITE_READ_NS), at the write's
        instant: the state that reports a command then says when it was written (position_ns)."""
        now = self.clock_ns()
        ns = self._written if self._written is not None and now - self._written <= WRITE_READ_NS else now
        self._written = None
        self._advance(ns)
        self.position_ns = ns
        return self._quantise(self._at(ns) + (self.rng.gauss(0.0, self.noise_rad) if self.noise_rad else 0.0))


class Replica:
    """The sim motor as another process sees it: the same SimMotor model on the same grid, fed with the goals
    that the sim actuator's motor states report, so a process that renders the slave (the capture's sim
    source) knows the shaft at any instant up to now without waiting for the motor's next report.

    The actuator publishes a state right after every goal it writes, stamped with the write's instant, and a
    goal takes effect latency_s (2 ms) later, so a goal is normally known here before the shaft moves; one
    that arrives late is put back in its place (the model is rewound to a snapshot before it). Every state
    also checks the model: its encoder reading must be within one tick of the model's shaft at the state's
    time. A model that fails the check (other motor settings than ours, a capture started while the motor
    moved, a state lost) is not trusted until the motor is seen at rest on its goal (two states 5 ms apart
    with the encoder on an unchanged goal), where it starts again from that rest. `trusted` says whether at()
    may be used; `mismatches` counts the failed checks. Times are the states' clock: wall nanoseconds. A noisy
    encoder (noise_deg: the sim source's encoder_noise=, which the sim actuator has too) widens both checks by 5
    deviations of its noise.

    A state that comes more than latency_s after its write (a loaded machine) is known too late for the frames
    exposed meanwhile, so the commands are counted too: `commanded` for each one seen on the command key,
    `counted` with the motor's own count from each state (which may come first); while the motor has not
    counted one seen here (`unanswered`), its goal may be missing, and the renderer waits (at most ANSWER_NS from
    its arrival, then it is let go and counted in `unheard`)."""

    KEEP_NS = 2_000_000_000  # snapshots kept, for instants back to this far before the newest
    SNAP_STEPS = 4  # a snapshot every this many grid steps of model time (1 ms)
    REST_NS = 5_000_000
    ANSWER_NS = 50_000_000  # the longest a command seen waits for the motor's state that counts it

    def __init__(self, settings: MotorSettings, noise_deg: float = 0.0, stall: tuple[float, float] | None = None):
        self.settings = settings
        self.stall, self.stall_ns, self.past_stall = stall, None, False  # (stall=: the sim actuator's too)
        # how far a reading may be off the model: a tick, and 5 deviations of the encoder's noise (encoder_noise=)
        self.tol = 2 * math.pi / settings.ticks_per_rev * 1.01 + 5 * math.radians(noise_deg)
        self._now = 0
        # the model is the actuator's SimMotor, in the motor's own angle: the pans the states report (MotorLoop's,
        # direction and offset applied) are turned into it, and the shafts it gives back into pans
        self.m = SimMotor(settings, clock_ns=lambda: self._now)
        self.tick_rad = self.m.tick_rad
        self.trusted = False
        self.mismatches = 0
        self.goal: float | None = None  # the newest goal reported (in the motor's angle)
        self._rest: tuple[int, float] | None = None  # (t_ns, goal) of a state seen on its goal, not yet trusted
        self.snaps: deque[tuple] = deque()
        self.out: deque[int] = deque()  # the arrivals (monotonic ns) of commands seen, not yet counted by the motor
        self.early: deque[int] = deque()  # the arrivals of states counting commands not seen here yet
        self.count: int | None = None  # the motor's count of commands in its newest state
        self.unheard = 0  # commands let go after ANSWER_NS with no state counting them

    # -- the model ------------------------------------------------------------------------------------------

    def _snap(self) -> tuple:
        m = self.m
        return m.k, m.pan, m.vel, m.goal, tuple(m.pending), m.torque

    def _restore(self, snap: tuple) -> None:
        m = self.m
        m.k, m.pan, m.vel, m.goal, pending, m.torque = snap
        m.pending = deque(pending)

    def _reset(self, t_ns: int, pan: float, goal: float) -> None:
        """The motor at rest on pan from t_ns on, heading for goal."""
        m = self.m
        m.k, m.pan, m.vel, m.goal, m.torque = t_ns // H_NS, pan, 0.0, m._quantise(goal), True
        m.pending.clear()
        self.snaps.clear()
        self.snaps.append(self._snap())

    def _advance(self, ns: int) -> None:
        """The model forward to ns, a snapshot every SNAP_STEPS steps."""
        m = self.m
        end = ns // H_NS
        while m.k < end:
            resting = m.pan == m.goal and m.vel == 0.0 and not m.pending
            m._advance((end if resting or not m.torque else min(end, m.k + self.SNAP_STEPS)) * H_NS)
            self.snaps.append(self._snap())
        keep = self.KEEP_NS // H_NS
        while len(self.snaps) > 2 and self.snaps[-1][0] - self.snaps[1][0] > keep:
            self.snaps.popleft()

    def _rewind(self, ns: int) -> bool:
        """The model back to its latest snapshot at or before ns; False when none is that old."""
        snaps, k = self.snaps, ns // H_NS
        while snaps and snaps[-1][0] > k:
            snaps.pop()
        if not snaps:
            return False
        self._restore(snaps[-1])
        return True

    def _shaft(self, ns: int) -> float:
        """The shaft at ns (also before the model's time: from the snapshot before it)."""
        m = self.m
        if ns >= m.k * H_NS:
            self._advance(ns)
            return m._at(ns)
        i = bisect.bisect_right(self.snaps, ns // H_NS, key=lambda snap: snap[0]) - 1
        if i < 0:
            return math.nan
        here = self._snap()
        try:
            self._restore(self.snaps[i])
            m._advance(ns)
            return m._at(ns)
        finally:
            self._restore(here)

    # -- the interface --------------------------------------------------------------------------------------

    def first_exposure(self, t_ns: int) -> None:
        """The exposure of the first frame commanded (the first plausible command seen, as the sim actuator's
        MotorLoop tells its motor): a stall's instants from it. The model is not trusted from the stall's start until
        the motor rests on its goal after its end (the motor dropped the goals meanwhile)."""
        if self.stall is not None and self.stall_ns is None:
            self.stall_ns = (t_ns + round(self.stall[0] * 1e9), t_ns + round(self.stall[1] * 1e9))

    def _stalled(self, t_ns: int) -> bool:
        if self.stall_ns is None or self.past_stall or t_ns < self.stall_ns[0]:
            return False
        self.trusted, self._rest = False, None
        return True

    def at(self, t_ns: int) -> float | None:
        """The shaft at t_ns, or None while the model is not trusted (or t_ns before what it keeps)."""
        if not self.trusted or self._stalled(t_ns):
            return None
        shaft = self._shaft(t_ns)
        return self.settings.from_motor(shaft) if math.isfinite(shaft) else None

    def commanded(self, now_ns: int) -> None:
        """A command seen on the command key (now_ns: its arrival, monotonic): out until a state counts it (or
        answered already, by a state that came first)."""
        self._expire(now_ns)
        if self.early:
            self.early.popleft()
        else:
            self.out.append(now_ns)

    def counted(self, commands: int, now_ns: int) -> None:
        """The motor's count of command messages received, from one of its states (now_ns: its arrival): the
        ones it counted since its last state answer those out, or, where none is (the state came first), the
        next ones seen. A count that went down is a restarted actuator's, from 0."""
        self._expire(now_ns)
        if self.count is not None:
            for _ in range(min(commands - self.count if commands >= self.count else commands, 64)):
                if self.out:
                    self.out.popleft()
                else:
                    self.early.append(now_ns)
        self.count = commands

    def _expire(self, now_ns: int) -> None:
        """Let go what waited over ANSWER_NS for its match: commands out (counted in unheard), answers early."""
        while self.out and now_ns - self.out[0] > self.ANSWER_NS:
            self.out.popleft()
            self.unheard += 1
        while self.early and now_ns - self.early[0] > self.ANSWER_NS:
            self.early.popleft()

    def unanswered(self, now_ns: int) -> int | None:
        """The arrival of the oldest command seen that the motor has not counted yet (its goal may be missing
        here), or None."""
        self._expire(now_ns)
        return self.out[0] if self.out else None

    def observe(self, t_ns: int, pan: float, goal: float, torque: bool = True) -> bool:
        """One motor state (its time, encoder reading, goal; torque False once the motor has stopped): a new
        goal from the instant the motor takes it (latency_s after the state, which a write stamps), the model
        checked against the reading. False when the check failed (the model is then not trusted until the
        motor rests on its goal)."""
        m = self.m
        pan, goal = self.settings.to_motor(pan), self.settings.to_motor(goal)  # the model's own angle
        self._stalled(t_ns)
        if self.trusted and goal != self.goal:
            if t_ns < m.k * H_NS and not self._rewind(t_ns):
                self.trusted = False
            elif m.latency_ns <= 0:
                self._advance(t_ns)
                m.goal = m._quantise(goal)
            else:
                m.pending.append((_ceil_step(t_ns + m.latency_ns), m._quantise(goal)))
        if self.trusted:
            if not torque:
                self._advance(t_ns)
                m.torque = False
            if not abs(self._shaft(t_ns) - pan) <= self.tol:
                self.mismatches += 1
                self.trusted = False
                self._rest = None
        self.goal = goal
        if not self.trusted:
            self._settle(t_ns, pan, goal)
        return self.trusted

    def _settle(self, t_ns: int, pan: float, goal: float) -> None:
        """Not trusted: two states with the encoder on the (unchanged) goal, REST_NS apart, restart the model (not
        before a stall's end)."""
        if self.stall_ns is not None and not self.past_stall and t_ns >= self.stall_ns[0]:
            if t_ns < self.stall_ns[1]:
                return
            self.past_stall = True
        q = self.m._quantise(goal)
        if not abs(pan - q) <= 1e-9 + self.tol - self.tick_rad * 1.01:
            self._rest = None
        elif self._rest is None or self._rest[1] != goal:
            self._rest = (t_ns, goal)
        elif t_ns - self._rest[0] >= self.REST_NS:
            self._reset(t_ns, q, goal)
            self.trusted = True
            self._rest = None
