"""From the network's decision to a pan set-point: pixels -> angle, gain, dead band, then the motor's limits.

Two modes ([control] mode):
- "p": each confident decision sets the target pan at capture + gain x the measured correction; an
  abstention does not move the slave.
- "predictive": each confident decision is a measurement of where the target is (the pan at capture + the
  measured correction) at its capture time; a constant-velocity Kalman filter (Predictor) estimates the
  target's pan and its rate from that stream, and the command is the estimate extrapolated `lead_s` plus
  half a decision interval past the capture (to when the motor will be acting on it). A measurement far
  off the prediction (gate_px) restarts the filter (a jump, not a motion). An abstention coasts on the
  estimate (its rate fading with the time constant coast_s / 2) for at most coast_s, then the slave
  holds. No command within dead_band_px of the present pan, nor of the last set-point while the motor is
  there (within 1 px or 0.1 degree: a motor settles on its nearest tick).

The pan limits and the step limit are the motor's ([actuator.motor] min_deg, max_deg, max_step_deg): the
Controller holds no copy of them, it asks the motor's safety layer (vergence.motors.base.Safety.limit_step)
to bound every set-point, so a set-point never leaves them; the actuator's own Safety bounds whatever
arrives again (the last line). Its dead band is the larger of [control] dead_band_px (the measurement's: at
the focal length, a correction smaller than this many pixels is noise) and the motor's dead_band_deg (a goal
change the actuator would hold anyway).

The default is "predictive": in `vergence bench tracking` p's error is 2.2-4.0 times its own on sines
from 0.5 Hz on (p lags by the loop's latency, about a frame plus the motor), 1.2-2.1 times at 0.25 Hz, and
both settle alike on a step; its cost, on still Middlebury scenes, is a few points of convergence where the
matcher hesitates between offsets a pixel apart. Its filter is kept calm
(accel_deg_s2 700, noise_px 1): a livelier one (1000 / 0.5) tracked a 2 Hz sine a little closer but rang
by +-2 px with the paper's network, whose whole-pixel decisions feed the filter a loop-correlated error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .motors.base import MotorSettings, Safety

__all__ = ["pixels_to_angle", "ControlSettings", "Controller", "Predictor", "MODES"]

MODES = ("p", "predictive")


def pixels_to_angle(offset_px: float, focal_px: float, centre_px: float = 0.0) -> float:
    """The pan (radians) that brings the content at `offset_px` right of the principal point to it.

    With a rotating pinhole camera, a column u px right of the principal point lies atan(u / f) off the
    optical axis; centre_px is the fovea window's own offset from the principal point (0 at the centre)."""
    return math.atan((offset_px + centre_px) / focal_px) - math.atan(centre_px / focal_px)


@dataclass(frozen=True)
class ControlSettings:
    """mode: "p" or "predictive" (see the module's docstring). gain: fraction of the measured correction
    applied per decision (p); dead_band_px: no move for a correction below it (pixels at the focal length:
    the measurement's dead band; the motor's, in degrees, is [actuator.motor] dead_band_deg). The pan limits
    and the step limit are not here: they are the motor's ([actuator.motor], vergence.motors.base.Safety).
    predictive: lead_s: how far past the capture the command aims, besides half the interval between
    decisions (capture-to-command latency + motor latency + the motor's time constant); accel_deg_s2: the
    standard deviation of the target's acceleration (the filter's process noise); noise_px: the
    measurement's noise; gate_px: a measurement further than this from the prediction restarts the filter; coast_s: how
    long abstentions coast on the estimate before the slave holds; max_rate_deg_s: the estimated rate is
    bounded by it; min_rate_deg_s: the rate extrapolated is the estimate less this (soft threshold)."""

    mode: str = "predictive"
    gain: float = 1.0
    dead_band_px: float = 0.25
    lead_s: float = 0.02
    accel_deg_s2: float = 700.0
    noise_px: float = 1.0
    gate_px: float = 10.0
    coast_s: float = 0.25
    max_rate_deg_s: float = 90.0
    min_rate_deg_s: float = 1.0

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"mode={self.mode!r}: must be one of {', '.join(MODES)}")
        for name in ("lead_s", "accel_deg_s2", "noise_px", "gate_px", "coast_s", "max_rate_deg_s",
                     "min_rate_deg_s"):
            v = getattr(self, name)
            if not (v >= 0 and math.isfinite(v)):
                raise ValueError(f"{name}={v}: must be a finite number >= 0")
        if not self.noise_px > 0:
            raise ValueError(f"noise_px={self.noise_px}: must be > 0")


