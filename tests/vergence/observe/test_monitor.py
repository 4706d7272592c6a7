"""The monitor's model and renderings, fed with messages built here (no Zenoh)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from vergence.wire import messages as m
from vergence.observe.monitor import Monitor
from vergence.observe.screen import profile_bars, render_text
from vergence.observe.plots import lines as plot_lines, monitor_figure, monitor_png, png_bytes

W, WIN = 640, 15
K = W - WIN + 1
KC = 313
T0 = 1_700_000_000_000_000_000
MS = 1_000_000


def scores(k_star: int = 300, rows: int = 1, v_row: int = 0) -> np.ndarray:
    k = np.arange(K, dtype=np.float64)
    y = np.full((rows, K), 20000.0) + 1000.0 * np.cos(k / 17.0)
    y[v_row] += 30000.0 * np.exp(-0.5 * ((k - k_star) / 3.0) ** 2)
    return y


def profile(frame: int, t_cap: int, k_star: int = 300, rows: int = 1, v_shift: int = 0,
            confident: bool = True) -> m.Profile:
    y = scores(k_star, rows, v_shift + (rows - 1) // 2)
    d = k_star - KC
    return m.Profile(rig="head", frame=frame, t_capture_ns=t_cap, t_reduced_ns=t_cap + 2 * MS, width=W,
                     window=WIN, rows=rows, scores=y.astype("<f8").tobytes(), k=k_star, k_sub=float(k_star),
                     v_shift=v_shift, k_centre=KC, direction=int(np.sign(d)), magnitude=abs(d),
                     offset_px=float(d), confidence=0.5, confident=confident, texture=30.0, pan_rad=0.01,
                     workers=["w-1", "w-2"])


def frame(fid: int, t_cap: int, plan=None) -> m.Frame:
    return m.Frame(rig="head", frame=fid, t_capture_ns=t_cap, pan_rad=0.0, width=W, height=480, x=320,
                   y=240, window=WIN, vsearch=0, focal_px=500.0, fovea=bytes((WIN + 2) ** 2),
                   band=bytes((WIN + 2) * (W + 2)),
                   plan=plan if plan is not None else [["w-1", 0, 313], ["w-2", 313, K]])


def command(fid: int, t_cap: int, latency_ms: float, target: float = 0.02) -> m.Command:
    return m.Command(rig="head", frame=fid, t_capture_ns=t_cap, pan_rad=target, correction_rad=0.01,
                     direction=-1, magnitude_px=13.0, confidence=0.5,
                     t_sent_ns=t_cap + int(latency_ms * MS))


def motor(t: int, pan: float) -> m.MotorState:
    return m.MotorState(rig="head", t_ns=t, pan_rad=pan, goal_rad=0.02, min_rad=-0.5, max_rad=0.5,
                        status="ok")


def run_stream(mon: Monitor, seconds: float = 10.0, hz: float = 100.0, skip=(), latency=lambda i: 1.0):
    """Frames at hz; each answered by a profile and a command 2 ms later unless its index is in skip."""
    n = int(seconds * hz)
    step = int(1e9 / hz)
    for i in range(n):
        t = T0 + i * step
        mon.feed("vergence/head/frame", frame(i, t).to_bytes(), t)
        if i not in skip:
            mon.feed("vergence/head/profile", profile(i, t).to_bytes(), t + 2 * MS)
            mon.feed("vergence/head/command", command(i, t, latency(i), 0.001 * i).to_bytes(), t + 2 * MS)
        mon.feed("vergence/head/motor_state", motor(t, 0.001 * i).to_bytes(), t + 3 * MS)
    return T0 + (n - 1) * step + 3 * MS


def test_rates_latency_and_drops():
    mon = Monitor("head", window_s=5.0, drop_grace_s=0.5)
    # latency of frame i: 1 ms for 98 % of frames, 9 ms for every 50th
    now = run_stream(mon, 10.0, 100.0, skip={100, 101, 950}, latency=lambda i: 9.0 if i % 50 == 0 else 1.0)
    # snapshots move forward in time (the model forgets what leaves its window): first at the last arrival
    s = mon.snapshot(now)
    assert s.frames == 1000 and s.profiles == 997 and s.commands == 997
    assert s.frames_per_s == pytest.approx(100.0)
    assert s.profiles_per_s == pytest.approx(99.8)   # frame 950 is in the window and has no profile
    assert s.latency_n == 499
    assert s.latency_p50_ms == pytest.approx(1.0)
    assert s.latency_p99_ms == pytest.approx(9.0)
    assert s.reduce_p50_ms == pytest.approx(2.0) and s.reduce_p99_ms == pytest.approx(2.0)
    assert s.dropped == 2 and s.dropped_from == "frames"   # 950 is still within its grace
    s = mon.snapshot(now + 600 * MS)  # frame 950's grace has passed
    assert s.dropped == 3
    # 0.6 s after the last arrivals: the last 5 s window holds frames 560..999
    assert s.frames_per_s == pytest.approx(440 / 5.0)
    assert s.pan_rad == pytest.approx(0.999) and s.goal_rad == 0.02 and s.target_rad == pytest.approx(0.999)
    assert s.motor_status == "ok"
    assert s.profile.frame == 999 and s.command.frame == 999
    # history keeps the last 30 s: all 1000 states, oldest first, ages from ~10 s to 0
    assert len(s.pan_history) == 1000
    assert s.pan_history[0][0] == pytest.approx(10.59, abs=0.01)
    assert s.pan_history[-1] == (pytest.approx(0.6), pytest.approx(0.999))


def test_rate_while_filling_and_after_silence():
    mon = Monitor("head", window_s=5.0)
    now = run_stream(mon, 1.0, 50.0)
    assert mon.snapshot(now).frames_per_s == pytest.approx(50.0, rel=1e-3)
    assert mon.snapshot(now + 6_000 * MS).frames_per_s == 0.0


def test_drops_from_profile_gaps_without_frames():
    mon = Monitor("head")
    for i in (1, 2, 5, 6, 10):
        mon.add(profile(i, T0 + i * MS), T0 + i * MS)
    s = mon.snapshot(T0 + 20 * MS)
    assert s.dropped == 5 and s.dropped_from == "gaps"


def test_malformed_counted_and_skipped():
    mon = Monitor("head")
    assert mon.feed("vergence/head/profile", b"\xc1garbage") is None
    assert mon.feed("vergence/head/frame", command(1, T0, 1).to_bytes()) is None
    bad = profile(1, T0)
    bad.scores = bad.scores[:-8]  # wrong size
    assert mon.feed("vergence/head/profile", bad.to_bytes()) is None
    assert mon.feed("vergence/other/profile", profile(1, T0).to_bytes()) is None  # other rig: ignored
    assert mon.feed("vergence/head/profile", profile(2, T0).to_bytes()).frame == 2
    s = mon.snapshot()
    assert s.malformed == {"profile": 2, "frame": 1}
    assert "bytes do not make" in s.last_error["profile"]
    assert s.ignored == 1 and s.profiles == 1
    text = render_text(s, color=False)
    assert "malformed 3" in text and "malformed profile: 2" in text


def test_workers_from_liveliness_and_plan():
    mon = Monitor("head")
    mon.liveliness("vergence/head/alive/worker/w-1", True)
    mon.liveliness("vergence/head/alive/worker/w-2", True)
    mon.liveliness("vergence/head/alive/worker/w-3", True)
    mon.liveliness("vergence/head/alive/reducer/r-9", True)
    mon.liveliness("vergence/other/alive/worker/x-1", True)
    mon.add(frame(7, T0), T0)
    s = mon.snapshot(T0)
    assert s.workers == {"w-1": (0, 313), "w-2": (313, K), "w-3": None}
    assert s.alive == {"reducer": ["r-9"], "worker": ["w-1", "w-2", "w-3"]}
    mon.liveliness("vergence/head/alive/worker/w-2", False)
    mon.add(frame(8, T0, plan=[["w-1", 0, 200], ["w-3", 200, K]]), T0)
    s = mon.snapshot(T0)
    assert s.workers == {"w-1": (0, 200), "w-3": (200, K)}
    text = render_text(s, color=False)
    assert "workers 2: w-1 k 0..199   w-3 k 200..625" in text
    assert "reducer r-9" in text


@pytest.mark.parametrize("k_star,rows,v_shift", [(300, 1, 0), (313, 1, 0), (40, 5, -1), (600, 5, 2)],
                         ids=["left13", "centre", "vsearch-up", "vsearch-down"])
def test_profile_bars_mark_winner_and_centre(k_star, rows, v_shift):
    p = profile(1, T0, k_star, rows, v_shift)
    lines, wc, cc = profile_bars(p, 90, rows=8)
    assert len(lines) == 8 and all(len(ln) == 90 for ln in lines)
    edges = np.linspace(0, K, 91).astype(int)
    assert wc == np.searchsorted(edges, k_star, side="right") - 1
    assert cc == np.searchsorted(edges, KC, side="right") - 1
    assert lines[0][wc] == "█"                              # the winner's bar is full height
    assert sum(ln.count("█") for ln in lines[:1]) <= 3       # and the only one that tall (a 3-px peak)
    text = render_text(Monitor("head").snapshot(), color=False)  # empty model renders
    assert "no profile yet" in text


def test_render_text_values():
    mon = Monitor("head")
    now = run_stream(mon, 2.0, 100.0)
    mon.liveliness("vergence/head/alive/worker/w-1", True)
    s = mon.snapshot(now)
    text = render_text(s, width=100, color=False)
    assert "frames   100.0/s" in text
    assert "capture→command p50 1.00 ms  p99 1.00 ms" in text
    assert "k*=300" in text and "k_c=313" in text and "◀ left 13 px" in text
    assert "confidence 0.500 moves" in text
    assert "pan +11.402°" in text and "target +11.402°" in text  # 0.199 rad: the 200th state, command
    mark = next(ln for ln in text.splitlines() if "▲" in ln and "┴" in ln and "winner" not in ln)
    wc, cc = mark.index("▲") - 8, mark.index("┴") - 8
    assert wc < cc  # winner left of centre
    colored = render_text(s, width=100, color=True)
    assert "\x1b[31m▲\x1b[0m" in colored


def test_png_of_profile():
    """The figure holds the winner's row, the winner and the centre, and the pan and target histories;
    its PNG opens at the asked size and is drawn."""
    mon = Monitor("head")
    now = run_stream(mon, 2.0, 50.0)
    s = mon.snapshot(now)
    fig = monitor_figure(s, 960, 720)
    top, bot = fig.axes
    got = plot_lines(top)
    y = scores()[0]
    np.testing.assert_array_equal(got["profile"].get_ydata(), y)
    assert list(got["profile"].get_xdata()) == list(range(K))
    assert list(got["winner"].get_xdata()) == [300, 300] and list(got["centre"].get_xdata()) == [KC, KC]
    assert list(got["winner_dot"].get_xdata()) == [300] and got["winner_dot"].get_ydata()[0] == y.max()
    assert top.get_title(loc="left") == ("layer 4, frame 99: winner k*=300 (300.00), centre k_c=313, left 13 px, "
                                         "confidence 0.500\n"
                                         "fovea (320, 240)   not converged, no depth")
    assert [t.get_text() for t in top.get_legend().get_texts()][1:] == ["winner k*=300 (300.00)", "centre k_c=313"]
    got = plot_lines(bot)
    pan, target = got["pan"], got["target"]
    # the motor's pan 0.001 rad x i at 50 Hz, the last state 3 ms before now; the targets 1 ms before it
    assert pan.get_ydata()[-1] == pytest.approx(np.degrees(0.099)) and pan.get_xdata()[-1] == 0
    assert np.diff(pan.get_ydata()) == pytest.approx(np.degrees(0.001))
    assert np.diff(pan.get_xdata()) == pytest.approx(0.02)
    assert list(target.get_ydata()) == pytest.approx(list(pan.get_ydata()))
    assert bot.get_xlim() == pytest.approx((-max(a for a, _ in s.target_history), 0))
    assert (bot.get_xlabel(), bot.get_ylabel()) == ("seconds before now", "pan (deg)")

    for w, h in [(960, 720), (640, 480), (160, 120)]:
        data = monitor_png(s, w, h)
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and img.shape == (h, w, 3)
        assert img.std() > 10                                                       # not blank
        red = (img[:, :, 2] > 180) & (img[:, :, 1] < 80) & (img[:, :, 0] < 80)
        assert red.sum() > h // 8                                                   # the red winner

    blank = monitor_figure(Monitor("head").snapshot(), 320, 240)
    assert [t.get_text() for t in blank.axes[0].texts] == ["no profile"]
    assert [t.get_text() for t in blank.axes[1].texts] == ["no pan history"]
    assert not plot_lines(blank.axes[0]) and not plot_lines(blank.axes[1])
    img = cv2.imdecode(np.frombuffer(png_bytes(blank), np.uint8), cv2.IMREAD_COLOR)
    assert img.shape == (240, 320, 3)


def test_drops_from_reducer_status():
    mon = Monitor("head")
    run_stream(mon, 1.0, 100.0, skip={5})
    g = {"frames": 1200, "correlations": 2400, "complete": 1190, "dropped": 7, "superseded": 3, "late": 0}
    st = {"role": "reducer", "id": "r-9", "pid": 9, "t_ns": T0, "counters": {"profiles": 1190},
          "bad": {}, "gatherer": g, "pending": 1}
    assert mon.feed("vergence/head/status/reducer/r-9", json.dumps(st).encode()).get("gatherer") == g
    assert mon.feed("vergence/head/status/reducer/r-8", b"{not json") is None
    assert mon.feed("vergence/head/status/worker/w-1", b"[1, 2]") is None
    s = mon.snapshot(T0 + 2_000 * MS)
    assert (s.dropped, s.dropped_of, s.dropped_from) == (10, 1200, "reducer")
    assert s.malformed == {"status": 2}
    text = render_text(s, color=False)
    assert "dropped 10 (0.83 % of 1200, reducer counters)" in text
    assert "reducer/r-9: frames 1200  complete 1190  dropped 7  superseded 3  late 0  pending 1" in text
    # the reducer's last status (exiting) removes it: drops fall back to the frames seen unanswered
    mon.feed("vergence/head/status/reducer/r-9", json.dumps(dict(st, exiting=True)).encode())
    s = mon.snapshot(T0 + 2_000 * MS)
    assert (s.dropped, s.dropped_of, s.dropped_from) == (1, 100, "frames")


def test_capture_status_says_what_each_camera_clips():
    """The capture's `clipped` (retina.clipped_share): a line per capture, in yellow with what to do once a
    camera clips CLIP_WARN (5 %) or more; a capture whose status has no pair yet ({}) shows nothing."""
    mon = Monitor("head")
    run_stream(mon, 1.0, 100.0)
    st = {"role": "capture", "id": "c-1", "pid": 1, "t_ns": T0, "counters": {}, "bad": {},
          "clipped": {"slave": 0.159, "master": 0.0}}
    mon.feed("vergence/head/status/capture/c-1", json.dumps(st).encode())
    mon.feed("vergence/head/status/capture/c-2", json.dumps(dict(st, id="c-2", clipped={})).encode())
    s = mon.snapshot(T0 + 2_000 * MS)
    text = render_text(s, color=False)
    assert ("capture/c-1: clipped master 0 %, slave 16 % of the fovea's rows: set both cameras' exposure alike"
            in text)
    assert "capture/c-2" not in text
    assert "\x1b[33mcapture/c-1: clipped" in render_text(s, color=True)
    mon.feed("vergence/head/status/capture/c-1", json.dumps(dict(st, clipped={"slave": 0.01, "master": 0.0}))
             .encode())
    text = render_text(mon.snapshot(T0 + 2_000 * MS), color=True)
    assert "capture/c-1: clipped master 0 %, slave 1 %\n" in text + "\n" and "\x1b[33mcapture/c-1" not in text
    # a forged status: a number too large for a float, a share over 1, a third camera: only what is plausible
    # is shown, and the screen still renders; NaN is not JSON: that status is malformed (counted, skipped)
    forged = {"slave": 10 ** 400, "master": 1.5, "left": 0.5, "extra" * 50: 0.9}
    assert mon.feed("vergence/head/status/capture/c-1", json.dumps(dict(st, clipped={"master": float("nan")}))
                    .encode()) is None
    mon.feed("vergence/head/status/capture/c-1", json.dumps(dict(st, clipped=forged)).encode())
    text = render_text(mon.snapshot(T0 + 2_000 * MS), color=False)
    assert "capture/c-1: clipped" not in text and "extra" not in text
    mon.feed("vergence/head/status/capture/c-1", json.dumps(dict(st, clipped={"slave": 2, "master": 0.06}))
             .encode())
    assert "capture/c-1: clipped master 6 % of the fovea's rows" in render_text(mon.snapshot(T0 + 2_000 * MS),
                                                                               color=False)


def test_a_named_fault_is_a_red_line_with_what_to_check():
    """The reducer's `fault` (vergence.head.doubt): first among its lines, in red, with its note; a name that is no
    fault shows nothing."""
    mon = Monitor("head")
    run_stream(mon, 1.0, 100.0)
    st = {"role": "reducer", "id": "r-1", "pid": 1, "t_ns": T0, "counters": {}, "bad": {}, "gatherer": {"frames": 3},
          "fault": "slave_frozen", "fault_note": "slave_frozen: check the camera's cable and driver"}
    mon.feed("vergence/head/status/reducer/r-1", json.dumps(st).encode())
    s = mon.snapshot(T0 + 2_000 * MS)
    assert "FAULT slave_frozen: slave_frozen: check the camera's cable and driver" in render_text(s, color=False)
    assert "\x1b[31mFAULT slave_frozen" in render_text(s, color=True)
    mon.feed("vergence/head/status/reducer/r-1", json.dumps(dict(st, fault="gremlins")).encode())
    assert "FAULT" not in render_text(mon.snapshot(T0 + 2_000 * MS), color=False)


def test_a_camera_named_late_is_a_yellow_line_with_what_to_set():
    """The reducer's `late_ms` (vergence.head.lag), no fault held: a yellow line with the lag and the setting; a lag
    that is no number of ms (a forged status) shows nothing."""
    mon = Monitor("head")
    run_stream(mon, 1.0, 100.0)
    st = {"role": "reducer", "id": "r-1", "pid": 1, "t_ns": T0, "counters": {}, "bad": {}, "gatherer": {"frames": 3},
          "fault": None, "late_ms": 66.2}
    mon.feed("vergence/head/status/reducer/r-1", json.dumps(st).encode())
    s = mon.snapshot(T0 + 2_000 * MS)
    assert ("camera late: the slave's image follows the motor 66 ms later than its frames say; set [camera] "
            "latency_s") in render_text(s, color=False).replace("\n  ", " ")
    assert "\x1b[33mcamera late" in render_text(s, color=True)
    for forged in ("66", -5, 1e9, None):
        mon.feed("vergence/head/status/reducer/r-1", json.dumps(dict(st, late_ms=forged)).encode())
        assert "camera late" not in render_text(mon.snapshot(T0 + 2_000 * MS), color=False)


def test_a_search_is_a_yellow_line_that_asks_whether_the_slave_can_see_the_point():
    """The reducer's `searching` with `sweeps_empty` (vergence.head.search): a yellow line, and from the first sweep
    that found nothing the question to check; not searching, or forged values, show nothing."""
    mon = Monitor("head")
    run_stream(mon, 1.0, 100.0)
    st = {"role": "reducer", "id": "r-1", "pid": 1, "t_ns": T0, "counters": {}, "bad": {}, "gatherer": {"frames": 3},
          "fault": None, "searching": True, "sweeps_empty": 0}
    mon.feed("vergence/head/status/reducer/r-1", json.dumps(st).encode())
    text = render_text(mon.snapshot(T0 + 2_000 * MS), color=False).replace("\n  ", " ")
    assert "searching: no confident match at the fovea" in text and "sweep" not in text
    mon.feed("vergence/head/status/reducer/r-1", json.dumps(dict(st, sweeps_empty=2)).encode())
    s = mon.snapshot(T0 + 2_000 * MS)
    assert ("searching: no confident match at the fovea; 2 sweeps of the pan range found nothing: is the point "
            "visible to the slave camera") in render_text(s, color=False).replace("\n  ", " ")
    assert "\x1b[33msearching" in render_text(s, color=True)
    for forged in (dict(searching=False), dict(searching="yes"), dict(sweeps_empty=-1), dict(sweeps_empty="2")):
        mon.feed("vergence/head/status/reducer/r-1", json.dumps(dict(st, **forged)).encode())
        assert "searching" not in render_text(mon.snapshot(T0 + 2_000 * MS), color=False), forged


def test_a_fovea_with_no_texture_is_a_yellow_line_that_says_the_slave_holds():
    """The reducer's `no_texture` (its last frame black or flat: vergence.head.search): a yellow line naming it;
    false, or a forged value, shows nothing."""
    mon = Monitor("head")
    run_stream(mon, 1.0, 100.0)
    st = {"role": "reducer", "id": "r-1", "pid": 1, "t_ns": T0, "counters": {}, "bad": {}, "gatherer": {"frames": 3},
          "fault": None, "searching": False, "no_texture": True}
    mon.feed("vergence/head/status/reducer/r-1", json.dumps(st).encode())
    s = mon.snapshot(T0 + 2_000 * MS)
    assert ("no texture at the fovea (a black or flat image: a lens cap, the light off, a blank surface, a camera "
            "sending black frames): the loop abstains and the slave holds") in render_text(s, color=False).replace(
                "\n  ", " ")
    assert "\x1b[33mno texture" in render_text(s, color=True)
    for forged in (dict(no_texture=False), dict(no_texture="yes"), dict(no_texture=1)):
        mon.feed("vergence/head/status/reducer/r-1", json.dumps(dict(st, **forged)).encode())
        assert "no texture" not in render_text(mon.snapshot(T0 + 2_000 * MS), color=False), forged


def test_screen_lines_fit_the_terminal():
    """Each screen line fits the terminal's width (ANSI codes do not count): a line too wide is broken between
    its fields, the rest on the next line indented by 2, nothing lost."""
    import re

    mon = Monitor("head")
    now = run_stream(mon, 2.0, 100.0)
    for width in (80, 100, 160):
        for color in (False, True):
            text = render_text(mon.snapshot(now), width=width, color=color)
            assert max(len(re.sub(r"\x1b\[[0-9;]*m", "", ln)) for ln in text.splitlines()) <= width
    lines = render_text(mon.snapshot(now), width=80, color=False).splitlines()
    i = next(i for i, ln in enumerate(lines) if ln.startswith("latency capture→command p50 1.00 ms"))
    assert lines[i + 1] == "  capture→profile p50 2.00 ms  p99 2.00 ms"
    assert any(ln.startswith("decision k*=300") for ln in lines) and "  confidence 0.500 moves   texture 30.0" in lines
    wide = render_text(mon.snapshot(now), width=160, color=False).splitlines()
    assert any("capture→command" in ln and "capture→profile" in ln for ln in wide)  # one line when it fits


def test_forged_reducer_counters_do_not_stop_the_screen():
    """A reducer status whose counters are no counters (a JSON integer too large for a float, negative, a
    bool) is shown without them: the drops come from the plausible ones, and the screen renders."""
    mon = Monitor("head")
    run_stream(mon, 1.0, 100.0)
    g = {"frames": 10 ** 400, "dropped": -5, "superseded": True, "complete": 1}
    st = {"role": "reducer", "id": "r-9", "pid": 9, "t_ns": T0, "counters": {}, "bad": {}, "gatherer": g}
    mon.feed("vergence/head/status/reducer/r-9", json.dumps(st).encode())
    mon.feed("vergence/head/status/reducer/r-8", json.dumps(dict(st, id="r-8", gatherer={"frames": 40,
                                                                                         "dropped": 2})).encode())
    s = mon.snapshot(T0 + 2_000 * MS)
    assert (s.dropped, s.dropped_of, s.dropped_from) == (2, 40, "reducer")
    assert "dropped 2 (5.00 % of 40, reducer counters)" in render_text(s, color=False)


def test_an_absent_motor_is_a_red_line_with_why():
    """Issue #29: a motor state `absent` (or `disconnected`) is a fault line, in red, with the state's note."""
    mon = Monitor("head")
    mon.add(motor(T0, 0.01), T0)
    assert "MOTOR" not in render_text(mon.snapshot(), color=False)
    note = "command ignored: motor absent for 3.0 s (no answer for 0.6 s: ping failed 3 times)"
    mon.add(m.replace(motor(T0 + MS, 0.01), status="absent", note=note), T0 + MS)
    text = render_text(mon.snapshot(), width=200, color=False)
    assert "status absent" in text and f"MOTOR ABSENT: commands are not executed; {note}" in text
    assert "\x1b[31mMOTOR ABSENT" in render_text(mon.snapshot(), width=200, color=True)


