"""vergence.head.latency: the camera's latency from the offsets the network measures and the motor's own history."""

import math

import numpy as np
import pytest

from vergence.head.latency import LatencyError, fit_latency, motion_plan

F = 500.0
TRUTH = -0.07


def _run(latency_s: float, stamped_s: float, noise_px: float = 0.2, seed: int = 0, still: bool = False):
    """A motor stepping as motion_plan says (a first-order approach, states at 50 Hz) and decisions at 60 Hz
    whose offsets are those of the slave's pan latency_s before their read, stamped stamped_s before it."""
    rng = np.random.default_rng(seed)
    plan = motion_plan(TRUTH, -0.5, 0.5, math.radians(0.5), 0.4)
    goal = lambda t: TRUTH if still else [p for at, p in plan if at <= t][-1] if t >= 0 else TRUTH  # noqa: E731
    dt, pan, hist = 0.0005, TRUTH, []
    for i in range(int(3.2 / dt)):
        t = i * dt
        pan += (goal(t) - pan) * dt / 0.02
        hist.append((t, pan))
    ts, ps = np.array(hist).T
    states = [(round(t * 1e9), p) for t, p in hist[::40]]  # 50 Hz
    decisions = []
    for k in range(1, 180):
        t_read = 0.1 + k / 60
        pan_exposed = float(np.interp(t_read - latency_s, ts, ps))
        off = F * math.tan(TRUTH - pan_exposed) + rng.normal(0, noise_px)
        stamp = t_read - stamped_s
        decisions.append((round(stamp * 1e9), round(t_read * 1e9), off))
    return decisions, states


@pytest.mark.parametrize("latency,stamped", [(0.0, 0.0), (0.033, 0.0), (0.066, 0.066), (0.1, 0.02), (0.047, 0.0)])
def test_the_fit_finds_the_latency_within_two_milliseconds(latency, stamped):
    # (the motor states are 20 ms apart: their straight-line interpolation of a first-order approach is what
    # limits it)
    fit = fit_latency(*_run(latency, stamped))
    assert fit.latency_s == pytest.approx(latency, abs=0.002)
    assert fit.delta_s == pytest.approx(latency - stamped, abs=0.002)
    assert fit.stamped_s == pytest.approx(stamped, abs=1e-6)
    assert fit.sigma_s < 0.002 and fit.r2 > 0.99 and fit.slope == pytest.approx(-F, rel=0.05)


def test_the_plan_steps_within_a_degree_and_the_limits():
    plan = motion_plan(0.0, -0.004, 1.0, math.radians(3), 0.5)
    assert [t for t, _ in plan] == [0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0]
    assert max(p for _, p in plan) == pytest.approx(math.radians(1.0))  # 3 degrees asked: 1 at most
    assert min(p for _, p in plan) == -0.004 and plan[-1][1] == 0.0


def test_a_motor_that_did_not_move_or_offsets_that_do_not_follow_it_are_refused():
    decisions, states = _run(0.05, 0.0, still=True)
    with pytest.raises(LatencyError, match="the motor moved 0.000 deg"):
        fit_latency(decisions, states)
    decisions, states = _run(0.05, 0.0)
    rng = np.random.default_rng(1)
    scrambled = [(s, r, float(o)) for (s, r, _), o in zip(decisions, rng.permutation([d[2] for d in decisions]))]
    with pytest.raises(LatencyError, match="do not follow the motor") as e:
        fit_latency(scrambled, states)
    assert e.value.slope is not None and e.value.r2 < 0.5  # (for calibrate and latency to name a frozen camera)
    with pytest.raises(LatencyError, match="only 3 confident decisions") as e:
        fit_latency(decisions[:3], states)
    assert e.value.slope is None
