"""The distributed steps as plain functions, no network: vergence.frames (capture), vergence.shards (worker),
vergence.gather (reducer) and vergence.sources."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from vergence import kernel, match, retina
from vergence.control import ControlSettings, Controller
from vergence.frames import WindowControl, make_frame, plan_shards
from vergence.gather import Gatherer, reduce
from vergence.retina import master_clipped
from vergence.messages import Frame, MessageError, Partial
from vergence.params import Params
from vergence.shards import compute_partial
from vergence.sources import FilesSource, SimSource, SourceError, open_source

SHIFT = 12  # the slave sees the scene 12 px further left: the match lies 12 px right of the centre


def textured(h=120, w=200, seed=1, shift=SHIFT):
    rng = np.random.default_rng(seed)
    base = cv2.GaussianBlur(rng.integers(0, 256, (h, w + 40), np.uint8), (5, 5), 1.5)
    return np.ascontiguousarray(base[:, 20 : 20 + w]), np.ascontiguousarray(base[:, 20 - shift : 20 - shift + w])


def frame_of(master, slave, params, workers=("a",), fid=1, pan=0.0, focal=100.0, window=None):
    k = master.shape[1] - (window or params.window) + 1
    return make_frame(master, slave, rig="r", frame=fid, pan_rad=pan, focal_px=focal, params=params,
                      plan=plan_shards(workers, k), window=window)


@pytest.mark.parametrize("n,k,expect", [
    (1, 10, [["w0", 0, 10]]),
    (2, 10, [["w0", 0, 5], ["w1", 5, 10]]),
    (3, 10, [["w0", 0, 3], ["w1", 3, 6], ["w2", 6, 10]]),
    (4, 2, [["w0", 0, 1], ["w1", 1, 2]]),
    (0, 10, []),
], ids=["one", "two", "three-uneven", "more-workers-than-offsets", "none"])
def test_plan_shards(n, k, expect):
    assert plan_shards([f"w{i}" for i in reversed(range(n))], k) == expect


def test_plan_is_a_valid_frame_plan():
    m, s = textured()
    f = frame_of(m, s, Params(), workers=["z", "b", "m"])
    assert [e[0] for e in f.plan] == ["b", "m", "z"]
    Frame.from_bytes(f.to_bytes())  # validates the partition


@pytest.mark.parametrize("params", [Params(), Params.paper(), Params(vsearch=0, circular=False),
                                    Params(support=True), Params(photometric="affine")],
                         ids=["default", "paper", "flat", "support", "affine"])
@pytest.mark.parametrize("nworkers", [1, 2, 3])
@pytest.mark.parametrize("gain", [1.0, 0.7])
def test_shards_concatenate_to_correlate(params, nworkers, gain):
    m, s = textured()
    s = np.clip(s * gain + (-15 if gain != 1 else 0), 0, 255).astype(np.uint8)  # the slave camera's gain
    f = Frame.from_bytes(frame_of(m, s, params, workers=[f"w{i}" for i in range(nworkers)]).to_bytes())
    parts = [Partial.from_bytes(compute_partial(f, f"w{i}").to_bytes()) for i in range(nworkers)]
    got = np.concatenate([p.array() for p in parts], axis=1)
    fovea, band = retina.features(m, s, window=params.window, vsearch=params.vsearch, photometric=params.photometric)
    w = kernel.support_weights(fovea, params.support_gamma, params.support_radius_at(params.window)) \
        if params.support else None
    want = np.atleast_2d(kernel.correlate(fovea, band, circular=params.circular, weights=w))
    assert got.shape == want.shape == (2 * params.vsearch + 1, m.shape[1] - params.window + 1)
    assert np.array_equal(got, want)
    assert compute_partial(f, "nobody") is None


@pytest.mark.parametrize("params", [Params(max_window=0), Params.paper()], ids=["default", "paper"])
def test_reduce_equals_match(params):
    m, s = textured()
    f = frame_of(m, s, params, pan=0.1, focal=150.0)
    scores = np.atleast_2d(compute_partial(f, "a").array())
    prof, cmd = reduce(f, scores, params, Controller())
    d = match(m, s, params=params).decision
    assert (prof.k, prof.k_sub, prof.v_shift, prof.confident) == (d.k, d.k_sub, d.v, d.confident)
    assert prof.k - prof.k_centre == SHIFT and prof.workers == ["a"]
    assert cmd is not None and cmd.frame == 1
    assert cmd.pan_rad == pytest.approx(0.1 + math.atan(d.offset_px / 150.0))
    assert cmd.correction_rad == pytest.approx(math.atan(d.offset_px / 150.0))
    assert cmd.direction == 1 and cmd.magnitude_px == pytest.approx(abs(d.offset_px))


def clipping_pair():
    """A textured pair whose slave is at gain 1.6, +40: a quarter of its band saturates (clip_master clips)."""
    m, s = textured()
    return m, np.clip(s * 1.6 + 40, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("clip", [True, False], ids=["clipped", "unclipped"])
def test_reduce_equals_match_for_either_clip(clip):
    """make_frame's clip (the dynamic window's clip_fallback states): the workers and the reducer compute what
    match() computes with that clip_master, layer 4 bit for bit; the two clips differ on this pair."""
    m, s = clipping_pair()
    params = Params(max_window=0)
    assert master_clipped(m, s, 60, 15, params)
    f = Frame.from_bytes(frame_of(m, s, params).to_bytes()) if clip else \
        Frame.from_bytes(make_frame(m, s, rig="r", frame=1, pan_rad=0.0, focal_px=100.0, params=params,
                                    plan=plan_shards(["a"], m.shape[1] - 14), clip=False).to_bytes())
    scores = np.atleast_2d(compute_partial(f, "a").array())
    want = match(m, s, params=params, clip_master=clip)
    other = match(m, s, params=params, clip_master=not clip)
    assert np.array_equal(scores, np.atleast_2d(want.scores))
    assert not np.array_equal(scores, np.atleast_2d(other.scores))
    prof, _ = reduce(f, scores, params, Controller())
    d = want.decision
    assert (prof.k, prof.k_sub, prof.v_shift, prof.confident) == (d.k, d.k_sub, d.v, d.confident)


def test_reduce_flat_fovea_gives_no_command():
    m = np.full((60, 100), 90, np.uint8)
    f = frame_of(m, m, Params())
    prof, cmd = reduce(f, np.atleast_2d(compute_partial(f, "a").array()), Params(), Controller())
    assert not prof.confident and cmd is None


def gather(params=Params(max_window=0), deadline=0.05):
    return Gatherer(params, ControlSettings(), deadline)


def test_gatherer_complete_in_any_order():
    m, s = textured()
    f = frame_of(m, s, Params(), workers=["a", "b"])
    pa, pb = compute_partial(f, "a"), compute_partial(f, "b")
    g = gather()
    assert g.add_partial(pb, now=0.0) == []
    assert g.add_frame(f, now=0.001) == []
    (r,) = g.add_partial(pa, now=0.002)
    assert r.profile.frame == 1 and r.command is not None and r.profile.workers == ["a", "b"]
    assert g.counters["complete"] == 1 and not g.pending
    assert g.add_partial(pa, now=0.003) == [] and g.counters["late"] == 1


def test_gatherer_drops_at_deadline_and_never_reduces_incomplete():
    m, s = textured()
    f = frame_of(m, s, Params(), workers=["a", "b"])
    g = gather(deadline=0.05)
    g.add_frame(f, now=0.0)
    g.add_partial(compute_partial(f, "a"), now=0.01)
    assert g.next_deadline() == pytest.approx(0.05)
    g.expire(now=0.06)
    assert g.counters["dropped"] == 1 and not g.pending
    assert g.add_partial(compute_partial(f, "b"), now=0.07) == []  # too late: nothing published
    assert g.counters["complete"] == 0 and g.counters["late"] == 1


def test_gatherer_supersedes_older_frames_and_rejects_foreign_partials():
    m, s = textured()
    f1 = frame_of(m, s, Params(), workers=["a", "b"], fid=1)
    f2 = frame_of(m, s, Params(), workers=["a"], fid=2)  # a worker left: the next frame has a new plan
    g = gather()
    g.add_frame(f1, now=0.0)
    g.add_partial(compute_partial(f1, "a"), now=0.0)
    g.add_frame(f2, now=0.001)
    wrong = compute_partial(f1, "b")
    wrong.frame = 2  # b's range of frame 1 does not fit frame 2's plan
    assert g.add_partial(wrong, now=0.002) == [] and g.counters["unexpected"] == 1
    (r,) = g.add_partial(compute_partial(f2, "a"), now=0.003)
    assert r.frame.frame == 2 and g.counters["superseded"] == 1 and not g.pending


def test_gatherer_bad_shape_drops_frame():
    m, s = textured()
    f = frame_of(m, s, Params(), workers=["a"])
    p = compute_partial(f, "a")
    p.rows, p.scores = 1, p.array()[:1].tobytes()  # fits its own sizes, not the frame's 5 rows
    g = gather()
    g.add_frame(f, now=0.0)
    assert g.add_partial(p, now=0.0) == []
    assert g.counters["bad"] == 1 and g.counters["dropped"] == 1 and g.counters["complete"] == 0


def test_gatherer_restart_and_no_plan():
    m, s = textured()
    g = gather()
    old = frame_of(m, s, Params(), workers=["a"], fid=5)
    g.add_frame(old, now=0.0)
    assert len(g.add_partial(compute_partial(old, "a"), now=0.0)) == 1
    stale = compute_partial(old, "a")
    stale.frame, stale.t_capture_ns = 3, old.t_capture_ns - 1  # reordered, older: late
    assert g.add_partial(stale, now=0.0) == [] and g.counters["late"] == 1
    f = frame_of(m, s, Params(), workers=["a"], fid=1)  # a new capture: ids from 1 again, later times
    f.t_capture_ns = old.t_capture_ns + 1
    g.add_frame(f, now=0.0)
    assert g.counters["restarts"] == 1
    assert len(g.add_partial(compute_partial(f, "a"), now=0.0)) == 1
    f.plan = []
    f.frame = 2
    g.add_frame(f, now=0.0)
    assert g.counters["no_plan"] == 1


def test_frame_master_band_round_trip_and_validation():
    m, s = textured()
    f = frame_of(m, s, Params())
    g = Frame.from_bytes(f.to_bytes())
    assert np.array_equal(g.master_band_strip(), retina.band_strip(m, 60, 15))  # the fovea's rows
    assert frame_of(m, s, Params(lr_check=False)).master_band == b""
    f.master_band = f.master_band[:-1]
    with pytest.raises(MessageError, match="master_band"):
        Frame.from_bytes(f.to_bytes())


def test_window_control():
    wc = WindowControl(Params(window=15, max_window=31), patience=2)
    assert wc.update(15, False) == 23
    assert wc.update(15, False) == 23  # an in-flight profile of the old window does not count
    assert wc.update(23, False) == 31 and wc.update(31, False) == 31
    assert wc.update(31, True) == 31 and wc.update(31, True) == 23
    assert WindowControl(Params(max_window=0)).update(15, False) == 15


def test_window_control_walks_the_windows_match_tries():
    """One dynamic-window rule: the capture's window steps through exactly Params.windows(), which
    vergence.match() tries in turn (15, 23, 31, 39 for max_window 40: never past it), and reset() is the base."""
    p = Params(window=15, max_window=40)
    assert p.windows() == [15, 23, 31, 39]
    wc, seen = WindowControl(p, patience=1), [15]
    for _ in range(5):
        seen.append(wc.update(seen[-1], False))
    assert seen == [15, 23, 31, 39, 39, 39]
    down = [wc.update(w, True) for w in (39, 31, 23, 15)]
    assert down == [31, 23, 15, 15]
    wc.update(15, False)
    wc.reset()
    assert wc.window == 15 and wc.update(15, False) == 23


def test_window_control_with_clip_fallback_then_the_unclipped_windows():
    """clip_fallback: the clipped windows, then (only where the master was clipped) the same windows unclipped,
    as match() tries them; a decision of another state (a frame in flight) does not count, a confident one
    clears the clipping seen, and a window that no longer fits goes on to the unclipped ones."""
    p = Params(window=15, max_window=31, clip_fallback=True)
    wc = WindowControl(p, patience=1)
    assert wc.states == [(15, True), (23, True), (31, True), (15, False), (23, False), (31, False)]
    assert wc.update(15, False) == 23 and wc.update(23, False) == 31
    assert wc.update(31, False) == 31 and wc.state == (31, True)  # the master never clipped: stays
    wc.clipped(False)
    assert wc.update(31, False) == 31 and wc.state == (31, True)
    wc.clipped(True)
    assert wc.update(31, False) == 15 and wc.state == (15, False)
    assert wc.update(15, False, clip=True) == 15 and wc.state == (15, False)  # in flight: the clipped 15
    assert wc.update(15, False, clip=False) == 23 and wc.state == (23, False)
    assert wc.update(23, True, clip=False) == 15 and wc.state == (15, False)  # patience 1: one step back
    assert wc.update(15, True, clip=False) == 31 and wc.state == (31, True)
    assert wc.update(31, False) == 31 and wc.state == (31, True)  # the confident ones cleared the clipping
    wc.clipped()
    wc.reset()  # 31 px no longer fits, the master was clipped: on to the unclipped windows
    assert wc.state == (15, False)
    wc.reset()
    assert wc.state == (15, True)
    for params in (Params(max_window=31, clip_fallback=False), Params(max_window=31, photometric="none"),
                   Params(max_window=31, clip_master=False)):
        assert WindowControl(params).states == [(15, True), (23, True), (31, True)]
    assert WindowControl(Params(max_window=0)).states == [(15, True), (15, False)]  # as match() then tries
    assert Params.paper().clip_fallback is False and WindowControl(Params.paper()).states == [(15, True)]


def test_files_source(tmp_path):
    m, s = textured()
    cv2.imwrite(str(tmp_path / "l.png"), m)
    cv2.imwrite(str(tmp_path / "r.png"), s)
    src = open_source(f"files:{tmp_path / 'l.png'},{tmp_path / 'r.png'}")
    a, b = src.read(0.3)
    assert isinstance(src, FilesSource) and src.size == (200, 120)
    assert np.array_equal(a, m) and np.array_equal(b, s)
    assert not src.follows_pan and src.start_pan_rad == 0.0  # taken at pan 0, whatever the motor does
    a, b = open_source(f"files:{tmp_path / 'l.png'},{tmp_path / 'r.png'}", master="right").read()
    assert np.array_equal(a, s)


@pytest.mark.parametrize("spec,msg", [
    ("files:/nonexistent/l.png,/nonexistent/r.png", "/nonexistent/l.png"),
    ("files:onlyone", "LEFT,RIGHT"),
    ("video:/nonexistent/a.avi,/nonexistent/b.avi", "no such file"),
    ("camera:97,98", "camera '97'"),
    ("nope:1", "unknown source"),
    ("sim:bogus=1", "bogus"),
], ids=["missing-file", "one-file", "missing-video", "no-camera", "unknown", "bad-sim-key"])
def test_source_errors_name_the_problem(spec, msg):
    with pytest.raises(SourceError, match=msg):
        open_source(spec)


def test_video_source(tmp_path):
    m, s = textured()
    for name, img in (("l.avi", m), ("r.avi", s)):
        vw = cv2.VideoWriter(str(tmp_path / name), cv2.VideoWriter_fourcc(*"MJPG"), 10, (200, 120))
        if not vw.isOpened():
            pytest.skip("no MJPG writer in this OpenCV")
        for _ in range(2):
            vw.write(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
        vw.release()
    src = open_source(f"video:{tmp_path / 'l.avi'},{tmp_path / 'r.avi'}")
    assert not src.follows_pan and src.start_pan_rad == 0.0
    for _ in range(5):  # rewinds at the end
        a, b = src.read()
        assert a.shape == (120, 200) and a.dtype == np.uint8
        assert np.abs(a.astype(int) - m).mean() < 4
    src.close()


def test_sim_source_renders_at_the_given_pan():
    src = open_source("sim:size=160x120:focal=128")
    assert isinstance(src, SimSource) and src.size == (160, 120) and src.focal_px == 128.0 and src.follows_pan
    a0, b0 = src.read(0.0)
    a1, b1 = src.read(0.05)
    assert a0.shape == (120, 160) and np.array_equal(a0, a1) and not np.array_equal(b0, b1)
