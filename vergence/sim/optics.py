"""The simulator's optics: a camera's rotation on its gimbal, its intrinsics, the homography between a source
image and a rotated view, and the option parser of a sim source's numbers; shared by the still rig (rig.py) and
the moving one (moving.py)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ..head.depth import GIMBALS  # (vergence.choices.Gimbal's words)

__all__ = ["GIMBALS", "Kept", "Region", "option_number", "rotation", "intrinsics", "homography"]




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
    if gimbal == "helmholtz":  # rx @ ry
        return np.array([[cp, 0.0, sp], [st * sp, ct, -st * cp], [-ct * sp, st, ct * cp]])
    if gimbal == "fick":  # ry @ rx
        return np.array([[cp, sp * st, sp * ct], [0.0, ct, -st], [-sp, cp * st, cp * ct]])
    raise ValueError(f"gimbal={gimbal!r}: must be one of {', '.join(GIMBALS)}")


def intrinsics(f: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


def homography(f: float, src_size: tuple[int, int], view_size: tuple[int, int], pan_rad: float,
               tilt_rad: float, gimbal: str = "helmholtz") -> np.ndarray:
    """K_v R^T K_s^-1: source pixel -> view pixel of a camera rotated by (pan, tilt) (K_s^-1 in closed form: the
    simulator asks this for every view it renders)."""
    cx, cy = src_size[0] // 2, src_size[1] // 2
    vx, vy = view_size[0] // 2, view_size[1] // 2
    r = rotation(pan_rad, tilt_rad, gimbal).T.tolist()
    # kv @ r @ ks_inv, written out (small numpy products cost more than the arithmetic)
    a = [[f * r[0][j] + vx * r[2][j] for j in range(3)], [f * r[1][j] + vy * r[2][j] for j in range(3)], r[2]]
    return np.array([[row[0] / f, row[1] / f, row[2] - (row[0] * cx + row[1] * cy) / f] for row in a])


@dataclass(frozen=True)
class Region:
    """What part of a view to render: rows y0..y1-1 at full resolution (`band`: what a frame reads, a tenth of
    the view or less), or the whole view scaled to (width, height) (`scaled`: a preview). `matrix` follows a
    view's homography (view pixel -> region pixel), `size` is the region's (width, height); `of` cuts the same
    region out of a rendered view."""

    matrix: np.ndarray
    size: tuple[int, int]
    y0: int = 0
    scale: bool = False

    @classmethod
    def band(cls, width: int, y0: int, y1: int) -> "Region":
        return cls(np.array([[1.0, 0.0, 0.0], [0.0, 1.0, -float(y0)], [0.0, 0.0, 1.0]]), (width, y1 - y0), y0)

    @classmethod
    def window(cls, x0: int, y0: int, x1: int, y1: int) -> "Region":
        """Columns x0..x1-1 and rows y0..y1-1 of the view's plane, which may reach past the view (what a distorted
        lens's pixels see: vergence.io.lens.distort_grid)."""
        return cls(np.array([[1.0, 0.0, -float(x0)], [0.0, 1.0, -float(y0)], [0.0, 0.0, 1.0]]), (x1 - x0, y1 - y0), y0)

    @classmethod
    def scaled(cls, view: tuple[int, int], size: tuple[int, int]) -> "Region":
        sx, sy = size[0] / view[0], size[1] / view[1]
        # pixel centres map onto pixel centres: (x + 0.5) * s - 0.5
        m = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])
        return cls(m, size, 0, True)

    @property
    def key(self) -> tuple:
        """What tells two regions' renders apart (a dict key): the matrix, the size, and whether it is a preview."""
        return self.matrix.tobytes(), self.size, self.scale

    def of(self, img: np.ndarray) -> np.ndarray:
        if self.scale:
            return cv2.resize(img, self.size, interpolation=cv2.INTER_AREA)
        return img[self.y0 : self.y0 + self.size[1]]


class Kept(dict):
    """The last `most` renders by key, the oldest forgotten first: what a camera that holds its pan sees again (the
    simulator's still scene and background stand still)."""

    def __init__(self, most: int):
        super().__init__()
        self.most = most

    def keep(self, key, value):
        """value under key (the oldest forgotten when `most` are kept); value."""
        if len(self) >= self.most:
            del self[next(iter(self))]
        self[key] = value
        return value
