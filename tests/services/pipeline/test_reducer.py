"""The reducer's own state in its process (no router): the hold a client puts on its commands, and what the
actuator says of its motor."""

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
