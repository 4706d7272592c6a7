"""vergence.tools.faults (`vergence bench faults`): its rows, small (60 Hz, no latency, three lies), hold the figures
issue #35 asks of each lie: named, no runaway, found again, and no false fault on the clean runs."""

from __future__ import annotations

import pytest

import background
import sweeps

# the rows, small: 60 Hz, no latency, three lies (done ahead in the background: tests/background.py)
SMALL = ((60.0,), (0.0,), (2,), (None, "freeze", "reverse"))
background.ahead(sweeps.faults, *SMALL, tests="test_bench_faults_rows_name_each_lie_and_bound_it")


@pytest.mark.slow
def test_bench_faults_rows_name_each_lie_and_bound_it():
    rows = background.get(sweeps.faults, *SMALL)
    by = {(r["lie"], r["scene"]): r for r in rows}
    assert sorted(by) == [(lie, scene) for lie in ("-", "freeze", "reverse") for scene in ("moving", "still")]
    assert all(by[("-", scene)]["false_fault_frames"] == 0 for scene in ("moving", "still"))
    for scene in ("moving", "still"):
        f = by[("freeze", scene)]
        assert f["fault"] == "slave_frozen" and f["diagnosed_s"] <= 0.5 and f["excursion_deg"] <= 2.0
        assert f["recovered_s"] is not None and f["recovered_s"] <= 2.0 and f["false_fault_frames"] == 0
        r = by[("reverse", scene)]
        assert r["fault"] == "reversed" and r["excursion_deg"] <= 3.0
    assert by[("reverse", "still")]["diagnosed_s"] <= 1.0
