"""Ground truth of the simulated rig for a fovea anywhere in the master view (not only at its centre): the
slave pan that converges on it and the disparity (hence the depth) of the point it shows; truth_pan_at gives
the pan for either rig (the still one and the moving target) at a time, which the capture's sim source
stamps on every frame for the fovea where `vergence fixate` has moved it."""

from __future__ import annotations

import math

import numpy as np

from .optics import homography
from .moving import MovingRig
from .rig import Rig

__all__ = ["truth_at", "truth_pan_at"]


def _project(h: np.ndarray, x: float, y: float) -> tuple[float, float]:
    p = h @ np.array([x, y, 1.0])
    return float(p[0] / p[2]), float(p[1] / p[2])


def truth_at(rig: Rig, x: float, y: float) -> tuple[float, float]:
    """(slave pan in radians, disparity in px) for the fovea at (x, y) of the master view: the pan at which
    the slave shows the point on the same column x, and the point's disparity in the rectified pair (its depth
    is b f / d). (NaN, NaN) where the disparity is unknown (no map and not the fixation point) or the point
    is off the source pair."""
    hm = homography(rig.focal_px, rig.src_size, rig.size, rig.master_pan_rad, rig.tilt_rad, rig.gimbal)
    xl, yl = _project(np.linalg.inv(hm), x, y)
    ws, hs = rig.src_size
    if rig.disparity_map is not None:
        ix, iy = int(round(xl)), int(round(yl))
        if not (0 <= ix < ws and 0 <= iy < hs):
            return math.nan, math.nan
        d = float(rig.disparity_map[iy, ix])
    elif (int(round(xl)), int(round(yl))) == rig.fixation:
        d = rig.disparity
    else:
        return math.nan, math.nan
    if not math.isfinite(d):
        return math.nan, math.nan
    xr = xl - d

    def column(pan: float) -> float:  # where the slave at this pan shows the point; decreases with the pan
        return _project(homography(rig.focal_px, rig.src_size, rig.size, pan, rig.slave_tilt_rad, rig.gimbal),
                        xr, yl)[0]

    lo, hi = -0.8, 0.8  # the head's pan range (45 deg) and more; much wider, the point can fall behind the camera
    if not column(lo) >= x >= column(hi):
        return math.nan, d
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if column(mid) > x:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi), d


def truth_pan_at(rig: Rig | MovingRig, x: float, y: float, t: float = 0.0) -> float:
    """The slave pan (radians) that converges on the point the master's pixel (x, y) shows at time t (seconds,
    the moving target's clock): for the still rig truth_at's, for the moving one the target's point (or the
    background's, where the fovea is off the target) seen on the slave's column x. NaN where unknown."""
    if isinstance(rig, MovingRig):
        return rig.truth_at(x, y, t)
    return truth_at(rig, x, y)[0]
