"""vergence.head.search (issue #35, item 3): a textured fovea with no confident match for LOST_S searches (back to
the last converged pan, then a sweep inside the limits in steps of part of the band) until a candidate appears; black
or flat frames hold. First the sweep on hand-made decisions, then `vergence sim`'s loop lost at either limit or
350-450 px off the target, on draws of their own (seeds 501-516: scenes, textures, depths and starts none of the other
tests use)."""

from __future__ import annotations

import math

import pytest

import background
import sweeps
from vergence.choices import Fault
from vergence.head.control import ControlSettings, Controller
from vergence.head.doubt import Doubt
from vergence.head.scenery import Verdict
from vergence.head.search import DWELL_S, HELD_S, LOST_S, REST_S, STEP_OF_BAND, Search

DEG = math.pi / 180
DT = 1 / 60
LO, HI = -45 * DEG, 45 * DEG
F, W = 500.0, 640


def run(s: Search, pan: float, n: int, t0: float = 0.0, confident=False, textured=True, offset=0.0):
    """n decisions 60 Hz apart, the motor at each goal by the next exposure: (t, goal) of each (goal None: none)."""
    out = []
    for k in range(n):
        t = t0 + k * DT
        goal = s.observe(t, pan, confident, textured, offset, F, W, LO, HI)
        out.append((t, goal))
        if goal is not None:
            pan = goal
    return out


def stops(goals) -> list[float]:
    """The distinct goals in order, degrees."""
    seen = []
    for _, g in goals:
        if g is not None and (not seen or abs(seen[-1] - g / DEG) > 1e-9):
            seen.append(g / DEG)
    return seen


def test_lost_at_a_limit_sweeps_inward_to_the_other_limit_rests_where_it_began_and_starts_over():
    """A sweep that found nothing goes back where it began and waits REST_S there, then sweeps again, then rests twice
    as long (before 2026-12-05 it swept on for ever: a look_at on a point the slave cannot see, occluded by a nearer
    object, swung a ROS 2 head between +-41 deg for as long as it lasted)."""
    s = Search()
    out = run(s, 45 * DEG, 900)
    first = next(t for t, g in out if g is not None)
    assert first == pytest.approx(LOST_S, abs=DT)  # lost after LOST_S of textured, unconfident exposures
    step = STEP_OF_BAND * math.degrees(math.atan((W / 2 - 16) / F))  # 18.78 deg: 0.6 of the band's 31.3
    assert step == pytest.approx(18.78, abs=0.01)
    got = stops(out)
    assert got[:5] == pytest.approx([45 - step, 45 - 2 * step, 45 - 3 * step, 45 - 4 * step, -45], abs=1e-6)
    assert got[5:12] == pytest.approx([45, 45 - step, 45 - 2 * step, 45 - 3 * step, 45 - 4 * step, -45, 45], abs=1e-6)
    assert all(-45 <= g <= 45 for g in got) and s.searching and s.searches == 1
    pairs = list(zip(out, out[1:]))
    back = [t for (_, g0), (t, g) in pairs if g == 45 * DEG and g0 != 45 * DEG]
    again = [t for (_, g0), (t, g) in pairs if g0 == 45 * DEG and g == pytest.approx((45 - step) * DEG)]
    assert len(back) == 3 and len(again) == 2  # 15 s: three sweeps, rests of 2 and 4 s between, the third one's on
    assert [a - b for a, b in zip(again, back)] == pytest.approx([REST_S, 2 * REST_S], abs=1.5 * DT)


def test_the_status_counts_the_sweeps_that_found_nothing_until_a_candidate():
    """sweeps_empty: 0 while the first sweep runs, 1 once it ended with nothing (the reducer's status; `vergence
    monitor` then asks whether the slave can see the point), 2 after the second; a confident decision ends the
    search and the count."""
    s = Search()
    assert s.status() == {"searching": False, "searches": 0, "found": 0, "sweeps_empty": 0, "no_texture": False}
    out = run(s, 45 * DEG, 60)
    assert s.status()["searching"] and s.status()["sweeps_empty"] == 0
    pan = next(g for _, g in reversed(out) if g is not None)
    counts = []
    t = out[-1][0]
    for _ in range(900):
        t += DT
        g = s.observe(t, pan, False, True, 0.0, F, W, LO, HI)
        pan = g if g is not None else pan
        counts.append(s.status()["sweeps_empty"])
    assert counts[0] == 0 and sorted(set(counts)) == [0, 1, 2, 3]  # three sweeps in those 15 s, as above
    assert all(b - a in (0, 1) for a, b in zip(counts, counts[1:]))
    s.observe(t + DT, pan, True, True, 0.3, F, W, LO, HI)
    assert s.status() == {"searching": False, "searches": 1, "found": 1, "sweeps_empty": 0, "no_texture": False}


