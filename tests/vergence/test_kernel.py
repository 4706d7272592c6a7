"""Layers 1-5 against plain reference implementations written here from ALGORITHM.md."""

from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import vergence
from vergence import kernel, retina, simd
from vergence.decide import centre_offset, decide


# ---- plain references (slow, obvious) -------------------------------------------------------------------------

def ref_features(img: np.ndarray) -> np.ndarray:
    """I, G, D of a whole gray image, as ALGORITHM.md states them (float64 maths, OpenCV's default border)."""
    gx = cv2.Sobel(img, cv2.CV_64F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_64F, 0, 1, ksize=3)
    g = np.sqrt(gx**2 + gy**2)
    gq = np.minimum(255, np.floor(g / 4 + 0.5))
    ang = np.arctan2(gy, gx) % (2 * math.pi)
    dq = np.floor(ang * 256 / (2 * math.pi) + 0.5) % 256
    dq[g == 0] = 0
    return np.stack([img, gq, dq]).astype(np.uint8)


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


def ref_match(master: np.ndarray, slave: np.ndarray, x: int, y: int, w: int = 15) -> int:
    """The paper's winner k* for the fovea at (x, y): features of the whole images, argmax of layer 4."""
    fm, fs = ref_features(master), ref_features(slave)
    h = w // 2
    return int(np.argmax(ref_scores(fm[:, y - h : y + h + 1, x - h : x + h + 1], fs[:, y - h : y + h + 1, :])[0]))


# ---- layer 1 ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("region", [(0, 60, 0, 50), (5, 20, 0, 50), (0, 10, 3, 9), (50, 60, 40, 50), (10, 25, 10, 20)],
                         ids=["whole", "band", "top-left", "bottom-right", "inside"])
def test_strip_features_equal_whole_image_features(region):
    img = cv2.GaussianBlur(np.random.default_rng(3).integers(0, 256, (60, 50), dtype=np.uint8), (3, 3), 0.8)
    r0, r1, c0, c1 = region
    assert np.array_equal(retina.planes(retina.strip(img, r0, r1, c0, c1)), ref_features(img)[:, r0:r1, c0:c1])


@pytest.mark.parametrize("grad,expect_d", [("right", 0), ("down", 64), ("left", 128), ("up", 192)])
def test_direction_feature_is_full_circle(grad, expect_d):
    ramp = np.tile(np.arange(0, 100, 10, dtype=np.uint8), (10, 1))  # intensity grows to the right
    img = {"right": ramp, "left": ramp[:, ::-1], "down": ramp.T, "up": ramp.T[::-1]}[grad]
    p = retina.planes(np.ascontiguousarray(img))
    assert (p[2, 2:-2, 2:-2] == expect_d).all()
    assert (p[1, 2:-2, 2:-2] == 20).all()  # Sobel of a 10/px ramp is 4 * 2 * 10 = 80; G = 80 / 4
    flat = retina.planes(np.full((5, 5), 77, np.uint8))
    assert flat[0].min() == 77 and not flat[1].any() and not flat[2].any()


def test_gradient_magnitude_saturates_at_255():
    step = np.zeros((5, 5), np.uint8)
    step[:, 3:] = 255  # Sobel gives 1020, 1020 / 4 = 255 exactly; a diagonal step would exceed it
    step2 = np.tril(np.full((5, 5), 255, np.uint8))
    assert retina.planes(step)[1].max() == 255
    assert retina.planes(step2)[1].max() == 255


def test_colour_images_are_converted_for_the_strips_only():
    rng = np.random.default_rng(0)
    bgr = rng.integers(0, 256, (40, 60, 3), dtype=np.uint8)
    gray = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    f1, b1 = vergence.features(bgr, bgr, (30, 20), 9, 2)
    f2, b2 = vergence.features(gray, gray, (30, 20), 9, 2)
    assert np.array_equal(f1, f2) and np.array_equal(b1, b2)
    assert f1.shape == (3, 9, 9) and b1.shape == (3, 13, 60)


@pytest.mark.parametrize("x,y,w,r,msg", [(3, 20, 15, 0, "left/right"), (30, 2, 15, 0, "top/bottom"),
                                         (30, 10, 15, 4, "top/bottom"), (30, 20, 14, 0, "odd"),
                                         (30, 20, 71, 0, "larger")])
def test_border_errors_say_why(x, y, w, r, msg):
    img = np.zeros((40, 60), np.uint8)
    with pytest.raises(vergence.BorderError, match=msg):
        vergence.features(img, img, (x, y), w, r)


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


