"""Layers 2-4: the correlation of the fovea with every window of the band, on exact integers.

y(k) = sum over the window of (255 - out(i, j, k)), out the mean absolute feature difference, equals
255 * w * w - S(k) / 3 with S(k) the integer sum of absolute differences over the three planes. The kernel
computes S for offsets k0..k1-1 only, so any split of 0..K-1 concatenates to the unsplit result.
"""

from __future__ import annotations

import functools

import numba
import numpy as np

from . import simd
from .arrays import readonly

__all__ = ["sad", "portable_sad", "half_sads", "correlate", "scores_from_sad", "support_weights", "warm_up"]


# The kernel is written for the vectoriser: the innermost loop runs over k with unsigned indices (so no
# negative-index check survives and no array view is made per row: views cost reference counting), the
# differences are taken on uint8 as max - min, four window columns are summed per pass, and each window
# row accumulates in uint16 lanes, flushed to int64 before they could overflow.


@numba.njit(inline="always")
def _ad(a, f):
    return np.uint16(max(a, f) - min(a, f))


@numba.njit(inline="always")
def _cd(a, f):
    d = np.uint8(max(a, f) - min(a, f))
    return np.uint16(min(d, np.uint8(np.uint8(0) - d)))  # min(d, 256 - d), 0 stays 0


