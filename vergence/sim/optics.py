"""The simulator's optics: a camera's rotation on its gimbal, its intrinsics, the homography between a source
image and a rotated view, and the option parser of a sim source's numbers; shared by the still rig (rig.py) and
the moving one (moving.py)."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["GIMBALS", "option_number", "rotation", "intrinsics", "homography"]


GIMBALS = ("helmholtz", "fick")


def option_number(items: dict, key: str, conv=float, default=None):
    """items[key] (a sim source's option text) as conv (float or int), default when absent; ValueError naming
    the key when it is not a finite number."""
    if key not in items:
        return default
    try:
        v = conv(items[key])
    except ValueError:
        raise ValueError(f"sim source: {key}={items[key]!r} is not a {conv.__name__}") from None
    if isinstance(v, float) and not math.isfinite(v):
        raise ValueError(f"sim source: {key}={items[key]!r} is not finite")
    return v


def rotation(pan_rad: float, tilt_rad: float, gimbal: str = "helmholtz") -> np.ndarray:
    """Camera to world (x right, y down, z forward): R_x(tilt) R_y(pan) (helmholtz) or R_y(pan) R_x(tilt)."""
    cp, sp = math.cos(pan_rad), math.sin(pan_rad)
    ct, st = math.cos(tilt_rad), math.sin(tilt_rad)
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, ct, -st], [0.0, st, ct]])
    if gimbal not in GIMBALS:
        raise ValueError(f"gimbal={gimbal!r}: must be one of {', '.join(GIMBALS)}")
    return rx @ ry if gimbal == "helmholtz" else ry @ rx


def intrinsics(f: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


def homography(f: float, src_size: tuple[int, int], view_size: tuple[int, int], pan_rad: float,
               tilt_rad: float, gimbal: str = "helmholtz") -> np.ndarray:
    """K_v R^T K_s^-1: source pixel -> view pixel of a camera rotated by (pan, tilt)."""
    ks = intrinsics(f, src_size[0] // 2, src_size[1] // 2)
    kv = intrinsics(f, view_size[0] // 2, view_size[1] // 2)
    return kv @ rotation(pan_rad, tilt_rad, gimbal).T @ np.linalg.inv(ks)