def test_first_back_to_the_last_converged_pan_then_about_it_alternating_from_where_it_was():
    s = Search()
    run(s, 5 * DEG, 3, confident=True, offset=0.4)  # converged at 5 deg
    got = stops(run(s, 30 * DEG, 600, t0=1.0))
    step = 18.78
    # the side it was lost on first; 5 + 2 x 18.78 = 42.56 is within a quarter step of the limit: no stop at 45
    assert got[:7] == pytest.approx([5.0, 5 + step, 5 - step, 5 + 2 * step, 5 - 2 * step, -45.0, 5.0], abs=0.01)


@pytest.mark.parametrize("start,look", [(10.9, 8.0), (8.2, 13.8)])
@pytest.mark.parametrize("followed", [False, True])
def test_a_search_whose_image_was_never_seen_to_follow_looks_within_the_leash_first(start, look, followed):
    """A search given a leash (8-13.8 deg: the pans it may go to until its image has been seen to follow the motor)
    looks first to the leash's end toward the range's middle (or the other end where that one is under 0.6 deg
    away: no turn to read): a camera reversed from the start is named over that move by its background, within the
    leash (before, a search's first step of 18.8 deg: Venus, seed 7205, 11.6 deg from its start before it was named,
    the issue's bound 3). After DWELL_S there the sweep, or at once when told that the image followed (no leash)."""
    s = Search()
    leash, pan, out = (8.0 * DEG, 13.8 * DEG), start * DEG, []
    for k in range(90):
        t = k * DT
        told = None if followed and abs(pan - look * DEG) < 1e-9 else leash  # (the background: it turned)
        g = s.observe(t, pan, False, True, 0.0, F, W, LO, HI, told)
        out.append((t, g))
        pan = g if g is not None else pan
    got = stops(out)
    assert got[0] == pytest.approx(look) and got[1] == pytest.approx(start - 18.78, abs=0.01)
    t_look = next(t for t, g in out if g is not None)
    t_sweep = next(t for t, g in out if g is not None and abs(g / DEG - look) > 1e-6)
    assert t_look == pytest.approx(LOST_S, abs=DT)
    assert t_sweep - t_look == pytest.approx(DT if followed else DT + DWELL_S, abs=DT / 2)


@pytest.mark.parametrize("trusted", [False, True])
@pytest.mark.parametrize("turned", [False, True])
def test_the_controllers_search_looks_within_leash_deg_until_the_background_turned_with_the_motor(trusted, turned):
    """Lost, the Controller's search first looks LEASH_DEG (1.5 deg) toward the range's middle, whether or not the
    image was ever seen to follow (a camera that froze or slipped since it did: a slip at a point that stopped
    deciding, Tsukuba seed 7103 with the slave's gain 1.3, ran a sweep's 18.8 deg step before it was named, now 1.4
    deg past), then sweeps as soon as a background verdict says the image turned with the motor, or after DWELL_S."""
    c = Controller(ControlSettings(mode="p"))
    pan = 5 * DEG
    if trusted:  # a correction whose image followed: the offset shrinks by the motor's moves (not converged: 4 px)
        for k, (p, off) in enumerate([(5, 3.5), (6, 2.5), (7, 1.5), (8, 0.5)]):
            c.target(p * DEG, F * math.tan(off * DEG), F, True, t_s=k * DT, width_px=W, fovea=(320, 240))
        pan = 8 * DEG
    assert c.doubt.trusted == trusted
    goals, t0 = [], 4 * DT
    for k in range(60):
        moved = turned and goals and any(g is not None for _, g in goals)
        g = c.target(pan, 0.0, F, False, t_s=t0 + k * DT, width_px=W, fovea=(320, 240),
                     background=Verdict(1.0) if moved else None)
        goals.append((t0 + k * DT, g))
        pan = g if g is not None else pan
    got = stops(goals)
    start = 8.0 if trusted else 5.0
    assert got[0] == pytest.approx(start - 1.5) and abs(got[1] - got[0]) >= 9.9  # the look, then a sweep's step
    t_look = next(t for t, g in goals if g is not None)
    t_sweep = next(t for t, g in goals if g is not None and abs(g / DEG - got[0]) > 1e-6)
    assert t_sweep - t_look == pytest.approx(DT if turned else DT + DWELL_S, abs=DT / 2) and c.doubt.fault is None


