"""vergence.io.lens: camera_info read and refused by field, the pinhole lens left alone, the model's two directions
inverse to each other, the distortion removed from a band as from the whole image, and the band's source rows."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vergence.io.lens import Lens, Undistorter, band_rows, distort_grid, distort_point, undistort_point
from vergence.network import retina

SIZE = (640, 480)
K = [500.0, 0.0, 335.0, 0.0, 500.0, 228.0, 0.0, 0.0, 1.0]
BARREL = Lens(500, 335, 228, k1=-0.25, k2=0.05)
RATIONAL = Lens(500, 335, 228, k1=0.1, k2=-0.05, p1=0.001, p2=-0.002, k4=0.35, k5=-0.02, k6=0.01)
MARGIN = 120  # px around the pinhole render: BARREL's corners see up to 96 px past the view's edges


def grid(step: int = 8):
    ys, xs = np.mgrid[0 : SIZE[1] : step, 0 : SIZE[0] : step].astype(np.float64)
    xs[:, -1], ys[-1] = SIZE[0] - 1, SIZE[1] - 1  # the corners themselves
    return xs, ys


# -- camera_info ---------------------------------------------------------------------------------------------------


def test_camera_info_plumb_bob_and_rational():
    lens = Lens.from_camera_info(K, [-0.25, 0.05, 0.001, -0.002, 0.01], "plumb_bob", SIZE)
    assert (lens.focal_px, lens.fy, lens.cx, lens.cy) == (500, 500, 335, 228)
    assert lens.coefficients == (-0.25, 0.05, 0.001, -0.002, 0.01, 0, 0, 0)
    assert lens.model == "plumb_bob" and not lens.is_pinhole
    np.testing.assert_array_equal(lens.matrix(), np.array(K).reshape(3, 3))
    assert lens.distortion().tolist() == [-0.25, 0.05, 0.001, -0.002, 0.01]
    k = list(K)
    k[4] = 502.5
    lens = Lens.from_camera_info(k, [0.1, -0.05, 0.001, -0.002, 0, 0.35, -0.02, 0.01], "rational_polynomial", SIZE)
    assert lens.fy == 502.5 and lens.model == "rational_polynomial" and lens.distortion().shape == (8,)
    assert lens == Lens(500, 335, 228, fy=502.5, k1=0.1, k2=-0.05, p1=0.001, p2=-0.002, k4=0.35, k5=-0.02, k6=0.01)
    # plumb_bob with 4 numbers (k3 left out) and trailing zeros beyond the model are read
    assert Lens.from_camera_info(K, [-0.2, 0.0, 0.0, 0.0], "plumb_bob", SIZE).k1 == -0.2
    assert Lens.from_camera_info(K, [-0.2, 0, 0, 0, 0, 0, 0, 0], "plumb_bob", SIZE).model == "plumb_bob"


@pytest.mark.parametrize("d, model", [([], ""), ([], "plumb_bob"), ([0.0] * 5, "plumb_bob"),
                                      ([0.0] * 8, "rational_polynomial"), ([], "none")])
def test_camera_info_without_distortion_is_a_pinhole(d, model):
    lens = Lens.from_camera_info(K, d, model, SIZE)
    assert lens.is_pinhole and lens.model == "none"
    assert lens == Lens(500, 335, 228)


@pytest.mark.parametrize("k, d, model, field", [
    (K[:8], [], "plumb_bob", r"camera_info k: 8 numbers"),
    ([float("nan")] + K[1:], [], "plumb_bob", r"k\[0\] \(fx\): nan is not finite"),
    ([0.0] * 9, [], "", r"k\[0\] \(fx\): 0.0 px is not a focal length.*uncalibrated"),
    ([0.0] + K[1:], [], "plumb_bob", r"k\[0\] \(fx\): 0.0 px is not a focal length"),
    (K[:4] + [-500.0] + K[5:], [], "plumb_bob", r"k\[4\] \(fy\)"),
    (K[:1] + [0.5] + K[2:], [], "plumb_bob", r"k\[1\] \(skew\).*skewed pixel"),
    (K[:8] + [2.0], [], "plumb_bob", r"k\[8\]: 2.0, expected 1"),
    (K[:2] + [640.0] + K[3:], [], "plumb_bob", r"k\[2\] \(cx\): 640.0 px, the principal point is outside"),
    (K[:5] + [-1.0] + K[6:], [], "plumb_bob", r"k\[5\] \(cy\)"),
    (K, [-0.2, float("inf")], "plumb_bob", r"d\[1\] \(k2\): inf is not finite"),
    (K, [-0.2, 0, 0, 0, 0, 0.3, 0, 0], "plumb_bob", r"d\[5\] \(k4\).*'plumb_bob' has 5"),
    (K, [-0.2] + [0.0] * 7 + [0.01], "rational_polynomial", r"d\[8\] \(a thin-prism or tilt"),
    (K, [-0.2], "", r"d\[0\] \(k1\).*'' has 0"),
    (K, [0.1, 0.01, 0, 0], "equidistant", r"distortion_model: 'equidistant' \(the fisheye model\) is not supp"),
    (K, [], "pinhole", r"distortion_model: 'pinhole' is not one of"),
])
def test_camera_info_refused_naming_the_field(k, d, model, field):
    with pytest.raises(ValueError, match=field):
        Lens.from_camera_info(k, d, model, SIZE)


def test_lens_fields_checked():
    with pytest.raises(ValueError, match="focal_px: 0.0 px"):
        Lens(0, 320, 240)
    with pytest.raises(ValueError, match="k1: nan"):
        Lens(500, 320, 240, k1=float("nan"))
    with pytest.raises(ValueError, match="k4: model 'plumb_bob' has no such coefficient"):
        Lens(500, 320, 240, k1=0.1, k4=0.2, model="plumb_bob")
    with pytest.raises(ValueError, match="k1: model 'none'"):
        Lens(500, 320, 240, k1=0.1, model="none")
    with pytest.raises(ValueError, match="model: 'fisheye'"):
        Lens(500, 320, 240, model="fisheye")
    assert BARREL.model == "plumb_bob" and RATIONAL.model == "rational_polynomial" and Lens(1, 0, 0).model == "none"
    assert Lens.pinhole(500, (640, 481)) == Lens(500, 320, 240, model="none")


# -- the pinhole lens ----------------------------------------------------------------------------------------------


def test_pinhole_rows_are_the_slice():
    img = np.random.default_rng(0).integers(0, 256, (480, 640), dtype=np.uint8)
    u = Undistorter(Lens.pinhole(500, SIZE), SIZE)
    out = u.rows(img, 200, 229)
    assert out.base is img and np.shares_memory(out, img)
    np.testing.assert_array_equal(out, img[200:229])
    assert u.source_rows(200, 229) == (200, 229)
    np.testing.assert_array_equal(u.rows(img[190:240], 200, 229, top=190), img[200:229])
    assert distort_point(Lens.pinhole(500, SIZE), 12.5, 7.0) == (12.5, 7.0)
    assert undistort_point(Lens.pinhole(500, SIZE), 12.5, 7.0) == (12.5, 7.0)


# -- the model, both ways ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("lens", [BARREL, RATIONAL], ids=["plumb_bob", "rational"])
def test_distort_point_is_opencvs_model(lens):
    xs, ys = grid(32)
    u, v = distort_point(lens, xs, ys)
    obj = np.stack([(xs - lens.cx) / lens.focal_px, (ys - lens.cy) / lens.fy, np.ones_like(xs)], -1).reshape(-1, 3)
    ref, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), lens.matrix(), lens.distortion())
    np.testing.assert_allclose(np.stack([u.ravel(), v.ravel()], -1), ref.reshape(-1, 2), atol=1e-9)


@pytest.mark.parametrize("lens", [BARREL, RATIONAL], ids=["plumb_bob", "rational"])
def test_round_trips_within_a_hundredth_of_a_pixel(lens):
    xs, ys = grid()
    # distorted pixel -> pinhole -> distorted, over the whole image (the iteration's hard case: the corners)
    ux, uy = undistort_point(lens, xs, ys)
    bx, by = distort_point(lens, ux, uy)
    err = np.hypot(bx - xs, by - ys)
    assert err.max() < 0.01  # measured 1e-6 (the criterion's epsilon)
    # pinhole pixel -> distorted -> pinhole
    dx, dy = distort_point(lens, xs, ys)
    rx, ry = undistort_point(lens, dx, dy)
    assert np.hypot(rx - xs, ry - ys).max() < 0.01
    # OpenCV's default 5 iterations are not enough at the corners (0.52 px for plumb_bob, 2.9 px for rational)
    pts = np.stack([xs.ravel(), ys.ravel()], -1).reshape(-1, 1, 2)
    five = cv2.undistortPoints(pts, lens.matrix(), lens.distortion(), P=lens.matrix()).reshape(-1, 2)
    fx, fy = distort_point(lens, five[:, 0], five[:, 1])
    assert np.hypot(fx - xs.ravel(), fy - ys.ravel()).max() > 0.4
    assert isinstance(undistort_point(lens, 3.0, 4.0)[0], float)


def test_a_straight_line_stays_straight():
    t = np.linspace(0, 1, 41)
    x, y = 10 + 620 * t, 40 + 62 * t  # a pinhole line across the top of the image

    def off(px, py):  # the points' distances from the chord of the first and the last
        n = np.array([py[0] - py[-1], px[-1] - px[0]]) / np.hypot(px[-1] - px[0], py[-1] - py[0])
        return np.abs((px - px[0]) * n[0] + (py - py[0]) * n[1])

    dx, dy = distort_point(BARREL, x, y)
    assert off(dx, dy).max() > 10  # distorted: a curve (measured: bowed 13 px off its chord)
    rx, ry = undistort_point(BARREL, dx, dy)
    assert off(rx, ry).max() < 0.01
    assert np.hypot(rx - x, ry - y).max() < 0.01


# -- images --------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def scene():
    """A pinhole render of a smooth random texture (with a margin: the barrel's corners see past the view), the
    distorted camera's image made from it through distort_grid."""
    rng = np.random.default_rng(1)
    h, w = SIZE[1] + 2 * MARGIN, SIZE[0] + 2 * MARGIN
    tex = cv2.GaussianBlur(rng.random((h, w), np.float32) * 255, (0, 0), 3.0)
    tex = cv2.normalize(tex, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    mx, my = distort_grid(BARREL, SIZE, 0, SIZE[1])
    assert MARGIN > max(-mx.min(), mx.max() - SIZE[0], -my.min(), my.max() - SIZE[1])
    distorted = cv2.remap(tex, mx + MARGIN, my + MARGIN, cv2.INTER_LINEAR)
    return tex[MARGIN:-MARGIN, MARGIN:-MARGIN], distorted


def test_undistorted_rows_match_the_pinhole_render(scene):
    pinhole, distorted = scene
    assert np.abs(distorted.astype(int) - pinhole).mean() > 20  # distortion does move the texture
    u = Undistorter(BARREL, SIZE)
    out = u.rows(distorted, 0, SIZE[1])
    err = np.abs(out.astype(int) - pinhole)[8:-8, 8:-8]
    # measured: mean 0.68 gray level, max 6 (the texture's std 30; two bilinear passes, rounded to uint8 twice),
    # against a mean 26 between the distorted image and the pinhole render
    assert err.mean() < 1.0 and err.max() <= 10
    band = u.rows(distorted, 214, 243)
    assert band.shape == (29, 640)
    assert np.abs(band.astype(int) - pinhole[214:243])[:, 8:-8].mean() < 1.0  # measured 0.53


@pytest.mark.parametrize("fixed", [False, True], ids=["float32", "fixed-point"])
def test_a_band_reads_only_its_source_rows(scene, fixed):
    _, distorted = scene
    u = Undistorter(BARREL, SIZE, fixed=fixed)
    mx, my = cv2.initUndistortRectifyMap(BARREL.matrix(), BARREL.distortion(), None, BARREL.matrix(), SIZE,
                                         cv2.CV_32FC1)
    if fixed:
        mx, my = cv2.convertMaps(mx, my, cv2.CV_16SC2)
    full = cv2.remap(distorted, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    rng = np.random.default_rng(2)
    for y0, y1 in ((0, 29), (214, 243), (226, 287), (451, 480), (100, 101)):
        a, b = u.source_rows(y0, y1)
        band = u.rows(distorted, y0, y1)
        np.testing.assert_array_equal(band, full[y0:y1])
        np.testing.assert_array_equal(u.rows(distorted[a:b], y0, y1, top=a), band)
        other = rng.integers(0, 256, distorted.shape, dtype=np.uint8)  # every row but a..b-1 replaced
        other[a:b] = distorted[a:b]
        np.testing.assert_array_equal(u.rows(other, y0, y1), band)
    # the barrel pulls the top and bottom bands' sources toward the centre row (228), wider at the image's corners
    # than at its centre column; the middle band reads its own rows
    assert u.source_rows(0, 29) == (11, 56) and u.source_rows(214, 243) == (214, 243)
    assert u.source_rows(451, 480) == (419, 465)
    with pytest.raises(ValueError, match="read the distorted rows 11..55, not all in the image.s rows 12..40"):
        u.rows(distorted[12:41], 0, 29, top=12)
    with pytest.raises(ValueError, match="rows 470..480"):
        u.rows(distorted, 470, 481)


def test_fixed_point_maps_within_a_gray_level(scene):
    _, distorted = scene
    a = Undistorter(BARREL, SIZE).rows(distorted, 0, 480).astype(int)
    b = Undistorter(BARREL, SIZE, fixed=True).rows(distorted, 0, 480)
    assert np.abs(a - b).max() <= 1


def test_distort_grid_cached_a_row_at_a_time():
    lens = Lens(500, 335, 228, k1=-0.2, k2=0.04)
    mx, my = distort_grid(lens, SIZE, 200, 229)
    assert mx.shape == (29, 640) and mx.dtype == np.float32 and not mx.flags.writeable
    again = distort_grid(lens, SIZE, 200, 229)
    assert np.shares_memory(again[0], mx)
    wider = distort_grid(lens, SIZE, 190, 260)
    np.testing.assert_array_equal(wider[1][10:39], my)
    ux, uy = undistort_point(lens, np.arange(640.0), np.full(640, 215.0))
    np.testing.assert_allclose(mx[15], ux, atol=1e-4)
    np.testing.assert_allclose(my[15], uy, atol=1e-4)
    # and its inverse is the Undistorter's map: a distorted pixel's pinhole point maps back onto the pixel
    bx, by = distort_point(lens, mx.astype(np.float64), my.astype(np.float64))
    assert np.hypot(bx - np.arange(640), by - np.arange(200, 229)[:, None]).max() < 1e-3


def test_band_rows_are_what_a_frame_reads():
    img = np.repeat(np.arange(200, dtype=np.uint8)[:, None], 64, axis=1)
    for y, w, r in ((100, 15, 6), (100, 47, 6), (13, 15, 6), (186, 15, 6), (30, 31, 0)):
        y0, y1 = band_rows(y, w, r, 200)
        assert y1 - y0 == min(200, y + w // 2 + r + 2) - max(0, y - w // 2 - r - 1)
        read = set(retina.band_strip(img, y, w, r)[:, 0].tolist())
        assert read <= set(range(y0, y1))
        if 0 < y0 and y1 < 200:
            assert read == set(range(y0, y1)) and y1 - y0 == w + 2 * r + 2
