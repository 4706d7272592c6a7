"""vergence.stages.gather, the reducer side: reduce equals match; the Gatherer completes, drops, supersedes and
refuses."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from samples import SHIFT, frame_of, textured

from vergence import match
from vergence.head.control import Controller, ControlSettings
from vergence.stages.frames import make_frame, plan_shards
from vergence.stages.gather import Gatherer, reduce
from vergence.wire.messages import Frame
from vergence.network.params import Params
from vergence.network.retina import master_clipped
from vergence.stages.shards import compute_correlation


def clipping_pair():
    """A textured pair whose slave is at gain 1.6, +40: a quarter of its band saturates (clip_master clips)."""
    m, s = textured()
    return m, np.clip(s * 1.6 + 40, 0, 255).astype(np.uint8)


def gather(params=Params(max_window=0), deadline=0.05):
    return Gatherer(params, ControlSettings(), deadline)


@pytest.mark.parametrize("params", [Params(max_window=0), Params.paper()], ids=["default", "paper"])
def test_reduce_equals_match(params):
    m, s = textured()
    # f = 500 px: the correction (under 2.5 degrees) is within the leash of a head not yet seen to follow
    f = frame_of(m, s, params, pan=0.1, focal=500.0)
    scores = np.atleast_2d(compute_correlation(f, "a").array())
    prof, cmd = reduce(f, scores, params, Controller())
    d = match(m, s, params=params).decision
    assert (prof.k, prof.k_sub, prof.v_shift, prof.confident) == (d.k, d.k_sub, d.v, d.confident)
    assert prof.k - prof.k_centre == SHIFT and prof.workers == ["a"]
    assert cmd is not None and cmd.frame == 1
    assert cmd.pan_rad == pytest.approx(0.1 + math.atan(d.offset_px / 500.0))
    assert cmd.correction_rad == pytest.approx(math.atan(d.offset_px / 500.0))
    assert cmd.direction == 1 and cmd.magnitude_px == pytest.approx(abs(d.offset_px))


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
    scores = np.atleast_2d(compute_correlation(f, "a").array())
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
    prof, cmd = reduce(f, np.atleast_2d(compute_correlation(f, "a").array()), Params(), Controller())
    assert not prof.confident and cmd is None


def test_gatherer_complete_in_any_order():
    m, s = textured()
    f = frame_of(m, s, Params(), workers=["a", "b"])
    pa, pb = compute_correlation(f, "a"), compute_correlation(f, "b")
    g = gather()
    assert g.add_correlation(pb, now=0.0) == []
    assert g.add_frame(f, now=0.001) == []
    (r,) = g.add_correlation(pa, now=0.002)
    assert r.profile.frame == 1 and r.command is not None and r.profile.workers == ["a", "b"]
    assert g.counters["complete"] == 1 and not g.pending
    assert g.add_correlation(pa, now=0.003) == [] and g.counters["late"] == 1


def test_gatherer_drops_at_deadline_and_never_reduces_incomplete():
    m, s = textured()
    f = frame_of(m, s, Params(), workers=["a", "b"])
    g = gather(deadline=0.05)
    g.add_frame(f, now=0.0)
    g.add_correlation(compute_correlation(f, "a"), now=0.01)
    assert g.next_deadline() == pytest.approx(0.05)
    g.expire(now=0.06)
    assert g.counters["dropped"] == 1 and not g.pending
    assert g.add_correlation(compute_correlation(f, "b"), now=0.07) == []  # too late: nothing published
    assert g.counters["complete"] == 0 and g.counters["late"] == 1


def test_gatherer_supersedes_older_frames_and_rejects_foreign_correlations():
    m, s = textured()
    f1 = frame_of(m, s, Params(), workers=["a", "b"], fid=1)
    f2 = frame_of(m, s, Params(), workers=["a"], fid=2)  # a worker left: the next frame has a new plan
    g = gather()
    g.add_frame(f1, now=0.0)
    g.add_correlation(compute_correlation(f1, "a"), now=0.0)
    g.add_frame(f2, now=0.001)
    wrong = compute_correlation(f1, "b")
    wrong.frame = 2  # b's range of frame 1 does not fit frame 2's plan
    assert g.add_correlation(wrong, now=0.002) == [] and g.counters["unexpected"] == 1
    (r,) = g.add_correlation(compute_correlation(f2, "a"), now=0.003)
    assert r.frame.frame == 2 and g.counters["superseded"] == 1 and not g.pending


def test_gatherer_bad_shape_drops_frame():
    m, s = textured()
    f = frame_of(m, s, Params(), workers=["a"])
    p = compute_correlation(f, "a")
    p.rows, p.scores = 1, p.array()[:1].tobytes()  # fits its own sizes, not the frame's 5 rows
    g = gather()
    g.add_frame(f, now=0.0)
    assert g.add_correlation(p, now=0.0) == []
    assert g.counters["bad"] == 1 and g.counters["dropped"] == 1 and g.counters["complete"] == 0


def test_gatherer_restart_and_no_plan():
    m, s = textured()
    g = gather()
    old = frame_of(m, s, Params(), workers=["a"], fid=5)
    g.add_frame(old, now=0.0)
    assert len(g.add_correlation(compute_correlation(old, "a"), now=0.0)) == 1
    stale = compute_correlation(old, "a")
    stale.frame, stale.t_capture_ns = 3, old.t_capture_ns - 1  # reordered, older: late
    assert g.add_correlation(stale, now=0.0) == [] and g.counters["late"] == 1
    f = frame_of(m, s, Params(), workers=["a"], fid=1)  # a new capture: ids from 1 again, later times
    f.t_capture_ns = old.t_capture_ns + 1
    g.add_frame(f, now=0.0)
    assert g.counters["restarts"] == 1
    assert len(g.add_correlation(compute_correlation(f, "a"), now=0.0)) == 1
    f.plan = []
    f.frame = 2
    g.add_frame(f, now=0.0)
    assert g.counters["no_plan"] == 1


def test_a_frame_prepared_when_it_arrives_decides_as_one_prepared_at_its_decision():
    """gather.prepare: the Frame's own part of the decision (its params, the fovea's planes and support weights, the
    master rows' planes), made by Gatherer.add_frame before the correlations come. Decisions equal with and without
    it, confident or not (a clipping pair, a shifted one, a flat one), and the Gatherer awaits correlations only
    while a Frame is in without all of them."""
    from vergence.network import retina
    from vergence.stages.gather import decide_frame, prepare

    m, s = textured()
    for mm, ss in [(m, s), clipping_pair(), (m, np.roll(s, 7, axis=1)), (np.full_like(m, 90), np.full_like(s, 90))]:
        for params in (Params(max_window=0), Params.paper()):
            f = Frame.from_bytes(frame_of(mm, ss, params).to_bytes())
            scores = np.atleast_2d(compute_correlation(f, "a").array())
            prep = prepare(f, params)
            assert decide_frame(f, scores, params, prep) == decide_frame(f, scores, params)
            if params.lr_check:
                assert np.array_equal(prep.master, retina.planes(f.master_band_strip()))
    f = frame_of(m, s, Params(), workers=["a", "b"])
    g = gather()
    assert not g.awaiting()
    g.add_correlation(compute_correlation(f, "a"), now=0.0)
    assert not g.awaiting()  # correlations without their Frame: the Frame is what comes next
    g.add_frame(f, now=0.001)
    assert g.awaiting() and g.pending[1].prep is not None
    (r,) = g.add_correlation(compute_correlation(f, "b"), now=0.002)
    assert not g.awaiting() and r.decision.confident


@pytest.mark.parametrize("follows,guessed", [(True, False), (False, False), (False, True)])
def test_a_frame_s_background_is_read_when_it_arrives(follows, guessed):
    """The reducer asks the controller for each Frame's background verdict (vergence.head.scenery) as the Frame
    arrives, from its slave band and its pan at the slave's exposure: the motor turning 0.4 deg a frame, a slave
    whose image turns with it reads 1 from the first frame whose pan is 0.6 deg from an earlier one's, one whose image
    stays (a slipping coupling) 0: a late verdict (a late image's too) until the pans 0.1 s before are known; the
    commands carry what the doubt made of it (the first named the fault). Frames whose pans the capture extrapolated
    past the motor's newest state (pan_guessed) read none. (The images are rendered as turns of a camera.)"""
    rng = np.random.default_rng(3)
    scene = cv2.GaussianBlur(rng.integers(0, 256, (120, 1000), np.uint8), (5, 5), 1.5)  # a column a direction

    def view(turn: float) -> np.ndarray:  # a camera turned `turn` rad (its columns' directions, f px a radian)
        cols = (620 + 500.0 * (np.arctan((np.arange(640) - 320) / 500.0) + turn)).astype(np.float32)
        return cv2.remap(scene, np.tile(cols, (120, 1)), np.tile(np.arange(120, dtype=np.float32)[:, None], (1, 640)),
                         cv2.INTER_LINEAR)

    master = view(0.0)
    focal, t0 = 500.0, 1_700_000_000_000_000_000
    g = Gatherer(Params(max_window=0), ControlSettings(), 0.05, wall_ns=lambda: t0)
    verdicts = []
    for i in range(12):
        pan = math.radians(0.4 * i)
        slave = view(pan if follows else 0.0)
        k = master.shape[1] - Params().window + 1
        f = make_frame(master, slave, rig="r", frame=i + 1, pan_rad=pan, focal_px=focal, params=Params(max_window=0),
                       plan=plan_shards(["a"], k), t_capture_ns=t0 + i * 16_666_667)
        f.pan_guessed = guessed
        g.add_frame(f, now=i * 0.0167)
        verdicts.append(g.pending[i + 1].scene)
        g.add_correlation(compute_correlation(f, "a"), now=i * 0.0167 + 0.001)[0].command
    first = 12 if guessed else 2
    known = 12 if guessed else 2 if follows else 7
    assert all(v is None for v in verdicts[:first]) and all(v.late for v in verdicts[first:known])
    assert all(v.r == pytest.approx(1.0 if follows else 0.0, abs=0.06) and not v.late for v in verdicts[known:])
    assert (g.controller.doubt.fault is None) == follows  # (guessed: the same bytes still say a frozen camera)
