"""The reducer's own state in its process (no router): the hold a client puts on its commands, what the actuator
says of its motor, and how its thread takes what arrived (the inbox on its two rings, the alarm)."""

import collections
import threading
import time

import pytest

from vergence.wire.messages import MAX_HOLD_S, Hold
from services.pipeline.reducer import Lease


class Health:
    def __init__(self):
        self.rejected = []

    def reject(self, kind, why):
        self.rejected.append((kind, str(why)))


def test_a_hold_lasts_until_its_time_and_a_hold_too_far_ahead_is_not_believed():
    now = [10**18]
    h = Health()
    lease = Lease(h, clock=lambda: now[0])
    assert not lease.held()
    lease.on_hold(Hold(until_ns=now[0] + 10**9, t_ns=now[0]).to_bytes())
    assert lease.held()
    now[0] += 10**9
    assert not lease.held()  # ends by itself
    lease.on_hold(Hold(until_ns=now[0] + int((MAX_HOLD_S + 1) * 1e9), t_ns=now[0]).to_bytes())
    assert not lease.held() and h.rejected[-1][0] == "hold" and "more than 5 s" in h.rejected[-1][1]
    lease.on_hold(b"\x93garbage")
    assert not lease.held() and len(h.rejected) == 2
    lease.on_hold(Hold(until_ns=now[0] + 10**9, t_ns=now[0]).to_bytes())
    lease.on_hold(Hold(until_ns=now[0], t_ns=now[0]).to_bytes())  # released
    assert not lease.held()



def test_the_reducer_sends_nothing_while_the_motor_is_absent_and_goes_on_by_itself():
    from vergence.wire.messages import MotorState
    from services.pipeline.reducer import MotorPresence

    def state(status):
        return MotorState(rig="r", t_ns=1, pan_rad=0.0, goal_rad=0.0, min_rad=-1, max_rad=1, status=status).to_bytes()

    now = [100.0]
    h = Health()
    m = MotorPresence(h, clock=lambda: now[0])
    assert not m.absent() and m.fields() == {"motor": "unknown"}
    m.on_state(state("absent"))
    assert m.absent() and m.fields() == {"motor": "absent"}
    now[0] += 0.5
    m.on_state(state("ok"))
    assert not m.absent() and m.fields() == {"motor": "ok"}
    m.on_state(state("absent"))
    now[0] += MotorPresence.FRESH_S  # no state since (the actuator gone, or a forgery not repeated)
    assert not m.absent()
    m.on_state(b"junk")
    assert h.rejected[-1][0] == "motor_state"


def test_the_summary_gives_the_windows_pans_and_its_tracking_error_against_the_truth():
    """The periodic log line on a moving target: the range of the pans at capture over the window and, where
    the frames carry the simulator's truth, their RMS and largest error, not one frame's pan."""
    import math
    from types import SimpleNamespace

    from services.pipeline.reducer import Window, summary

    w = Window()
    f_px, errs = 500.0, [0.5, -1.5, 0.25, 1.0]
    for i, e in enumerate(errs):
        truth = -0.07 + 0.001 * i
        w.add(SimpleNamespace(pan_rad=truth + math.atan(e / f_px), truth_pan_rad=truth, focal_px=f_px))
    w.add(SimpleNamespace(pan_rad=-0.05, truth_pan_rad=None, focal_px=f_px))  # a frame with no truth: pan only
    last = SimpleNamespace(decision=SimpleNamespace(offset_px=0.4, confident=True, confidence=0.9),
                           frame=SimpleNamespace(frame=77, window=15))
    line = summary(5.0, 5, 0, 3, last, w.take())
    rms = math.sqrt(sum(e * e for e in errs) / 4)
    lo = math.degrees(min(-0.07 + 0.001 * i + math.atan(e / f_px) for i, e in enumerate(errs)))
    assert line == (f"last 5 s: frames 5 decided, 0 dropped, commands 3; frame 77: offset +0.40 px, confident "
                    f"(margin 0.90, w 15); slave pan at capture {lo:+.3f}..-2.865 deg, {rms:.2f} px RMS off the "
                    f"simulator's truth (max 1.50 px, 4 frames)")
    assert w.pans == [] and w.errors == []  # taken: the next window begins empty
    real = summary(5.0, 1, 0, 0, last, Window())  # a camera's frames: no truth, no tracking error
    assert "truth" not in real and real.endswith("(margin 0.90, w 15)")
    # an abstention says why where the fovea had no texture (a black or flat image), not where it had
    flat = SimpleNamespace(decision=SimpleNamespace(offset_px=0.0, confident=False, confidence=0.0),
                           frame=SimpleNamespace(frame=78, window=15), textured=False)
    assert summary(5.0, 1, 0, 0, flat, Window()).endswith(
        "frame 78: offset +0.00 px, abstains: no texture at the fovea (a black or flat image) (margin 0.00, w 15)")
    weak = SimpleNamespace(**dict(flat.__dict__, textured=True))
    assert summary(5.0, 1, 0, 0, weak, Window()).endswith("frame 78: offset +0.00 px, abstains (margin 0.00, w 15)")


