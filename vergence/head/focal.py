"""The focal length's ratio (issue #35): how far the image moves per radian of the motor, over what [rig] focal_px
predicts. Named from the check's fast pairs (vergence.head.doubt: the median of FOCAL_PAIRS precise ones or more,
where the middle half of them agree: a fast target turning, whose rate the check's learnt one lags, spreads them), or,
until then, from pursuit: the motor's own small moves while it follows a target, where no move is fast enough for a
pair to be judged.

Each confident decision says a = atan(offset / focal_px) = rho (T - pan) to first order: T the target's pan, pan the
slave's at its exposure, rho the image's motion over the motor's (1 where focal_px is right; 1.6 where the images
are taken at 1.6 x focal_px). Over the last WINDOW_S the target's pan is smooth (a cubic in time), the motor's is
not: its corrections, and the oscillation a wrong gain makes, move it back and forth. So a least-squares fit of a on
a cubic in t and -pan reads rho off the part of the motor's motion no cubic explains. A fit counts where that part
is at least MOTION_DEG (RMS: against the encoder's noise, which biases rho towards 0 as the square of their ratio)
and rho's standard error at most SE. The median of the last KEEP such fits (FITS at least) names the ratio where it
is off (vergence.head.follows.focal_off) and above 1: a gain too high is what makes the loop oscillate, and a camera
later than its frames say reads as a ratio below 1 (docs/FAULTS.md has the figures). A fovea off the principal point
reads a ratio off the focal length's (the angles are read with the focal length told): each pair's and the pursuit's
are taken back to the axis (on_axis)."""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Sequence

import numpy as np

from .follows import FOCAL_OFF, FOLLOWS_MAX, focal_off

__all__ = ["Focal", "Pursuit", "on_axis"]

log = logging.getLogger("vergence.doubt")

FOCAL_PAIRS = 6  # precise fast pairs before their median names the ratio (it then stands over pursuit's) ...
SPREAD = 0.2  # ... where the middle half of them spans at most this x the median (the focal's 1.6: 0.06)

WINDOW_S = 0.6  # the fits' span: a target's pan is a cubic over it
MIN_SAMPLES = 12  # decisions in a window before it is fitted
EVERY = 3  # a fit every this many decisions
MOTION_DEG = 0.25  # the motor's motion no cubic explains, RMS, for a fit to count
SE = 0.05  # the largest standard error of rho of a fit that counts
FITS = 4  # fits that count before the ratio is named ...
KEEP = 9  # ... from the median of the last this many (one window of a transient can be 20 % off)


class Pursuit:
    """add() every confident decision (its exposure t in s, the slave's pan then and the offset's angle a, rad);
    `ratio` is the image's motion over the motor's once named (None before). clear() after a fault or a new
    target: what the window holds says nothing of the next one."""

    def __init__(self):
        self.seen: deque[tuple[float, float, float]] = deque()
        self.fits: list[float] = []
        self.ratio: float | None = None
        self.n = 0

    def clear(self) -> None:
        self.seen.clear()
        self.fits.clear()

    def add(self, t: float, pan: float, a: float) -> float | None:
        seen = self.seen
        if seen and t < seen[-1][0]:  # out of order (Doubt.observe never gives one): every older one looked at
            self.seen = seen = deque(s for s in seen if s[0] > t - WINDOW_S)
        while seen and seen[0][0] <= t - WINDOW_S:  # in order, the ones past the window are the oldest
            seen.popleft()
        seen.append((t, pan, a))
        self.n += 1
        if len(self.seen) < MIN_SAMPLES or self.n % EVERY:
            return self.ratio
        rho = fit(self.seen)
        if rho is None:
            return self.ratio
        self.fits = (self.fits + [rho])[-KEEP:]
        if len(self.fits) >= FITS:
            med = sorted(self.fits)[len(self.fits) // 2]
            # above 1 only: a camera later than its frames say reads as a ratio below 1 (the motor's wobble seen a
            # phase late), and a ratio below 1 only slows the loop; the fast pairs name those. Once named, it stays
            # until the median is within half of FOCAL_OFF of 1 (each naming starts the controller's filters afresh)
            off = focal_off(med) if self.ratio is None else med - 1 > FOCAL_OFF / 2
            self.ratio = med if off and 1 < med <= FOLLOWS_MAX else None
        return self.ratio


class Focal:
    """The ratio as named (`ratio`, None while the focal length is right or not yet known): pair(r) every precise
    fast pair's r, add() every confident decision (Pursuit.add), clear() after a fault or a new target."""

    def __init__(self):
        self.pairs: list[float] = []
        self.pursuit = Pursuit()
        self.ratio: float | None = None
        self.off_axis = 0.0  # the fovea's column off the principal point over the focal length told (on_axis())

    def pair(self, r: float) -> None:
        self.pairs = (self.pairs + [on_axis(r, self.off_axis)])[-4 * FOCAL_PAIRS:]
        self._name()

    def add(self, t: float, pan: float, a: float) -> None:
        self.pursuit.add(t, pan, a)
        self._name()

    def clear(self) -> None:
        self.pursuit.clear()

    def _name(self) -> None:
        s, n = sorted(self.pairs), len(self.pairs)
        if n >= FOCAL_PAIRS and s[3 * n // 4] - s[n // 4] <= SPREAD * s[n // 2]:  # (the middle half agree)
            ratio = s[n // 2] if focal_off(s[n // 2]) else None
        else:
            ratio = None if self.pursuit.ratio is None else on_axis(self.pursuit.ratio, self.off_axis)
        if ratio is not None and self.ratio is None:
            log.warning("the focal length is off: the image moves %.2f x what focal_px predicts", ratio)
        self.ratio = ratio


def on_axis(r: float, u: float) -> float:
    """The focal length's ratio k from r, the image's motion over the motor's as read at a fovea u x the focal length
    told off the principal point: the angles read with the focal length told, a column there moves k (1 + u^2) / (1 +
    (u / k)^2) x what they predict, so k is the root of k^2 - r (1 + u^2) k + u^2 = 0 near r (k = r on the axis; 200
    px off at 500 told and 800 true, r reads 1.466 for 1.6: the outside check's Cones and Tsukuba, docs/FAULTS.md)."""
    b = r * (1 + u * u)
    d = b * b - 4 * u * u
    return (b + math.sqrt(d)) / 2 if d >= 0 and r > 0 else r


def fit(seen: Sequence[tuple[float, float, float]]) -> float | None:
    """rho of one window, or None where it does not count (see the module's text)."""
    t, pan, a = (np.array(c) for c in zip(*seen))
    tc = (t - t.mean()) / WINDOW_S
    cubic = np.column_stack([tc ** k for k in range(4)])
    rest = pan - cubic @ np.linalg.lstsq(cubic, pan, rcond=None)[0]  # the motor's motion no cubic explains
    if math.degrees(float(np.sqrt(np.mean(rest ** 2)))) < MOTION_DEG:
        return None
    design = np.column_stack([cubic, -pan])
    sol = np.linalg.lstsq(design, a, rcond=None)[0]
    resid = a - design @ sol
    dof = len(a) - design.shape[1]
    # rho's standard error: its own column's, net of the cubic's (the residual's variance over rest's energy)
    se = math.sqrt(float(resid @ resid) / dof / float(rest @ rest))
    return float(sol[-1]) if se <= SE else None
