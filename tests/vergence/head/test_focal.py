"""vergence.head.focal: the focal length's ratio read off the motor's own moves in pursuit, and in the loop."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vergence.head.control import ControlSettings
from vergence.head.focal import FITS, FOCAL_PAIRS, Focal, Pursuit, fit, on_axis
from vergence.head.timing import CameraTiming
from vergence.sim.loop import closed_loop
from vergence.sim.moving import MovingRig


def pursuit(rho: float, wobble_deg: float, noise_deg: float = 0.0, seconds: float = 1.5, rate: float = 60.0,
            seed: int = 0):
    """(t, pan, a) of a head following a target (a slow sine) with a wobble of wobble_deg at 3.3 Hz on top (its
    corrections), the image moving rho x what the motor's motion predicts, the encoder noise_deg off at each frame."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(int(seconds * rate)):
        t = i / rate
        target = math.radians(5.0) * math.sin(2 * math.pi * 0.4 * t)
        pan = target + math.radians(wobble_deg) * math.sin(2 * math.pi * 3.3 * t)
        a = math.atan(rho * math.tan(target - pan)) + rng.normal(0, math.atan(0.3 / 500))  # 0.3 px of offset noise
        out.append((t, pan + math.radians(rng.normal(0, noise_deg)) if noise_deg else pan, a))
    return out


@pytest.mark.parametrize("rho", [0.7, 1.0, 1.6])
def test_one_window_reads_the_ratio_off_the_motion_no_cubic_explains(rho):
    seen = pursuit(rho, 0.8)[:36]
    assert fit(seen) == pytest.approx(rho, abs=0.04)  # (0.3 px of offset noise: within 0.026 on seeds 0-5)


def test_a_window_where_the_motor_only_follows_the_target_says_nothing():
    """Perfect pursuit: the motor's pan is the target's, a smooth curve; nothing tells the ratio."""
    assert fit(pursuit(1.6, 0.0)[:36]) is None
    assert fit(pursuit(1.6, 0.1)[:36]) is None  # a wobble under MOTION_DEG does not count


def test_pursuit_names_a_ratio_off_after_its_fits_and_never_a_right_one():
    p = Pursuit()
    ratios = [p.add(*s) for s in pursuit(1.6, 0.8)]
    first = next(i for i, r in enumerate(ratios) if r is not None)
    assert ratios[-1] == pytest.approx(1.6, abs=0.03)
    assert first >= 11 + 3 * (FITS - 1)  # a full window, then FITS fits three decisions apart
    for seed in range(5):  # the encoder 0.05 deg off at each frame: no ratio of 1 taken for one off
        q = Pursuit()
        assert all(q.add(*s) is None for s in pursuit(1.0, 0.4, noise_deg=0.05, seed=seed, seconds=3.0))


def test_a_named_ratio_stays_until_the_fits_come_within_half_the_threshold():
    p = Pursuit()
    p.ratio = 1.3  # named before; the fits now read 1.15: still off by more than half of FOCAL_OFF
    for s in pursuit(1.15, 0.8):
        p.add(*s)
    assert p.ratio == pytest.approx(1.15, abs=0.03)
    q = Pursuit()
    assert all(q.add(*s) is None for s in pursuit(1.15, 0.8))  # never named: 1.15 is within FOCAL_OFF of 1
    for s in pursuit(1.05, 0.8, seconds=3.0):
        p.add(*s)
    assert p.ratio is None


def test_precise_fast_pairs_stand_over_pursuit_and_a_clear_forgets_the_window():
    f = Focal()
    for s in pursuit(1.6, 0.8):
        f.add(*s)
    assert f.ratio == pytest.approx(1.6, abs=0.03)
    for _ in range(FOCAL_PAIRS):
        f.pair(1.02)
    assert f.ratio is None  # the pairs say the focal length is right
    g = Focal()
    g.add(0.0, 0.0, 0.0)
    g.clear()
    assert not g.pursuit.seen and g.ratio is None


def test_fast_pairs_that_disagree_name_nothing_and_leave_it_to_pursuit():
    """A fast target turning near the head (session 48's draw 4732: 35 deg/s, 100 ms) outruns the check's learnt rate,
    and its precise pairs read 1.26, 1.21, 1.40, 0.60, 0.58, 0.69 where the image followed at 1: their median named
    1.21, then 0.74. Pairs name the ratio only where the middle half of them spans at most SPREAD x their median."""
    f = Focal()
    for r in (1.26, 1.21, 1.40, 0.60, 0.58, 0.69, 0.74, 0.68):
        f.pair(r)
        assert f.ratio is None
    for s in pursuit(1.6, 0.8):
        f.add(*s)
    assert f.ratio == pytest.approx(1.6, abs=0.03)  # (pursuit stands in while the pairs disagree)
    g = Focal()
    for r in (1.58, 1.72, 1.62, 1.64, 1.60, 1.57):  # focal_true's steps at 60 Hz: within 0.1 of 1.6
        g.pair(r)
    assert g.ratio == pytest.approx(1.62)
    for r in (0.9, 0.95):  # two wild pairs of eight: the middle half still agree
        g.pair(r)
    assert g.ratio == pytest.approx(1.60)
    g.pair(1.0)  # a third: they do not, and pursuit has said nothing
    assert g.ratio is None

