"""vergence.tools.faults (`vergence bench faults`): its rows, small (60 Hz, no latency, three lies), hold the figures
issue #35 asks of each lie: named, no runaway, found again, and no false fault on the clean runs."""

from __future__ import annotations

import pytest

import background
import sweeps

# the rows, small: 60 Hz, no latency, five lies (done ahead in the background: tests/background.py)
SMALL = ((60.0,), (0.0,), (2,), (None, "freeze", "reverse", "focal_true", "backlash"))
background.ahead(sweeps.faults, *SMALL, tests="test_bench_faults_rows_name_each_lie_and_bound_it")


@pytest.mark.slow
def test_bench_faults_rows_name_each_lie_and_bound_it():
    rows = background.get(sweeps.faults, *SMALL)
    by = {(r["lie"], r["scene"]): r for r in rows}
    assert sorted(by) == sorted([(lie, scene) for lie in ("-", "backlash", "focal_true", "freeze", "reverse")
                                 for scene in ("moving", "still")] + [("-", "steps"), ("focal_true", "steps")])
    assert all(by[("-", scene)]["false_fault_frames"] == 0 for scene in ("moving", "still", "steps"))
    # images at 1.6 x the focal length told: named by the steps' fast moves within 5 %, the steps after within 3 px
    f = by[("focal_true", "steps")]
    assert f["focal_ratio"] == pytest.approx(1.6, rel=0.05) and f["overshoot_px"] <= 3.0
    assert f["false_fault_frames"] == 0
    assert by[("focal_true", "moving")]["overshoot_px"] is None  # (a step's overshoot: the stepping target's only)
    # backlash 0.2 deg and encoder noise 0.05 deg: no fault; the camera's own error under a pixel RMS
    for scene in ("moving", "still"):
        b = by[("backlash", scene)]
        assert b["false_fault_frames"] == 0 and b["rms_px"] < 1.0 and b["rms_vs_clean"] is not None
    # ... against the clean runs over four shifts of the encoder's lattice: within the Must's 1.2 x on this draw (1.17)
    assert by[("backlash", "moving")]["rms_vs_clean"] <= 1.2
    for scene in ("moving", "still"):
        f = by[("freeze", scene)]
        assert f["fault"] == "slave_frozen" and f["diagnosed_s"] <= 0.5 and f["excursion_deg"] <= 2.0
        assert f["recovered_s"] is not None and f["recovered_s"] <= 2.0 and f["false_fault_frames"] == 0
        r = by[("reverse", scene)]
        assert r["fault"] == "reversed" and r["excursion_deg"] <= 3.0
    assert by[("reverse", "still")]["diagnosed_s"] <= 1.0
