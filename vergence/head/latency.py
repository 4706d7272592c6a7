"""Measuring a camera's latency on the head (`vergence latency`): move the slave through a known motion on a
still textured scene, and find the instant at which the image offsets the network measured agree best with
the motor's own position history.

On a still scene with a fixed master, each decision's offset is f tan(truth - pan(t)) with t the instant the
slave's image was exposed: a linear function of the slave's pan then (offset ~ a + b pan, b about -f). The
frames carry a stamp, their exposure as the capture believes it; the true exposure is delta earlier. For
each delta on a grid the offsets are regressed on the motor's pan at (stamp - delta); the delta that leaves
the least residual is the stamps' error, and the latency is the read time less the stamp, plus delta. Its
uncertainty is the spread of delta over bootstrap resamples of the decisions. A fixed master on a still scene
says nothing of the master's own timing: the skew between the cameras cannot be told this way.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["LatencyFit", "LatencyError", "fit_latency", "motion_plan"]


class LatencyError(ValueError):
    """The measurement cannot be made; the message says why and what to do. slope and r2: where the motor moved
    but the offsets did not follow it, the best fit's (px/rad, and its share of the offsets' variance)."""

    def __init__(self, message: str, slope: float | None = None, r2: float | None = None):
        super().__init__(message)
        self.slope, self.r2 = slope, r2


@dataclass(frozen=True)
class LatencyFit:
    """latency_s: the slave camera's exposure-to-read latency; sigma_s: its one sigma (bootstrap); delta_s:
    how much earlier than their stamps the images were exposed; stamped_s: the read time less the stamp (the
    latency the capture assumed); slope: px per radian (about -f); r2: how much of the offsets' variance the
    motor's motion explains; n: the decisions used."""

    latency_s: float
    sigma_s: float
    delta_s: float
    stamped_s: float
    slope: float
    r2: float
    n: int


def motion_plan(p0: float, lo: float, hi: float, amplitude_rad: float, hold_s: float) -> list[tuple[float, float]]:
    """[(seconds from the start, pan)]: steps of +-amplitude (and half of it) about p0, each held hold_s, then
    back to p0; every pan within [lo, hi] (the motor's soft limits)."""
    a = min(amplitude_rad, math.radians(1.0))
    out = []
    for i, k in enumerate((1.0, -1.0, 0.5, -0.5, 1.0, -0.5, 0.0)):
        out.append((i * hold_s, min(hi, max(lo, p0 + k * a))))
    return out


def _residual(t: np.ndarray, off: np.ndarray, st: np.ndarray, sp: np.ndarray, delta: float):
    """(sum of squared residuals, slope, r2) of offsets regressed on the pan at t - delta (the decisions whose
    instant lies inside the history), or None with fewer than 10 of them."""
    at = t - delta
    inside = (at >= st[0]) & (at <= st[-1])
    if inside.sum() < 10:
        return None
    pan = np.interp(at[inside], st, sp)
    y = off[inside]
    x = np.stack([np.ones_like(pan), pan], 1)
    coef, *_ = np.linalg.lstsq(x, y, rcond=None)
    ss = float(np.sum((x @ coef - y) ** 2))
    tot = float(np.sum((y - y.mean()) ** 2))
    # per decision used, so that deltas that leave a few decisions out are not favoured
    return ss / inside.sum(), float(coef[1]), 1.0 - ss / tot if tot > 0 else 0.0


def _best(t, off, st, sp, grid) -> tuple[float, float, float]:
    res = [_residual(t, off, st, sp, d) for d in grid]
    ok = [(r[0], d, r[1], r[2]) for r, d in zip(res, grid) if r is not None]
    if not ok:
        raise LatencyError("the decisions and the motor's history do not overlap in time")
    i = min(range(len(ok)), key=lambda k: ok[k][0])
    ss, d, slope, r2 = ok[i]
    if 0 < i < len(ok) - 1:  # a parabola through the neighbours
        (a, _, _, _), (c, _, _, _) = ok[i - 1], ok[i + 1]
        den = a - 2 * ss + c
        if den > 0:
            d += 0.5 * (a - c) / den * (ok[i + 1][1] - d)
    return d, slope, r2


def fit_latency(decisions: list[tuple[int, int, float]], states: list[tuple[int, float]],
                search_s: tuple[float, float] = (-0.3, 0.7), step_s: float = 0.001, boots: int = 60,
                seed: int = 0, either_sign: bool = False) -> LatencyFit:
    """decisions: [(stamp ns, read ns, offset px)] of confident decisions; states: [(t ns, pan rad)] of the
    motor, in its own time. Raises LatencyError where the motor did not move or the offsets do not follow it
    (no texture, a moving scene); with either_sign, offsets that follow it the other way (a positive slope, a
    camera turning against the motor) are fitted too, for the caller to name."""
    if len(decisions) < 20:
        raise LatencyError(f"only {len(decisions)} confident decisions: the network abstains on this scene "
                           "(point the master at a still, textured scene) or no rig is running")
    d = np.array(sorted(decisions), float)
    s = np.array(sorted(states), float)
    if len(s) < 10:
        raise LatencyError(f"only {len(s)} motor states: is an actuator running on this rig?")
    if np.ptp(s[:, 1]) < math.radians(0.1):
        raise LatencyError(f"the motor moved {math.degrees(np.ptp(s[:, 1])):.3f} deg: it does not follow "
                           "the commands (torque off, at a limit, or another rig's motor)")
    t0 = d[0, 0]
    t, off = (d[:, 0] - t0) / 1e9, d[:, 2]
    st, sp = (s[:, 0] - t0) / 1e9, s[:, 1]
    grid = np.arange(search_s[0], search_s[1] + step_s / 2, step_s)
    delta, slope, r2 = _best(t, off, st, sp, grid)
    if r2 < 0.5 or (slope >= 0 and not either_sign):
        raise LatencyError(f"the offsets do not follow the motor (r2 {r2:.2f}, slope {slope:.0f} px/rad): the "
                           "scene must be still and textured, the master fixed", slope, r2)
    rng = np.random.default_rng(seed)
    near = np.arange(delta - 0.03, delta + 0.03 + step_s / 4, step_s / 2)
    spread = []
    for _ in range(boots):
        i = np.sort(rng.integers(0, len(t), len(t)))
        try:
            spread.append(_best(t[i], off[i], st, sp, near)[0])
        except LatencyError:
            continue
    stamped = float(np.median(d[:, 1] - d[:, 0])) / 1e9
    return LatencyFit(latency_s=stamped + delta, sigma_s=float(np.std(spread)) if spread else math.nan,
                      delta_s=delta, stamped_s=stamped, slope=slope, r2=r2, n=len(t))
