"""The photometric mapping (issue #34: apart from the features, vergence.network.retina): the slave camera's gray levels
mapped onto the master's before the features are made, for two cameras of different gain and offset; `affine`
fits a gain and an offset on robust statistics of the two strips (quantiles of their histograms, a numba pass),
`histogram` matches their histograms; photometric_map also says which master levels the slave's gain clipped
(there the slave is black or saturated: its texture gone), for clip_master. vergence.network.retina applies it to the
strips it reads (mapped_strips)."""

from __future__ import annotations

import cv2
import numba
import numpy as np

from .arrays import readonly
from .params import PHOTOMETRIC

__all__ = ["photometric", "photometric_map", "AFFINE_QUANTILES", "CLAMP_MIN_SHARE"]


AFFINE_QUANTILES = (0.3, 0.5, 0.7)


BORDER_MIN_COLUMNS = 3  # a shorter run of dark columns at a strip's end is taken as the scene's


@numba.njit(cache=True, nogil=True)
def _dark_column(s, j, lo):
    for i in range(s.shape[0]):
        if s[i, j] != lo:
            return False
    return True


@numba.njit(cache=True, nogil=True)
def _border_columns(s):
    """How many whole columns at the left and at the right end of a gray strip are at the strip's darkest
    level: (left, right), each 0 when fewer than BORDER_MIN_COLUMNS; (0, 0) when little else would be left."""
    lo = np.uint8(255)
    for i in range(s.shape[0]):
        for j in range(s.shape[1]):
            lo = min(lo, s[i, j])
    n = s.shape[1]
    a = 0
    while a < n and _dark_column(s, a, lo):
        a += 1
    if a == n:  # every column dark
        return 0, 0
    b = 0
    while _dark_column(s, n - 1 - b, lo):  # stops at column a at the latest
        b += 1
    a = a if a >= BORDER_MIN_COLUMNS else 0
    b = b if b >= BORDER_MIN_COLUMNS else 0
    return (0, 0) if a + b >= n - 2 else (a, b)


@numba.njit(cache=True, nogil=True)
def _histogram(s, a, b):
    """The 256-level histogram (as float64 counts) of a gray strip's columns a .. width - b - 1 (what
    cv2.calcHist counts), four correlation histograms interleaved so that repeated levels do not wait on each other."""
    h = np.zeros((4, 256), np.int64)
    j1 = s.shape[1] - b
    for i in range(s.shape[0]):
        j = a
        while j + 4 <= j1:
            h[0, s[i, j]] += 1
            h[1, s[i, j + 1]] += 1
            h[2, s[i, j + 2]] += 1
            h[3, s[i, j + 3]] += 1
            j += 4
        while j < j1:
            h[0, s[i, j]] += 1
            j += 1
    out = np.empty(256, np.float64)
    for level in range(256):
        out[level] = np.float64(h[0, level] + h[1, level] + h[2, level] + h[3, level])
    return out


@numba.njit(cache=True, nogil=True)
def _ends(h):
    """The first and the last level with a count."""
    lo, hi = 0, 255
    while h[lo] == 0:
        lo += 1
    while h[hi] == 0:
        hi -= 1
    return lo, hi


@numba.njit(cache=True, nogil=True)
def _mid_quantiles(h, total):
    """(cumsum(h) - h / 2) / total, level by level (the cumulative counts are exact integers)."""
    q = np.empty(256, np.float64)
    c = 0.0
    for level in range(256):
        c += h[level]
        q[level] = (c - 0.5 * h[level]) / total
    return q


@numba.njit(cache=True, nogil=True)
def _statistics(s, m):
    """photometric_map's statistics of the two strips, up to its quantiles: (ok, lo_s, hi_s, lo_m, hi_m, cut_lo,
    cut_hi, f_lo, f_hi, qs, ls, qs_in, lm, qm_in), ok False where photometric_map leaves the slave as it is.
    Every sum here is of integer counts (exact), every other step the same IEEE operation photometric_map's
    numpy expressions make, in the same order: the same doubles."""
    a, b = _border_columns(s)
    hs = _histogram(s, a, b)
    hm = _histogram(m, a, b)
    ns, nm = hs.sum(), hm.sum()
    if ns == 0 or nm == 0:  # photometric_map asks for non-empty strips
        raise ValueError("an empty strip")
    lo_s, hi_s = _ends(hs)
    lo_m, hi_m = _ends(hm)
    x = hs[lo_s] / ns - hm[lo_m] / nm
    cut_lo = x if x > 0.0 else 0.0  # max(0.0, x)
    x = hs[hi_s] / ns - hm[hi_m] / nm
    cut_hi = x if x > 0.0 else 0.0
    hs[lo_s] = 0.0
    hs[hi_s] = 0.0
    hm[lo_m] = 0.0
    hm[hi_m] = 0.0
    ss, sm = hs.sum(), hm.sum()
    empty = np.empty(0, np.float64)
    f_lo, f_hi = 0.0, 0.0
    ok = ss >= 2 and sm >= 2
    if ok:
        f_lo, f_hi = cut_lo * nm / sm, cut_hi * nm / sm
        ok = not f_lo + f_hi >= 0.9
    if not ok:
        return False, lo_s, hi_s, lo_m, hi_m, cut_lo, cut_hi, f_lo, f_hi, empty, empty, empty, empty, empty
    qs = _mid_quantiles(hs, ss)
    qm = _mid_quantiles(hm, sm)
    levels = np.arange(256).astype(np.float64)
    ins, inm = hs > 0, hm > 0
    return True, lo_s, hi_s, lo_m, hi_m, cut_lo, cut_hi, f_lo, f_hi, qs, levels[ins], qs[ins], levels[inm], qm[inm]


