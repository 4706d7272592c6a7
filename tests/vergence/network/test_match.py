"""The whole network (vergence.match, vergence.network.params): known shifts recovered, abstention on a textureless
fovea, the vertical search, the faithful parameters, and the slave camera's gain."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

import vergence


@pytest.mark.parametrize("fill", [0, 128], ids=["black", "flat-grey"])
def test_textureless_fovea_abstains(fill):
    master = np.full((120, 160), fill, np.uint8)
    slave = np.random.default_rng(0).integers(0, 256, (120, 160), dtype=np.uint8)
    m = vergence.match(master, slave)
    assert not m.confident and m.decision.texture == 0.0
    assert vergence.match(master, slave, faithful=True).confident  # the paper has no abstention


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