class _Sample:
    def __init__(self, key: str, payload: bytes):
        self.key_expr, self._payload = key, payload

    @property
    def payload(self):
        return self

    def to_bytes(self) -> bytes:
        return self._payload


class _Ring:
    """A zenoh RingChannel subscriber as the inbox reads it: recv() blocks (here: must have something), try_recv()
    gives None when empty."""

    def __init__(self, samples=()):
        self.q = collections.deque(samples)

    def recv(self):
        assert self.q, "recv() on an empty ring would block for good"
        return self.q.popleft()

    def try_recv(self):
        return self.q.popleft() if self.q else None


def test_the_inbox_takes_both_rings_whole_keeps_the_newest_and_counts_the_rest():
    from services.pipeline.reducer import Inbox, WAKE

    frames = _Ring([_Sample("vergence/r/frame", b"f%d" % i) for i in range(5)])
    corr = _Ring([_Sample("vergence/r/correlation/w", b"c%d" % i) for i in range(5)]
                 + [_Sample(f"vergence/r/correlation/{WAKE}", b"")])
    box = Inbox(frames, corr, frames=2, correlations=3)
    assert box.take() == [("frame", ("vergence/r/frame", b"f3")), ("frame", ("vergence/r/frame", b"f4")),
                          ("correlation", ("vergence/r/correlation/w", b"c2")),
                          ("correlation", ("vergence/r/correlation/w", b"c3")),
                          ("correlation", ("vergence/r/correlation/w", b"c4"))]
    assert box.shed == {"frame": 3, "correlation": 2}
    # a wake alone (the alarm's, or the exit's) gives nothing and sheds nothing; a frame that came meanwhile is taken
    corr.q.append(_Sample(f"vergence/r/correlation/{WAKE}", b""))
    frames.q.append(_Sample("vergence/r/frame", b"f5"))
    assert box.take() == [("frame", ("vergence/r/frame", b"f5"))] and box.shed == {"frame": 3, "correlation": 2}
    # a forged correlation with a payload on the wake key is not a wake: it goes on to be decoded (and rejected)
    corr.q.append(_Sample(f"vergence/r/correlation/{WAKE}", b"x"))
    assert box.take() == [("correlation", (f"vergence/r/correlation/{WAKE}", b"x"))]


@pytest.mark.realtime  # times a thread or a wake-up: kept in the main process of a split run
def test_the_alarm_wakes_at_the_time_set_then_every_expire_s_and_stops():
    from services.pipeline.reducer import EXPIRE_S, Alarm

    stop = threading.Event()
    woken: list[float] = []
    alarm = Alarm(lambda: woken.append(time.monotonic()), stop)
    th = threading.Thread(target=alarm.run, daemon=True)
    t0 = time.monotonic()
    th.start()
    alarm.set(t0 + 0.01)  # sooner than the EXPIRE_S it was armed for
    deadline = time.monotonic() + 5
    while len(woken) < 3 and time.monotonic() < deadline:
        time.sleep(0.005)
    stop.set()
    th.join(1)
    assert not th.is_alive()
    assert len(woken) >= 3
    assert 0.01 <= woken[0] - t0 < EXPIRE_S  # the time set, not the one it was armed for
    assert all(b - a >= EXPIRE_S * 0.99 for a, b in zip(woken, woken[1:]))  # then every EXPIRE_S
    alarm.set(time.monotonic() + 10)  # later than armed: changes nothing
    assert alarm.at < time.monotonic() + EXPIRE_S + 0.01


