"""The simulated rig: rendering geometry (sign conventions), the spec parser, the generated scene."""

import math

import cv2
import numpy as np
import pytest

import vergence
from vergence.sim import Rig, generate, homography


def _dot_pair(x, y, d, size=(320, 240)):
    """A black pair with a bright 3 x 3 dot at (x, y) of LEFT and (x - d, y) of RIGHT."""
    w, h = size
    left, right = np.zeros((h, w), np.uint8), np.zeros((h, w), np.uint8)
    left[y - 1:y + 2, x - 1:x + 2] = 255
    right[y - 1:y + 2, x - d - 1:x - d + 2] = 255
    return left, right


def _centroid(img):
    ys, xs = np.nonzero(img > 40)
    wts = img[ys, xs].astype(float)
    return float((xs * wts).sum() / wts.sum()), float((ys * wts).sum() / wts.sum())


def test_positive_pan_moves_content_left():
    left, right = _dot_pair(160, 120, 0)
    rig = Rig(left, right, focal=300.0)
    x0, _ = _centroid(rig.render(0.0)[1])
    x1, _ = _centroid(rig.render(math.radians(2.0))[1])
    assert x0 == pytest.approx(160, abs=0.05)
    assert x1 == pytest.approx(160 - 300 * math.tan(math.radians(2.0)), abs=0.1)


def test_homography_is_k_rt_kinv():
    f, pan = 400.0, 0.1
    h = homography(f, (640, 480), (640, 480), pan, 0.0)
    # The source column at angle `pan` right of the axis lands on the view centre.
    p = h @ np.array([320 + f * math.tan(pan), 240.0, 1.0])
    assert p[:2] / p[2] == pytest.approx([320.0, 240.0], abs=1e-9)


POINTS = pytest.mark.parametrize("x,y,d", [(230, 60, 12), (90, 190, 5), (160, 120, 0)],
                                 ids=["up-right", "down-left", "centre"])


@POINTS
def test_master_fixates_and_truth_pan_centres_slave(x, y, d):
    """Common tilt axis (default): the converged slave shows the point on its centre, on the master's row."""
    left, right = _dot_pair(x, y, d)
    rig = Rig(left, right, fixate=(x, y), disparity=float(d), focal=280.0)
    master, slave = rig.render(rig.truth_pan_rad)
    assert _centroid(master) == pytest.approx((160, 120), abs=0.1)
    assert _centroid(slave) == pytest.approx((160, 120), abs=0.1)  # no vertical disparity
    assert rig.truth_pan_rad == pytest.approx(math.atan2(x - d - 160, math.hypot(280.0, y - 120)))
    assert rig.error_px(rig.truth_pan_rad) == 0.0
    assert rig.error_px(rig.pan_off_truth(7.0)) == pytest.approx(7.0, abs=1e-9)
    # ... and the point is then 7 px left of the slave centre.
    assert _centroid(rig.render(rig.pan_off_truth(7.0))[1])[0] == pytest.approx(153, abs=0.15)


@POINTS
def test_fick_gimbal_truth_is_the_plain_formula_with_vertical_disparity(x, y, d):
    left, right = _dot_pair(x, y, d)
    rig = Rig(left, right, fixate=(x, y), disparity=float(d), focal=280.0, gimbal="fick")
    master, slave = rig.render(rig.truth_pan_rad)
    assert _centroid(master) == pytest.approx((160, 120), abs=0.1)
    sx, sy = _centroid(slave)
    assert sx == pytest.approx(160, abs=0.1)
    assert abs(sy - 120) < 3  # off the centre row when the pans differ and y != cy
    assert rig.truth_pan_rad == pytest.approx(math.atan((x - d - 160) / 280.0))
    if (x, y) == (230, 60):
        assert sy - 120 == pytest.approx(-0.54, abs=0.05)  # analytic: f * y'' / z'' = -0.54 px


def test_vertical_misalignment_moves_slave_content_down():
    left, right = _dot_pair(160, 120, 0)
    rig = Rig(left, right, focal=300.0, vmis_px=6.0)
    _, sy = _centroid(rig.render(0.0)[1])
    assert sy == pytest.approx(126.0, abs=0.1)


def test_photometric_options_and_determinism():
    a = Rig.from_spec("noise=3:gain=1.2:offset=-10:blur=1:seed=5")
    b = Rig.from_spec("noise=3:gain=1.2:offset=-10:blur=1:seed=5")
    ma, sa = a.render(0.01)
    mb, sb = b.render(0.01)
    assert np.array_equal(ma, mb) and np.array_equal(sa, sb)
    clean = Rig.from_spec("seed=5")
    mc, _ = clean.render(0.01)
    assert 2.0 < np.abs(ma.astype(float) - mc).mean() < 4.0  # noise sigma 3