def photometric(slave_strip: np.ndarray, master_strip: np.ndarray, mode: str = "affine") -> np.ndarray:
    """The slave's gray strip with its intensities mapped onto the master's over the same rows (ours: two
    cameras never have the same gain and offset, and layers 2-4 compare raw I and G).

    mode "affine": s' = m50 + (s - s50) * (m70 - m30) / (s70 - s30), from the 30th, 50th and 70th percentiles
    of the two strips (robust to black borders and to clipping at either end; a flat slave strip is only shifted
    to the master's median); "histogram": each slave level goes to the master level at the same quantile (any
    monotonic response); "none": unchanged. The map is a lookup table on the 256 levels and the result uint8,
    so that layers 1-4 stay exact integers."""
    if mode == "none":
        return slave_strip
    lut, _ = photometric_map(slave_strip, master_strip, mode, clip=False)
    return slave_strip if lut is None else cv2.LUT(np.ascontiguousarray(slave_strip), lut)


CLAMP_MIN_SHARE = 0.01  # the share of a strip its gain must clip before the master is clipped alike


def photometric_map(slave_strip: np.ndarray, master_strip: np.ndarray, mode: str = "affine", clip: bool = True
                    ) -> tuple[np.ndarray | None, tuple[int, int] | None]:
    """photometric()'s lookup table for the slave's 256 levels (None: leave the slave as it is), and the master
    levels (lo, hi) that the slave's gain clipped (None when it clipped under CLAMP_MIN_SHARE of the strip at
    either end): the master pixels under lo (over hi) are black (saturated) in the slave, their texture gone.
    The table then maps the slave's clipped levels to lo and hi, and mapped_strips clips the master's strips to
    lo..hi: clipped areas are flat and equal in both views instead of textured in one and flat in the other.
    clip=False: no such levels, the table alone (as photometric() maps a strip)."""
    if mode not in PHOTOMETRIC:
        raise ValueError(f"photometric must be one of {', '.join(PHOTOMETRIC)}, got {mode!r}")
    s = readonly(slave_strip)
    m = readonly(master_strip)
    if s.dtype != np.uint8 or m.dtype != np.uint8 or s.ndim != 2 or m.ndim != 2:
        raise ValueError(f"photometric maps 2-D uint8 strips, got {s.dtype} {s.shape} and {m.dtype} {m.shape}")
    if s.size == 0 or m.size == 0:
        raise ValueError(f"photometric maps non-empty strips, got {s.shape} and {m.shape}")
    levels = np.arange(256, dtype=np.float64)
    # A turned camera sees past the scene: whole columns at one end of the slave strip at its darkest level (the
    # simulator's black border, at the slave's offset; up to 40 % of the band on Middlebury). They are no part of
    # the scene the master sees, so they are left out of the slave's statistics, and as many columns at the same
    # end of the master's (about the scene the slave does not see there): _border_columns.
    # Each strip's darkest and brightest level is taken as clipped (black or saturated: 0 and 255 when the camera
    # clips; a black border, a turned camera seeing past the scene in the simulator, is such a level too, at the
    # slave's offset): those pixels say nothing of the gain and would drag any statistic. They are left out of
    # both strips; the share by which the slave has more of them than the master (its gain clipped those) is cut
    # off the master's darkest / brightest end, so that the two distributions left still correspond.
    # Then the mid-quantile of each level on each strip's cumulative histogram; a slave quantile q lies at the
    # master's f_lo + q (1 - f_lo - f_hi). All in _statistics, in one compiled pass.
    ok, lo_s, hi_s, lo_m, hi_m, cut_lo, cut_hi, f_lo, f_hi, qs, ls, qs_in, lm, qm_in = _statistics(s, m)
    if mode == "none" or not ok:
        return None, None
    if mode == "affine":
        # gain and offset from the 30th, 50th and 70th percentiles
        q = np.asarray(AFFINE_QUANTILES)
        ps = np.interp(q, qs_in, ls)
        pm = np.interp(f_lo + q * (1.0 - f_lo - f_hi), qm_in, lm)
        a = (pm[2] - pm[0]) / (ps[2] - ps[0]) if ps[2] - ps[0] >= 1.0 else 1.0
        lut = pm[1] + (levels - ps[1]) * a
    else:
        # each slave level to the master level at the same quantile
        lut = np.interp(f_lo + qs * (1.0 - f_lo - f_hi), qm_in, lm)
        if cut_lo > 0:  # the slave's clipped level: to the middle of the share its gain clipped
            lut[lo_s] = np.interp(0.5 * f_lo, qm_in, lm)
        if cut_hi > 0:
            lut[hi_s] = np.interp(1.0 - 0.5 * f_hi, qm_in, lm)
    # a clipped level the master has as much of (black on both sides, say): to the master's
    if cut_lo <= 0:
        lut[lo_s] = lo_m
    if cut_hi <= 0:
        lut[hi_s] = hi_m
    lims = None
    if clip and max(cut_lo, cut_hi) >= CLAMP_MIN_SHARE:
        t_lo = int(np.rint(np.interp(f_lo, qm_in, lm))) if cut_lo >= CLAMP_MIN_SHARE else 0
        t_hi = int(np.rint(np.interp(1.0 - f_hi, qm_in, lm))) if cut_hi >= CLAMP_MIN_SHARE else 255
        if t_lo < t_hi:
            lims = (t_lo, t_hi)
            if t_lo > 0:
                lut[lo_s] = t_lo
            if t_hi < 255:
                lut[hi_s] = t_hi
            lut = np.clip(lut, t_lo, t_hi)
    lut = np.clip(np.rint(lut), 0, 255).astype(np.uint8)
    return lut, lims
