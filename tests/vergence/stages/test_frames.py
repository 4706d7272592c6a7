"""vergence.stages.frames, the capture side's steps as plain functions: the plan of shards, a frame's master band, the
dynamic window."""

from __future__ import annotations

import numpy as np
import pytest
from samples import frame_of, textured

from vergence.network import retina
from vergence.head.control import ControlSettings
from vergence.stages.frames import WindowControl, plan_shards
from vergence.stages.gather import Gatherer
from vergence.wire.messages import Frame, MessageError
from vergence.network.params import Params


def clipping_pair():
    """A textured pair whose slave is at gain 1.6, +40: a quarter of its band saturates (clip_master clips)."""
    m, s = textured()
    return m, np.clip(s * 1.6 + 40, 0, 255).astype(np.uint8)


def gather(params=Params(max_window=0), deadline=0.05):
    return Gatherer(params, ControlSettings(), deadline)


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


@pytest.mark.parametrize("clips", [True, False])
def test_make_frame_says_whether_it_clipped_the_master_as_master_clipped_does(clips):
    """The capture's clip_fallback asks make_frame (one photometric map per frame), not master_clipped (two)."""
    from vergence.stages.frames import make_frame

    m, s = clipping_pair() if clips else textured()
    params = Params(photometric="affine")
    y = m.shape[0] // 2
    got: list[bool] = []
    make_frame(m, s, rig="r", frame=1, pan_rad=0.0, focal_px=100.0, params=params, plan=[["w", 0, 10]],
               clipped=got)
    assert got == [retina.master_clipped(m, s, y, params.window, params)] == [clips]


def test_a_frames_digests_are_of_the_base_windows_rows_whatever_window_it_grew_to():
    """The digests the frozen-camera check compares (vergence.head.frozen) are over the base window's band: a window
    that grows while the fovea is undecided (15 -> 31 -> 47) reads more rows, but a repeated image keeps its digest, so
    the run of repeats it counts goes on (2026-12-05: through a ROS 2 camera frozen at a fovea on an edge, each growth
    restarted it, named after 0.61-0.66 s; now 0.34). Rows outside that band change nothing; one inside does."""
    from vergence.stages.frames import make_frame

    m, s = textured()
    params = Params()
    frames = [make_frame(m, s, rig="r", frame=1, pan_rad=0.0, focal_px=500.0, params=params, plan=[], window=w)
              for w in (params.window, 31, 47)]
    assert len({(f.master_digest, f.slave_digest) for f in frames}) == 1 and frames[0].slave_digest not in (0, None)
    y, reach = m.shape[0] // 2, params.window // 2 + params.vsearch + 1
    far, near = s.copy(), s.copy()
    far[y + reach + 2] ^= 1
    near[y + reach] ^= 1
    digests = [make_frame(m, img, rig="r", frame=1, pan_rad=0.0, focal_px=500.0, params=params, plan=[],
                          window=47).slave_digest for img in (far, near)]
    assert digests[0] == frames[0].slave_digest and digests[1] != frames[0].slave_digest
