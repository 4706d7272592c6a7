"""Layers 2-4 (vergence.network.kernel, vergence.network.simd): the sums of absolute differences and the scores
against plain reference implementations written here from ALGORITHM.md."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vergence.network import kernel, simd


# ---- plain references (slow, obvious) -------------------------------------------------------------------------

def ref_sad(fovea: np.ndarray, band: np.ndarray, circular: bool = False) -> np.ndarray:
    """S(v, k) = sum over the window and the three planes of |difference| (integers)."""
    c, w, _ = fovea.shape
    nv, kk = band.shape[1] - w + 1, band.shape[2] - w + 1
    f = fovea.astype(np.int64)
    s = np.empty((nv, kk), np.int64)
    for v in range(nv):
        for k in range(kk):
            e = np.abs(f - band[:, v : v + w, k : k + w].astype(np.int64))
            if circular:
                e[2] = np.minimum(e[2], 256 - e[2])
            s[v, k] = e.sum()
    return s


def ref_scores(fovea: np.ndarray, band: np.ndarray, circular: bool = False) -> np.ndarray:
    """y(v, k) = sum over the window of 255 - (|dI| + |dG| + |dD|) / 3."""
    c, w, _ = fovea.shape
    nv, kk = band.shape[1] - w + 1, band.shape[2] - w + 1
    f = fovea.astype(np.int64)
    y = np.empty((nv, kk))
    for v in range(nv):
        for k in range(kk):
            e = np.abs(f - band[:, v : v + w, k : k + w].astype(np.int64))
            if circular:
                e[2] = np.minimum(e[2], 256 - e[2])
            y[v, k] = np.sum(255 - e.sum(axis=0) / 3)
    return y


# ---- layers 2-4 ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("circular", [False, True], ids=["linear-D", "circular-D"])
@pytest.mark.parametrize("w,nv,width", [(15, 1, 64), (15, 5, 40), (3, 1, 3), (31, 3, 50), (47, 1, 60), (63, 3, 70)])
def test_kernel_equals_reference(w, nv, width, circular):
    rng = np.random.default_rng(w * 100 + nv)
    fovea = rng.integers(0, 256, (3, w, w), dtype=np.uint8)
    band = rng.integers(0, 256, (3, w + nv - 1, width), dtype=np.uint8)
    y = kernel.correlate(fovea, band, circular=circular)
    ref = ref_sad(fovea, band, circular)
    assert np.array_equal(kernel.sad(fovea, band, circular=circular), ref)
    assert np.array_equal(kernel.portable_sad(fovea, band, circular=circular), ref)
    assert np.allclose(np.atleast_2d(y), ref_scores(fovea, band, circular), rtol=0, atol=1e-6)
    assert y.ndim == (1 if nv == 1 else 2)


@pytest.mark.parametrize("wmax", [9, 65, 256], ids=["support-weights", "simd-limit", "any-uint8-no-overflow"])
def test_weighted_kernel_equals_reference(wmax):
    rng = np.random.default_rng(7)
    fovea = rng.integers(0, 256, (3, 31, 31), dtype=np.uint8)
    band = rng.integers(0, 256, (3, 33, 70), dtype=np.uint8)
    fovea[:, :4, :4], band[:, :4, :4] = 0, 255  # the largest differences meet the largest weights
    wt = rng.integers(0, wmax, (31, 31), dtype=np.uint8)
    wt[:4, :4] = wmax - 1
    ref = np.array([[np.sum(np.abs(fovea.astype(np.int64) - band[:, v : v + 31, k : k + 31]) * wt)
                     for k in range(40)] for v in range(3)])
    assert np.array_equal(kernel.sad(fovea, band, weights=wt, circular=False), ref)
    assert np.array_equal(kernel.portable_sad(fovea, band, weights=wt, circular=False), ref)


@pytest.mark.skipif(not simd.AVAILABLE, reason="this CPU has no AVX-512BW")
@settings(max_examples=80, deadline=None)
@given(w=st.integers(1, 32).map(lambda h: 2 * h - 1), r=st.integers(0, 10), extra=st.integers(0, 150),
       k0=st.floats(0, 1), k1=st.floats(0, 1), seed=st.integers(0, 2**31 - 1), weighted=st.booleans(),
       strided=st.booleans())
def test_simd_kernel_equals_portable_kernel(w, r, extra, k0, k1, seed, weighted, strided):
    """The AVX-512 kernel against the portable one: windows 1..63 (all three lane widths), vertical search
    (1..21 shifts: passes of 8, 4, 2 and 1), any k-range, support weights up to simd.MAX_WEIGHT, a band that
    is a view with strides."""
    rng = np.random.default_rng(seed)
    fovea = rng.integers(0, 256, (3, w, w), dtype=np.uint8)
    band = rng.integers(0, 256, (3, w + 2 * r, w + extra + 5), dtype=np.uint8)
    band = band[:, :, 5:] if strided else np.ascontiguousarray(band[:, :, 5:])
    wt = rng.integers(0, simd.MAX_WEIGHT + 1, (w, w), dtype=np.uint8) if weighted else None
    kk = extra + 1
    a, b = sorted((int(k0 * kk), int(k1 * kk)))
    got = simd.sad(fovea, band, a, b, wt)
    assert np.array_equal(got, kernel.portable_sad(fovea, band, a, b, circular=True, weights=wt))


def test_identical_window_scores_maximum():
    rng = np.random.default_rng(1)
    band = rng.integers(0, 256, (3, 15, 200), dtype=np.uint8)
    fovea = band[:, :, 120:135].copy()
    y = kernel.correlate(fovea, band)
    assert y[120] == 255 * 15 * 15 and int(np.argmax(y)) == 120


@settings(max_examples=60, deadline=None)
@given(w=st.integers(1, 12).map(lambda h: 2 * h - 1), r=st.integers(0, 3), extra=st.integers(0, 60),
       cuts=st.lists(st.floats(0, 1), max_size=4), seed=st.integers(0, 2**31 - 1), circ=st.booleans(),
       weighted=st.booleans())
def test_any_split_of_k_concatenates_to_the_whole(w, r, extra, cuts, seed, circ, weighted):
    rng = np.random.default_rng(seed)
    width = w + extra
    fovea = rng.integers(0, 256, (3, w, w), dtype=np.uint8)
    band = rng.integers(0, 256, (3, w + 2 * r, width), dtype=np.uint8)
    wt = rng.integers(0, 9, (w, w), dtype=np.uint8) if weighted else None
    kk = width - w + 1
    bounds = sorted({0, kk, *(int(c * kk) for c in cuts)})
    whole = kernel.correlate(fovea, band, circular=circ, weights=wt)
    parts = [kernel.correlate(fovea, band, a, b, circular=circ, weights=wt) for a, b in zip(bounds, bounds[1:])]
    assert np.array_equal(np.concatenate(parts, axis=-1), whole)


def test_kernel_rejects_bad_shapes():
    f = np.zeros((3, 15, 15), np.uint8)
    with pytest.raises(ValueError, match="does not fit"):
        kernel.correlate(f, np.zeros((3, 16, 100), np.uint8))
    with pytest.raises(ValueError, match="outside"):
        kernel.correlate(f, np.zeros((3, 15, 100), np.uint8), 10, 200)
    with pytest.raises(TypeError):
        kernel.correlate(f.astype(np.int16), np.zeros((3, 15, 100), np.uint8))


def test_warm_up_compiles_both_kernels():
    """Services call kernel.warm_up() before announcing themselves: afterwards a frame compiles nothing."""
    kernel.warm_up()
    assert kernel._sad.signatures
    if simd.AVAILABLE:
        assert simd._drive.signatures
        n = len(simd._drive.signatures)
        rng = np.random.default_rng(3)
        fovea = rng.integers(0, 256, (3, 15, 15), dtype=np.uint8)
        band = rng.integers(0, 256, (3, 27, 640), dtype=np.uint8)
        kernel.sad(fovea, band, weights=kernel.support_weights(fovea))  # a frame's size: the simd kernel
        assert len(simd._drive.signatures) == n


@settings(max_examples=60, deadline=None)
@given(h=st.integers(1, 24), extra=st.integers(0, 60), k0=st.floats(0, 1), k1=st.floats(0, 1),
       seed=st.integers(0, 2**31 - 1), circ=st.booleans(), weighted=st.booleans())
def test_half_sads_equal_sad_with_the_half_masks(h, extra, k0, k1, seed, circ, weighted):
    """kernel.half_sads (the halves check's one pass) against kernel.sad with each half's 0/1 mask as weights:
    left and right keep the centre column, top and bottom the centre row."""
    w = 2 * h - 1
    rng = np.random.default_rng(seed)
    fovea = rng.integers(0, 256, (3, w, w), dtype=np.uint8)
    rows = rng.integers(0, 256, (3, w, w + extra), dtype=np.uint8)
    wt = rng.integers(0, 9, (w, w), dtype=np.uint8) if weighted else np.ones((w, w), np.uint8)
    left = np.zeros((w, w), np.uint8)
    left[:, : w // 2 + 1] = 1
    masks = [left, left[:, ::-1], left.T, left.T[::-1]]
    a, b = sorted((int(k0 * (extra + 1)), int(k1 * (extra + 1))))
    got = kernel.half_sads(fovea, rows, a, b, circular=circ, weights=wt if weighted else None)
    want = np.stack([kernel.sad(fovea, rows, a, b, circular=circ, weights=m * wt)[0] for m in masks])
    assert np.array_equal(got, want.reshape(4, b - a))
