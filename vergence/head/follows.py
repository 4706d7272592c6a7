"""Whether the slave's image follows the motor, as one judgement: r, the image's motion over the motor's (at the
frames' focal length: 1 where all is right), judged the same by the loop's check pair by pair (vergence.head.doubt)
and by `vergence calibrate` over its steps (vergence.head.calibrate), and what to check for each fault, in the same
words wherever it is named (the reducer's status, /diagnostics, the monitor, calibrate's and latency's refusals)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..choices import Fault

__all__ = ["ADVICE", "FOLLOWS_MAX", "FOLLOWS_MIN", "REVERSED_MAX", "FOCAL_OFF", "SAME_PAN_DEG", "Held", "Seen",
           "focal_off", "note", "verdict"]

FOLLOWS_MIN, FOLLOWS_MAX = 0.5, 2.2  # r in this range: the image follows (r: image motion / motor motion)
REVERSED_MAX = -0.35  # r at most this: the camera turns the other way
FOCAL_OFF = 0.2  # |r - 1| above this: the focal length is off
SAME_PAN_DEG = 0.1  # the motor is at one pan (at rest: a fault's anchor, a probe's reference, Held's run) within this

ADVICE = {
    Fault.SLAVE_FROZEN: "the slave's image does not follow the motor: a frozen slave camera (the driver repeating "
                        "its last image) or a slipping coupling between the motor and the camera; check the "
                        "camera's cable and driver, and the coupling (or images more than 0.25 s later than their "
                        "stamps: stamp them at the exposure or set [camera] latency_s; `vergence latency` measures "
                        "up to 0.7 s)",
    Fault.REVERSED: "the slave's image moves against the motor: the motor turns the other way than the encoder "
                    "says; flip [actuator.motor] direction (or the camera's mounting) and restart",
    Fault.STALLED: "the motor does not follow its commands: stalled, jammed, or its torque off (an overload); "
                   "check the motor's power, its torque and what blocks it",
    Fault.MASTER_FROZEN: "the master camera repeats the same image: a frozen master camera; check its cable and "
                         "driver",
}


def verdict(r: float) -> Fault | None:
    """What r, the slave image's motion over the motor's (as the frames' focal length predicts it), says of the
    camera: Fault.REVERSED at or below REVERSED_MAX (it turns the other way than the encoder says),
    Fault.SLAVE_FROZEN below FOLLOWS_MIN (it does not follow: a frozen camera, a slipping coupling), None where it
    follows (r far from 1: the focal length is off, focal_off). The one judgement of the check here, pair by pair,
    and of `vergence calibrate` on its fit of the steps (vergence.head.calibrate)."""
    if r <= REVERSED_MAX:
        return Fault.REVERSED
    return Fault.SLAVE_FROZEN if r < FOLLOWS_MIN else None


def note(fault: Fault | None, focal_ratio: float | None, late_s: float | None) -> str:
    """What to check, in one line: the fault's advice, or else what the check measured off (the focal length's ratio,
    a camera later than its frames say); "" where all is right."""
    if fault is not None:
        return f"{fault}: {ADVICE[fault]}"
    notes = []
    if focal_ratio is not None:
        notes.append(f"focal length off: the image moves {focal_ratio:.2f} x what [rig] focal_px predicts")
    if late_s is not None:
        notes.append(f"camera late: the slave's image follows the motor {late_s * 1e3:.0f} ms later than its frames "
                     "say; set [camera] latency_s (`vergence latency` measures it) or stamp the images at their "
                     "exposure")
    return "; ".join(notes)


def focal_off(r: float) -> bool:
    """r (as verdict's) far enough from 1 to name the focal length off."""
    return abs(r - 1) > FOCAL_OFF


def fail_kind(r: float) -> str:
    """The kind of a pair that did not follow (vergence.head.doubt): "reversed" where r <= 2 REVERSED_MAX (-0.7: a
    slipping camera's pair, its target's motion mispredicted, reaches -0.6), else "frozen"."""
    return "reversed" if r <= 2 * REVERSED_MAX else "frozen"


@dataclass
class Seen:
    """One confident decision, as the check keeps it (vergence.head.doubt)."""
    t: float  # the slave's exposure, s
    pan: float  # the slave's pan then, rad
    a: float  # the angle of the measured offset, rad
    u: float = 0.0  # how far off pan may be (a late camera's pan, read between two frames' pans), rad

    @property
    def z(self) -> float:
        return self.pan + self.a  # where the target is, as this decision says


class Held:
    """The target's own motion while the motor holds still (during a fault, at its anchor; before the leash's probes
    of vergence.head.doubt, at the motor's last rest): the offset's angle over the last WINDOW_S, a least-squares
    parabola where one fits (a target turning), else a line where one does; none with too few frames or off both.
    Where the motor does not move, the offset moves with the target only, whether the camera follows the motor or
    not, so a probe's image motion less the target's is the probe's own (a probe read without it during pursuit took
    the target's motion for the camera's: a slipping camera's fault cleared by a probe that had not moved it; read
    without the parabola, the same at a sine's turn, and the chase then ran 4.7 deg)."""

    WINDOW_S, MIN = 0.25, 4
    RESID_RAD = math.radians(0.1)  # a line's (a parabola's) RMS residual at most this (0.1 deg: 0.9 px at f 500)

    def __init__(self):
        self.seen: list[tuple[float, float]] = []  # (t, a) at the anchor
        self.pan: float | None = None  # the run's first pan (None: not kept)

    def add(self, t: float, a: float, pan: float | None = None) -> None:
        """A frame's offset angle a at t; with its pan, a frame that moved starts a new run (the motor at rest)."""
        if pan is not None and not self._here(pan):  # (a frame SAME_PAN_DEG from the run's first pan: a new run)
            self.seen, self.pan = [], pan
        self.seen = [s for s in self.seen if t - s[0] <= self.WINDOW_S] + [(t, a)]

    def ratios(self, t0: float, pan0: float, a0: float, t: float, pan: float, a: float) -> tuple[float, ...]:
        """A probe's r from (t0, pan0, a0) at the anchor to (t, pan, a): less the target's own motion where that was
        a line or a parabola (motion), else as seen."""
        dp, m = pan - pan0, self.motion(t0, t)
        seen = -(a - a0) / dp
        return (seen,) if m is None else (-(a - a0 - m) / dp, min(seen, FOLLOWS_MAX))

    def motion(self, t0: float, t: float, pan0: float | None = None) -> float | None:
        """The target's own change of the offset's angle from t0 to t (rad), along a parabola through the last WINDOW_S
        (MIN + 1 frames or more; MIN: a line), where that leaves at most RESID_RAD RMS; None off it
        (a target that stepped: no motion to take out; the probe is read as seen). A parabola: a target turns or
        speeds up within a probe's time (the near turn of a 0.4 Hz sine at 0.5-1 m, 27 deg/s^2: a line through the
        turn, within 0.1 deg of it, missed 0.27 deg of the target's motion over a 0.5 deg probe's 0.09 s). With pan0
        (the reference's pan), None where that is not the run's (frames added with their pans)."""
        fit = self._fit(pan0)
        return None if fit is None else float(np.polyval(fit[0], t - fit[1]) - np.polyval(fit[0], t0 - fit[1]))

    def fits(self, pan0: float | None = None) -> bool:
        """Whether motion() has a fit to give (at pan0: see there)."""
        return self._fit(pan0) is not None

    def _fit(self, pan0: float | None) -> tuple[np.ndarray, float] | None:
        """The parabola's (or line's) coefficients over the run and the times' mean they are about (None: too few
        frames, off both, or pan0 not this run's pan)."""
        n = len(self.seen)
        if n < self.MIN or (pan0 is not None and not self._here(pan0)):
            return None
        ts, offs = np.array(self.seen).T
        mt = ts.mean()
        c = np.polyfit(ts - mt, offs, 2 if n > self.MIN else 1)  # (off a parabola, off its line too)
        return None if np.mean((np.polyval(c, ts - mt) - offs) ** 2) > self.RESID_RAD ** 2 else (c, mt)

    def _here(self, pan: float) -> bool:  # the run's pan, within SAME_PAN_DEG
        return self.pan is not None and abs(pan - self.pan) <= math.radians(SAME_PAN_DEG)