# ---- winner-takes-all and layer 5 ---------------------------------------------------------------------------

def test_centre_neuron_is_313_for_640_and_15():
    assert centre_offset(640, 15) == 313


@pytest.mark.parametrize("winner,direction,magnitude", [(300, -1, 13), (313, 0, 0), (340, 1, 27)])
def test_layer5_direction_and_magnitude(winner, direction, magnitude):
    y = np.zeros(626)
    y[winner] = 1000.0
    d = decide(y, 15, subpixel=False)
    assert (d.k, d.k_centre, d.direction, d.magnitude, d.offset_px) == (winner, 313, direction, magnitude,
                                                                          winner - 313)


def test_subpixel_parabola_vertex():
    k = np.arange(100, dtype=float)
    y = 5000 - 3.0 * (k - 40.3) ** 2
    d = decide(y, 15)
    assert d.k == 40 and d.k_sub == pytest.approx(40.3, abs=1e-9)
    assert decide(y, 15, subpixel=False).k_sub == 40


def test_vertical_search_reports_the_row_shift():
    y = np.zeros((5, 50))
    y[4, 20] = 9.0  # row 4 of 5 = shift +2
    d = decide(y, 15)
    assert (d.k, d.v) == (20, 2)


def test_vshift_cost_prefers_the_unshifted_row_unless_a_shifted_one_is_clearly_better():
    """Each row of shift costs vshift_cost * w * w of y: +2 rows at w 15 and cost 0.5 cost 225."""
    y = np.full((5, 50), 1000.0)
    y[2, 30] = 5000.0  # v = 0
    y[4, 20] = 5200.0  # v = +2, better by 200 < 225
    d = decide(y, 15, vshift_cost=0.5)
    assert (d.k, d.v, d.score) == (30, 0, 5000.0)
    y[4, 20] = 5300.0  # better by 300 > 225: the shifted row wins, its own y is the score
    d = decide(y, 15, vshift_cost=0.5)
    assert (d.k, d.v, d.score) == (20, 2, 5300.0)
    assert d.confidence == pytest.approx((5300 - 225 - 5000) / (255 * 225 - 5000))
    assert decide(y, 15).v == 2 and decide(y[2:3], 15, vshift_cost=0.5).k == 30


def test_margin_is_zero_for_a_tie_and_one_without_rival():
    y = np.zeros(60)
    y[10] = y[40] = 100.0
    assert decide(y, 15).confidence == 0.0 and not decide(y, 15).confident
    assert decide(np.array([1.0, 5.0, 1.0]), 3).confidence == 1.0


@pytest.mark.parametrize("fill", [0, 128], ids=["black", "flat-grey"])
def test_textureless_fovea_abstains(fill):
    master = np.full((120, 160), fill, np.uint8)
    slave = np.random.default_rng(0).integers(0, 256, (120, 160), dtype=np.uint8)
    m = vergence.match(master, slave)
    assert not m.confident and m.decision.texture == 0.0
    assert vergence.match(master, slave, faithful=True).confident  # the paper has no abstention


# ---- the whole network ---------------------------------------------------------------------------------------

def shifted_pair(shift: int, seed: int = 0, size=(240, 320)):
    """A textured master and the same scene seen `shift` px further left by the slave (disparity = shift)."""
    rng = np.random.default_rng(seed)
    big = cv2.GaussianBlur(rng.integers(0, 256, (size[0], size[1] + 64), dtype=np.uint8), (5, 5), 1.2)
    return big[:, 32 : 32 + size[1]].copy(), big[:, 32 + shift : 32 + shift + size[1]].copy()


@pytest.mark.parametrize("shift", [-20, -3, 0, 7, 25])
def test_match_recovers_a_known_shift(shift):
    master, slave = shifted_pair(shift)
    for params in (vergence.Params(), vergence.FAITHFUL):
        m = vergence.match(master, slave, params=params)
        assert m.confident
        assert m.decision.k == 160 - 7 - shift and m.offset_px == pytest.approx(-shift, abs=0.05)
        assert m.decision.direction == -int(np.sign(shift))


def test_vertical_misalignment_is_found_by_vertical_search():
    master, slave = shifted_pair(5, seed=2)
    slave = np.roll(slave, 2, axis=0)  # slave content 2 rows lower
    m = vergence.match(master, slave, vsearch=3)
    assert m.decision.v == 2 and m.offset_px == pytest.approx(-5.0, abs=0.02)