@pytest.mark.parametrize("rate,latency,seed", [(60.0, 0.066, 21), (30.0, 0.05, 22)])
def test_in_the_loop_a_1_6_x_focal_length_is_named_in_pursuit_and_the_loop_tracks_as_if_told_right(rate, latency, seed):
    """The images at 1.6 x the focal length told, a target moving back and forth (no step: nothing fast enough for
    the check's pairs): named within a second at 1.6 within 5 %, no fault, and the last 3 s of an 8 s run track as
    the same run told the right focal length does (before the pursuit's fits: never named, and the wrong gain's
    oscillation 2.9-6.3 px RMS at 66 ms). At 60 Hz, 66 ms within 1.3 x its RMS (seeds 30-41: 0.97-1.02 x); at 30 Hz,
    50 ms, where one draw's RMS over 3 s swings with the draw either way (seeds 30-41 told right 0.51-0.97 px, told
    wrong 0.48-1.13 px, 0.50-1.66 x; 2026-12-05), within 1.5 px."""
    motion = "sine:z=0.9,amp=0.25,hz=0.4"

    def run(told: float):
        rig = MovingRig.from_options(motion=motion, focal="800", seed=str(seed), noise="1")
        steps = list(closed_loop(rig, int(8 * rate), None, ControlSettings(), None, rate,
                                 timing=CameraTiming(latency), seed=seed, focal_px=told))
        late = [s.camera_error_px for s in steps if s.t_s >= 5.0]
        return steps, math.sqrt(sum(e * e for e in late) / len(late))

    steps, rms = run(500.0)
    named = next(s for s in steps if s.focal_ratio is not None)
    assert named.t_s < 1.0 and steps[-1].focal_ratio == pytest.approx(1.6, rel=0.05)
    assert not [s for s in steps if s.fault]
    right, rms_right = run(800.0)
    assert all(s.focal_ratio is None for s in right)
    if rate >= 60:
        assert rms <= 1.3 * rms_right, (rms, rms_right)
    else:
        assert rms <= 1.5 and rms_right <= 1.5, (rms, rms_right)


@pytest.mark.parametrize("latency,seed", [(0.066, 24), (0.1, 23)])
def test_once_the_focal_length_is_named_the_loop_tracks_as_if_told_right_from_then_on(latency, seed):
    """The bench's sine (0.8 +- 0.3 m, 0.5 Hz) at 60 Hz, the images at 1.6 x the focal length told: from half a second
    after the ratio is named, for 2.5 s, within 1.3 x the RMS of the same draw told the right focal length. What the
    periodic fit learnt is taken to the measured focal length, not learnt anew (Controller._refocus): before, the loop
    chased the target for a period, x3.4 and x7.6 on these draws (2026-12-07; seeds 25 at 100 ms: x0.85 against
    x6.2)."""
    def run(told: float):
        rig = MovingRig.from_options(motion="sine:z=0.8,amp=0.3,hz=0.5", focal="800", seed=str(seed), noise="1")
        rig.start_pan_rad = rig.truth_pan(0.0)
        return list(closed_loop(rig, 360, None, ControlSettings(), None, 60.0, timing=CameraTiming(latency), seed=seed,
                                focal_px=told))

    steps, right = run(500.0), run(800.0)
    named = next(s.t_s for s in steps if s.focal_ratio is not None)
    assert steps[-1].focal_ratio == pytest.approx(1.6, rel=0.05) and not [s for s in steps if s.fault]

    def rms(run):
        e = [s.camera_error_px for s in run if named + 0.5 <= s.t_s < named + 3.0]
        return math.sqrt(sum(x * x for x in e) / len(e))

    assert rms(steps) <= 1.3 * rms(right), (rms(steps), rms(right))


@pytest.mark.parametrize("seed", [61, 65])
def test_a_target_stepping_in_depth_names_no_focal_length_and_its_fast_pairs_read_1(seed, monkeypatch):
    """A target stepping between 0.6 and 1.0 m every second (bench faults' steps scene) at 60 Hz, 0 ms, the focal
    length told right: each step is 2.3 deg of the target's alone, a jump. It was learnt as a rate (its pair's 137
    deg/s spread over LONG_S: 17 deg/s), the correction's fast pair read 1.26-1.27 x the motor's motion, and the
    sixth step, at 6.03 s, named the focal length off, 1.27 x, on every draw (seeds 61-64)."""
    import vergence.head.doubt as doubt
    pairs, pair = [], doubt.Focal.pair
    monkeypatch.setattr(doubt.Focal, "pair", lambda self, r: (pairs.append(r), pair(self, r))[1])
    rig = MovingRig.from_options(motion="square:z0=0.6,z1=1.0,hz=0.5", focal="500", seed=str(seed), noise="1")
    rig.start_pan_rad = rig.truth_pan(0.0)
    steps = list(closed_loop(rig, 480, None, ControlSettings(), None, 60.0, timing=CameraTiming(0.0), seed=seed,
                             focal_px=500.0))
    assert len(pairs) >= 6 and all(abs(r - 1) < 0.1 for r in pairs), pairs
    assert all(s.focal_ratio is None and s.fault is None for s in steps)


def test_the_ratio_read_off_the_axis_is_the_focal_lengths_once_the_column_is_accounted_for():
    """Images at 800 px, the loop told 500, a fovea 200 px off the principal point: the angles read with 500 px make
    a column there move 1.6 (1 + 0.4^2) / (1 + 0.25^2) = 1.466 x what they predict (the outside check's Cones and
    Tsukuba named 1.449-1.518); on_axis gives 1.6 back, and r itself on the axis."""
    f_told, f_true, c, d = 500.0, 800.0, 200.0, 1e-4
    moved = f_true * (math.tan(math.atan(c / f_true) + d) - c / f_true)  # px, the column's shift for a turn d
    r = (math.atan((c + moved) / f_told) - math.atan(c / f_told)) / d  # as the check reads it, angles at 500 px
    assert r == pytest.approx(1.466, abs=0.002)
    assert on_axis(r, c / f_told) == pytest.approx(1.6, abs=0.002)
    assert on_axis(1.3, 0.0) == 1.3 and on_axis(0.0, 0.4) == 0.0