@pytest.mark.parametrize("latency", [0.0, 0.066])
def test_a_camera_reversed_from_a_start_it_never_decides_is_named_within_the_leash(latency):
    """Venus, seed 7205 (a draw of the outside checks, docs/FAULTS.md): the slave on the truth at the image's centre,
    the fovea at (312, 73), then (326, 375) from 0.3 s, the camera reversed from the start. The start never decides
    and the loop searches: the reversal named over the search's look, at most 2.9 deg from the start (before: after
    its first step, 8.8 and 11.6 deg away), then only the move back and probes."""
    rig, steps = sweeps.middlebury_lie("venus", (312, 73), "reverse", {18: (326, 375)}, latency, 7205, 150)
    start = math.degrees(rig.start_pan_rad)
    assert max(abs(s.pan_deg - start) for s in steps) <= 3.0
    first = next(s for s in steps if s.fault)
    assert first.fault == "reversed" and first.t_s <= 1.0
    assert all(abs(s.target_deg - start) <= 0.6 for s in steps if s.frame > first.frame and s.target_deg is not None)


def test_converged_and_held_with_sparse_confident_decisions_waits_held_s_not_lost_s():
    s = Search()
    run(s, 2 * DEG, 1, confident=True, offset=0.3)  # converged at 2 deg
    out = run(s, 2 * DEG, 240, t0=DT)  # then 4 s of abstentions, still at 2 deg
    first = next(t for t, g in out if g is not None)
    assert first == pytest.approx(DT + HELD_S, abs=DT) and HELD_S > LOST_S
    moved = Search()
    run(moved, 2 * DEG, 1, confident=True, offset=0.3)
    first = next(t for t, g in run(moved, 10 * DEG, 60, t0=DT) if g is not None)  # elsewhere than where it converged
    assert first == pytest.approx(DT + LOST_S, abs=DT)


def test_at_the_pan_the_last_confident_decision_put_the_target_waits_held_s():
    """A weakly textured point decided once, 8 px off, then never again: the slave moved there and waits HELD_S as at a
    converged one (it searched after LOST_S: a fixate's new point on Venus, seeds 7500-7509, then found a look-alike a
    sweep's step away and stayed there, 30-195 px off the truth). Where the motor did not get there, LOST_S."""
    there = math.atan(8 / F)
    for at, wait in ((there, HELD_S), (0.0, LOST_S)):
        s = Search()
        run(s, 0.0, 1, confident=True, offset=8.0)
        first = next(t for t, g in run(s, at, 240, t0=DT) if g is not None)
        assert first == pytest.approx(DT + wait, abs=DT)
    s = Search()  # the Controller's angle, off the principal point: the pan it names
    s.observe(0.0, 0.0, True, True, 8.0, F, W, LO, HI, None, 2 * DEG)
    assert next(t for t, g in run(s, 2 * DEG, 240, t0=DT) if g is not None) == pytest.approx(DT + HELD_S, abs=DT)


def test_black_frames_hold_and_a_confident_decision_ends_the_search():
    s = Search()
    assert all(g is None for _, g in run(s, 10 * DEG, 120, textured=False))  # 2 s of black: no search
    assert s.status()["no_texture"] is True  # ... and named (the status says it: the monitor, /diagnostics)
    out = run(s, 10 * DEG, 60, t0=3.0)
    assert s.status()["no_texture"] is False  # texture again
    assert s.searching and any(g is not None for _, g in out)
    assert run(s, 0.0, 1, t0=5.0, confident=True, offset=-40.0) == [(5.0, None)]
    assert not s.searching and s.found == 1 and s.status() == {"searching": False, "searches": 1, "found": 1,
                                                        "sweeps_empty": 0, "no_texture": False}


