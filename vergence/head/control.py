"""From the network's decision to a pan set-point: pixels -> angle, gain, dead band, then the motor's limits.

Every measurement is referred to the instant the slave's image was exposed (vergence.head.timing): the pan it
is given is the slave's pan then, t_s that exposure's time, t_now the time of the command. While the motor rests
(no command for a while), that pan is the mean of the motor's readings since it came to rest, not the frame's one
reading (vergence.head.rest): a noisy encoder's noise is not taken for the target's motion. Where the play between
the motor and the camera is measured (vergence.head.play), the pan is the camera's through it, and each set-point
goes to the motor half the play past, on the side the camera moves to.

Two modes ([control] mode):
- "p": each confident decision sets the target pan at exposure + gain x the measured correction; an
  abstention does not move the slave. Its gain is at most 1 for an image older than LATE_S (above 1 the loop
  overshoots more, the older the image).
- "predictive": each confident decision is a measurement of where the target was (the pan at exposure + the
  measured correction) at the slave's exposure; the command is the target's pan predicted for t_now +
  `lead_s` + half a decision interval (when the motor will be acting on it), however old the image. Three
  predictions, refereed by how well each has predicted (Referee): hold (the filter's pan), a constant-velocity
  Kalman filter (Predictor) of the target's pan and rate, and, with `periodic`, a periodic fit (Periodic) that
  predicts a target moving to and fro far past where any polynomial holds (its fit and the referee take no decision
  made after the motor moved more than FAST_DEG since the last one: its pan at the exposure is the least sure, a
  skewed or blurred exposure's most of all; the filter takes every one). A measurement far off the filter's
  prediction (gate_px) restarts them all (a jump, not a motion); a new fovea's first one more than NEW_TARGET_PX
  off it moves the filter there at rest (another target: a fixate's new point, under the gate, was taken for a
  motion and overshot). An abstention coasts on the filter's
  estimate (its rate fading with the time constant coast_s / 2) for at most coast_s, then the slave holds.
  No command within dead_band_px of the present pan, nor of the last set-point while the motor is there
  (within 1 px or 0.1 degree: a motor settles on its nearest tick).

The pan limits and the step limit are the motor's ([actuator.motor] min_deg, max_deg, max_step_deg): the
Controller holds no copy of them, it asks the motor's safety layer (vergence.motors.base.Safety.limit_step)
to bound every set-point, so a set-point never leaves them; the actuator's own Safety bounds whatever
arrives again (the last line). Its dead band is the larger of [control] dead_band_px (the measurement's: at
the focal length, a correction smaller than this many pixels is noise) and the motor's dead_band_deg (a goal
change the actuator would hold anyway).

The default is "predictive": "p" lags by the loop's latency, so its error grows with the target's speed; the
predictive filter is kept calm (accel_deg_s2, noise_px) because the paper's whole-pixel decisions feed a livelier
one a loop-correlated error. The figures behind both choices, and their commands: docs/SIMULATOR.md, "Why the
predictive controller is the default, and its cost".
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..motors.base import MotorSettings, Safety
from ..choices import ControlMode, Fault
from ..ranges import Range, check
from .doubt import LEASH_DEG, PROBE_MIN_DEG, UNTRUSTED_DEG, Doubt
from .play import Play
from .search import Search
from .predict import Periodic, Predictor, Referee
from .rest import Rest
from .shaft import Shaft
from .scenery import MIN_MOVE_DEG, Background, Verdict, central, profile
from .timing import MAX_AGE_S

__all__ = ["pixels_to_angle", "ControlSettings", "Controller", "Predictor", "MODES"]

MODES = tuple(ControlMode)  # (vergence.choices)


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
    lead_s: float = 0.015
    accel_deg_s2: float = 700.0
    periodic: bool = True
    noise_px: float = 1.0
    gate_px: float = 10.0
    coast_s: float = 0.25
    max_rate_deg_s: float = 90.0
    min_rate_deg_s: float = 1.0

    RANGES: ClassVar[dict[str, Range]] = {
        "gain": Range(0, 2, lo_open=True, hi_open=True, note="at 2 and above each correction overshoots by as "
                      "much as it corrects: the loop never settles"),
        "dead_band_px": Range(0, 100, note="pixels"),
        "lead_s": Range(0, 1, note="seconds"),
        "accel_deg_s2": Range(0, 1e6),
        "noise_px": Range(0, 1000, lo_open=True),
        "gate_px": Range(0, 10_000),
        "coast_s": Range(0, 60),
        "max_rate_deg_s": Range(0, 10_000),
        "min_rate_deg_s": Range(0, 10_000),
    }

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"mode={self.mode!r}: must be one of {', '.join(MODES)}")
        check(self, self.RANGES)


LATE_S = 0.02  # an image older than this when its command goes out: p's gain is at most 1
PREDICTORS = ("hold", "rate", "periodic")  # what the predictive mode's Referee weighs, in this order
PERIOD_ALPHA = 0.1  # the decisions' interval is smoothed with this weight per decision (about 10 decisions)
FAST_DEG = 1.0  # a decision made after the motor moved this much since the last one: no periodic sample
PERIOD_GAP_S = 1.0  # an interval this long or longer is a pause, not the decisions' rate
NEW_TARGET_PX = 3.0  # a new fovea's first decision this far off the prediction: a new target (the filter there at rest)
log = logging.getLogger("vergence.control")


class Controller:
    """Turns decisions into absolute pan targets for the slave, each bounded by the motor's limits.

    limits: the motor's safety layer (a Safety, whose inside / limit_step / dead_band_rad it asks; only
    those, never its state), or the MotorSettings to build one from ([actuator.motor]); default
    MotorSettings()."""

    def __init__(self, settings: ControlSettings | None = None, limits: Safety | MotorSettings | None = None):
        self.s = settings or ControlSettings()
        self.limits = limits if isinstance(limits, Safety) else Safety(limits or MotorSettings())
        self.predictor: Predictor | None = None
        self.gain_lowered = 0  # p commands whose gain was lowered to 1 (an old image)
        self.periodic: Periodic | None = None
        self.referee: Referee | None = None
        self.t_confident: float | None = None  # capture time of the last confident decision
        self.coasting = 0  # abstentions answered from the estimate
        self.last_goal: float | None = None  # the predictive mode's last set-point
        self.t_prev: float | None = None  # the last decision's capture time
        self.pan_prev = 0.0  # the last decision's pan at exposure
        self.period: float | None = None  # the decisions' interval, smoothed
        self.doubt = Doubt()  # whether the image follows the motor, and the leash it keeps (issue #35)
        self.doubt.stall.dead_band = self.limits.dead_band_rad
        self.background = Background()  # whether the slave's background moves with the motor (the doubt's too)
        self.search = Search()  # lost: where to look (issue #35)
        self.turned = False  # the background turned with the motor since the search began: its image follows
        self.fovea: tuple[int, int] | None = None  # the master point of the last decision ...
        self.fovea_new = False  # ... new since the last confident one (a new point: maybe a new target)
        self.rest = Rest()  # the motor's readings while it rests: a frame's pan then is their mean (a noisy encoder)
        self.shaft = Shaft(self.rest, self.limits.s)  # ... in motion, the goals sent as a servo follows them
        self.play = Play()  # the play between the motor and the camera (backlash), measured and taken out

    def _bounded(self, pan_at_capture: float, step: float) -> float:
        """The set-point pan_at_capture + step, as the motor's Safety bounds it (limits, step)."""
        return self.limits.limit_step(pan_at_capture, pan_at_capture + step)

    def motor(self, t_s: float, pan: float) -> None:
        """The motor's own report of the slave's pan (rad) at t_s (the frames' clock, s): a camera's lag is fitted
        on these (vergence.head.lag), denser than the frames' pans, and a resting motor's pan is their mean
        (vergence.head.rest). Only plausible reports (the caller's checks)."""
        self.doubt.lag.motor(t_s, pan)
        self.rest.motor(t_s, pan)  # (the shaft's model reads them too)

    def scene(self, t_s: float, pan: float, band, focal_px: float, fovea_col: float, fovea=None,
              centre_col: float | None = None) -> Verdict | None:
        """Whether the slave's background moved with the motor (vergence.head.scenery): one frame's slave band (t_s
        its exposure as stamped, pan the slave's then as the motor reported it, not extrapolated past its newest
        report: vergence.head.scenery; fovea_col the fovea's column in the band, centre_col the principal point's,
        default the band's middle), its verdict for target(background=); during a fault on moves from PROBE_MIN_DEG
        (its probes are PROBE_DEG from the anchor).
        None where a camera is named late (its stamps are not its image's: no verdict), or none is due. A reducer
        asks when the Frame arrives, while the workers compute. The play between the motor and the camera is read off
        the same bands (vergence.head.play), and where it is named the verdict is on the camera's pan."""
        d = self.doubt
        if d.lag.late_s is not None:
            return None
        probing = d.fault in (Fault.SLAVE_FROZEN, Fault.REVERSED)
        if getattr(band, "ndim", 0) != 2:
            return None
        shaft, rows = self._shaft(t_s, pan), central(band)
        seen = profile(rows)  # (the play's and the background's)
        centre = (band.shape[1] - 1) / 2 if centre_col is None else centre_col
        if d.fault is not None or self.search.searching:
            if self.play.lost(t_s if d.fault is not None else None):
                self._replay(self.play.replay())
        elif self.play.see(t_s, shaft, seen, (rows.shape, fovea), focal_px, fovea_col, centre,
                           repan=self.shaft.past, ready=not self.shaft.raw(t_s)):
            self._replay(self.play.replay())
        if self.play.half:
            pan = self.play.peek(shaft)  # (the camera's: the background turns as it does)
        # (bands from before a fault cleared are no reference: the camera then may not have followed the motor)
        return self.background.see(t_s, pan, rows, focal_px, fovea_col, key=(fovea, d.resumed), centre_col=centre,
                                   seen=seen, min_move_deg=PROBE_MIN_DEG if probing else MIN_MOVE_DEG)

    def target(self, pan_at_capture: float, offset_px: float, focal_px: float, confident: bool = True,
               centre_px: float = 0.0, t_s: float | None = None, t_now: float | None = None,
               slave: int | None = None, master: int | None = None,
               fovea: tuple[int, int] | None = None, doubt: bool = True, textured: bool = True,
               width_px: int | None = None, background: Verdict | None = None) -> float | None:
        """The new absolute pan (radians) or None when the camera should not move (not confident, inside
        the dead band, a non-finite input, or a fault: vergence.head.doubt). pan_at_capture: the slave's pan at
        its exposure; t_s: that exposure's time in seconds (any epoch; the predictive mode needs it, and acts as
        "p" without it); t_now: the time of this command on the same clock (default t_s: an image with no
        latency); slave, master: the images' digests (frozen cameras repeat them), None when not known; fovea: the
        master point decided at (a new one is a new target); doubt: False where the slave's image cannot follow the
        motor (a still pair, a video: nothing to check); textured: the fovea has texture (False: a black or flat
        frame, which holds; an unconfident textured one for long is lost, and searches: vergence.head.search);
        width_px: the images' width (the band's reach, which sizes the search's steps); background: the frame's
        verdict of scene() (None: none). While the motor rests, the pan is the mean of its readings since it came to
        rest (vergence.head.rest), not the one reading the frame carries; while it moves, a noisy encoder's pan is the
        goals sent as the motor follows them (vergence.head.shaft). Where a play is named (vergence.head.play) the pan
        is the camera's through it, and the goal returned is the motor's (half the play past the camera's)."""
        if t_s is not None and self.doubt.lag.late_s is None:
            pan_at_capture = self._shaft(t_s, pan_at_capture)
        shaft = pan_at_capture
        if t_s is not None:
            pan_at_capture = self.play.pan(t_s, pan_at_capture)
        goal = self._target(pan_at_capture, offset_px, focal_px, confident, centre_px, t_s, t_now, slave, master,
                            fovea, doubt, textured, width_px, background)
        if goal is not None and self.play.half:  # (a fault's probes, a search's moves too: the camera goes as asked)
            goal = self.limits.limit_step(shaft, self.play.goal(goal))
        when = t_now if t_now is not None and math.isfinite(t_now) else t_s
        if goal is not None and when is not None:
            self.rest.commanded(when)
            self.shaft.commanded(when, goal)
        return goal

    def _shaft(self, t_s: float, pan: float) -> float:
        """The slave's pan at t_s, `pan` the frame's: the resting motor's mean, else the noisy encoder's model."""
        rest = self.rest.at(t_s, pan)
        return rest if rest != pan else self.shaft.at(t_s, pan)

    def _target(self, pan_at_capture: float, offset_px: float, focal_px: float, confident: bool, centre_px: float,
                t_s: float | None, t_now: float | None, slave: int | None, master: int | None,
                fovea: tuple[int, int] | None, doubt: bool, textured: bool, width_px: int | None,
                background: Verdict | None) -> float | None:
        """target(), the pan as the rest gives it."""
        d, a = self.doubt, None
        if fovea != self.fovea:
            self.fovea, self.fovea_new = fovea, True
        if not doubt:
            return self._aim(pan_at_capture, offset_px, focal_px, confident, centre_px, t_s, t_now)
        if t_s is not None and math.isfinite(t_s) and math.isfinite(pan_at_capture):
            t_s, pan_at_capture = d.shift(t_s, pan_at_capture)  # (a camera named late: as its image shows it)
            ok = confident and math.isfinite(offset_px) and math.isfinite(focal_px) and focal_px > 0
            a = pixels_to_angle(offset_px, focal_px, centre_px) if ok else None
            fault, told = d.fault, d.focal.ratio is None
            d.observe(t_s, pan_at_capture, a, slave, master, fovea, background=background,
                      off_axis=centre_px / focal_px if ok and math.isfinite(centre_px) else 0.0)
            if d.fault == fault and told and d.focal.ratio is not None:
                self._refocus(d.focal.ratio)
            elif (d.fault, d.focal.ratio is None) != (fault, told):
                self.reset()  # what the filter learnt while the image lied (or before the fault) says nothing now
            if d.focal.ratio is not None and math.isfinite(focal_px):
                focal_px = focal_px * d.focal.ratio  # the measured focal length
        now = t_now if t_now is not None and math.isfinite(t_now) else t_s
        if d.fault is not None:
            self.search.reset()
            self.turned = False
            return d.gate(pan_at_capture, None, now if now is not None else 0.0)
        if t_s is not None and math.isfinite(t_s):
            was = self.search.searching
            self.turned = (background is not None and background.turned) or (self.turned and was)
            leash = None  # a search's first move stays within LEASH_DEG (and the doubt's first leash where the image
            # never followed) until its background turned with the motor: a camera that lies is named over that look
            # (reversed from the start, or frozen, slipping since it followed), not over a sweep's step of 19 deg
            if not self.turned:
                look, first = math.radians(LEASH_DEG), math.radians(UNTRUSTED_DEG)
                lo, hi = pan_at_capture - look, pan_at_capture + look
                if not d.trusted and d.anchor is not None:
                    lo, hi = max(lo, d.anchor - first), min(hi, d.anchor + first)
                leash = (lo, hi)
            look = self.search.observe(t_s, pan_at_capture, confident, textured, offset_px, focal_px, width_px,
                                       self.limits.lo, self.limits.hi, leash, None if a is None else pan_at_capture + a)
            if look is not None:
                look = self.limits.limit_step(pan_at_capture, look)
                d.stall.commanded(pan_at_capture, look, now)  # (a motor that never moves while it searches is stalled)
                return look
            if was and not self.search.searching:
                d.relocate(pan_at_capture)  # found: from here, not yet trusted
                self.reset()
        goal = self._aim(pan_at_capture, offset_px, focal_px, confident, centre_px, t_s, t_now)
        if goal is None and confident and now is not None:
            d.stall.commanded(pan_at_capture, pan_at_capture, now)  # content where it is: no move asked of the motor
        if goal is None or now is None:
            return goal
        gated = d.gate(pan_at_capture, goal, now)
        return None if gated is None else self.limits.limit_step(pan_at_capture, gated)

    def status(self) -> dict:
        """For the reducer's status: the doubt's fields, the search's, the encoder's noise (vergence.head.shaft) and the
        play (vergence.head.play)."""
        return {**self.doubt.status(), **self.search.status(), **self.shaft.status(), **self.play.status()}

    def _replay(self, moved: list[tuple[float, float]]) -> None:
        """A new play: the targets learnt (each a frame's pan plus its offset's angle) move as their frames' camera pans
        do (vergence.head.play.Play.replay), not the predictors anew (they would chase the target for a period)."""
        if not moved:
            return
        ts, ds = [m[0] for m in moved], [m[1] for m in moved]
        if self.periodic is not None:
            self.periodic.move(ts, ds)
        if self.predictor is not None and self.predictor.t is not None:
            self.predictor.x += float(np.interp(self.predictor.t, ts, ds))
        self.last_goal = None

    def _refocus(self, ratio: float) -> None:
        """The focal length named: the periodic predictor's targets (each a frame's pan plus its offset's angle at the
        focal length told) are taken to the measured one, not learnt anew (afresh, the loop chased the target for a
        period: docs/FAULTS.md, "The focal length named"); the rate filter and the referee start again."""
        if self.periodic is None or not self.play.past:
            self.reset()
            return
        self.periodic.refocus([q[0] for q in self.play.past], [q[2] for q in self.play.past], ratio)
        self.referee.reset()
        self.predictor = None  # (made again at the measured focal length: its noise and gate are pixels)
        self.last_goal = self.t_confident = None

    def reset(self) -> None:
        """Forget the target's estimate (a fault began or ended): the next decision starts afresh."""
        self.predictor = None  # (made again at the next decision's focal length: its noise and gate are pixels)
        if self.periodic is not None:
            self.periodic.reset()
            self.referee.reset()
        self.last_goal = None
        self.t_confident = None

    def _aim(self, pan_at_capture: float, offset_px: float, focal_px: float, confident: bool, centre_px: float,
             t_s: float | None, t_now: float | None) -> float | None:
        """The controller's set-point, before the doubt's leash (target's arguments)."""
        if self.s.mode == "predictive" and t_s is not None and math.isfinite(t_s):
            # (an image older than MAX_AGE_S is not believed: vergence.head.timing)
            now = t_s if t_now is None or not math.isfinite(t_now) else min(max(t_s, t_now), t_s + MAX_AGE_S)
            return self._predictive(pan_at_capture, offset_px, focal_px, confident, centre_px, t_s, now)
        if not confident or not all(math.isfinite(v) for v in (pan_at_capture, offset_px, focal_px)):
            return None
        if focal_px <= 0 or abs(offset_px) < self.s.dead_band_px:
            return None
        step = self._gain(t_s, t_now) * pixels_to_angle(offset_px, focal_px, centre_px)
        if abs(step) < self.limits.dead_band_rad:
            return None
        return self._bounded(pan_at_capture, step)

    def _gain(self, t_s: float | None, t_now: float | None) -> float:
        """p's gain: [control] gain, but at most 1 for an image older than LATE_S when its command goes out.
        Referred to the pan at its exposure, each command is (1 - g) x that pan + g x the target there: at
        gain <= 1 a low-pass of the target, stable at any latency; above 1 it overshoots, and the motor's own
        lag makes that grow with the latency (gain 1.9 at 100 ms never converged on a still target)."""
        g = self.s.gain
        if g > 1 and t_s is not None and t_now is not None and t_now - t_s > LATE_S:
            if not self.gain_lowered:
                log.warning("p controller: gain %.2f lowered to 1 for images %.0f ms old (above 1 the loop "
                            "overshoots more the older the image)", g, (t_now - t_s) * 1e3)
            self.gain_lowered += 1
            return 1.0
        return g

    def _predictive(self, pan: float, offset_px: float, focal_px: float, confident: bool, centre_px: float,
                    t: float, now: float) -> float | None:
        if not (math.isfinite(pan) and math.isfinite(focal_px) and focal_px > 0):
            return None
        if self.predictor is None:
            one = math.atan(1.0 / focal_px)
            self.predictor = Predictor(q=math.radians(self.s.accel_deg_s2) ** 2, r=(self.s.noise_px * one) ** 2,
                                       gate=self.s.gate_px * one, vmax=math.radians(self.s.max_rate_deg_s))
        f = self.predictor
        if self.periodic is None and self.s.periodic:
            self.periodic, self.referee = Periodic(), Referee(len(PREDICTORS))
        fast = False
        if self.t_prev is not None and 0 < t - self.t_prev < PERIOD_GAP_S:
            dt = t - self.t_prev
            self.period = dt if self.period is None else (1 - PERIOD_ALPHA) * self.period + PERIOD_ALPHA * dt
            fast = abs(pan - self.pan_prev) > math.radians(FAST_DEG)
        self.t_prev, self.pan_prev = t, pan
        # a set-point holds until the next decision: aim at the middle of that interval, from when the motor
        # acts on this command (now + lead_s), however old the image it comes from
        at = now + self.s.lead_s + 0.5 * (self.period or 0.0)
        if confident and math.isfinite(offset_px):
            z = pan + pixels_to_angle(offset_px, focal_px, centre_px)
            if self.fovea_new:
                # a new point's first decision: where it is off the prediction, it is another target (another depth),
                # not the target's motion (a jump under gate_px was learnt as a rate: a 66 ms loop ran past a fixate's
                # new point by up to 22 px); near it, the same target (a look_at streamed along an object)
                self.fovea_new = False
                if f.t is not None and abs(z - f.at(t)) > NEW_TARGET_PX * math.atan(1.0 / focal_px):
                    f.jump(t, z)
                    if self.periodic is not None:
                        self.periodic.reset()
                        self.referee.reset()
            restarts = f.restarts
            f.update(t, z)
            self.t_confident = t
            if self.periodic is not None:
                if f.restarts != restarts:  # a jump: what the target did before it says nothing now
                    self.periodic.reset()
                    self.referee.reset()
                if not fast:
                    self.referee.measured(t, z)
                    self.periodic.add(t, z)
            # the rate, less min_rate_deg_s (soft threshold): the noise of a still target's rate estimate
            # (whole-tick encoder readings during small moves, a hesitating matcher) is not extrapolated
            vmin = math.radians(self.s.min_rate_deg_s)
            v = math.copysign(max(0.0, abs(f.v) - vmin), f.v)
            goal = f.x + v * (at - f.t)
            if self.periodic is not None:
                preds = [f.x, goal, self.periodic.predict(at)]
                self.referee.predicted(at, preds)
                goal = self.referee.blend(preds)
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