class Predictor:
    """A constant-velocity Kalman filter of the target's pan (radians) over capture times (seconds).

    update(t, z) takes a measurement z of the target's pan captured at t; at(t) is the estimate there.
    q: the variance of the target's acceleration (rad^2/s^4, piecewise constant between measurements),
    r: the measurement variance (rad^2), gate: the largest innovation (rad) taken as motion (larger:
    restart at z), vmax: the bound of the estimated rate (rad/s)."""

    def __init__(self, q: float, r: float, gate: float, vmax: float):
        self.q, self.r, self.gate, self.vmax = q, r, gate, vmax
        self.t: float | None = None
        self.x = self.v = 0.0
        self.p = [[0.0, 0.0], [0.0, 0.0]]
        self.restarts = 0

    def reset(self) -> None:
        self.t = None

    def _start(self, t: float, z: float) -> None:
        self.t, self.x, self.v = t, z, 0.0
        self.p = [[self.r, 0.0], [0.0, (self.vmax / 2) ** 2]]

    def update(self, t: float, z: float) -> None:
        if self.t is None or t < self.t - 1.0:  # none yet, or time went back (a new capture): start over
            self._start(t, z)
            return
        dt = max(0.0, t - self.t)
        (p00, p01), (_, p11) = self.p
        x = self.x + self.v * dt
        q = self.q  # piecewise-constant white acceleration of variance q
        p00 = p00 + dt * (2 * p01 + dt * p11) + q * dt ** 4 / 4
        p01 = p01 + dt * p11 + q * dt ** 3 / 2
        p11 = p11 + q * dt ** 2
        y = z - x
        if abs(y) > self.gate:
            self.restarts += 1
            self._start(t, z)
            return
        s = p00 + self.r
        k0, k1 = p00 / s, p01 / s
        self.x = x + k0 * y
        self.v = max(-self.vmax, min(self.vmax, self.v + k1 * y))
        self.p = [[(1 - k0) * p00, (1 - k0) * p01], [(1 - k0) * p01, p11 - k1 * p01]]
        self.t = t

    def at(self, t: float) -> float:
        """The estimated pan at time t (the last estimate carried at the estimated rate)."""
        return self.x + self.v * (t - self.t)


