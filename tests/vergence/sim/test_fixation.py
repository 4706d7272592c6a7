"""The simulator's truth for a fovea anywhere in the master view (vergence.sim.fixation): checked against the
rendered views themselves, so that the truth the capture stamps on a frame is where the slave really shows the
fovea's point."""

from __future__ import annotations

import math

import cv2
import pytest

from vergence.sim import Rig
from vergence.sim.fixation import truth_at, truth_pan_at
from vergence.sim.moving import MovingRig


def _column_in_slave(master, slave, x: int, y: int, half: int = 12) -> float:
    """Where the master's patch around (x, y) is found in the slave's rows around y (sub-pixel column)."""
    patch = master[y - half:y + half + 1, x - half:x + half + 1]
    band = slave[y - 3 * half:y + 3 * half + 1, :]
    res = cv2.matchTemplate(band, patch, cv2.TM_CCOEFF_NORMED)
    _, best, _, (cx, cy) = cv2.minMaxLoc(res)
    assert best > 0.9
    row = res[cy]
    d = 0.0
    if 0 < cx < len(row) - 1:
        a, b, c = float(row[cx - 1]), float(row[cx]), float(row[cx + 1])
        d = 0.5 * (a - c) / (a - 2 * b + c)
    return cx + d + half


# (x, y, t): on the target at three times of its sine, and two points off it (the background, 3 m)
@pytest.mark.parametrize("x,y,t", [(320, 240, 0.0), (380, 262, 1.3), (251, 197, 2.9), (610, 240, 0.4),
                                   (30, 400, 3.7)])
def test_the_moving_targets_truth_at_a_fovea_shows_the_point_on_its_column(x, y, t):
    rig = MovingRig("sine:z=0.7,amp=0.25,hz=0.3", seed=5)
    pan = truth_pan_at(rig, x, y, t)
    col = _column_in_slave(rig.master_view(t), rig.slave_view(pan, t), x, y)
    assert col == pytest.approx(x, abs=0.3)
    # and the pan one degree off it does not
    col = _column_in_slave(rig.master_view(t), rig.slave_view(pan + math.radians(1), t), x, y)
    assert abs(col - x) > 5


def test_the_moving_targets_truth_differs_on_and_off_the_target():
    rig = MovingRig("still:z=0.8", seed=1)
    centre = truth_pan_at(rig, 320, 240)
    assert centre == pytest.approx(rig.truth_pan(0.0), abs=1e-12) == pytest.approx(-math.atan(0.06 / 0.8))
    # the background at 3 m (off the 240 px target): about -atan(0.06 / 3), the ray's angle aside
    off = truth_pan_at(rig, 610, 240)
    assert math.degrees(off - centre) > 3
    assert off == pytest.approx(math.atan2(3 * 290 / 512 - 0.06, 3) - math.atan(290 / 512), abs=1e-12)


def test_the_still_rigs_truth_at_is_truth_at():
    rig = Rig.from_spec("")
    assert truth_pan_at(rig, 440, 240) == truth_at(rig, 440, 240)[0]
    assert truth_pan_at(rig, 320, 240) == pytest.approx(rig.truth_pan_rad, abs=1e-9)
