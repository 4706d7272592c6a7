"""vergence.tools.evaluate: the accuracy measurement on any pair with ground truth (`vergence accuracy`), whose
visible() and points() the tests' own draws (tests/middlebury.py) are."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

import vergence
from vergence.tools import evaluate
from middlebury import load, needs_data, points, visible

# recorded from tests/middlebury.points("teddy", 500, 0, 40, mask=visible("teddy")) before it became
# vergence.tools.evaluate.points: every accuracy figure in README and docs/MEASUREMENTS.md was measured on this draw
TEDDY_FIRST = [(354, 227), (229, 119), (153, 52), (67, 44), (104, 279), (280, 309), (226, 218), (399, 255)]
TEDDY_SHA256 = "ea5139741359b6e1e3e3446d844b17c6d240fcc6883c515772b017ed834b2f94"  # of repr(the 500 points)


def test_visible_hides_what_a_nearer_point_covers():
    d = np.array([[0, 1, 1, 3, 1, 1],  # x=3 (d 3) lands on right column 0, left of where x=1, 2 land (0, 1)
                  [2, 2, 2, 2, 2, 2],  # a plane: every point seen
                  [np.nan, 1, 1, 2, 0, 1]], dtype=np.float64)  # x=3 lands on 1, as x=2 does: x=2 hidden
    want = np.array([[0, 0, 0, 1, 1, 1],
                     [1, 1, 1, 1, 1, 1],
                     [0, 1, 0, 1, 0, 1]], dtype=bool)
    got = evaluate.visible(d)
    assert got.dtype == bool and (got == want).all(), got.astype(int)


@needs_data
def test_the_tests_draw_is_the_library_draw_and_unchanged():
    mask = visible("teddy")
    assert (mask == evaluate.visible(load("teddy")[2])).all()
    got = points("teddy", 500, 0, 40, mask=mask)
    assert got == evaluate.points(mask, 500, 0, 40)
    assert got[:len(TEDDY_FIRST)] == TEDDY_FIRST
    assert hashlib.sha256(repr(got).encode()).hexdigest() == TEDDY_SHA256


def test_points_refuses_a_draw_that_would_never_end():
    ok = np.zeros((100, 100), dtype=bool)
    ok[:10] = True  # only within the margin
    with pytest.raises(ValueError, match="no pixel"):
        evaluate.points(ok, 5, 0, 40)
    with pytest.raises(ValueError, match="too small"):
        evaluate.points(np.ones((60, 60), dtype=bool), 5, 0, 40)


def test_gained_is_float32_multiply_add_clipped():
    img = np.array([[0, 10, 100, 200, 255]], dtype=np.uint8)
    assert evaluate.gained(img, 1.0, 0.0) is img
    assert evaluate.gained(img, 1.3, 20.0).tolist() == [[20, 33, 150, 255, 255]]
    assert evaluate.gained(img, 0.7, -15.0).tolist() == [[0, 0, 55, 125, 163]]


def test_load_disparity_npz_unknowns_and_errors(tmp_path):
    p = tmp_path / "d.npz"
    np.savez(p, np.array([[1.5, np.inf], [-2.0, np.nan]], dtype=np.float32))
    assert evaluate.load_disparity(str(p)).tolist() == [[1.5, 0.0], [0.0, 0.0]]
    with pytest.raises(ValueError, match="nothere.npz.*no such file"):
        evaluate.load_disparity(str(tmp_path / "nothere.npz"))
    (tmp_path / "junk.npz").write_bytes(b"junk")
    with pytest.raises(ValueError, match="junk.npz"):
        evaluate.load_disparity(str(tmp_path / "junk.npz"))
    (tmp_path / "junk.png").write_bytes(b"junk")
    with pytest.raises(ValueError, match="junk.png"):
        evaluate.load_disparity(str(tmp_path / "junk.png"))


@needs_data
def test_static_is_a_loop_over_match_on_the_tests_points():
    left, right, disp = load("teddy")
    (got,) = evaluate.static(left, right, disp, vergence.Params(), seeds=[0], n=40, gains=["equal"])
    pts = points("teddy", 40, 0, 40, mask=visible("teddy"))
    ms = [vergence.match(left, right, p, vergence.Params()) for p in pts]
    conf = [abs(m.offset_px + disp[y, x]) <= 1.0 for m, (x, y) in zip(ms, pts) if m.confident]
    assert (got.gain, got.n, len(got.seeds), got.seeds[0].seed) == ("equal", 40, 1, 0)
    assert got.seeds[0].coverage == 100 * len(conf) / 40
    assert got.seeds[0].right == 100 * sum(conf) / len(conf)
    edges = evaluate.depth_edges(disp)
    near = [abs(m.offset_px + disp[y, x]) <= 1.0 for m, (x, y) in zip(ms, pts) if m.confident and edges[y, x]]
    away = [abs(m.offset_px + disp[y, x]) <= 1.0 for m, (x, y) in zip(ms, pts) if m.confident and not edges[y, x]]
    assert len(near) > 0 and len(away) > 0
    assert got.seeds[0].near == len(near) and got.near_pooled == (len(near), 100 * sum(near) / len(near))
    assert got.seeds[0].right_near == 100 * sum(near) / len(near)
    assert got.seeds[0].right_away == got.away_worst == 100 * sum(away) / len(away)
    assert 80 <= got.seeds[0].coverage <= 100 and got.seeds[0].right >= 90  # teddy: 92.5 / 100 at this draw
    assert got.mean == (got.seeds[0].coverage, got.seeds[0].right) == got.worst


def test_depth_edges_mark_steps_over_1_px_and_their_surroundings():
    d = np.tile(np.arange(20) * 0.5 + 10, (12, 1))  # a slanted surface: 0.5 px per column, no edge
    assert not evaluate.depth_edges(d).any()
    d[:, 10:] += 2.0  # a step of 2.5 px between columns 9 and 10
    cols = np.flatnonzero(evaluate.depth_edges(d).all(axis=0))
    assert cols.tolist() == list(range(6, 14))  # 9 and 10, and 3 px around them
    assert evaluate.depth_edges(d, radius=0).any(axis=0).nonzero()[0].tolist() == [9, 10]
    d2 = np.full((12, 20), 30.0)
    d2[5, 15] = 0.0  # an unknown pixel in a known surface: the border of an occlusion
    e = evaluate.depth_edges(d2, radius=1)
    assert np.argwhere(e).min(axis=0).tolist() == [3, 13] and np.argwhere(e).max(axis=0).tolist() == [7, 17]
    assert e.sum() == 25 - 4  # the five pixels (centre and its four neighbours), 1 px around: a 5 x 5 less its corners


def test_sizes_and_names_are_checked():
    a = np.zeros((100, 120), dtype=np.uint8)
    with pytest.raises(ValueError, match="sizes differ"):
        evaluate.static(a, a, np.ones((100, 121)), n=1, seeds=[0])
    with pytest.raises(ValueError, match="unknown gain.*grey"):
        evaluate.static(a, a, np.ones((100, 120)), n=1, seeds=[0], gains=["grey"])