class Controller:
    """Turns decisions into absolute pan targets for the slave, each bounded by the motor's limits.

    limits: the motor's safety layer (a Safety, whose inside / limit_step / dead_band_rad it asks; only
    those, never its state), or the MotorSettings to build one from ([actuator.motor]); default
    MotorSettings()."""

    def __init__(self, settings: ControlSettings | None = None, limits: Safety | MotorSettings | None = None):
        self.s = settings or ControlSettings()
        self.limits = limits if isinstance(limits, Safety) else Safety(limits or MotorSettings())
        self.predictor: Predictor | None = None
        self.t_confident: float | None = None  # capture time of the last confident decision
        self.coasting = 0  # abstentions answered from the estimate
        self.last_goal: float | None = None  # the predictive mode's last set-point
        self.t_prev: float | None = None  # the last decision's capture time
        self.period: float | None = None  # the decisions' interval, smoothed

    def _bounded(self, pan_at_capture: float, step: float) -> float:
        """The set-point pan_at_capture + step, as the motor's Safety bounds it (limits, step)."""
        return self.limits.limit_step(pan_at_capture, pan_at_capture + step)

    def target(self, pan_at_capture: float, offset_px: float, focal_px: float, confident: bool = True,
               centre_px: float = 0.0, t_s: float | None = None) -> float | None:
        """The new absolute pan (radians) or None when the camera should not move (not confident, inside
        the dead band, or a non-finite input). t_s: the frame's capture time in seconds (any epoch; the
        predictive mode needs it, and acts as "p" without it)."""
        if self.s.mode == "predictive" and t_s is not None and math.isfinite(t_s):
            return self._predictive(pan_at_capture, offset_px, focal_px, confident, centre_px, t_s)
        if not confident or not all(math.isfinite(v) for v in (pan_at_capture, offset_px, focal_px)):
            return None
        if focal_px <= 0 or abs(offset_px) < self.s.dead_band_px:
            return None
        step = self.s.gain * pixels_to_angle(offset_px, focal_px, centre_px)
        if abs(step) < self.limits.dead_band_rad:
            return None
        return self._bounded(pan_at_capture, step)

    def _predictive(self, pan: float, offset_px: float, focal_px: float, confident: bool, centre_px: float,
                    t: float) -> float | None:
        if not (math.isfinite(pan) and math.isfinite(focal_px) and focal_px > 0):
            return None
        if self.predictor is None:
            one = math.atan(1.0 / focal_px)
            self.predictor = Predictor(q=math.radians(self.s.accel_deg_s2) ** 2,
                                       r=(self.s.noise_px * one) ** 2, gate=self.s.gate_px * one,
                                       vmax=math.radians(self.s.max_rate_deg_s))
        f = self.predictor
        if self.t_prev is not None and 0 < t - self.t_prev < 1.0:
            self.period = t - self.t_prev if self.period is None else 0.9 * self.period + 0.1 * (t - self.t_prev)
        self.t_prev = t
        # a set-point holds until the next decision: aim at the middle of that interval
        at = t + self.s.lead_s + 0.5 * (self.period or 0.0)
        if confident and math.isfinite(offset_px):
            f.update(t, pan + pixels_to_angle(offset_px, focal_px, centre_px))
            self.t_confident = t
            # the rate, less min_rate_deg_s (soft threshold): the noise of a still target's rate estimate
            # (whole-tick encoder readings during small moves, a hesitating matcher) is not extrapolated
            vmin = math.radians(self.s.min_rate_deg_s)
            v = math.copysign(max(0.0, abs(f.v) - vmin), f.v)
            goal = f.x + v * (at - f.t)
        elif f.t is None or self.t_confident is None or t - self.t_confident > self.s.coast_s \
                or t < self.t_confident:
            f.reset()  # nothing to coast on, or coasted long enough: hold
            self.last_goal = None
            return None
        else:
            # coast on the estimate, its rate fading (time constant coast_s / 2): never more than
            # rate x coast_s / 2 past the last estimate
            self.coasting += 1
            tau = self.s.coast_s / 2
            goal = f.x + f.v * tau * (1 - math.exp(-max(0.0, at - f.t) / tau)) if tau > 0 else f.x
        # the dead band around the present pan, and around the set-point already sent while the motor is
        # there (re-sending about the same goal would only pass the estimate's noise, and the encoder's
        # whole ticks, to the motor); a set-point the motor is not at (lost, or no motor listening) is sent
        # again
        db = max(math.atan(self.s.dead_band_px / focal_px), self.limits.dead_band_rad)
        if abs(goal - pan) < db:
            return None
        if self.last_goal is not None and abs(goal - self.last_goal) < db \
                and abs(self.last_goal - pan) <= max(math.atan(1.0 / focal_px), math.radians(0.1)):
            return None
        self.last_goal = self._bounded(pan, goal - pan)
        return self.last_goal
