"""Layer 1, the retina: the three features I, G, D of the master fovea and the slave band.

Only two strips of each image are ever read: the fovea (w x w around the fixation point) of the master
and the band (the full width, the same rows, plus 2R rows for vertical search) of the slave, each with
a one-pixel margin for the Sobel kernels. Outside the image the margin is mirrored (OpenCV's
BORDER_REFLECT_101), so features of a strip equal those of the whole image computed with cv2.Sobel.
"""

from __future__ import annotations

import functools
import math

import cv2
import numba
import numpy as np

from .arrays import readonly
from .params import PHOTOMETRIC  # the modes of photometric, beside the parameter that names one
from .photometric import photometric, photometric_map  # the slave's gray levels onto the master's

__all__ = ["BorderError", "gray", "strip", "fovea_strip", "band_strip", "planes", "features", "check_point",
           "PHOTOMETRIC", "photometric", "photometric_map", "slave_band_strip", "mapped_strips", "master_clipped",
           "clipped_share", "CLIP_WARN", "warm_up"]


class BorderError(ValueError):
    """The requested window does not fit in the image."""


def gray(img: np.ndarray) -> np.ndarray:
    """A uint8 grayscale view of an image (BGR, BGRA or already gray)."""
    if img.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        img = cv2.cvtColor(np.ascontiguousarray(img), code)
    if img.dtype != np.uint8:
        raise TypeError(f"images must be 8-bit, got {img.dtype}")
    return img


def _reflect(idx: np.ndarray, n: int) -> np.ndarray:
    """BORDER_REFLECT_101 for indices at most one outside 0..n-1."""
    idx = np.where(idx < 0, -idx, idx)
    return np.where(idx >= n, 2 * (n - 1) - idx, idx)