def test_faithful_params_turn_every_extension_off():
    p = vergence.FAITHFUL
    assert (p.vsearch, p.circular, p.subpixel, p.min_margin, p.min_texture, p.min_correlation, p.lr_check,
            p.support, p.halves_check, p.max_window, p.photometric) == (0, False, False, 0.0, 0.0, 0.0, False, False,
                                                                        False, 0, "none")
    with pytest.raises(TypeError, match="unknown parameter"):
        vergence.Params.build(windw=3)
    with pytest.raises(ValueError, match="photometric must be one of none, affine, histogram"):
        vergence.Params(photometric="gamma")


@pytest.mark.parametrize("mode", ["affine", "histogram"])
def test_photometric_undoes_the_slave_cameras_gain_and_offset(mode):
    """retina.photometric maps the slave's gray strip onto the master's: a slave seeing the same rows at
    gain 1.3 / +20 or 0.7 / -15 comes back within a level or two (bar its saturated pixels), the same strip
    comes back unchanged, and 'none' leaves it alone."""
    rng = np.random.default_rng(3)
    master = cv2.GaussianBlur(rng.integers(30, 200, (29, 642), dtype=np.uint8), (5, 5), 1.0)
    assert np.array_equal(retina.photometric(master, master, mode), master)
    for gain, off in ((1.3, 20), (0.7, -15)):
        slave = np.clip(master * gain + off, 0, 255).astype(np.uint8)
        assert np.abs(slave.astype(int) - master).mean() > 10
        back = retina.photometric(slave, master, mode).astype(int)
        unsat = (slave > 0) & (slave < 255)
        assert np.abs(back - master)[unsat].mean() < 1.0 and np.abs(back - master)[unsat].max() <= 3
        assert retina.photometric(slave, master, "none") is slave
    flat = np.full_like(master, 77)
    assert np.all(retina.photometric(flat, master, mode) == retina.photometric(flat, master, mode)[0, 0])


@pytest.mark.parametrize("gain,off", [(1.3, 20), (0.7, -15)])
def test_match_holds_under_the_slave_cameras_gain(gain, off):
    """The default network (photometric 'affine') gives the same winner with the slave at another gain
    and offset as at the master's; the same pair without the mapping is thrown off."""
    master, slave = shifted_pair(7, seed=5)
    dim = np.clip(slave * gain + off, 0, 255).astype(np.uint8)
    same = vergence.match(master, slave)
    m = vergence.match(master, dim)
    assert m.confident and (m.decision.k, m.decision.v) == (same.decision.k, same.decision.v)
    assert m.offset_px == pytest.approx(same.offset_px, abs=0.1)
    raw = vergence.match(master, dim, photometric="none")
    assert raw.decision.confidence < m.decision.confidence


def test_correlation_check_tells_a_match_from_two_fields_of_noise():
    """correlation(): 1 for the same content (whatever the gain and offset between the cameras), 0 for a flat
    window, and below 0.3 (the default min_correlation is 0.35) for independent noise, even at the best offset."""
    from vergence.decide import correlation

    rng = np.random.default_rng(4)
    fovea = retina.planes(rng.integers(0, 256, (17, 17)).astype(np.uint8))
    band = np.zeros((3, 15, 40), np.uint8)
    band[:, :, 10:25] = fovea
    win = replace(decide(np.arange(26.0), 15), k=10, v=0)  # the check reads the winner's k and v only
    assert correlation(fovea, band, win) == pytest.approx(1.0)
    band[0, :, 10:25] = np.clip(fovea[0] * 0.5 + 40, 0, 255).astype(np.uint8)
    assert correlation(fovea, band, win) == pytest.approx(1.0, abs=0.01)
    band[0, :, 10:25] = 90
    assert correlation(fovea, band, win) == 0.0
    # a flat wall with sigma-3 sensor noise in each camera: the network's own best offset does not pass
    p = vergence.Params(max_window=0)
    for seed in range(10):
        master, slave = (np.clip(128 + np.random.default_rng(2 * seed + i).normal(0, 3, (240, 320)), 0, 255)
                         .astype(np.uint8) for i in (0, 1))
        m = vergence.match(master, slave, params=replace(p, min_correlation=0.0, lr_check=False, halves_check=False))
        fov, bnd = retina.features(master, slave, None, 15, p.vsearch)
        assert correlation(fov, bnd, m.decision) < 0.3
        assert not vergence.match(master, slave, params=p).confident


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
