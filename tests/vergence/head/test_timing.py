"""vergence.head.timing: the cameras' timing, the exposure stamps a capture believes, the motor's pan history."""

import math

import pytest

from vergence.sim.camera import Schedule, expose, sub_times
from vergence.sim.moving import MovingRig
from vergence.head.timing import CameraTiming, PanHistory, Stamper

MS = 1_000_000  # ns


# -- CameraTiming -------------------------------------------------------------------------------------------------

def test_exposures_put_the_later_image_latency_before_the_read():
    assert CameraTiming(0.066).exposures(10.0) == pytest.approx((9.934, 9.934))
    assert CameraTiming(0.033, skew_s=0.008).exposures(10.0) == pytest.approx((9.959, 9.967))
    assert CameraTiming(0.033, skew_s=-0.008).exposures(10.0) == pytest.approx((9.967, 9.959))
    assert CameraTiming(0.033, skew_s=0.008).read_time(1.0) == pytest.approx(1.041)
    assert CameraTiming(0.033, skew_s=-0.008).read_time(1.0) == pytest.approx(1.033)


@pytest.mark.parametrize("kw,says", [({"latency_s": -0.01}, "latency_s"), ({"latency_s": 1.5}, "latency_s"),
                                     ({"exposure_s": math.nan}, "exposure_s"), ({"jitter_s": -1}, "jitter_s"),
                                     ({"skew_s": 0.6}, "skew_s")])
def test_timing_refuses_nonsense_naming_the_field(kw, says):
    with pytest.raises(ValueError, match=says):
        CameraTiming(**kw)


# -- Stamper --------------------------------------------------------------------------------------------------------

def test_a_believable_stamp_is_taken_as_it_is():
    st = Stamper(CameraTiming(0.05))
    assert st.stamp(1000 * MS, (960 * MS, 962 * MS)) == (960 * MS, 962 * MS, None)
    assert st.rejected == {"future": 0, "old": 0, "backwards": 0}


def test_no_stamp_is_the_read_time_less_the_configured_latency_and_skew():
    st = Stamper(CameraTiming(0.05, skew_s=0.004))
    assert st.stamp(1000 * MS) == (946 * MS, 950 * MS, None)


@pytest.mark.parametrize("claim,why", [((5010 * MS, 5010 * MS), "future"), ((1, 1), "old"),
                                       ((3990 * MS, 4990 * MS), "old")])
def test_an_implausible_stamp_is_counted_and_replaced_by_the_configured_latency(claim, why):
    st = Stamper(CameraTiming(0.02))
    tm, ts, reason = st.stamp(5000 * MS, claim)
    assert (tm, ts, reason) == (4980 * MS, 4980 * MS, why)
    assert st.rejected[why] == 1 and sum(st.rejected.values()) == 1


def test_a_stamp_going_backwards_is_refused_and_the_fallback_never_goes_back_either():
    st = Stamper(CameraTiming(0.0))
    assert st.stamp(2000 * MS, (1990 * MS, 1990 * MS))[2] is None
    tm, _, why = st.stamp(2001 * MS, (1980 * MS, 1980 * MS))  # older than the last believed one
    assert why == "backwards" and tm == 2001 * MS
    # a configured stamp behind a believed one (a source that stamps ahead of its reads) is moved past it
    st = Stamper(CameraTiming(0.5))
    st.stamp(2000 * MS, (1999 * MS, 1999 * MS))
    assert st.stamp(2010 * MS)[0] == 1999 * MS + 1


# -- PanHistory -----------------------------------------------------------------------------------------------------

def test_history_interpolates_between_the_motor_states_around_a_time():
    h = PanHistory(max_gap_s=0.1)
    for t, p in ((1.00, 0.10), (1.02, 0.12), (1.04, 0.16)):
        assert h.add(t, p)
    assert h.at(1.01) == pytest.approx(0.11)
    assert h.at(1.03) == pytest.approx(0.14)
    assert h.at(1.02) == pytest.approx(0.12)


def test_history_says_nothing_before_its_oldest_state_nor_across_a_gap():
    h = PanHistory(max_gap_s=0.1)
    h.add(1.0, 0.1)
    h.add(1.5, 0.2)  # 0.5 s without a state
    assert h.at(0.99) is None and h.older == 1
    assert h.at(1.2) is None and h.gaps == 1
    assert h.at(1.7) is None and h.gaps == 2  # further past the newest than a gap


def test_history_extrapolates_a_little_past_its_newest_state_at_the_rate_over_15_ms():
    h = PanHistory(max_gap_s=0.1)
    for i in range(6):
        h.add(1.0 + 0.005 * i, 0.1 + 0.01 * i)  # 2 rad/s
    h.add(1.0255, 0.1501)  # a reading 0.5 ms after the last: no rate of its own
    assert h.at(1.0355) == pytest.approx(0.1501 + 2.0 * 0.01, rel=0.02)


def test_history_refuses_a_state_not_newer_than_its_newest_and_forgets_beyond_keep():
    h = PanHistory(max_gap_s=0.1, keep_s=1.0)
    assert h.add(1.0, 0.1) and not h.add(1.0, 0.2) and not h.add(0.5, 0.2) and not h.add(2.0, math.nan)
    assert h.refused == 3 and h.newest() == 0.1
    for i in range(1, 40):
        h.add(1.0 + 0.05 * i, 0.0)
    assert h.t[-1] - h.t[0] <= 1.0 and h.at(1.2) is None


# -- the simulated cameras -------------------------------------------------------------------------------------------

def test_schedule_puts_the_slave_skew_after_the_master_and_keeps_the_frames_in_order():
    s = Schedule(60.0, CameraTiming(0.05, skew_s=0.008, jitter_s=0.004), seed=3)
    frames = [s.frame(i) for i in range(200)]
    assert frames[0] == pytest.approx((0.0, 0.008, 0.058))
    assert all(ts - tm == pytest.approx(0.008) and tr - ts == pytest.approx(0.05) for tm, ts, tr in frames)
    masters = [f[0] for f in frames]
    assert all(b > a for a, b in zip(masters, masters[1:]))
    off = [tm - i / 60 for i, (tm, _, _) in enumerate(frames)]
    assert 0.002 < max(abs(o) for o in off) <= 0.4 / 60 + 1e-12  # jittered, never past 0.4 frame


def test_an_exposure_integrates_the_views_over_its_duration():
    assert sub_times(1.0, 0.0) == [1.0]
    assert sub_times(1.0, 0.008) == pytest.approx([0.997, 0.999, 1.001, 1.003])
    rig = MovingRig("still:z=0.8")
    pans = [(-0.08, 0.0), (-0.06, 0.0)]
    _, blurred = expose(rig, [0.0], pans)
    a, b = (rig.slave_view(p) for p, _ in pans)
    mean = (a.astype(float) + b) / 2
    assert abs(blurred.astype(float) - mean).max() <= 0.5 + 1e-9  # the rounded mean, no noise
    sharp = expose(rig, [0.0], pans[:1])[1]
    assert (sharp == a).all()


def test_an_image_is_read_after_its_exposure_ends_even_at_no_latency():
    from vergence.sim.loop import closed_loop

    t = CameraTiming(0.0, exposure_s=0.008)
    assert t.age_s == 0.004 and t.read_time(1.0) == pytest.approx(1.004)
    assert t.exposures(1.004) == pytest.approx((1.0, 1.0))
    steps = list(closed_loop(MovingRig("sine:z=0.8,amp=0.3,hz=1"), 10, rate_hz=60.0, timing=t))
    assert [s.frame for s in steps] == list(range(11))
