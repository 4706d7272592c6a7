"""A simulated pan motor that behaves like a servo: latency, top speed, acceleration, a first-order final
approach, whole ticks, hard limits.

A goal written at time t reaches the motor at t + latency_s (quantised to a whole tick when `quantise`).
The shaft then heads for it at the speed v* = min(|e| / tau, max_speed, sqrt(2 a |e|)) (e: the distance
left; the last term brakes in time), its speed changing by at most max_accel_deg_s2. The state is
integrated in fixed 0.25 ms steps on a grid anchored at the motor's start, so positions do not depend on
how often the motor is polled; a motor at rest on its goal skips ahead. read_position() is the present
position as the encoder reports it (a whole tick when quantising), `shaft` the exact angle the camera is at.
The hard limits are the soft limits plus one degree: the safety layer never lets a goal past the soft ones
anyway.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable

from .base import Driver, MotorSettings

__all__ = ["SimMotor"]

H = 0.00025  # the integration step, s


class SimMotor(Driver):
    name = "sim"

    def __init__(self, settings: MotorSettings | None = None, clock: Callable[[], float] = time.monotonic):
        super().__init__(settings or MotorSettings())
        s = self.settings
        self.clock = clock
        self.tick_rad = 2 * math.pi / s.ticks_per_rev
        self.pan = math.radians(s.start_deg)  # the shaft at the grid time self.t
        self.vel = 0.0
        self.goal = self.pan
        self.pending: deque[tuple[float, float]] = deque()  # (time it reaches the motor, goal)
        self.t = clock()
        self.torque = False
        self.hard = (s.min_rad - math.radians(1), s.max_rad + math.radians(1))
        self.vmax = math.radians(s.max_speed_deg_s) or math.inf
        self.amax = math.radians(s.max_accel_deg_s2) or math.inf

    def _quantise(self, pan: float) -> float:
        if not self.settings.quantise:
            return pan
        return round(pan / self.tick_rad) * self.tick_rad

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

    def _advance(self) -> None:
        now = self.clock()
        while self.t + H <= now:
            while self.pending and self.pending[0][0] <= self.t:  # every goal due by now: the newest wins
                self.goal = self.pending.popleft()[1]
            if not self.torque:
                self.vel = 0.0
            elif self.pan == self.goal and self.vel == 0.0:
                pass
            elif abs(self.goal - self.pan) < 1e-12 and abs(self.vel) < 1e-9:
                self.pan, self.vel = self.goal, 0.0
            else:
                self._step(H)
                self.t += H
                continue
            # at rest: skip to the next pending goal (or to now), on the grid
            nxt = self.pending[0][0] if self.pending else now
            n = max(1, int((min(nxt, now) - self.t) / H))
            self.t += n * H

    @property
    def shaft(self) -> float:
        """The exact shaft angle now (between grid steps: extrapolated at the present speed)."""
        self._advance()
        return self.pan + self.vel * max(0.0, self.clock() - self.t)

    def open(self) -> float:
        self._advance()
        self.torque = True
        return self._quantise(self.pan)

    def close(self, torque_off: bool = True) -> None:
        self._advance()
        if torque_off:
            self.torque = False

    def write_goal(self, pan_rad: float) -> None:
        self._advance()
        goal = self._quantise(pan_rad)
        at = self.clock() + self.settings.latency_s
        if self.settings.latency_s <= 0:
            self.goal = goal
        else:
            self.pending.append((at, goal))

    def read_position(self) -> float:
        return self._quantise(self.shaft)
