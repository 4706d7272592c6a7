"""The distance of the fixated point: from the two cameras' pans (and the decision's sub-pixel residual) to
Z, and its one-sigma uncertainty from the decision's sub-pixel precision.

The rig model is vergence.sim.rig's: two pinhole cameras of focal length f (px), each with its principal point
(the frame's: a camera_info's, the settings', else the view centre (W // 2, H // 2); issue #36), rotating about
their optical centres, which are b metres apart on the baseline (the head's x axis; the slave b to the right of a
left master, to the left of a right one). Pan 0 and tilt 0 look straight ahead, parallel to each other (a
rectified pair); a positive pan turns toward increasing image x, a positive tilt toward decreasing y. Z is the
point's depth along the head's forward axis (perpendicular to the baseline), the Z of a rectified pair: Z = b f / d
for a disparity of d px.

A pixel (u, v) off the principal point of a camera at (pan p, tilt t) sees along the ray R (u, v, f):
- helmholtz, R = R_x(t) R_y(p) (both cameras pan on one tilting platform): in the tilted plane the ray is
  q = R_y(p) (u, v, f) and its azimuth tangent T = q_x / q_z. The two rays meet at depth
  P_z = s b / (T_m - T_s) within the tilted plane (s = +1 for a left master, -1 for a right one), height
  P_y = P_z q_y / q_z, and Z = P_z cos t + P_y sin t. At the view centres (u = v = 0):
  Z = s b cos t / (tan p_m - tan p_s).
- fick, R = R_y(p) R_x(t) (each camera tilts on its own pan joint): the world ray's azimuth tangent T = x / z
  gives Z = s b / (T_m - T_s) directly; at the view centres Z = s b / (tan p_m - tan p_s).

The master's pixel is the fovea centre (x, y); the slave's is where the decision found it, (x + offset_px,
y + v_shift), so a slave off by a fraction of a pixel, or by a motor tick (0.088 deg at f = 500 px is 0.77 px),
still gives the exact depth. Its sigma: dZ = Z^2 / (b f) * sigma_d (from Z = b f / d), with sigma_d the
sub-pixel sigma of the disparity (disparity_sigma)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..choices import Gimbal

__all__ = ["GIMBALS", "CONVERGED_PX", "SIGMA_FLOOR_PX", "SIGMA_CURVATURE", "azimuth_tan", "depth_from_pans",
           "depth_sigma", "disparity_sigma", "Depth", "fixated_depth", "depth_from_disparity"]

GIMBALS = tuple(Gimbal)  # (vergence.choices)
CONVERGED_PX = 1.0  # |offset_px| at or under this: the slave is converged on the fovea (the loop's tolerance)
# The sub-pixel sigma of a decision, sigma_d = sqrt(FLOOR^2 + (CURVATURE / c)^2) px, c the winning peak's
# curvature per fovea pixel. Fitted on 560 confident points of the four Middlebury pairs (draw seed 7) so that
# 92 % of the disparity errors lie within 2 sigma; checked on other draws in tests/vergence/head/test_depth.py.
SIGMA_FLOOR_PX = 0.14
SIGMA_CURVATURE = 1.7


def azimuth_tan(pan_rad: float, tilt_rad: float, u: float, v: float, f: float, gimbal: str = "helmholtz"):
    """(T, elevation ratio): the azimuth tangent of the ray through pixel (u, v) off the principal point of a
    camera at (pan, tilt), in the tilted plane (helmholtz) or the world (fick), and q_y / q_z (helmholtz: the
    ray's height per depth in the tilted plane; fick: 0, unused)."""
    cp, sp = math.cos(pan_rad), math.sin(pan_rad)
    if gimbal == "helmholtz":
        qx, qy, qz = u * cp + f * sp, v, -u * sp + f * cp
        return qx / qz, qy / qz
    if gimbal == "fick":
        ct, st = math.cos(tilt_rad), math.sin(tilt_rad)
        c = v * st + f * ct  # the depth component of R_x(t) (u, v, f); its height is not needed
        return (u * cp + c * sp) / (-u * sp + c * cp), 0.0
    raise ValueError(f"gimbal={gimbal!r}: must be one of {', '.join(GIMBALS)}")


def depth_from_pans(master_pan_rad: float, slave_pan_rad: float, baseline_m: float, focal_px: float, *,
                    tilt_rad: float = 0.0, master_px: tuple[float, float] = (0.0, 0.0),
                    slave_px: tuple[float, float] = (0.0, 0.0), gimbal: str = "helmholtz",
                    master: str = "left", axis_m: float = 0.0) -> float:
    """Z (m) of the point seen at master_px = (u, v) off the master's principal point and slave_px off the
    slave's (both default: the view centres), the cameras at the given pans and common tilt. NaN when the
    rays do not converge in front of the head (parallel or diverging). axis_m: the slave's pan axis that far
    behind its optical centre, which then turns on a circle about it: at pan p it sits axis_m sin p sideways and
    axis_m (1 - cos p) back of where it sits at pan 0."""
    tm, em = azimuth_tan(master_pan_rad, tilt_rad, master_px[0], master_px[1], focal_px, gimbal)
    ts, _ = azimuth_tan(slave_pan_rad, tilt_rad, slave_px[0], slave_px[1], focal_px, gimbal)
    s = 1.0 if master == "left" else -1.0
    den = s * (tm - ts)
    if not den > 0:
        return math.nan
    # the slave's centre (s b + d sin p, d (cos p - 1)); its ray x = x0 + ts (z - z0) meets the master's x = tm z
    x0, z0 = axis_m * math.sin(slave_pan_rad), axis_m * (math.cos(slave_pan_rad) - 1.0)
    pz = (baseline_m + s * (x0 - ts * z0)) / den
    if gimbal == "helmholtz":
        return pz * math.cos(tilt_rad) + pz * em * math.sin(tilt_rad)
    return pz


def depth_from_disparity(disparity_px: float, baseline_m: float, focal_px: float) -> float:
    """Z = b f / d of a rectified pair; NaN for d <= 0."""
    return baseline_m * focal_px / disparity_px if disparity_px > 0 else math.nan


def depth_sigma(z_m: float, baseline_m: float, focal_px: float, sigma_d_px: float) -> float:
    """dZ = Z^2 / (b f) * sigma_d: one sigma of Z for a disparity known to sigma_d px."""
    return z_m * z_m / (baseline_m * focal_px) * sigma_d_px


def disparity_sigma(row: np.ndarray, k: int, window: int) -> float:
    """One sigma (px) of the sub-pixel winner k_sub of a decision, from the winning row of layer 4 `row`
    (scores y(k), higher is better) and the winner k: sqrt(SIGMA_FLOOR_PX^2 + (SIGMA_CURVATURE / c)^2), c the
    peak's curvature y(k-1) - 2 y(k) + y(k+1), negated, per fovea pixel (w^2). A sharp peak (much texture,
    little noise) is placed to about 0.14 px (the parabola's own bias and what the window averages over a
    slanted surface), a flat one to less. No parabola (the winner at the edge, or no strict peak): 0.5 px."""
    row = np.asarray(row, dtype=np.float64).ravel()
    if not 0 < k < row.size - 1:
        return math.hypot(SIGMA_FLOOR_PX, 0.5)
    c = -(row[k - 1] - 2.0 * row[k] + row[k + 1]) / float(window * window)
    if not c > 0:
        return math.hypot(SIGMA_FLOOR_PX, 0.5)
    return min(math.hypot(SIGMA_FLOOR_PX, SIGMA_CURVATURE / c), math.hypot(SIGMA_FLOOR_PX, 0.5))


@dataclass(frozen=True)
class Depth:
    """A decision's depth: depth_m and depth_sigma_m (NaN unless confident and converged), converged
    (confident and |offset_px| <= CONVERGED_PX), and the disparity sigma it used (px)."""

    depth_m: float
    depth_sigma_m: float
    converged: bool
    sigma_d_px: float = math.nan


NO_DEPTH = Depth(math.nan, math.nan, False)


def fixated_depth(*, x: float, y: float, width: int, height: int, focal_px: float, slave_pan_rad: float,
                  offset_px: float, v_shift: int, confident: bool, sigma_d_px: float, baseline_m: float,
                  master_pan_rad: float = 0.0, tilt_rad: float = 0.0, gimbal: str = "helmholtz",
                  master: str = "left", converged_px: float = CONVERGED_PX,
                  principal: tuple[float, float] | None = None,
                  slave_principal: tuple[float, float] | None = None, axis_m: float = 0.0) -> Depth:
    """The depth of a decision: the fovea at master pixel (x, y) of a width x height view, found offset_px to
    the right (v_shift rows down) in the slave at slave_pan_rad. NaN (and converged False) unless the decision
    is confident and within converged_px of the fovea; NaN with converged True when the geometry gives no
    point in front of the head (or baseline_m is not positive: no rig geometry). principal, slave_principal: each
    camera's principal point (default: the view centre, (width // 2, height // 2)); axis_m: depth_from_pans'."""
    values = (x, y, focal_px, slave_pan_rad, offset_px, master_pan_rad, tilt_rad)
    if not confident or not all(math.isfinite(v) for v in values) or not abs(offset_px) <= converged_px:
        return NO_DEPTH
    if not (baseline_m > 0 and focal_px > 0):
        return Depth(math.nan, math.nan, True, sigma_d_px)
    cx, cy = principal if principal is not None else (width // 2, height // 2)
    sx, sy = slave_principal if slave_principal is not None else (width // 2, height // 2)
    z = depth_from_pans(master_pan_rad, slave_pan_rad, baseline_m, focal_px, tilt_rad=tilt_rad,
                        master_px=(x - cx, y - cy), slave_px=(x + offset_px - sx, y + v_shift - sy),
                        gimbal=gimbal, master=master, axis_m=axis_m)
    if not math.isfinite(z):
        return Depth(math.nan, math.nan, True, sigma_d_px)
    return Depth(z, depth_sigma(z, baseline_m, focal_px, sigma_d_px), True, sigma_d_px)


def decision_fields(frame, decision, scores: np.ndarray, baseline_m: float, gimbal: str = "helmholtz",
                    master: str = "left", axis_m: float = 0.0) -> dict:
    """The fields the reducer adds to a decision's Decision and Profile: the fovea centre x, y it was decided
    for, converged, depth_m and depth_sigma_m. frame: a messages.Frame; decision: its vergence.network.decide.Decision;
    scores: its layer-4 scores (rows x K, row v + R the winning one). A frame whose slave pan is not known
    (pan_stale: before the motor's first state, or older than its history) has no depth."""
    y2 = np.atleast_2d(scores)
    row = y2[decision.v + (y2.shape[0] - 1) // 2]
    dep = fixated_depth(x=frame.x, y=frame.y, width=frame.width, height=frame.height, focal_px=frame.focal_px,
                        slave_pan_rad=frame.pan_rad, offset_px=decision.offset_px, v_shift=decision.v,
                        confident=decision.confident, sigma_d_px=disparity_sigma(row, decision.k, frame.window),
                        baseline_m=baseline_m, master_pan_rad=frame.master_pan_rad, tilt_rad=frame.tilt_rad,
                        gimbal=gimbal, master=master, principal=frame.principal,
                        slave_principal=frame.slave_principal, axis_m=axis_m)
    if frame.pan_stale:  # the slave's pan at the exposure is not known: neither is the depth
        return dict(x=frame.x, y=frame.y, converged=dep.converged, depth_m=math.nan, depth_sigma_m=math.nan)
    return dict(x=frame.x, y=frame.y, converged=dep.converged, depth_m=dep.depth_m,
                depth_sigma_m=dep.depth_sigma_m)


def pair_depth(m, baseline_m: float, focal_px: float, master: str = "left") -> dict:
    """The depth of a vergence.network.match.Match on a rectified pair (vergence match --baseline --focal): the
    disparity d = -offset_px (a left master; +offset_px for a right one), Z = b f / d and dZ = Z^2 / (b f)
    sigma_d, with the decision's sub-pixel sigma_d (disparity_sigma). None for the depth of a point that is
    not confident or has no positive disparity."""
    d = m.decision
    disp = -d.offset_px if master == "left" else d.offset_px
    y2 = np.atleast_2d(m.scores) if m.scores is not None else None
    sd = disparity_sigma(y2[d.v + (y2.shape[0] - 1) // 2], d.k, m.window) if y2 is not None else math.nan
    z = depth_from_disparity(disp, baseline_m, focal_px) if d.confident else math.nan
    ok = math.isfinite(z)
    return dict(disparity_px=disp, disparity_sigma_px=sd, depth_m=z if ok else None,
                depth_sigma_m=depth_sigma(z, baseline_m, focal_px, sd) if ok else None)
