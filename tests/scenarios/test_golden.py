"""Golden outputs (issue #34: before the library's modules move, what they print is pinned): `vergence sim --json`
over a few option sets, `vergence match --json` on a real pair, and the monitor's text on a fixed stream of
messages. Each must equal the file in tests/golden/ that was written by the code before the move.

JSON values compare exactly (ints, strings, booleans, nulls, the keys and their order) but for floats, which may
differ in their last bits between numpy's SIMD builds on other CPUs (reductions sum in another order): within
1e-9, relative, far below anything a change of behaviour moves. The monitor's text compares byte for byte.
`VERGENCE_WRITE_GOLDEN=1 python -m pytest tests/scenarios/test_golden.py` writes the files again (only for a change of
behaviour that is meant, said in its commit)."""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
from pathlib import Path

import pytest

import middlebury
from services.ops import cli

HERE = Path(__file__).resolve().parents[1] / "golden"
WRITE = os.environ.get("VERGENCE_WRITE_GOLDEN") == "1"

SIM = {
    "sim-still": ["--frames", "12"],
    "sim-photometric": ["--frames", "12", "--noise", "3", "--gain", "1.3", "--offset", "20", "--seed", "5",
                        "--start-pan", "2", "--blur", "0.8", "--vmis", "1"],
    "sim-faithful-fick": ["--frames", "10", "--faithful", "--gimbal", "fick", "--start-pan", "-1.5"],
    "sim-moving": ["--frames", "30", "--motion", "sine:z=0.8,amp=0.3,hz=0.5", "--camera-latency", "0.033",
                   "--skew", "0.004", "--rate", "60"],
    "sim-fovea-move": ["--frames", "16", "--fixate-at", "6:250,200", "--mode", "p"],
}


def run_cli(*argv: str) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = cli.main(list(argv))
    assert code == 0, argv
    return out.getvalue()


def same(got, want, where: str = "") -> None:
    """got equals want: exactly, but floats within 1e-9 relative (and NaN with NaN)."""
    if isinstance(want, float) and isinstance(got, float):
        assert got == want or (math.isnan(got) and math.isnan(want)) or math.isclose(got, want, rel_tol=1e-9,
                                                                                      abs_tol=1e-12), where
    elif isinstance(want, dict):
        assert isinstance(got, dict) and list(got) == list(want), where
        for k in want:
            same(got[k], want[k], f"{where}.{k}")
    elif isinstance(want, list):
        assert isinstance(got, list) and len(got) == len(want), where
        for i, (g, w) in enumerate(zip(got, want)):
            same(g, w, f"{where}[{i}]")
    else:
        assert type(got) is type(want) and got == want, (where, got, want)


def check_lines(name: str, text: str) -> None:
    path = HERE / f"{name}.jsonl"
    if WRITE:
        path.write_text(text)
    want = path.read_text().splitlines()
    got = text.splitlines()
    assert len(got) == len(want), name
    for i, (g, w) in enumerate(zip(got, want)):
        same(json.loads(g), json.loads(w), f"{name}:{i + 1}")


@pytest.mark.parametrize("name", list(SIM))
def test_sim_json_is_the_golden_one(name):
    check_lines(name, run_cli("sim", "--json", *SIM[name]))


@middlebury.needs_data
def test_match_json_is_the_golden_one():
    scene = json.loads((middlebury.ROOT / "scenes.json").read_text())["teddy"]
    left, right = (str(middlebury.ROOT / scene[k]) for k in ("left", "right"))
    text = run_cli("match", left, right, "--json", "--at", "150,150", "--at", "300,200", "--at", "225,300",
                   "--baseline", "0.16", "--focal", "375")
    text += run_cli("match", left, right, "--json", "--faithful", "--at", "150,150", "--window", "21")
    check_lines("match-teddy", text)


def monitor_text() -> str:
    """The monitor's text (100 columns, no colour) after 3 s of a 100 Hz stream: frames, profiles of 3 rows
    (vertical search), commands 1-4 ms after their frames, a profile lost every 25th frame, motor states, two
    workers alive and the capture's status."""
    import numpy as np

    from vergence.wire import messages as m
    from vergence.observe.monitor import Monitor
    from vergence.observe.screen import render_text

    w, win, t0, ms = 640, 15, 1_700_000_000_000_000_000, 1_000_000
    kk = w - win + 1
    mon = Monitor("head")
    k = np.arange(kk, dtype=np.float64)
    for i in range(300):
        t = t0 + i * 10 * ms
        k_star = 300 + (i % 7)
        y = np.full((3, kk), 20000.0) + 1000.0 * np.cos(k / 17.0)
        y[1] += 30000.0 * np.exp(-0.5 * ((k - k_star) / 3.0) ** 2)
        mon.feed("vergence/head/frame", m.Frame(
            rig="head", frame=i, t_capture_ns=t, pan_rad=0.001 * i, width=w, height=480, x=320, y=240, window=win,
            vsearch=1, focal_px=500.0, fovea=bytes((win + 2) ** 2), band=bytes((win + 4) * (w + 2)),
            plan=[["w-1", 0, 313], ["w-2", 313, kk]]).to_bytes(), t)
        if i % 25 != 24:
            d = k_star - 313
            mon.feed("vergence/head/profile", m.Profile(
                rig="head", frame=i, t_capture_ns=t, t_reduced_ns=t + 2 * ms, width=w, window=win, rows=3,
                scores=y.astype("<f8").tobytes(), k=k_star, k_sub=k_star + 0.25, v_shift=0, k_centre=313,
                direction=int(np.sign(d)), magnitude=abs(d), offset_px=d + 0.25, confidence=0.4 + 0.001 * i,
                confident=i % 10 != 3, texture=30.0, pan_rad=0.001 * i, workers=["w-1", "w-2"]).to_bytes(), t + 2 * ms)
            mon.feed("vergence/head/command", m.Command(
                rig="head", frame=i, t_capture_ns=t, pan_rad=0.001 * i + 0.01, correction_rad=0.01, direction=-1,
                magnitude_px=13.0, confidence=0.5, t_sent_ns=t + (1 + i % 4) * ms).to_bytes(), t + 3 * ms)
        mon.feed("vergence/head/motor_state", m.MotorState(
            rig="head", t_ns=t + 3 * ms, pan_rad=0.001 * i, goal_rad=0.001 * i + 0.01, min_rad=-0.5, max_rad=0.5,
            status="ok").to_bytes(), t + 3 * ms)
    mon.liveliness("vergence/head/alive/worker/w-1", True)
    mon.liveliness("vergence/head/alive/worker/w-2", True)
    return render_text(mon.snapshot(t0 + 299 * 10 * ms + 4 * ms), width=100, color=False)


def test_monitor_text_is_the_golden_one(monkeypatch):
    import time

    monkeypatch.setenv("TZ", "UTC")  # the header's clock is local time
    time.tzset()
    try:
        text = monitor_text()
    finally:
        monkeypatch.undo()
        time.tzset()
    path = HERE / "monitor.txt"
    if WRITE:
        path.write_text(text)
    assert text == path.read_text()
