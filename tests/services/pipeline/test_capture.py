"""The capture's time model in its own process (no router): the exposure stamps it gives each frame and what its
status says of them, and the slave's pan it gives a frame from the motor's history."""

import logging
import threading

import pytest

from vergence.head.timing import CameraTiming, PanHistory
from services.pipeline.capture_time import ExposureClock, Pacer, PanLookup

MS = 1_000_000


class Source:
    follows_pan = True
    start_pan_rad = 0.25


def test_the_status_reports_the_latency_and_skew_it_sees_and_the_stamps_it_did_not_believe(caplog):
    clock = ExposureClock(CameraTiming(0.03, skew_s=0.002), frame_s=1 / 60)
    with caplog.at_level(logging.WARNING, "vergence.capture"):
        assert clock.stamp(5000 * MS, (4950 * MS, 4951 * MS)) == (4950 * MS, 4951 * MS)
        assert clock.stamp(5017 * MS, (4967 * MS, 4968 * MS)) == (4967 * MS, 4968 * MS)
        for k in range(3):  # from the future: the configured timing instead, one warning for all three
            assert clock.stamp((5034 + k) * MS, (9000 * MS, 9000 * MS)) == ((5002 + k) * MS, (5004 + k) * MS)
    assert [r.getMessage().count("not believed") for r in caplog.records] == [1]
    f = clock.fields()
    assert f["stamps_rejected"] == {"future": 3, "old": 0, "backwards": 0}
    assert f["latency_ms"] == 32.0 and f["skew_ms"] == 2.0
    assert "latency_ms" not in clock.fields()  # each status speaks of its own period


def test_a_skew_over_half_a_frame_is_warned_of_once(caplog):
    clock = ExposureClock(CameraTiming(0.0), frame_s=1 / 30)
    with caplog.at_level(logging.WARNING, "vergence.capture"):
        for k in range(3):
            clock.stamp((1000 + 33 * k) * MS, ((980 + 33 * k) * MS, (1000 + 33 * k) * MS))
            clock.fields()
    assert sum("over half a frame" in r.getMessage() for r in caplog.records) == 1


def test_a_frame_gets_the_slave_pan_at_its_exposure_or_none_where_the_history_cannot_tell():
    h = PanHistory(max_gap_s=0.1)
    lock = threading.Lock()
    look = PanLookup(h, lock, Source())
    # no motor state yet: rendered at the source's start pan, and stale (the motor may be anywhere: it commands nothing)
    assert look.frame(10**9) == (0.25, True, False)
    for t, p in ((1.00, 0.10), (1.02, 0.12), (1.04, 0.14)):
        h.add(t, p)
    look = PanLookup(h, lock, Source())
    assert look.frame(1010 * MS) == (pytest.approx(0.11), False, False)
    # older than the history: stale, its oldest (the motor was there; its newest rendered a late camera's first frames
    # at a move not yet made)
    assert look.frame(500 * MS) == (pytest.approx(0.10), True, False)
    # past the newest state: extrapolated at the last rate, a guess (no background verdict is read on it) ...
    assert look.frame(1060 * MS) == (pytest.approx(0.16), False, True)
    h.add(1.08, 0.13)  # ... even once the motor has told a turn since: the frame carries the pan it was rendered at
    assert look.frame(1060 * MS) == (pytest.approx(0.16), False, True)
    assert PanLookup(h, lock, Source()).frame(1060 * MS) == (pytest.approx(0.135), False, False)
    src = Source()
    src.follows_pan = False
    assert PanLookup(h, lock, src).frame(1010 * MS) == (0.25, False, False)  # a still pair keeps its own pan


