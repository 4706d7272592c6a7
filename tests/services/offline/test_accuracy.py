"""`vergence accuracy` as a user runs it: a real process on a pair written to files (PNG + a .npz disparity), its
figures those of the library (vergence.tools.evaluate), one-line errors with exit status 2."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

import vergence
from vergence.tools import evaluate
from middlebury import load, needs_data
from procs import run

pytestmark = [needs_data, pytest.mark.slow]  # every test here runs the real command as a process


def vergence_cli(*args):
    return run(*args, timeout=120)


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("pair")
    left, right, disp = load("teddy")
    cv2.imwrite(str(d / "left.png"), left)
    cv2.imwrite(str(d / "right.png"), right)
    np.savez(d / "disp.npz", disp)
    cv2.imwrite(str(d / "small.png"), left[:100, :100])
    return d


def files(d, disp="disp.npz"):
    return [str(d / "left.png"), str(d / "right.png"), str(d / disp)]


def test_json_is_the_library_static_figures(pair):
    r = vergence_cli("accuracy", *files(pair), "--n", "30", "--seeds", "0", "--gains", "equal", "--json")
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout)
    left, right, disp = load("teddy")
    (want,) = evaluate.static(left, right, disp, vergence.Params(), seeds=[0], n=30, gains=["equal"])
    assert got == {"mode": "static", "seeds": [0], "n": 30, "gains": [want.to_dict()]}
    s = got["gains"][0]["seeds"][0]
    assert 80 <= s["coverage"] <= 100 and s["right"] >= 90  # teddy, seed 0: 93.3 / 100


def test_human_lines_and_set(pair):
    r = vergence_cli("accuracy", *files(pair), "--n", "20", "--seeds", "0,1", "--gains", "equal,dark",
                     "--set", "clip_fallback=false", "--set", "min_margin=0.3")
    assert r.returncode == 0, r.stderr
    left, right, disp = load("teddy")
    params = vergence.Params(clip_fallback=False, min_margin=0.3)
    want = evaluate.static(left, right, disp, params, seeds=[0, 1], n=20, gains=["equal", "dark"])
    assert r.stdout.splitlines() == [g.line() for g in want]
    assert r.stdout.startswith("equal: confident / right among confident, per seed [0, 1]: ")


@pytest.mark.parametrize("which", ["left.png", "right.png", "disp.npz"])
def test_a_missing_file_is_named(pair, which):
    args = [a if not a.endswith(which) else str(pair / ("nothere_" + which)) for a in files(pair)]
    r = vergence_cli("accuracy", *args, "--n", "5", "--seeds", "0")
    assert r.returncode == 2 and r.stdout == ""
    assert "nothere_" + which in r.stderr and "no such file" in r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_sizes_that_differ_are_named(pair):
    r = vergence_cli("accuracy", str(pair / "left.png"), str(pair / "small.png"), str(pair / "disp.npz"))
    assert r.returncode == 2 and "sizes differ" in r.stderr and "small.png is" not in r.stderr
    assert "small.png 100 x 100" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.parametrize("kv,says", [("nosuchfield=1", "nosuchfield: unknown setting"),
                                     ("window=abc", "window: expected `int`"),
                                     ("photometric=bogus", "photometric must be one of")])
def test_a_bad_set_names_the_field(pair, kv, says):
    r = vergence_cli("accuracy", *files(pair), "--n", "5", "--seeds", "0", "--set", kv)
    assert r.returncode == 2 and says in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_loop_is_the_library_loop(pair):
    r = vergence_cli("accuracy", *files(pair), "--loop", "--n", "5", "--seeds", "3", "--gains", "equal,bright",
                     "--json")
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout)
    left, right, disp = load("teddy")
    want = evaluate.loop(left, right, disp, vergence.Params(), seeds=[3], n=5, gains=["equal", "bright"])
    assert got == {"mode": "loop", "seeds": [3], "n": 5, "gains": [g.to_dict() for g in want]}
    equal, bright = got["gains"]
    assert equal["points"] == bright["points"] == 5
    assert 0 <= equal["converged"] <= 100 and 0 <= bright["converged"] <= 100
    assert equal["paired"] is None and bright["paired"] == pytest.approx(bright["converged"] - equal["converged"])