@numba.njit(cache=True, nogil=True)
def _sad(fovea, band, weights, k0, k1, circular, out):
    nplanes, w, _ = fovea.shape
    nv = band.shape[1] - w + 1
    n = np.uint64(k1 - k0)
    one, two, three = np.uint64(1), np.uint64(2), np.uint64(3)
    wmax = 1
    for i in range(w):
        for j in range(w):
            wmax = max(wmax, np.int64(weights[i, j]))
    chunk = max(1, 65535 // (255 * wmax))  # columns a uint16 lane takes before it must be flushed
    acc = np.zeros(k1 - k0, np.uint16)
    for v in range(nv):
        o = out[v]
        for c in range(nplanes):
            circ = circular and c == 2
            for i in range(w):
                row = band[c, v + i]
                fr = fovea[c, i]
                wr = weights[i]
                for j0 in range(0, w, chunk):
                    j1 = min(w, j0 + chunk)
                    j = j0
                    while j + 4 <= j1:
                        f0, f1, f2, f3 = fr[j], fr[j + 1], fr[j + 2], fr[j + 3]
                        w0, w1 = np.uint16(wr[j]), np.uint16(wr[j + 1])
                        w2, w3 = np.uint16(wr[j + 2]), np.uint16(wr[j + 3])
                        b = np.uint64(k0 + j)
                        if circ:
                            for k in range(n):
                                q = b + k
                                acc[k] += (w0 * _cd(row[q], f0) + w1 * _cd(row[q + one], f1)) + \
                                          (w2 * _cd(row[q + two], f2) + w3 * _cd(row[q + three], f3))
                        elif w0 == 1 and w1 == 1 and w2 == 1 and w3 == 1:
                            for k in range(n):
                                q = b + k
                                acc[k] += (_ad(row[q], f0) + _ad(row[q + one], f1)) + \
                                          (_ad(row[q + two], f2) + _ad(row[q + three], f3))
                        else:
                            for k in range(n):
                                q = b + k
                                acc[k] += (w0 * _ad(row[q], f0) + w1 * _ad(row[q + one], f1)) + \
                                          (w2 * _ad(row[q + two], f2) + w3 * _ad(row[q + three], f3))
                        j += 4
                    while j < j1:
                        f0, w0 = fr[j], np.uint16(wr[j])
                        b = np.uint64(k0 + j)
                        if circ:
                            for k in range(n):
                                acc[k] += w0 * _cd(row[b + k], f0)
                        else:
                            for k in range(n):
                                acc[k] += w0 * _ad(row[b + k], f0)
                        j += 1
                    for k in range(n):
                        o[k] += acc[k]
                        acc[k] = 0


@numba.njit(cache=True, nogil=True)
def _half_sads(fovea, rows, weights, k0, k1, circular, out):
    nplanes, w, _ = fovea.shape
    c = w // 2
    n = k1 - k0
    part = np.zeros((3, n), np.int64)  # one fovea row's columns left of c, column c, right of c
    for i in range(w):
        part[:] = 0
        for p in range(nplanes):
            circ = circular and p == 2
            row = rows[p, i]
            for j in range(w):
                wt = np.int64(weights[i, j])
                if wt == 0:
                    continue
                f = np.int64(fovea[p, i, j])
                acc = part[0 if j < c else 1 if j == c else 2]
                b = k0 + j
                if circ:
                    for k in range(n):
                        e = abs(np.int64(row[b + k]) - f)
                        acc[k] += min(e, 256 - e) * wt
                else:
                    for k in range(n):
                        acc[k] += abs(np.int64(row[b + k]) - f) * wt
        for k in range(n):
            left = part[0, k] + part[1, k]  # the left half and the right half each with the centre column
            right = part[1, k] + part[2, k]
            whole = left + part[2, k]
            out[0, k] += left
            out[1, k] += right
            if i <= c:  # top, bottom: each with the centre row
                out[2, k] += whole
            if i >= c:
                out[3, k] += whole


def half_sads(fovea: np.ndarray, rows: np.ndarray, k0: int, k1: int, *, circular: bool = True,
              weights: np.ndarray | None = None) -> np.ndarray:
    """S of the left, right, top and bottom halves of the fovea (each with the centre column or row) at offsets
    k0..k1-1 along rows ((3, w, W): no vertical search), in one pass: a (4, k1 - k0) int64 array, row h equal
    to sad() with the half's 0/1 mask (times weights) as the weights."""
    k0, k1 = _check(fovea, rows, k0, k1)
    if rows.shape[1] != fovea.shape[1]:
        raise ValueError(f"rows must be as tall as the fovea ({fovea.shape[1]}), got {rows.shape[1]}")
    w = fovea.shape[1]
    weights = _ones(w) if weights is None else readonly(weights, np.uint8)
    out = np.zeros((4, k1 - k0), np.int64)
    _half_sads(readonly(fovea), readonly(rows), weights, k0, k1, circular, out)
    return out


def _check(fovea: np.ndarray, band: np.ndarray, k0: int, k1: int | None) -> tuple[int, int]:
    if fovea.dtype != np.uint8 or band.dtype != np.uint8:
        raise TypeError("fovea and band must be uint8 feature planes")
    if fovea.ndim != 3 or band.ndim != 3 or fovea.shape[1] != fovea.shape[2]:
        raise ValueError(f"fovea must be (3, w, w) and band (3, w + 2R, W); got {fovea.shape} and {band.shape}")
    nplanes, w, _ = fovea.shape
    if band.shape[0] != nplanes or band.shape[1] < w or (band.shape[1] - w) % 2 or band.shape[2] < w:
        raise ValueError(f"band {band.shape} does not fit fovea {fovea.shape}: want ({nplanes}, w + 2R, W >= w)")
    kk = band.shape[2] - w + 1
    k1 = kk if k1 is None else k1
    if not (0 <= k0 <= k1 <= kk):
        raise ValueError(f"offsets {k0}..{k1} outside 0..{kk}")
    return k0, k1


@functools.lru_cache(maxsize=64)
def _ones(w: int) -> np.ndarray:
    ones = np.ones((w, w), np.uint8)
    ones.flags.writeable = False
    return ones


def sad(fovea: np.ndarray, band: np.ndarray, k0: int = 0, k1: int | None = None, *, circular: bool = True,
        weights: np.ndarray | None = None) -> np.ndarray:
    """S(v, k): integer sums of absolute feature differences, a (2R + 1, k1 - k0) int64 array.

    circular compares the direction plane on the circle (min(|dD|, 256 - |dD|)); weights, a (w, w) array
    of small non-negative integers, weighs each fovea pixel (adaptive support weights). On a CPU with
    AVX-512BW (simd.AVAILABLE) the circular comparison runs the vergence.network.simd kernel, anything else the
    portable one: the same integers."""
    k0, k1 = _check(fovea, band, k0, k1)
    w = fovea.shape[1]
    if weights is not None:
        weights = np.ascontiguousarray(weights, dtype=np.uint8)
        if weights.shape != (w, w):
            raise ValueError(f"weights must be ({w}, {w}), got {weights.shape}")
    big = (k1 - k0) * (band.shape[1] - w + 1) >= 1024  # below, setting up the padded copies costs more
    if simd.AVAILABLE and circular and big and w <= simd.MAX_WINDOW and (
            weights is None or weights.max() <= simd.MAX_WEIGHT):
        return simd.sad(fovea, band, k0, k1, weights)
    return portable_sad(fovea, band, k0, k1, circular=circular, weights=weights)


def portable_sad(fovea: np.ndarray, band: np.ndarray, k0: int = 0, k1: int | None = None, *,
                 circular: bool = True, weights: np.ndarray | None = None) -> np.ndarray:
    """sad() on any CPU (the kernel above, vectorised by numba over k)."""
    k0, k1 = _check(fovea, band, k0, k1)
    w = fovea.shape[1]
    out = np.zeros((band.shape[1] - w + 1, k1 - k0), np.int64)
    weights = _ones(w) if weights is None else readonly(weights, np.uint8)
    _sad(readonly(fovea), readonly(band), weights, k0, k1, circular, out)
    return out


def scores_from_sad(s: np.ndarray, window: int, weight_sum: int | None = None) -> np.ndarray:
    """Layer-4 scores y = 255 * w * w - S / 3 (with support weights: normalised to the same scale).

    Computed as (S / -3) + 255 w w in place: the same doubles as the formula, without its temporaries."""
    if weight_sum is None:
        y = np.divide(s, -3.0)
    else:
        y = np.multiply(s, -(window * window / (3.0 * max(weight_sum, 1))))  # all-zero weights: S = 0
    y += 255.0 * window * window
    return y


def correlate(fovea: np.ndarray, band: np.ndarray, k0: int = 0, k1: int | None = None, *,
              circular: bool = True, weights: np.ndarray | None = None) -> np.ndarray:
    """Layers 2-4: the scores y(k) of the fovea against every window of the band, for offsets k0..k1-1.

    Args:
        fovea, band: features() planes, (3, w, w) and (3, w + 2R, W), uint8.
        k0, k1: the offsets to score (a shard's range; all W - w + 1 by default).
        circular: compare the direction D on the circle. weights: (w, w) support weights, or None.

    Returns:
        y(k), 1-D when the band is w rows tall; (2R + 1, k1 - k0) when it is taller (row v is the vertical
        shift v - R).

    Raises:
        ValueError, TypeError: planes of the wrong type or shape, offsets outside the band, bad weights."""
    s = sad(fovea, band, k0, k1, circular=circular, weights=weights)
    w = fovea.shape[1]
    y = scores_from_sad(s, w, None if weights is None else int(weights.astype(np.int64).sum()))
    return y[0] if y.shape[0] == 1 else y


@functools.lru_cache(maxsize=64)
def _nearness(w: int, radius: float) -> np.ndarray:
    yy, xx = np.mgrid[0:w, 0:w]
    return np.exp(-np.hypot(yy - w // 2, xx - w // 2) / radius)


@functools.lru_cache(maxsize=64)
def _likeness(gamma: float) -> np.ndarray:
    return np.exp(-np.arange(256) / gamma)


def support_weights(fovea: np.ndarray, gamma: float = 8.0, radius: float = 7.0, levels: int = 8) -> np.ndarray:
    """Adaptive support weights (Yoon & Kweon 2006) of the fovea: each pixel weighed by the likeness of its
    intensity to the centre pixel and by its nearness, exp(-|I - I_c| / gamma - distance / radius),
    quantised to integers 0..levels so that the kernel stays exact and sharding bit-identical. At a depth
    edge this lets the centre pixel's own surface decide, instead of the most textured one in the window."""
    w = fovea.shape[1]
    i = fovea[0].astype(np.int16)
    like = _likeness(float(gamma))[np.abs(i - i[w // 2, w // 2])]
    return np.rint(like * _nearness(w, float(radius)) * levels).astype(np.uint8)


def warm_up() -> None:
    """Compile, or load from numba's cache, both kernels (sad() picks one by size): a service calls this
    before it announces itself, so that no frame pays for it."""
    fovea = np.zeros((3, 3, 3), np.uint8)
    band = np.zeros((3, 3, 8), np.uint8)
    portable_sad(fovea, band)
    half_sads(fovea, band, 0, 6)
    if simd.AVAILABLE:
        simd.sad(fovea, band, 0, 6, None)