def test_a_held_pan_renders_its_view_once_and_the_same_bytes():
    """The still scene's slave views are kept per pan and region: equal byte for byte to a fresh render, read-only,
    a band not mistaken for another band or the whole view, a new pan rendered anew."""
    from vergence.sim.optics import Region

    a = Rig.from_spec("gain=1.2:offset=-10:blur=1:seed=5")
    band, other = Region.band(a.size[0], 200, 260), Region.band(a.size[0], 100, 160)
    first = a.slave_view(0.01, 0.0, band)
    again = a.slave_view(0.01, 0.5, band)
    assert again is first and not first.flags.writeable
    with pytest.raises(ValueError):
        first[0, 0] = 1
    fresh = Rig.from_spec("gain=1.2:offset=-10:blur=1:seed=5")
    assert np.array_equal(first, fresh.slave_view(0.01, 0.0, band))
    assert np.array_equal(a.slave_view(0.01, 0.0, other), fresh.slave_view(0.01)[100:160])
    assert np.array_equal(a.slave_view(0.01), fresh.slave_view(0.01)) and a.slave_view(0.01).shape == (480, 640)
    turned = a.slave_view(0.02, 0.0, band)
    assert turned is not first and not np.array_equal(turned, first)
    assert np.array_equal(turned, fresh.slave_view(0.02)[200:260])
    for k in range(3 * Rig.VIEWS):  # the cache keeps a few views, not every pan
        a.slave_view(0.001 * k, 0.0, band)
    assert len(a._views) == Rig.VIEWS


def test_the_two_cameras_noise_is_independent():
    """Sensor noise is drawn for each camera apart: the slave's noise field is never the master's shifted
    (they once shared pre-drawn fields, and the network matched the noise pattern of a flat wall)."""
    flat = np.full((240, 320), 128, np.uint8)
    rig = Rig(flat, flat, noise=4.0, seed=1)
    for _ in range(12):
        master, slave = (v.astype(np.float32) for v in rig.render(0.0))
        probe = master[88:152, 128:192]  # 64 x 64 from the middle, searched over every shift
        best = cv2.matchTemplate(slave, probe, cv2.TM_CCOEFF_NORMED).max()
        assert best < 0.3


def test_generated_scene_is_a_consistent_pair():
    sc = generate(seed=1, size=(320, 240))
    ys, xs = np.mgrid[0:240, 0:320]
    d = sc.disparity.astype(int)
    ok = xs - d >= 0
    # Every visible left pixel is found in RIGHT at x - d unless a nearer surface hides it there.
    same = sc.left[ok] == sc.right[ys[ok], (xs - d)[ok]]
    assert same.mean() > 0.9
    assert set(np.unique(sc.disparity)) >= {8.0, 24.0}
    assert sc.disparity[120, 160] == 24.0


def test_default_rig_matches_the_truth():
    rig = Rig.from_spec("")
    assert rig.size == (640, 480) and rig.focal_px == pytest.approx(512.0)
    assert rig.start_pan_rad == 0.0
    for px in (-30.0, 0.0, 20.0):
        m = vergence.match(*rig.render(rig.pan_off_truth(px)))
        assert m.confident
        assert m.offset_px == pytest.approx(-px, abs=0.3)


@pytest.mark.parametrize("spec,word", [
    ("colour=red", "colour"), ("noise=abc", "noise"), ("fixate=1", "fixate"), ("focal=-3", "focal"),
    ("left=/nonexistent.png:right=/nonexistent.png", "left"), ("left=/x.png", "right"),
    ("noise", "noise"), ("fixate=5000,10", "fixate"), ("d=3", "d="), ("pan=nan", "pan"),
    ("gimbal=euler", "gimbal"),
], ids=lambda v: str(v)[:20])
def test_bad_spec_names_the_key(spec, word):
    with pytest.raises(ValueError, match=word):
        Rig.from_spec(spec)


def test_spec_reads_a_pair_and_disparity(tmp_path):
    import cv2
    sc = generate(seed=2, size=(320, 240))
    cv2.imwrite(str(tmp_path / "l.png"), sc.left)
    cv2.imwrite(str(tmp_path / "r.png"), sc.right)
    cv2.imwrite(str(tmp_path / "d.png"), (sc.disparity * 4).astype(np.uint8))
    rig = Rig.from_spec(f"left={tmp_path}/l.png:right={tmp_path}/r.png:disparity={tmp_path}/d.png:dscale=4"
                        ":fixate=100,80:focal=250:pan=1.5")
    assert rig.size == (320, 240) and rig.fixation == (100, 80)
    assert rig.disparity == sc.disparity[80, 100]
    assert rig.start_pan_rad == pytest.approx(math.radians(1.5))
    nod = Rig.from_spec(f"left={tmp_path}/l.png:right={tmp_path}/r.png")
    assert math.isnan(nod.truth_pan_rad)