def strip(img: np.ndarray, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
    """Rows r0..r1-1 and columns c0..c1-1 of a gray image with a one-pixel mirrored margin.

    Colour images are converted for the rows that are read only."""
    h, w = img.shape[:2]
    if r0 < 0 or c0 < 0 or r1 > h or c1 > w or r0 >= r1 or c0 >= c1:
        raise BorderError(f"region rows {r0}..{r1 - 1}, columns {c0}..{c1 - 1} is outside the {w} x {h} image")
    if 1 <= r0 and r1 + 1 <= h:
        rows = img[r0 - 1 : r1 + 1]
    else:
        rows = img[_reflect(np.arange(r0 - 1, r1 + 1), h)]
    rows = gray(rows)
    if 1 <= c0 and c1 + 1 <= w:
        return np.ascontiguousarray(rows[:, c0 - 1 : c1 + 1])
    out = np.empty((rows.shape[0], c1 - c0 + 2), np.uint8)
    out[:, 1:-1] = rows[:, c0:c1]
    out[:, 0] = rows[:, abs(c0 - 1)]
    out[:, -1] = rows[:, c1 if c1 < w else 2 * (w - 1) - c1]
    return out


def check_point(shape: tuple[int, ...], x: int, y: int, window: int, vsearch: int = 0) -> None:
    """Raise BorderError (saying why) unless a w x w fovea at (x, y) and its band fit in the image."""
    h, w = shape[:2]
    if window < 1 or window % 2 == 0:
        raise BorderError(f"window must be a positive odd number of pixels, got {window}")
    if window > w or window + 2 * vsearch > h:
        raise BorderError(f"window {window} (+-{vsearch} rows of vertical search) is larger than the {w} x {h} image")
    half = window // 2
    if not (half <= x < w - half):
        raise BorderError(f"point ({x}, {y}) is too close to the left/right border for window {window}: "
                          f"x must be in {half}..{w - half - 1}")
    if not (half + vsearch <= y < h - half - vsearch):
        raise BorderError(f"point ({x}, {y}) is too close to the top/bottom border for window {window} and "
                          f"vertical search {vsearch}: y must be in {half + vsearch}..{h - half - vsearch - 1}")


def fovea_strip(master: np.ndarray, x: int, y: int, window: int) -> np.ndarray:
    """The (w+2, w+2) gray strip of the master fovea centred at (x, y), with its Sobel margin."""
    half = window // 2
    return strip(master, y - half, y + half + 1, x - half, x + half + 1)


def band_strip(slave: np.ndarray, y: int, window: int, vsearch: int = 0) -> np.ndarray:
    """The (w+2R+2, W+2) gray strip of the slave band on rows y-w/2-R .. y+w/2+R, with its Sobel margin."""
    half = window // 2 + vsearch
    return strip(slave, y - half, y + half + 1, 0, slave.shape[1])


GRAD_MAX = 4 * 255  # the largest |Sobel gradient| of a uint8 strip, either axis


@functools.cache
def direction_table() -> np.ndarray:
    """D for every Sobel gradient a uint8 strip can have: table[gy + GRAD_MAX, gx + GRAD_MAX] (4.2 MB, made once a
    process in tens of ms). Computed in float64, where every entry is ALGORITHM.md's exact D on any CPU: no
    integer gradient's angle comes nearer than 4e-6 of a step to a rounding boundary (test_retina), far past
    float64's error; float32 atan2 per pixel, as before, rounded 10 of the 4.2M entries the other way (and
    SIMD builds of numpy may differ there), and took a third of a worker's time per frame. atan2 is evaluated on
    one quadrant only (every process start pays for it: 0.04 s instead of 0.23): the others are its mirror
    images, exact in whole steps since no step lies on a boundary (x -> -x: 128 - s; y -> -y: -s, mod 256)."""
    g = np.arange(0, GRAD_MAX + 1, dtype=np.float64)
    quad = np.floor(np.arctan2(g[:, None], g[None, :]) * (128 / math.pi) + 0.5).astype(np.int16)  # 0..64
    n = 2 * GRAD_MAX + 1
    table = np.empty((n, n), np.int16)
    c = GRAD_MAX
    table[c:, c:] = quad  # gy >= 0, gx >= 0
    table[c:, :c + 1] = (128 - quad)[:, ::-1]  # gx <= 0
    table[:c + 1, :] = (-table[c:, :])[::-1, :]  # gy <= 0
    table = (table & 255).astype(np.uint8)
    table[c, c] = 0  # no gradient, no direction
    table.flags.writeable = False
    return table


@numba.njit(cache=True, nogil=True)
def _features(s, out, table):
    """I, G and D of a strip's interior into out (3, h, n), D looked up in direction_table()."""
    h = s.shape[0] - 2
    n = s.shape[1] - 2
    for i in range(h):
        r0 = s[i]
        r1 = s[i + 1]
        r2 = s[i + 2]
        o0 = out[0, i]
        o1 = out[1, i]
        o2 = out[2, i]
        for j in range(n):
            a = np.int32(r0[j])
            b = np.int32(r0[j + 1])
            c = np.int32(r0[j + 2])
            d = np.int32(r1[j])
            f = np.int32(r1[j + 2])
            g = np.int32(r2[j])
            k = np.int32(r2[j + 1])
            m = np.int32(r2[j + 2])
            gx = (c + 2 * f + m) - (a + 2 * d + g)
            gy = (g + 2 * k + m) - (a + 2 * b + c)
            o0[j] = r1[j + 1]
            # float32 sqrt is exact on perfect squares below 2**24, so the rounding is exact too
            mag = np.int32(np.sqrt(np.float32(gx * gx + gy * gy)) * np.float32(0.25) + np.float32(0.5))
            o1[j] = min(mag, 255)
            o2[j] = table[gy + GRAD_MAX, gx + GRAD_MAX]


def _check_strip(s: np.ndarray) -> None:
    if s.ndim != 2 or s.dtype != np.uint8 or s.shape[0] < 3 or s.shape[1] < 3:
        raise ValueError(f"a strip must be a 2-D uint8 array of at least 3 x 3, got {s.dtype} {s.shape}")


def planes(s: np.ndarray) -> np.ndarray:
    """Features of the interior of a gray strip with a one-pixel margin: a (3, h-2, n-2) uint8 array.

    Plane 0 is the intensity I, plane 1 the Sobel gradient magnitude G = min(255, round(|grad| / 4)),
    plane 2 the direction D = round(atan2(Gy, Gx) * 256 / 2pi) mod 256, 0 where the gradient is 0.
    One fused pass, D looked up in direction_table()."""
    _check_strip(s)
    out = np.empty((3, s.shape[0] - 2, s.shape[1] - 2), np.uint8)
    _features(readonly(s), out, direction_table())
    return out


def mapped_strips(master: np.ndarray, slave: np.ndarray, x: int, y: int, window: int, vsearch: int = 0,
                  mode: str = "none", master_rows: bool = False, clip_master: bool = False
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, tuple[int, int] | None]:
    """The gray strips layer 1 reads, photometric `mode` applied: (the master's fovea strip, the slave's band strip
    mapped onto the master's same rows, the master's own rows of the fovea (band_strip without vertical search)
    when master_rows, for the left-right check, the levels the master was clipped to). With clip_master, where
    the slave's gain clipped (photometric_map), the master's strips are clipped to those levels (None when they
    were not: what master_clipped says for the same arguments)."""
    half = window // 2
    h, wd = master.shape[:2]
    if mode == "none" or master.ndim != 2 or window % 2 != 1 or not (half <= x < wd - half and half <= y < h - half):
        fovea = fovea_strip(master, x, y, window)
        band = band_strip(slave, y, window, vsearch)
        mrows = band_strip(master, y, window) if master_rows else None
        mband = None if mode == "none" else band_strip(master, y, window, vsearch)
    else:
        band = band_strip(slave, y, window, vsearch)
        mband = band_strip(master, y, window, vsearch)
        # the fovea's and the master rows' strips are rows vsearch .. vsearch + w + 1 of the master's band strip
        # (the band fits, so with vsearch > 0 they are off the image's top and bottom rows; at the left and right
        # ends both mirror the same column): the same pixels, not read again
        rows = mband[vsearch : vsearch + window + 2]
        fovea = np.ascontiguousarray(rows[:, x - half : x + half + 3])
        mrows = rows if master_rows else None
    lims = None
    if mode != "none":
        lut, lims = photometric_map(band, mband, mode, clip=clip_master)
        if lut is not None:
            band = cv2.LUT(band, lut)
        if lims is not None:
            fovea = np.clip(fovea, *lims).astype(np.uint8)
            mrows = None if mrows is None else np.clip(mrows, *lims).astype(np.uint8)
    return fovea, band, mrows, lims


def slave_band_strip(master: np.ndarray, slave: np.ndarray, y: int, window: int, vsearch: int = 0,
                     mode: str = "none") -> np.ndarray:
    """band_strip of the slave, its intensities mapped onto the master's same rows (photometric, `mode`)."""
    band = band_strip(slave, y, window, vsearch)
    if mode == "none":
        return band
    return photometric(band, band_strip(master, y, window, vsearch), mode)


def features(master: np.ndarray, slave: np.ndarray, at: tuple[int, int] | None = None, window: int = 15,
             vsearch: int = 0, photometric: str = "none") -> tuple[np.ndarray, np.ndarray]:
    """Layer 1 for one fixation point: the features I, G, D of the master's fovea and of the slave's band.

    Args:
        master, slave: uint8 images (gray or BGR) of the same size.
        at: (x, y) in the master image; the image centre (W // 2, H // 2) by default.
        window: w, the fovea's side (odd). vsearch: R, rows searched above and below.
        photometric: map the slave band's intensities onto the master's first ("none", "affine", "histogram").

    Returns:
        (fovea (3, w, w), band (3, w + 2R, W)), both uint8.

    Raises:
        BorderError: the window (with its vertical search) does not fit around `at`.
        ValueError, TypeError: the images differ in size or are not 8-bit."""
    if master.shape[:2] != slave.shape[:2]:
        raise ValueError(f"master and slave differ in size: {master.shape[1]} x {master.shape[0]} and "
                         f"{slave.shape[1]} x {slave.shape[0]}")
    x, y = at if at is not None else (master.shape[1] // 2, master.shape[0] // 2)
    check_point(master.shape, x, y, window, vsearch)
    fovea, band, _, _ = mapped_strips(master, slave, x, y, window, vsearch, photometric)
    return planes(fovea), planes(band)


def master_clipped(master: np.ndarray, slave: np.ndarray, y: int, window: int, params) -> bool:
    """Whether params.clip_master clips the master for the fovea at row y, window w: the slave's gain clipped
    enough of the band (photometric_map's levels; mapped_strips returns the same). The capture asks it (for
    frames.WindowControl); match() reads it off mapped_strips. params: a vergence.Params (not imported: params
    imports this module)."""
    if not params.clip_master or params.photometric == "none":
        return False
    levels = photometric_map(band_strip(slave, y, window, params.vsearch),
                             band_strip(master, y, window, params.vsearch), params.photometric)[1]
    return levels is not None


CLIP_WARN = 0.05  # a clipped_share over which the capture's log and the monitor say a camera's exposure is off


def clipped_share(master: np.ndarray, slave: np.ndarray, y: int, window: int, vsearch: int = 0) -> dict[str, float]:
    """For each camera, the share of the other camera's band (the rows of the fovea at row y, window w) that it
    clips away: levels it shows black or saturated where the other still has texture, lost to the match whatever
    the photometric mapping does (photometric_map's levels, affine, either way round; a share under
    CLAMP_MIN_SHARE counts as 0). The capture reports it so that a user sees a camera's exposure is off."""
    m, s = band_strip(master, y, window, vsearch), band_strip(slave, y, window, vsearch)
    out = {}
    for name, mine, other in (("slave", s, m), ("master", m, s)):
        levels = photometric_map(mine, other, "affine")[1]
        out[name] = 0.0 if levels is None else float(np.mean((other < levels[0]) | (other > levels[1])))
    return out


def warm_up() -> None:
    """Compile, or load from numba's cache, the photometric mapping's statistics (3 s the first time, 0.2 s from
    the cache): the capture calls this before it announces itself, so that no frame pays for it."""
    s = np.arange(64, dtype=np.uint8).reshape(4, 16)
    photometric_map(s, s)