def test_the_controller_searches_only_where_the_image_can_follow_and_holds_in_a_fault():
    """Lost, it searches; a motor that never moves while it searches is stalled (STALL_S after the search's first
    command) and holds; without the doubt (a still pair: the image cannot follow) it never searches."""
    c = Controller(ControlSettings(mode="p"))
    goals = [c.target(0.2, 0.0, F, False, t_s=k * DT, width_px=W) for k in range(40)]
    assert goals[-1] is not None and c.search.searching  # lost, searching
    goals = [c.target(0.2, 0.0, F, False, t_s=k * DT, width_px=W) for k in range(40, 60)]
    assert c.doubt.fault is Fault.STALLED and goals[-1] is None and not c.search.searching
    still = Controller(ControlSettings(mode="p"))
    assert all(still.target(0.2, 0.0, F, False, t_s=k * DT, width_px=W, doubt=False) is None for k in range(60))


# at a limit (either) or 350-450 px off (either side), depths 0.6-1.5 m, 0 and 66 ms of camera latency
DRAWS = [(501 + i, i % 4, (0.6, 0.9, 1.2, 1.5)[i // 4 % 4], 0.066 if i % 2 else 0.0) for i in range(16)]


for _d in DRAWS:
    background.ahead(sweeps.lost, *_d, tests=("test_a_lost_slave_is_found_within_3_s_in_16_draws",
                                              "test_a_lost_slave_finds_the_target_within_3_s_inside_the_limits"))


@pytest.mark.parametrize("seed,kind,z,latency", DRAWS[:2])
def test_a_lost_slave_finds_the_target_within_3_s_inside_the_limits(seed, kind, z, latency):
    found, widest, faults = background.get(sweeps.lost, seed, kind, z, latency)
    assert found is not None and found <= 3.0 and widest <= 45.0 + 1e-9 and not faults, (found, widest, faults)


@pytest.mark.slow
def test_a_lost_slave_is_found_within_3_s_in_16_draws():
    """The issue's 95 %: all 16 here (40 of 40 measured at 60 Hz and at 30 Hz with 66 ms, and 40 of 40 on a sine
    with 100 ms: docs/FAULTS.md). The draws are done ahead in the background (tests/background.py)."""
    got = [(d, background.get(sweeps.lost, *d)) for d in DRAWS]
    bad = [(d, r) for d, r in got if not (r[0] is not None and r[0] <= 3.0 and r[1] <= 45.0 + 1e-9 and not r[2])]
    print("\nfound after (s):", sorted(round(r[0], 2) for _, r in got if r[0] is not None))
    assert bad == []


def test_a_fault_at_a_searchs_candidate_never_seen_to_follow_holds_where_the_search_began():
    """The image never followed at the start (2 deg: the anchor, untrusted); a search took a candidate at 12 deg,
    and the background then turns against the motor: the reversal is held at 2 deg, where the search began (it was
    held at the candidate, 10 deg off: Cones, seed 7203, a camera reversed from the start, docs/FAULTS.md); once a
    candidate's image has followed, a fault there holds there."""
    d = Doubt()
    d.observe(0.0, math.radians(2.0), None, 1, 7, (320, 240))
    d.relocate(math.radians(12.0))
    for k in range(1, 4):
        d.observe(k / 60, math.radians(12.0 + 0.7 * k), math.radians(0.5), 1 + k, 7 + k, (320, 240),
                  background=Verdict(-1.0))
    assert d.fault is Fault.REVERSED and math.degrees(d.anchor) == pytest.approx(2.0)
    t = Doubt()
    t.observe(0.0, math.radians(2.0), None, 1, 7, (320, 240))
    t.relocate(math.radians(12.0), trusted=True)  # (a fault cleared there: its image followed)
    for k in range(1, 4):
        t.observe(k / 60, math.radians(12.0 + 0.7 * k), math.radians(0.5), 1 + k, 7 + k, (320, 240),
                  background=Verdict(-1.0))
    assert t.fault is Fault.REVERSED and math.degrees(t.anchor) == pytest.approx(12.0)