def test_the_inbox_waits_on_the_frames_ring_when_told_and_still_takes_both():
    """Reducer.run waits on the frames' ring while no Frame awaits its correlations (Gatherer.awaiting): the Frame
    wakes it, to be prepared while the workers compute; the frames' own wake (<frame>/_wake) gives nothing."""
    from services.pipeline.reducer import Inbox, WAKE

    frames = _Ring([_Sample("vergence/r/frame", b"f1")])
    corr = _Ring([_Sample("vergence/r/correlation/w", b"c0")])
    box = Inbox(frames, corr)
    assert box.take("frame") == [("frame", ("vergence/r/frame", b"f1")),
                                 ("correlation", ("vergence/r/correlation/w", b"c0"))]
    frames.q.append(_Sample(f"vergence/r/frame/{WAKE}", b""))
    assert box.take("frame") == [] and box.shed == {"frame": 0, "correlation": 0}


def test_a_frame_on_any_other_key_under_the_frames_is_no_frame():
    """The frames' ring hears vergence/<rig>/frame/** (for its wake): a Frame forged on a key under it is rejected
    (counted under bad.frame), not gathered (no worker hears it: it would wait for correlations that never come)."""
    from samples import frame_of, textured

    from services.pipeline.reducer import Reducer
    from vergence.config import load
    from vergence.network.params import Params

    m, s = textured()
    data = frame_of(m, s, Params()).to_bytes()
    r = Reducer(load(None), 0.05)
    r.health = Health()
    assert r.decode("frame", ("vergence/head/frame/x", data)) is None
    assert r.health.rejected == [("frame", "frame on key vergence/head/frame/x")]
    assert r.decode("frame", ("vergence/head/frame", data)).frame == 1


def test_the_motors_plausible_reports_reach_the_controller_and_the_others_are_counted():
    """Each motor state the reducer reads goes to the controller (a late camera's lag is fitted on the motor's own
    reports, vergence.head.lag) where the capture would take it too: a pan outside the motor's limits, a time far off
    this host's clock or ahead of it (counted under bad.motor_state) and a motor that does not know its pan
    (disconnected, absent)
    do not; one that does not decode is counted by the presence."""
    from vergence.wire.messages import MotorState
    from services.pipeline.reducer import Reducer
    from vergence.config import load

    r = Reducer(load(None), 0.05)
    r.health = Health()
    now = time.time_ns()

    def state(t_ns, pan, status="ok"):
        return MotorState(rig="r", t_ns=t_ns, pan_rad=pan, goal_rad=pan, min_rad=-1, max_rad=1, status=status)

    r.motor_state(state(now - 20_000_000, 0.01))
    r.motor_state(state(now - 10_000_000, 0.02))
    r.motor_state(state(now - 5_000_000, 3.0))  # past the limits
    r.motor_state(state(now - 3_600 * 10**9, 0.03))  # an hour off our clock
    r.motor_state(state(now + 10**9, 0.05))  # a second ahead (it would push the true ones out of the lag's second)
    r.motor_state(state(now - 4_000_000, 0.04, "absent"))
    r.motor_state(None)  # (did not decode: the presence counted it)
    kept = list(r.gatherer.controller.doubt.lag.pans)
    assert [(round(t * 1e9 - now, -3), p) for t, p in kept] == [(-20_000_000, 0.01), (-10_000_000, 0.02)]
    assert [k for k, _ in r.health.rejected] == ["motor_state"] * 3
    assert "outside the motor limits" in r.health.rejected[0][1] and "off our clock" in r.health.rejected[1][1]
    assert "ahead of our clock" in r.health.rejected[2][1]