def test_a_frame_from_the_sim_motors_replica_carries_what_a_noisy_encoder_reads_the_slave_rendered_on_the_shaft():
    """The sim source with encoder_noise=0.1: the slave is rendered where the replica says the shaft is, and the frame
    carries one noisy reading of it (as `vergence sim` gives each frame's pan); from the motor's history (its states,
    already readings) no noise is added."""
    from vergence.io.sources import SimSource
    from vergence.motors import MotorSettings
    from vergence.motors.simulated import Replica

    ms = MotorSettings()
    rep = Replica(ms, noise_deg=0.1)
    t0 = 1_764_000_000 * 10**9
    for k in range(3):  # at rest on its goal, 0
        rep.observe(t0 + k * 10 * MS, 0.0, 0.0)
    assert rep.trusted
    src = SimSource("stall=1-2:encoder_noise=0.1:size=160x120")
    assert src.motor_faults.spec() == "stall=1-2:encoder_noise=0.1"
    frames = [PanLookup(PanHistory(max_gap_s=0.1), threading.Lock(), src, rep) for _ in range(400)]
    rendered = {look(t0 + 30 * MS) for look in frames}
    pans = [look.frame(t0 + 30 * MS)[0] for look in frames]
    assert rendered == {0.0}
    rms = (sum(p * p for p in pans) / len(pans)) ** 0.5
    assert 0.08 <= rms * 180 / 3.141592653589793 <= 0.12, rms
    h = PanHistory(max_gap_s=0.1)
    h.add(1.0, 0.1)
    h.add(1.02, 0.1)
    assert PanLookup(h, threading.Lock(), src).frame(1010 * MS) == (pytest.approx(0.1), False, False)


@pytest.mark.realtime  # times a thread or a wake-up: kept in the main process of a split run
def test_a_rendering_source_waits_for_the_motors_report_of_its_instant_but_not_for_ever():
    h = PanHistory(max_gap_s=0.1)
    lock = threading.Lock()
    h.add(1.0, 0.1)
    look = PanLookup(h, lock, Source())
    later = threading.Timer(0.005, lambda: h.add(1.02, 0.12))
    later.start()
    look.settle(1010 * MS, timeout=1.0)
    assert h.t[-1] == 1.02
    look.settle(5000 * MS, timeout=0.02)  # a motor that stopped reporting: returns after the timeout
    assert look(1010 * MS) == pytest.approx(0.11)


@pytest.mark.realtime  # times a thread or a wake-up: kept in the main process of a split run
def test_with_a_trusted_replica_the_exposure_waits_for_the_motor_to_count_the_commands_seen():
    """PanLookup.ready: no wait with nothing out; with a command out, until a state counts it (the capture's
    on_motor notifies), or at most Replica.ANSWER_NS."""
    import time

    from vergence.motors import MotorSettings
    from vergence.motors.simulated import Replica

    rep = Replica(MotorSettings())
    cond = threading.Condition()
    t = 10**18
    for k in range(3):  # at rest on its goal: trusted
        rep.observe(t + k * 5 * MS, 0.0, 0.0)
    assert rep.trusted
    rep.counted(4, time.monotonic_ns())
    look = PanLookup(PanHistory(max_gap_s=0.1), cond, Source(), rep)
    look.ready()
    assert not look.waited
    rep.ANSWER_NS = 5_000_000_000  # (this instance's: a loaded machine's timer may fire past the 50 ms)
    rep.commanded(time.monotonic_ns())
    answered = threading.Event()

    def answer():
        with cond:
            rep.counted(5, time.monotonic_ns())
            answered.set()
            cond.notify_all()

    t0 = time.monotonic()
    threading.Timer(0.01, answer).start()
    look.ready()
    assert look.waited and answered.is_set() and 0.01 <= time.monotonic() - t0 < 2.5 and rep.unheard == 0
    del rep.ANSWER_NS
    rep.commanded(time.monotonic_ns())  # never counted: let go after ANSWER_NS
    t0 = time.monotonic()
    PanLookup(PanHistory(max_gap_s=0.1), cond, Source(), rep).ready()
    assert rep.ANSWER_NS / 1e9 <= time.monotonic() - t0 < 1.0 and rep.unheard == 1