def test_the_truth_follows_beside_the_pan_and_the_tracking_error_is_over_the_window():
    """A simulated source's frames carry the truth at capture: the screen gives the tracking over the window
    (RMS and max of the frames' pans off it) and the truth's history under the pan's, on one scale and span."""
    mon = Monitor(rig="head", window_s=5.0, history_s=30.0)
    f_px = 500.0
    errs, now, seen = [], T0 + int(299 / 30 * 1e9) + 1, []
    for i in range(300):  # 10 s at 30 Hz: the truth a sine, the pan a little behind it
        t = T0 + int(i / 30 * 1e9)
        truth = -0.06 + 0.02 * np.sin(2 * np.pi * 0.2 * i / 30)
        pan = truth + np.arctan((0.5 if i % 2 else -1.0) / f_px)
        fr = frame(i, t)
        fr.truth_pan_rad, fr.pan_rad = float(truth), float(pan)
        mon.add(fr, t)
        mon.add(motor(t, float(pan)), t)
        seen += [truth, pan]
        if t > now - 5e9:
            errs.append(f_px * np.tan(pan - truth))
    s = mon.snapshot(now)
    assert s.tracking_n == len(errs) == 150
    assert s.tracking_rms_px == pytest.approx(float(np.sqrt(np.mean(np.square(errs)))), rel=1e-9)
    assert s.tracking_max_px == pytest.approx(1.0, rel=1e-6)
    text = render_text(s, width=100, color=False)
    assert (f"tracking over the last 5 s: the frames' pans are {s.tracking_rms_px:.2f} px RMS off the truth "
            f"(max 1.00 px, 150 frames)") in text
    pan_line = next(ln for ln in text.splitlines() if ln.startswith("pan history"))
    truth_line = next(ln for ln in text.splitlines() if ln.startswith("truth history"))
    assert pan_line.index(")") == truth_line.index(")")  # one scale, one span: the cells line up in time
    assert f"({np.degrees(min(seen)):+.2f}°..{np.degrees(max(seen)):+.2f}°, 10 s)" in truth_line
    cells = truth_line[truth_line.index(")") + 2:]
    assert len(cells) == 55 and len(set(cells)) >= 6  # the sine, drawn over the ▁..█ range
