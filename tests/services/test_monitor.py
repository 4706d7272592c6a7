"""`vergence monitor --once` and `--png` against a running `vergence up` (real processes, bounded waits)."""

from __future__ import annotations

import re

import cv2
import pytest

from procs import Procs, free_port, textured_pair

pytestmark = pytest.mark.slow  # every test here runs real processes


@pytest.fixture
def pair(tmp_path):
    cfg = tmp_path / "settings.toml"
    cfg.write_text("[network]\nmax_window = 0\n[capture]\npreview_hz = 0\n")
    return textured_pair(tmp_path), str(cfg)


def test_monitor_once_and_png_against_up(tmp_path, pair):
    source, cfg = pair
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with Procs(tmp_path) as P:
        P.endpoint = endpoint
        P.start("up", "up", "--listen", endpoint, "--source", source, "--workers", "2", "--rate", "20",
                "--config", cfg, connect=False)
        P.wait_port(20)
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
        png = tmp_path / "fig5.png"
        mon2 = P.start("monitor-png", "monitor", "--png", str(png), "--history", "1", "--size", "640x480",
                       "--timeout", "30")
        assert mon2.wait(40) == 0, mon2.tail()
        img = cv2.imread(str(png))
        assert img.shape == (480, 640, 3) and img.std() > 10
        assert ((img[:, :, 2] > 180) & (img[:, :, 1] < 60)).sum() > 100  # the red winner marker
