"""A simulated pan motor: first-order response toward the goal, speed-limited, inside hard limits.

The position follows d pan / dt = (goal - pan) / tau, never faster than max_speed_deg_s, and is integrated
exactly between reads (so the answer does not depend on how often it is polled). The hard limits are the
soft limits plus one degree: the safety layer never lets a goal past the soft ones anyway.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

from .base import Driver, MotorSettings

__all__ = ["SimMotor"]


class SimMotor(Driver):
    name = "sim"

    def __init__(self, settings: MotorSettings | None = None, clock: Callable[[], float] = time.monotonic):
        super().__init__(settings or MotorSettings())
        self.clock = clock
        self.pan = math.radians(self.settings.start_deg)
        self.goal = self.pan
        self.t = clock()
        self.torque = False
        self.hard = (self.settings.min_rad - math.radians(1), self.settings.max_rad + math.radians(1))

    def _advance(self) -> None:
        now = self.clock()
        dt, self.t = max(0.0, now - self.t), now
        if not self.torque or dt == 0:
            return
        err = self.goal - self.pan
        tau = self.settings.tau_s
        vmax = math.radians(self.settings.max_speed_deg_s) or math.inf
        if tau <= 0:
            move = math.copysign(min(abs(err), vmax * dt), err)
        else:
            # speed-limited phase while |err| / tau > vmax, then the exponential tail
            move = 0.0
            if abs(err) > vmax * tau:
                t_lin = (abs(err) - vmax * tau) / vmax
                if dt <= t_lin:
                    move = math.copysign(vmax * dt, err)
                    dt = 0.0
                else:
                    move = math.copysign(vmax * t_lin, err)
                    dt -= t_lin
            rest = err - move
            move += rest * (1 - math.exp(-dt / tau))
        self.pan = min(self.hard[1], max(self.hard[0], self.pan + move))

    def open(self) -> float:
        self.t = self.clock()
        self.torque = True
        return self.pan

    def close(self, torque_off: bool = True) -> None:
        self._advance()
        if torque_off:
            self.torque = False

    def write_goal(self, pan_rad: float) -> None:
        self._advance()
        self.goal = pan_rad

    def read_position(self) -> float:
        self._advance()
        return self.pan