def test_the_pan_is_known_half_the_motors_latency_ahead_only_with_a_trusted_replica():
    """PanLookup.ahead_ns, how far ahead a rendering source may expose (issue #33's render ahead): a goal takes
    effect the sim motor's latency_s (2 ms) after its write, so with a trusted replica 1 ms ahead is known; a
    history (no replica, or one not trusted) knows nothing past its newest state."""
    from vergence.motors import MotorSettings
    from vergence.motors.simulated import Replica

    rep, cond = Replica(MotorSettings()), threading.Condition()
    assert PanLookup(PanHistory(max_gap_s=0.1), cond, Source()).ahead_ns() == 0
    look = PanLookup(PanHistory(max_gap_s=0.1), cond, Source(), rep)
    assert look.ahead_ns() == 0
    for k in range(3):  # at rest on its goal: trusted
        rep.observe(10**18 + k * 5 * MS, 0.0, 0.0)
    assert rep.trusted and look.ahead_ns() == 1 * MS
    rep.observe(10**18 + 20 * MS, 0.3, 0.3)  # a reading the model cannot explain: a history's again
    assert not rep.trusted and look.ahead_ns() == 0


def test_a_motor_state_from_our_future_is_forgotten_when_the_true_ones_come():
    from vergence.wire.messages import MessageError, MotorState
    from services.pipeline.capture_time import remember

    def state(t_ns, pan):
        return MotorState(rig="r", t_ns=t_ns, pan_rad=pan, goal_rad=pan, min_rad=-1, max_rad=1, status="ok")

    h = PanHistory(max_gap_s=0.1)
    now = 10**18
    remember(h, state(now - 20 * MS, 0.1), now)
    with pytest.raises(MessageError, match="not newer"):
        remember(h, state(now - 30 * MS, 0.2), now)  # older than the newest: refused
    remember(h, state(now + 1500 * MS, 0.7), now)  # a forgery 1.5 s ahead, within max_skew_s
    remember(h, state(now, 0.11), now)  # the next true state: the forgery is forgotten
    assert list(h.pan) == [0.11]
    remember(h, state(now + 30 * MS, 0.12), now)  # 30 ms ahead: clock skew, kept
    with pytest.raises(MessageError):
        remember(h, state(now + 10 * MS, 0.13), now)
    # a disconnected or absent motor's state carries its goal, not a pan it knows: left out
    for status in ("disconnected", "absent"):
        st = MotorState(rig="r", t_ns=now + 40 * MS, pan_rad=0.0, goal_rad=0.0, min_rad=-1, max_rad=1, status=status)
        assert remember(h, st, now) is False
    assert list(h.pan) == [0.11, 0.12]


def test_the_pacer_makes_up_a_stall_of_a_period_at_once_and_counts_the_reads_given_up_past_it():
    now = [100.0]
    clock = lambda: now[0]  # noqa: E731

    class Stop:  # stop.wait advances the clock by what it was asked to wait
        def wait(self, s):
            now[0] += s

    pacer, stop, p = Pacer(0.004, clock), Stop(), 0.004
    reads = []

    def read(stall=0.0):
        missed = pacer.wait(stop)
        reads.append(round((now[0] - 100.0) / p, 6))
        now[0] += stall
        return missed

    assert [read() for _ in range(3)] == [0, 0, 0]
    assert reads == [0, 1, 2]  # on the schedule, each a period after the last
    assert read(1.9 * p) == 0  # a stall of nearly two periods...
    assert [read() for _ in range(3)] == [0, 0, 0]
    assert reads[3:] == [3, 4.9, 5, 6]  # ...is made up at once: no read given up, back on the schedule
    reads.clear()
    assert read(5.5 * p) == 0
    assert read() == 3  # 5.5 periods late: the read due at 8, then 12 at once; 9-11 given up
    assert [read() for _ in range(2)] == [0, 0]
    assert reads == [7, 12.5, 12.5, 13]
