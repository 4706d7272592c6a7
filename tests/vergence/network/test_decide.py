"""Winner-takes-all and layer 5 (vergence.decide): the winner, its direction and magnitude, the sub-pixel
vertex, the vertical search, the margin and the correlation check."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import vergence
from vergence.network import retina
from vergence.network.decide import centre_offset, decide


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
    d = decide(y, 15, vshift_cost=0.0)
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
    assert decide(y, 15, vshift_cost=0.0).v == 2 and decide(y[2:3], 15, vshift_cost=0.5).k == 30
    dd = decide(y, 15)  # the default cost is Params' (0.5)
    assert (dd.k, dd.v, dd.score, dd.confidence) == (d.k, d.v, d.score, d.confidence)


def test_margin_is_zero_for_a_tie_and_one_without_rival():
    y = np.zeros(60)
    y[10] = y[40] = 100.0
    assert decide(y, 15).confidence == 0.0 and not decide(y, 15).confident
    assert decide(np.array([1.0, 5.0, 1.0]), 3).confidence == 1.0


def test_correlation_check_tells_a_match_from_two_fields_of_noise():
    """pearson(): 1 for the same content (whatever the gain and offset between the cameras), 0 for a flat
    window, and below 0.3 (the default min_correlation is 0.35) for independent noise, even at the best offset."""
    from vergence.network.decide import pearson

    rng = np.random.default_rng(4)
    fovea = retina.planes(rng.integers(0, 256, (17, 17)).astype(np.uint8))
    band = np.zeros((3, 15, 40), np.uint8)
    band[:, :, 10:25] = fovea
    win = replace(decide(np.arange(26.0), 15), k=10, v=0)  # the check reads the winner's k and v only
    assert pearson(fovea, band, win) == pytest.approx(1.0)
    band[0, :, 10:25] = np.clip(fovea[0] * 0.5 + 40, 0, 255).astype(np.uint8)
    assert pearson(fovea, band, win) == pytest.approx(1.0, abs=0.01)
    band[0, :, 10:25] = 90
    assert pearson(fovea, band, win) == 0.0
    # a flat wall with sigma-3 sensor noise in each camera: the network's own best offset does not pass
    p = vergence.Params(max_window=0)
    for seed in range(10):
        master, slave = (np.clip(128 + np.random.default_rng(2 * seed + i).normal(0, 3, (240, 320)), 0, 255)
                         .astype(np.uint8) for i in (0, 1))
        m = vergence.match(master, slave, params=replace(p, min_correlation=0.0, lr_check=False, halves_check=False))
        fov, bnd = retina.features(master, slave, None, 15, p.vsearch)
        assert pearson(fov, bnd, m.decision) < 0.3
        assert not vergence.match(master, slave, params=p).confident


def test_decide_defaults_are_params_so_it_agrees_with_match():
    """vergence.decide(y, w) on the scores match() decided on gives match's winner and confidence, and is
    confident wherever match is (match adds the checks that need the images, never removes a confidence): its
    defaults are Params' (issue #34: they were min_margin 0.04, min_texture 4, no vertical shift cost, and
    decide said confident where match abstained on the margin alone)."""
    import inspect

    import vergence
    from vergence.sim.scene import generate

    defaults = {k: v.default for k, v in inspect.signature(decide).parameters.items() if v.default is not v.empty}
    p = vergence.Params()
    assert {k: defaults[k] for k in ("subpixel", "min_margin", "min_texture", "vshift_cost")} == {
        "subpixel": p.subpixel, "min_margin": p.min_margin, "min_texture": p.min_texture, "vshift_cost": p.vshift_cost}
    sc = generate(seed=3, size=(320, 240))
    agree = 0
    for x, y in [(160, 120), (100, 80), (220, 160), (60, 200), (250, 60)]:
        m = vergence.match(sc.left, sc.right, at=(x, y))
        d = vergence.decide(m.scores, m.window, k_centre=x - m.window // 2)
        assert (d.k, d.v) == (m.decision.k, m.decision.v) and d.confidence == pytest.approx(m.decision.confidence)
        assert d.confident or not m.confident
        assert d.confident == (m.decision.confidence >= p.min_margin)  # the margin alone: the same call
        agree += d.confident == m.confident
    assert agree >= 4
