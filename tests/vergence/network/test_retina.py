"""Layer 1 (vergence.network.retina): the feature planes I, G, D against a plain reference written from ALGORITHM.md
(tests/references.py), the strips, the border errors, and the photometric mapping of the slave's gray levels."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

import vergence
import middlebury
from references import ref_features
from vergence.network import retina


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


def test_the_direction_table_is_the_exact_direction_on_any_cpu():
    """planes() looks D up in a table of every Sobel gradient: each entry is round(atan2 * 128 / pi) mod 256 of
    exact maths, because no integer gradient's angle lies within 1e-6 of a step of a rounding boundary (float64's
    error is 1e-15 of one; float32's, the old per-pixel route, is not: it rounded 10 entries the other way). The
    planes of noise, of 0/255 edges (the extreme gradients, +-1020) and of a real photo equal the float64
    reference of ALGORITHM.md."""
    g = retina.GRAD_MAX
    table = retina.direction_table()
    assert table.shape == (2 * g + 1,) * 2 and not table.flags.writeable
    assert table[g, g] == 0 and table[g, g + 5] == 0 and table[g + 5, g] == 64  # no gradient; right; down
    assert table[g, g - 5] == 128 and table[g - 5, g] == 192 and table[g + g, g + g] == 32
    v = np.arange(-g, g + 1, dtype=np.float64)
    steps = (np.arctan2(v[:, None], v[None, :]) % (2 * np.pi)) * (128 / np.pi) + 0.5
    near = np.abs(steps - np.round(steps))
    near[g, g] = 1.0
    assert near.min() > 1e-6
    assert table[g - 834, g + 382] == int(np.floor(steps[g - 834, g + 382])) % 256  # one float32 rounded wrong
    exact = np.floor(steps).astype(np.int64) % 256
    exact[g, g] = 0
    assert np.array_equal(table, exact)  # every entry (the table mirrors one quadrant)
    rng = np.random.default_rng(11)
    images = [rng.integers(0, 256, (33, 643), dtype=np.uint8), (rng.integers(0, 2, (17, 300)) * 255).astype(np.uint8),
              cv2.GaussianBlur(rng.integers(0, 256, (40, 200), dtype=np.uint8), (5, 5), 1.5)]
    if (middlebury.ROOT / "scenes.json").is_file():
        images.append(middlebury.load("teddy")[0])
    for img in images:
        assert np.array_equal(retina.planes(retina.strip(img, 0, img.shape[0], 0, img.shape[1])), ref_features(img))


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


def test_clipped_share_says_which_camera_lost_what_share():
    """retina.clipped_share: the share of the fovea's rows (band) one camera shows black or saturated where the
    other still has texture. A random texture, every level alike: the slave at gain 1.3, +20 saturates the
    master's levels >= 181 (29 % of the band), at 0.7, -15 it blacks out the levels <= 22 (9 %); the same pair
    swapped names the master; equal cameras, and a camera that is merely dimmer (0.8, +0: nothing clipped),
    lose nothing."""
    master = np.random.default_rng(5).integers(0, 256, (480, 640), dtype=np.uint8)
    band = retina.band_strip(master, 240, 15, 6)
    for (gain, off), lost in (((1.3, 20), np.mean(band >= 181)), ((0.7, -15), np.mean(band <= 22))):
        slave = np.clip(master.astype(np.float32) * np.float32(gain) + np.float32(off), 0, 255).astype(np.uint8)
        got = retina.clipped_share(master, slave, 240, 15, 6)
        assert got["master"] == 0.0 and got["slave"] == pytest.approx(lost, abs=0.01), got
        swapped = retina.clipped_share(slave, master, 240, 15, 6)
        assert swapped["slave"] == 0.0 and swapped["master"] == pytest.approx(lost, abs=0.01), swapped
    assert retina.clipped_share(master, master, 240, 15, 6) == {"slave": 0.0, "master": 0.0}
    dim = (master.astype(np.float32) * np.float32(0.8)).astype(np.uint8)
    assert retina.clipped_share(master, dim, 240, 15, 6) == {"slave": 0.0, "master": 0.0}
