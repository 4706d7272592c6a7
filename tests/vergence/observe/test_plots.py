"""vergence.observe.plots: the figures of `vergence sim --plot` hold the run's values (read back from the returned
matplotlib Figure, line by line), the PNGs open at their size and are drawn, and importing the module does not
import matplotlib. The monitor's figure is tested in test_monitor.py, with the monitor's model."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys

import cv2
import numpy as np
import pytest

from vergence.observe import plots
from vergence.head.control import ControlSettings
from vergence.network.decide import centre_offset
from vergence.sim import Rig, generate
from vergence.sim.loop import closed_loop, tracking_error
from vergence.sim.moving import Head, MovingRig


@pytest.fixture(scope="module")
def still():
    """A still scene, the slave started 20 px off the converged pan: 8 frames of the closed loop."""
    sc = generate(0)
    rig = Rig(sc.left, sc.right, disparity=sc.disparity, size=(640, 480))
    rig.start_pan_rad = rig.pan_off_truth(-20.0)
    return rig, list(closed_loop(rig, 8, None, ControlSettings(mode="p")))


@pytest.fixture(scope="module")
def moving():
    rig = MovingRig("sine:z=0.8,amp=0.3,hz=1", Head(0.06, 500.0), seed=0)
    return list(closed_loop(rig, 90, None, ControlSettings(mode="predictive"), None, 60.0))


def read_png(path) -> np.ndarray:
    img = cv2.imread(str(path))
    assert img is not None, f"{path} does not open as an image"
    return img


def drawn(img: np.ndarray) -> None:
    """Not blank: ink on a good part of it, in several colours."""
    assert (img < 200).any(axis=2).mean() > 0.01
    assert len(np.unique(img.reshape(-1, 3) // 32, axis=0)) >= 6


def test_run_figure_holds_the_pan_the_profiles_and_the_winners(still, tmp_path):
    rig, steps = still
    one_px = math.degrees(rig.one_px_rad)
    fig = plots.plot_run(steps, str(tmp_path / "run.png"), one_px)
    top, bot = fig.axes
    got = plots.lines(top)
    assert list(got["pan"].get_xdata()) == [s.frame for s in steps] == list(range(9))
    assert list(got["pan"].get_ydata()) == [s.pan_deg for s in steps]
    truth = math.degrees(rig.truth_pan_rad)
    assert got["truth"].get_ydata() == pytest.approx([truth] * 9)
    assert got["band+"].get_ydata() == pytest.approx([truth + one_px] * 9)
    assert got["band-"].get_ydata() == pytest.approx([truth - one_px] * 9)
    lo, hi = top.get_ylim()  # the band is inside the axes, not clipped by autoscaling
    assert lo < truth - one_px and truth + one_px < hi and lo < min(got["pan"].get_ydata())
    assert (top.get_xlabel(), top.get_ylabel()) == ("frame", "pan (deg)")
    # the run started 20 px off and converged: the first pan is outside the band, the last inside
    assert abs(steps[0].pan_deg - truth) > 10 * one_px and abs(steps[-1].pan_deg - truth) < one_px

    got = plots.lines(bot)
    first, last = steps[0], steps[-1]
    np.testing.assert_array_equal(got["profile_first"].get_ydata(), first.scores)
    np.testing.assert_array_equal(got["profile_last"].get_ydata(), last.scores)
    assert got["winner_first"].get_xdata()[0] == first.k and got["winner_last"].get_xdata()[0] == last.k
    kc = centre_offset(first.scores.size + first.window - 1, first.window)
    assert got["centre"].get_xdata()[0] == kc
    assert abs(last.k - kc) <= 1 < abs(first.k - kc)  # the winner moved to the centre
    assert (bot.get_xlabel(), bot.get_ylabel()) == ("k (offset of the slave window)", "y(k)")
    labels = [t.get_text() for t in bot.get_legend().get_texts()]
    assert f"k* frame 0 = {first.k}" in labels and f"k_c = {kc}" in labels

    img = read_png(tmp_path / "run.png")
    assert img.shape == (760, 900, 3)
    drawn(img)


def test_run_figure_without_truth(still):
    """A pair without ground truth: the pan alone, no converged pan, no band; the title says so."""
    _, steps = still
    blind = [dataclasses.replace(s, truth_pan_deg=math.nan, error_px=math.nan) for s in steps]
    fig = plots.run_figure(blind, 0.1, 640, 480)
    got = plots.lines(fig.axes[0])
    assert set(got) == {"pan"} and "unknown" in fig.axes[0].get_title(loc="left")
    img = cv2.imdecode(np.frombuffer(plots.png_bytes(fig), np.uint8), cv2.IMREAD_COLOR)
    assert img.shape == (480, 640, 3)


def test_tracking_figure_holds_truth_pan_and_error(moving, tmp_path):
    steps = moving
    fig = plots.plot_tracking(steps, str(tmp_path / "t.png"), "sine test", first=60)
    top, bot = fig.axes
    got = plots.lines(top)
    t = [s.t_s for s in steps]
    assert list(got["pan"].get_xdata()) == t and list(got["pan"].get_ydata()) == [s.pan_deg for s in steps]
    assert list(got["truth"].get_ydata()) == [s.truth_pan_deg for s in steps]
    assert min(got["truth"].get_ydata()) < -5 < -4 < max(got["truth"].get_ydata())  # the sine's swing
    assert top.get_title(loc="left") == "Slave pan and truth: sine test"
    got = plots.lines(bot)
    assert list(got["error"].get_xdata()) == t[60:]
    assert list(got["error"].get_ydata()) == [s.error_px for s in steps[60:]]
    assert [got[g].get_ydata()[0] for g in ("band+", "band-", "zero")] == [1.0, -1.0, 0.0]
    e = tracking_error(steps, 60)
    assert bot.get_title(loc="left") == (f"Error f tan(pan - truth) from 1 s: RMS {e['rms_px']:.2f} px, "
                                         f"max {e['max_px']:.2f} px")
    assert (bot.get_xlabel(), bot.get_ylabel()) == ("time (s)", "error (px)")
    img = read_png(tmp_path / "t.png")
    assert img.shape == (700, 900, 3)
    drawn(img)


@pytest.mark.parametrize("size", [(900, 700), (641, 479), (1201, 803)])
def test_png_has_the_asked_size(moving, size):
    img = cv2.imdecode(np.frombuffer(plots.png_bytes(plots.tracking_figure(moving, "", 0, *size)), np.uint8),
                       cv2.IMREAD_COLOR)
    assert img.shape == (size[1], size[0], 3)


def test_unwritable_path_says_which(still, tmp_path):
    with pytest.raises(OSError, match="cannot write .*nope/run.png"):
        plots.plot_run(still[1], str(tmp_path / "nope" / "run.png"), 0.1)


def test_importing_plots_does_not_import_matplotlib():
    code = "import sys, vergence.observe.plots, vergence.observe.monitor; print('matplotlib' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == "False", out.stderr
