"""`vergence monitor --once` and `--png` against a running `vergence up` (real processes, bounded waits). The tests
that only watch `up` share one (the module's `rig`)."""

from __future__ import annotations

import re
import shutil

import cv2
import pytest

from procs import Procs, free_port, gives_up_without_a_router, textured_pair, tmux

pytestmark = pytest.mark.slow  # every test here runs real processes


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """`vergence up` on a textured pair (2 workers, 20 Hz) on a free port, for the tests that only watch it; its
    Procs (the tests start their monitors with it: the rig's --rig and --connect)."""
    tmp = tmp_path_factory.mktemp("up")
    cfg = tmp / "settings.toml"
    cfg.write_text("[network]\nmax_window = 0\n[capture]\npreview_hz = 0\n")
    with Procs(tmp) as P:
        P.endpoint = f"tcp/127.0.0.1:{free_port()}"
        P.start("up", "up", "--listen", P.endpoint, "--source", textured_pair(tmp), "--workers", "2", "--rate", "20",
                "--config", str(cfg), "--no-standby", connect=False)
        P.wait_port(20)
        yield P


def test_monitor_once_and_png_against_up(tmp_path, rig):
    P = rig
    mon = P.start("monitor", "monitor", "--once", "--color", "never", "--timeout", "30")
    assert mon.wait(40) == 0, mon.tail()
    text = mon.text()
    # the fovea's match lies 12 px left of the centre column (the first decision, before any move)
    # or at the centre once the slave turned; both are screens of a live rig
    assert re.search(r"decision k\*=\d+ .* k_c=153 ", text), text
    assert re.search(r"rate   frames +\d+\.\d/s", text)
    assert "workers 2:" in text, text
    shards = re.findall(r"k (\d+)\.\.(\d+)", text.split("workers 2:")[1].splitlines()[0])
    assert sorted((int(a), int(b)) for a, b in shards) == [(0, 152), (153, 305)]  # K = 320 - 15 + 1
    assert "▲" in text and "┴" in text
    png = tmp_path / "fig5.png"  # (the test's own folder; the monitors' logs are in the rig's)
    mon2 = P.start("monitor-png", "monitor", "--png", str(png), "--history", "1", "--size", "640x480",
                   "--timeout", "30")
    assert mon2.wait(40) == 0, mon2.tail()
    img = cv2.imread(str(png))
    assert img.shape == (480, 640, 3) and img.std() > 10
    assert ((img[:, :, 2] > 180) & (img[:, :, 1] < 60)).sum() > 100  # the red winner marker


@pytest.mark.skipif(shutil.which("tmux") is None, reason="needs tmux (apt-get install tmux)")
def test_live_monitor_in_a_terminal(tmp_path, rig):
    """`vergence monitor` as a person runs it: in a 100 x 40 terminal (tmux), against `vergence up`. The screen
    is redrawn in place (one header, at the top, not a scroll of screens), no line wraps, it shows the decision,
    both workers' shards and the pan, moves on (the frame id changes between two looks), and Ctrl-C ends it
    (the pane's process exits 0)."""
    from procs import VERGENCE, wait_for

    name = f"vergence-monitor-{tmp_path.name}"[:60].replace(".", "-")
    P, endpoint = rig, rig.endpoint
    # COLUMNS=80: a stale width inherited from the environment; the screen follows the terminal's own (100)
    cmd = (f"COLUMNS=80 LINES=24 {VERGENCE} monitor --connect {endpoint} --rig {P.rig} --refresh 0.3; "
           f"echo monitor-exit=$?; sleep 30")
    tmux("new-session", "-d", "-s", name, "-x", "100", "-y", "40", cmd)
    try:
        def screen() -> str:
            return tmux("capture-pane", "-p", "-J", "-t", name)  # -J: a line tmux wrapped comes back whole

        first = wait_for(lambda: (lambda t: t if "workers 2:" in t and "decision k*=" in t else None)(screen()),
                         40, "the monitor's screen", logs=P.logs)
        print(first)  # the screen (pytest -s)
        assert first.count("rate   frames") == 1, first  # redrawn in place
        assert first.splitlines()[0].startswith("vergence monitor · rig "), first  # from the top
        assert max(len(ln) for ln in first.splitlines()) <= 100, first  # nothing wrapped
        axis = next(ln for ln in first.splitlines() if ln.lstrip().startswith("k=0"))
        assert len(axis) == 100 and axis.endswith("k=305"), first  # the profile spans the terminal's width
        assert re.search(r"decision k\*=\d+ .* k_c=153 ", first) and "pan " in first, first
        assert "▲" in first and "┴" in first
        frame_of = re.compile(r"frame (\d+)")
        f0 = frame_of.search(first)
        assert f0, first
        wait_for(lambda: (m := frame_of.search(screen())) and int(m.group(1)) > int(f0.group(1)), 10,
                 "the screen to move on", logs=P.logs)
        tmux("send-keys", "-t", name, "C-c")
        end = wait_for(lambda: (lambda t: t if "monitor-exit=" in t else None)(screen()), 10,
                       "the monitor to exit on Ctrl-C", logs=P.logs)
        assert "monitor-exit=0" in end, end
    finally:
        tmux("kill-session", "-t", name, check=False)


@pytest.mark.parametrize("argv", [[], ["--once"]], ids=["live", "once"])
def test_monitor_without_a_router_gives_up_within_its_wait(argv):
    """Issue #28: the live view kept trying forever, --once for 10 s; --wait (default 5 s) bounds both."""
    gives_up_without_a_router("monitor", *argv, "--wait", "1", within=1)
