"""vergence.head.doubt (issue #35): the loop checks every decision against the motor's own motion, names what it
finds (a frozen or slipping slave camera, a reversed motor, a stalled motor, a frozen master), goes back to the last
pan at which the image followed, holds with probing moves only, and resumes by itself; a moving target, a step and a
new fovea are not faults. First the check on hand-made decisions, then `vergence sim`'s loop with the simulator's
lies (vergence.sim.faults) on a Middlebury scene and on the generated moving target."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest

import background
import sweeps
from middlebury import ROOT as MIDDLEBURY, needs_data
from vergence.head.control import ControlSettings
from vergence.head.doubt import ADVICE, LEASH_DEG, PROBE_DEG, SUSPECT_S, UNTRUSTED_DEG, Doubt, Fault
from vergence.head.lag import MAX_LAG_S, Lag
from vergence.head.scenery import Verdict
from vergence.head.timing import CameraTiming
from vergence.sim.faults import Faults
from vergence.sim.fixation import truth_at
from vergence.sim.loop import closed_loop
from vergence.sim.moving import MovingRig
from vergence.spec import SpecError, parse
from vergence.sim.faults import FAULT_KEYS

DEG = math.pi / 180
DT = 1 / 60


def feed(d: Doubt, frames, t0: float = 0.0):
    """(pan_deg, offset angle_deg, slave digest) per frame, 60 Hz: the faults after each."""
    out = []
    for k, (pan, a, slave) in enumerate(frames):
        out.append(d.observe(t0 + k * DT, pan * DEG, None if a is None else a * DEG, slave, None, (320, 240)))
    return out


# -- the check on hand-made decisions -------------------------------------------------------------------------------

def test_an_image_that_follows_a_correction_verifies_the_pan_and_trusts_the_head():
    d = Doubt()
    # the target 3 degrees right; the motor moves 1, then 2, and the offset shrinks by as much
    assert feed(d, [(0, 3, 1), (1, 2, 2), (2, 1, 3), (3, 0, 4)]) == [None] * 4
    assert d.trusted and d.anchor == pytest.approx(3 * DEG) and d.fault is None


def test_an_offset_that_stays_while_the_motor_corrects_it_is_a_frozen_camera_or_a_slip():
    d = Doubt()
    faults = feed(d, [(0, 3, 1), (0.3, 3, 2), (1.2, 3, 3), (2.0, 3, 4)])  # fresh bytes each frame: a slip, with noise
    assert faults[:2] == [None, None] and faults[-1] is Fault.SLAVE_FROZEN
    assert d.anchor == pytest.approx(0.0)  # the last pan at which the image followed: the start
    assert d.gate(2.0 * DEG, 5 * DEG, 0.1) == pytest.approx(0.0)  # back there, whatever the controller wants
    assert d.gate(0.0, 5 * DEG, 0.11) is None  # then nothing but probes
    assert "slipping coupling" in d.note and "check the camera" in d.note
    # a camera later than any lag the check fits (vergence.head.lag) looks the same: the note names that too
    assert f"more than {MAX_LAG_S:g} s later than their stamps" in d.note


@pytest.mark.parametrize("background,names", [(None, True), (1.0, False), (0.98, False), (0.0, True), (-1.0, True)])
def test_a_fovea_pair_that_did_not_follow_where_the_background_turned_with_the_motor_names_nothing(background, names):
    """The offset that stays while the motor corrects it, above, with the background read on each frame: where it
    turned with the motor (r 0.5-2.2, not late) the camera follows and the fovea misread (a doubt: held, probed, no
    fault; Cones seed 7205 at 66 ms, a clean run of the outside draws: a fixate's first decision 10 px short of the
    truth, its image then moving 0.19 x the motor by the fovea while the background turned 1.03 and 0.99 x, was named
    slave_frozen and cleared 0.2 s later); with no verdict, or one that did not move or turned against, as before."""
    d = Doubt()
    for k, (pan, a) in enumerate([(0, 3), (0.3, 3), (1.2, 3), (2.0, 3)]):
        d.observe(k * DT, pan * DEG, a * DEG, k + 1, None, (320, 240),
                  background=None if background is None or k == 0 else Verdict(background))
    assert (d.fault is not None) == names and d.faults == int(names)
    if not names:  # held where it is (no further from the anchor than 2 deg), to probe
        assert d.fails == ["doubt", "doubt"] and d.gate(2.0 * DEG, 5 * DEG, 0.1) == pytest.approx(2.0 * DEG)


def test_a_byte_identical_slave_image_after_the_motor_moved_is_a_frozen_camera_at_once():
    d = Doubt()
    assert feed(d, [(0, 0.5, 7), (0.3, 0.5, 7), (0.6, 0.5, 7)]) == [None, None, Fault.SLAVE_FROZEN]
    still = Doubt()  # the same bytes while the motor stands: a clean still scene, nothing wrong
    assert feed(still, [(0, 0, 7), (0, 0, 7), (0, 0, 7)]) == [None] * 3


def test_an_image_moving_against_the_motor_is_a_reversed_motor():
    d = Doubt()
    faults = feed(d, [(0, 3, 1), (1, 4, 2), (2, 5, 3)])  # the encoder says right, the image goes left
    assert faults[-1] is Fault.REVERSED and "flip [actuator.motor] direction" in ADVICE[Fault.REVERSED]


@pytest.mark.parametrize("trend", [25.0, 0.0])
def test_a_pair_short_of_the_motor_only_at_a_lagging_learnt_rate_is_a_doubt_that_holds_and_names_nothing(trend):
    d = Doubt()
    feed(d, [(0, 3, 1), (1, 2, 2), (2, 1, 3), (3, 0, 4)])  # trusted at 3 deg
    d.rate, d.trend = 0.0, trend * DEG  # the learnt rate lags a target that turned; its last pair showed `trend`
    step = 25 / 60  # the target moves 25 deg/s; the motor 0.8 deg a frame (48 deg/s), the image follows both
    faults = feed(d, [(3 + 0.8 * k, (step - 0.8) * k, 10 + k) for k in (1, 2)], t0=4 * DT)
    if trend:  # at the target's latest rate the image followed: a doubt, held, nothing named
        assert faults == [None, None] and d.fails == ["doubt", "doubt"]
        assert d.gate(4.6 * DEG, 6 * DEG, 6 * DT) == pytest.approx((3 + LEASH_DEG) * DEG)  # no further out
    else:  # no rate says the target moved: two pairs short of the motor name a frozen camera
        assert faults == [None, Fault.SLAVE_FROZEN]


@pytest.mark.parametrize("follows", [False, True])
def test_one_pair_that_did_not_follow_holds_the_motor_then_a_probe_back_confirms_or_clears_it(follows):
    d = Doubt()
    feed(d, [(0, 3, 1), (1, 2, 2), (2, 1, 3), (3, 0, 4)])  # trusted, the anchor at 3 deg
    assert feed(d, [(4.0, 0.0, 5)], t0=4 * DT) == [None] and d.fails == ["frozen"]  # 1 deg the image did not show
    t = 5 * DT
    assert d.gate(4 * DEG, 6 * DEG, t) == pytest.approx(4 * DEG)  # held: no further from the anchor
    assert d.gate(4 * DEG, 6 * DEG, t + 3 * DT) == pytest.approx(4 * DEG)  # ... for SUSPECT_S
    probe = d.gate(4 * DEG, 6 * DEG, t + SUSPECT_S + 0.01)
    assert probe == pytest.approx((4 - PROBE_DEG) * DEG)  # then a probe back toward the anchor
    assert d.gate(4 * DEG, 6 * DEG, t + SUSPECT_S + 0.03) == pytest.approx(probe)  # until its image is seen
    # the probe's image: moved by the probe (the target is at 4 deg) or not at all (a slipping coupling)
    fault = feed(d, [(4 - PROBE_DEG, PROBE_DEG if follows else 0.0, 20)], t0=t + 8 * DT)[0]
    if follows:
        assert fault is None and d.trusted and not d.fails and d.anchor == pytest.approx((4 - PROBE_DEG) * DEG)
    else:
        assert fault is Fault.SLAVE_FROZEN and d.anchor == pytest.approx(3 * DEG)


@pytest.mark.parametrize("hz,latency,seed", [(2.0, 0.1, 5), (2.0, 0.1, 6), (1.8, 0.09, 7)])
def test_the_leash_lets_a_fast_target_be_followed_whose_image_is_old(hz, latency, seed):
    """A sine of 0.8 +- 0.3 m at 1.8-2 Hz, 60 Hz, the image 90-100 ms old: its target moves up to 2.6 deg between
    the newest image's exposure and the command, and turns within that. The leash widens by that motion (at the
    fastest rate learnt over SPEED_S), so the loop follows: no fault, RMS over 1-5 s under 1 px (0.36-0.48 per
    second; before, the learnt rate moved the leash past each turn and held the loop 3.5-3.8 px off for good)."""
    rig = MovingRig.from_options(motion=f"sine:z=0.8,amp=0.3,hz={hz:g}", focal="500", seed=str(seed))
    steps = list(closed_loop(rig, 300, None, ControlSettings(), None, 60.0, timing=CameraTiming(latency), seed=seed))
    late = [s.error_px for s in steps if s.t_s >= 1.0]
    assert not [s for s in steps if s.fault]
    assert math.sqrt(sum(e * e for e in late) / len(late)) < 1.0


@pytest.mark.parametrize("age,fast_deg_s", [(0.1, 25.0), (0.5, 25.0), (0.1, 0.0)])
def test_the_leash_widens_by_the_targets_motion_since_its_newest_image_and_no_more_than_age_s_of_it(age, fast_deg_s):
    """A trusted head, the last consistent decision's target at 0 moving at the learnt 5 deg/s, the fastest rate learnt
    over SPEED_S fast_deg_s, a goal 30 deg away asked `age` after the newest image: the goal let out is LEASH_DEG +
    5 deg/s x LEAD_S + fast_deg_s x min(age, AGE_S) past the centre (a frame 0.5 s old widens it by AGE_S of it)."""
    from vergence.head.doubt import AGE_S, LEAD_S
    from vergence.head.follows import Seen

    d = Doubt()
    d.trusted, d.anchor, d.t_last = True, 0.0, 10.0
    d.centre, d.rate = Seen(10.0, 0.0, 0.0), math.radians(5.0)
    d.speeds = [(9.5, math.radians(fast_deg_s))]
    out = d.gate(0.0, math.radians(30.0), 10.0 + age)
    centre = 5.0 * age
    assert math.degrees(out) == pytest.approx(centre + LEASH_DEG + 5.0 * LEAD_S + fast_deg_s * min(age, AGE_S))


def test_the_leash_over_a_long_gap_is_a_cone_not_the_learnt_rate_run_on():
    """A trusted head, the last consistent decision's target at 0 moving at the learnt -4.2 deg/s, the first decision
    after 2 s of black frames asking 0.4 deg: let out as asked (the centre run on at the learnt rate for the 2 s put
    the leash 8.4 deg away, and the goal sent was 6.5 deg astray: `bench faults`' black rows once the head is
    trusted); a goal 30 deg away stops at the rate over REF_MAX_S, then LEASH_DEG and the rate over the rest."""
    from vergence.head.doubt import LEAD_S, REF_MAX_S
    from vergence.head.follows import Seen

    d = Doubt()
    d.trusted, d.anchor, d.t_last = True, 0.0, 10.0
    d.centre, d.rate = Seen(10.0, 0.0, 0.0), math.radians(-4.2)
    assert d.gate(0.0, math.radians(0.4), 12.0) == pytest.approx(math.radians(0.4))
    far = -4.2 * REF_MAX_S - LEASH_DEG - 4.2 * (LEAD_S + 2.0 - REF_MAX_S)
    assert math.degrees(d.gate(0.0, math.radians(-30.0), 12.0)) == pytest.approx(far)


def test_a_trusted_head_after_black_frames_is_not_sent_where_the_learnt_rate_ran_on():
    """`vergence sim`'s rig: a sine of 0.8 +- 0.3 m at 0.5 Hz, 30 Hz, the slave converging from parallel (trusted by
    that move), every frame black from 1 to 3 s: over the 0.5 s after, within 6 px (4.0; before the cone, the first
    decision's command went where the leash's centre ran on at the learnt rate for 2 s: 48.8 px off)."""
    rig = MovingRig.from_options(motion="sine:z=0.8,amp=0.3,hz=0.5", focal="500", seed="7", noise="1")
    faults = Faults.take(parse("black=1-3", FAULT_KEYS, "test"))
    steps = list(closed_loop(rig, 4 * 30, None, ControlSettings(), None, 30.0, faults=faults, seed=7, focal_px=500.0))
    assert max(abs(s.camera_error_px) for s in steps if 3.0 <= s.t_s < 3.5) <= 6.0


def test_a_head_not_yet_seen_to_follow_moves_at_most_untrusted_deg_then_leash_deg_past_its_target():
    d = Doubt()
    feed(d, [(0, 10, 1)])
    assert d.gate(0.0, 10 * DEG, 0.0) == pytest.approx(UNTRUSTED_DEG * DEG)
    t = Doubt()
    feed(t, [(0, 3, 1), (1, 2, 2), (2, 1, 3), (3, 0, 4)])
    assert t.trusted
    # the last consistent measurement asked for 3 degrees: no set-point further than LEASH_DEG past it
    assert t.gate(3 * DEG, 9 * DEG, 4 * DT) == pytest.approx((3 + LEASH_DEG) * DEG)
    assert t.gate(3 * DEG, 3.5 * DEG, 4 * DT) == pytest.approx(3.5 * DEG)


def test_pursuit_and_a_jump_of_the_target_are_not_faults():
    d = Doubt()
    # a target moving at 12 deg/s, followed with the offset near 0: z moves, the motor with it
    frames = [(0.2 * k, 0.02 * (-1) ** k, k + 1) for k in range(30)]
    assert set(feed(d, frames)) == {None}
    # then it jumps 3 degrees while the motor stands, and the motor goes after it
    more = [(5.8, 3.0, 100), (5.8, 3.0, 101), (7.0, 1.8, 102), (8.0, 0.8, 103), (8.8, 0.0, 104)]
    assert set(feed(d, more, t0=0.5)) == {None}


def test_a_new_fovea_is_a_new_target():
    d = Doubt()
    feed(d, [(0, 0, 1), (0, 0, 2)])
    d.observe(2 * DT, 0.0, 2 * DEG, 3, None, (100, 100))
    assert d.ref.a == pytest.approx(2 * DEG) and d.rate == 0.0 and d.fault is None
    # during a fault, the offsets at the anchor are the target's own motion (follows.Held), the new point's only
    # (the old point's and the new one's read together were a motion: Tsukuba, seed 7207, docs/FAULTS.md)
    feed(d, [(0, 3, 4), (0.3, 3, 5), (1.2, 3, 6), (2.0, 3, 7)], t0=0.1)
    assert d.fault is Fault.SLAVE_FROZEN
    feed(d, [(0, 3, 8 + k) for k in range(5)], t0=0.2)
    assert len(d.held.seen) == 5
    d.observe(0.3, 0.0, 1 * DEG, 20, None, (200, 100))
    assert d.held.seen == [(0.3, pytest.approx(1 * DEG))]


def test_a_faults_move_back_that_the_safety_cut_short_is_sent_again():
    """A camera named reversed 20 deg from where it started: the move back to the anchor, cut at the Safety's
    max_step_deg (10 deg), is sent again RETURN_S later where the pan is not back (before: it waited half a probe's
    period, 0.5 s, 9 deg off: Cones, seed 7213, the camera reversed from the start, docs/FAULTS.md); none while the
    motor is on its way, and none once it is back."""
    d = Doubt()
    feed(d, [(0, 3, 1), (10, 13, 2), (20, 23, 3)])
    assert d.fault is Fault.REVERSED and d.anchor == 0.0
    t = 3 * DT
    assert d.gate(20 * DEG, None, t) == 0.0
    assert [d.gate(10 * DEG, None, t + k * DT) for k in range(1, 15)] == [None] * 14  # (on its way: 0.23 s)
    assert d.gate(10 * DEG, None, t + 15 * DT) == 0.0
    assert [d.gate(0.0, None, t + k * DT) for k in range(16, 50)] == [None] * 34  # back: until the first probe


@pytest.mark.parametrize("sides,clears", [((1,), False), ((-1,), False), ((1, -1), True)])
def test_a_reversed_fault_is_cleared_only_by_probes_that_follow_to_both_sides_one_after_the_other(sides, clears):
    """A camera named reversed, probed PROBE_DEG either side of its anchor in turn, one probe every PROBE_S: the
    image read as a following camera's on the probes to `sides` only, as a reversed one's elsewhere. One side's
    probes are what a false match gives (Tsukuba, seed 7207, 66 ms: a fovea with two matches 15 px apart, taken in
    turn; at a probe's pan the other one read r = 1.15, the fault cleared, and the slave ran 10.8 deg from its
    start); a camera named reversed falsely follows both ways, and is cleared by the second probe."""
    d = Doubt()
    feed(d, [(0, 3, 1), (1, 4, 2), (2, 5, 3)])
    assert d.fault is Fault.REVERSED and d.anchor == 0.0
    pan, cleared = 2.0, None
    for k in range(4, int(3.6 / DT)):  # 3.5 s: three probes
        t = k * DT
        if (g := d.gate(pan * DEG, None, t)) is not None:
            pan = g / DEG  # (at the goal by the next exposure)
        side = (pan > 0.2) - (pan < -0.2)
        d.observe(t, pan * DEG, (3 - pan if side in sides else 3 + pan) * DEG, k, None, (320, 240))
        if d.fault is None:
            cleared = t
            break
    assert (cleared is not None) == clears, cleared
    if clears:
        assert 2.0 < cleared < 2.3 and d.resumed == 1  # the second probe's first frame (the first one: 1.0-1.5 s)


def test_a_motor_that_does_not_follow_its_commands_is_stalled_and_a_move_clears_it():
    d = Doubt()
    feed(d, [(0, 2, 1)])
    assert d.gate(0.0, 2 * DEG, DT) == pytest.approx(2 * DEG)  # commanded 2 degrees away
    for k in range(2, 40):
        d.observe(k * DT, 0.0, 2 * DEG, k, None, (320, 240))
    assert d.fault is Fault.STALLED
    first_probe = next(t for t in (k * 0.05 for k in range(60)) if d.gate(0.0, None, 1.0 + t) not in (None, 0.0))
    assert first_probe <= 1.0
    d.observe(3.0, 0.5 * DEG, 1.5 * DEG, 99, None, (320, 240))  # the encoder moves again
    assert d.fault is None and d.resumed == 1


def test_a_frozen_master_is_named_where_its_images_used_to_change_and_clears_when_they_do():
    d = Doubt()
    for k in range(10):
        d.observe(k * DT, 0.0, 0.0, k, 1000 + k, (320, 240))
    for k in range(10, 40):
        d.observe(k * DT, 0.0, 0.0, k, 1009, (320, 240))
    assert d.fault is Fault.MASTER_FROZEN
    assert d.gate(0.0, 1 * DEG, 1.0) is None  # no move, not even a probe
    d.observe(41 * DT, 0.0, 0.0, 41, 5, (320, 240))
    assert d.fault is None
    clean = Doubt()  # a clean still scene repeats its master from the start: not a fault
    for k in range(60):
        clean.observe(k * DT, 0.0, 0.0, 1, 1, (320, 240))
    assert clean.fault is None
    # nor where it changed a few times apart and then repeats (a simulator rendering the rows of a growing window)
    grown = Doubt()
    for k in range(60):
        grown.observe(k * DT, 0.0, 0.0, 1, 1 + (k >= 5) + (k >= 9) + (k >= 14), (320, 240))
    assert grown.fault is None


def test_a_probe_the_image_follows_clears_the_fault():
    d = Doubt()
    feed(d, [(0, 3, 1), (0.3, 3, 2), (1.2, 3, 3), (2.0, 3, 4)])
    assert d.fault is Fault.SLAVE_FROZEN
    assert d.gate(2.0 * DEG, None, 0.1) == pytest.approx(0.0)
    d.observe(0.2, 0.0, 3 * DEG, 10, None, (320, 240))  # back at the anchor: the reference
    probe = d.gate(0.0, None, 0.1 + 1.0)
    assert abs(probe) == pytest.approx(PROBE_DEG * DEG)
    d.observe(1.2, probe, 3 * DEG - probe, 11, None, (320, 240))  # the image moved by the probe
    assert d.fault is None and d.resumed == 1 and d.faults == 1


@pytest.mark.parametrize("follows", [False, True])
def test_a_probe_during_pursuit_is_read_less_the_targets_own_motion_at_the_anchor(follows):
    """A fault held at the anchor while the target moves 6 deg/s: the offset moves by itself. A probe of 0.5 deg three
    frames later whose image shows the target's motion only (a slipping camera) must not clear the fault (read as
    seen it moved the image r = 0.6); one whose image also shows the probe clears it."""
    d = Doubt()
    feed(d, [(0, 3, 1), (0.3, 3, 2), (1.2, 3, 3), (2.0, 3, 4)])
    assert d.fault is Fault.SLAVE_FROZEN
    rate = -6.0  # deg/s: the offset at the anchor, the target's own motion
    for k in range(20):  # 0.33 s at the anchor
        d.observe(0.2 + k * DT, 0.0, (3 + rate * k * DT) * DEG, 10 + k, None, (320, 240))
    t0, a0 = 0.2 + 19 * DT, 3 + rate * 19 * DT
    probe = 0.5  # with the target: seen as is, the target's motion alone reads r = 0.6
    for k in range(1, 4):
        t = t0 + k * DT
        a = a0 + rate * k * DT - (probe if follows else 0.0)
        d.observe(t, probe * DEG, a * DEG, 40 + k, None, (320, 240))
    assert (d.fault is None) == follows and d.resumed == int(follows)


@pytest.mark.parametrize("moved", [None, 0.0, 1.0])
def test_a_probe_whose_background_did_not_move_clears_nothing_whatever_its_offset_reads(moved):
    """The probe of the test above as a slipping camera's target moving with it shows it (its offset moved by the
    probe: the target's own motion changed just then): read on the offset alone it clears the fault. The background
    behind (vergence.head.scenery) did not move with the probe: no clearing; one that moved with it, or none read
    (a band without background texture), leaves the offset's reading as it was."""
    d = Doubt()
    feed(d, [(0, 3, 1), (0.3, 3, 2), (1.2, 3, 3), (2.0, 3, 4)])
    for k in range(20):
        d.observe(0.2 + k * DT, 0.0, 3 * DEG, 10 + k, None, (320, 240))
    t0 = 0.2 + 19 * DT
    for k in range(1, 4):
        d.observe(t0 + k * DT, 0.5 * DEG, 2.5 * DEG, 40 + k, None, (320, 240),
                  background=None if moved is None else Verdict(moved))
    assert d.resumed == int(moved != 0.0) and (d.fault is None) == (moved != 0.0)


@pytest.mark.parametrize("verdicts,clears", [([1.05, 1.04], True), ([1.05], False), ([1.05, 0.0, 1.0], False),
                                             ([0.9, 0.4], False), ([-1.0, -1.0], False)])
def test_a_fault_whose_fovea_decides_nothing_is_cleared_by_its_probes_background(verdicts, clears):
    """A fault held where the fovea has no confident decision (a fovea 2 px off a near target's edge: its window holds
    both depths; tests/scenarios/test_ros2_faults.py): the probes' background (vergence.head.scenery) tells
    whether the image follows; two verdicts in a row that it moved with the motor clear the fault, one, or one and
    then a still one, or one under FOLLOWS_MIN, or a reversed one, do not. Before, such a fault held for good
    (seen through a ROS 2 camera: thawed, the background read r = 1.04 on every probe for 10 s)."""
    d = Doubt()
    feed(d, [(0, 3, 1), (0.3, 3, 2), (1.2, 3, 3), (2.0, 3, 4)])
    assert d.fault is Fault.SLAVE_FROZEN
    for k in range(20):  # at the anchor, undecided
        d.observe(0.2 + k * DT, 0.0, None, 10 + k, None, (320, 240))
    t0 = 0.2 + 19 * DT
    for k, r in enumerate(verdicts, 1):
        d.observe(t0 + k * DT, 0.5 * DEG, None, 40 + k, None, (320, 240), background=Verdict(r))
    assert (d.fault is None) == clears and d.resumed == int(clears)
    if clears:
        assert d.anchor == pytest.approx(0.5 * DEG) and d.trusted


def test_background_verdicts_that_followed_under_a_decided_fovea_then_a_frame_with_neither_clear_nothing():
    """Two verdicts that followed while the fovea decided (read there, not from the background), then an undecided
    frame with no verdict: nothing clears and nothing fails (a frame without a verdict was read as one)."""
    d = Doubt()
    feed(d, [(0, 3, 1), (0.3, 3, 2), (1.2, 3, 3), (2.0, 3, 4)])
    t0 = 0.2
    for k, r in enumerate([1.05, 1.04]):
        d.observe(t0 + k * DT, 0.0, 3 * DEG, 10 + k, None, (320, 240), background=Verdict(r))
    assert d.observe(t0 + 2 * DT, 0.0, None, 12, None, (320, 240), background=None) is Fault.SLAVE_FROZEN
    assert d.resumed == 0


@pytest.mark.parametrize("offset_deg", [0.1, 2.0])
def test_a_background_still_as_a_late_image_would_be_holds_the_chase_and_names_nothing(offset_deg):
    """A head trusted in pursuit whose background reads still where a late image would too (Verdict.late: the motor's
    turn up to scenery.LATE_S earlier explains it), its offset small (a chase, as a slipping camera's starts): no
    command further from the anchor than the slave is, no fault; SUSPECT_S later a probe back; two verdicts that no
    late image explains name the fault. With the offset past LEASH_DEG (a correction toward a target seen far off,
    which a late camera's image lags) the turn goes on."""
    d = Doubt()
    feed(d, [(0, 3, 1), (1, 2, 2), (2, 1, 3), (3, 0, 4)])
    assert d.trusted and d.fault is None
    t = 4 * DT
    d.observe(t, 3.4 * DEG, offset_deg * DEG, 5, None, (320, 240), background=Verdict(0.0, late=True))
    goal = d.gate(3.4 * DEG, 4.5 * DEG, t)
    assert d.fault is None and goal == pytest.approx((3.4 if offset_deg < LEASH_DEG else 4.5) * DEG)
    if offset_deg > LEASH_DEG:
        return
    probe = d.gate(3.4 * DEG, 4.5 * DEG, t + SUSPECT_S + DT)
    assert probe == pytest.approx((3.4 - PROBE_DEG) * DEG)
    for k in (1, 2):
        d.observe(t + k * DT, 3.4 * DEG, 0.2 * DEG, 5 + k, None, (320, 240), background=Verdict(0.0))
    assert d.fault is Fault.SLAVE_FROZEN


def test_the_targets_motion_at_the_anchor_is_taken_out_only_where_it_was_a_line_or_a_parabola():
    """follows.Held: a steady drift gives its rate (the probe read less it, and as seen at least FOLLOWS_MIN); a target
    that stepped while the motor held (a square wave), or too few frames, gives none, and the probe is read as seen
    only (a step's 'rate' taken out kept a late camera's fault on a stepping target for good)."""
    from vergence.head.follows import Held

    drift, step = Held(), Held()
    for k in range(12):
        drift.add(k * DT, (0.5 - 3.0 * k * DT) * DEG)
        step.add(k * DT, (0.5 if k < 6 else -1.8) * DEG)
    assert drift.motion(0.0, 1.0) == pytest.approx(-3.0 * DEG) and step.motion(0.0, DT) is None
    a0 = 0.5 - 3.0 * 11 * DT  # the last frame at the anchor; then a probe of +0.5 deg, its image seen 3 frames on
    less, seen = drift.ratios(11 * DT, 0.0, a0 * DEG, 14 * DT, 0.5 * DEG, (a0 - 3.0 * 3 * DT - 0.5) * DEG)
    assert seen == pytest.approx(1.3) and less == pytest.approx(1.0)  # as seen, the target's 0.15 deg counts too
    assert len(step.ratios(0.0, 0.0, 0.0, DT, 0.5 * DEG, -0.5 * DEG)) == 1


def test_a_probe_at_a_targets_turn_is_read_less_the_turn():
    """A target that turns while the motor holds at the anchor (a sine's near turn, 27 deg/s^2 in the image: within
    0.1 deg of a line over the window) and a probe of -0.53 deg whose camera did not move (a slipping coupling): the
    target's own motion over the probe's 0.09 s, 0.34 deg, read as seen or less a line is the probe followed (r 0.64
    and 0.51: the fault cleared and the slave ran 4.7 deg, `vergence sim` at 45 Hz, seed 31); less the parabola, 0.
    A camera that follows on a target turning fast the probe's way reads 1 less it, and more than 2.2 as seen."""
    from vergence.head.follows import FOLLOWS_MAX, FOLLOWS_MIN, Held

    acc, turn, dt = 27.0 * DEG, 4.38, 1 / 45

    def a(t: float, gain: float = 1.0) -> float:
        return -3.33 * DEG + gain * 0.5 * acc * (t - turn) ** 2

    for gain, probe_follows in ((1.0, False), (1.0, True), (6.0, True)):
        held = Held()
        ts = [4.533 - k * dt for k in range(12)][::-1]
        for t in ts:
            held.add(t, a(t, gain))
        t0, t1, dp = ts[-1], ts[-1] + 4 * dt, -0.527 * DEG
        rs = held.ratios(t0, 0.0, a(t0, gain), t1, dp, a(t1, gain) - (dp if probe_follows else 0.0))
        followed = all(FOLLOWS_MIN <= r <= FOLLOWS_MAX for r in rs)
        assert followed == probe_follows, (gain, probe_follows, rs)
        if gain == 1.0 and not probe_follows:  # a line fits the window within 0.1 deg, and misses the turn
            line = float(np.polyfit(ts, [a(t, gain) for t in ts], 1)[0])  # (the line through the window)
            seen_less_line = -(a(t1, gain) - a(t0, gain) - line * (t1 - t0)) / dp
            assert FOLLOWS_MIN <= seen_less_line and FOLLOWS_MIN <= rs[1] and rs[0] == pytest.approx(0.0, abs=0.05)
        if gain == 6.0:
            assert rs[1] == FOLLOWS_MAX and -(a(t1, gain) - dp - a(t0, gain)) / dp > FOLLOWS_MAX  # (as seen: clipped)
    few = Held()
    for k in range(Held.MIN - 1):
        few.add(k * DT, k * DEG)
    assert few.motion(0.0, DT) is None


def test_the_targets_motion_at_rest_is_kept_for_one_pan_at_a_time():
    """follows.Held given the frames' pans (the leash's probes, vergence.head.doubt): a frame within SAME_PAN_DEG
    of the run's first pan joins it, one further starts a new run (another pan's offsets: no target's motion)."""
    from vergence.head.follows import Held

    held = Held()
    for k in range(8):
        held.add(k * DT, (0.5 - 3.0 * k * DT) * DEG, (-8.61 + 0.01 * (k % 2)) * DEG)
    assert held.pan == pytest.approx(-8.61 * DEG) and held.motion(0.0, 1.0) == pytest.approx(-3.0 * DEG)
    assert held.motion(0.0, 1.0, -8.6 * DEG) == pytest.approx(-3.0 * DEG) and held.motion(0.0, 1.0, -8.4 * DEG) is None
    assert Held().motion(0.0, 1.0, 0.0) is None
    held.add(8 * DT, 0.0, -8.17 * DEG)  # a probe's frame, 0.44 deg on
    assert held.pan == pytest.approx(-8.17 * DEG) and len(held.seen) == 1 and held.motion(0.0, 1.0) is None


def test_a_large_move_read_within_the_slack_but_short_of_follows_min_verifies_nothing():
    """A move of 0.7 deg over two frames (21 deg/s: no faster than a target, not judged) whose image moved 0.3 (r 0.43:
    within the slack and half the move, as a slipping camera's runaway reads while the target's learnt rate absorbs it)
    neither trusts the head nor moves the anchor; one whose image moved 0.7 does."""
    d = Doubt()
    feed(d, [(0, 0.0, 1), (0.35, None, 2), (0.7, -0.3, 3)])
    assert not d.trusted and d.anchor == pytest.approx(0.0) and d.fault is None
    ok = Doubt()
    feed(ok, [(0, 0.0, 1), (0.35, None, 2), (0.7, -0.7, 3)])
    assert ok.trusted and ok.anchor == pytest.approx(0.7 * DEG)


# -- the simulator's lies ---------------------------------------------------------------------------------------------

def test_the_fault_keys_parse_and_refuse_by_name():
    f = Faults.take(parse("freeze=1-3:reverse:backlash=0.2:focal_true=800", FAULT_KEYS, "x"))
    assert f.freeze == (1.0, 3.0) and f.reverse and f.backlash == 0.2 and f.focal_true == 800.0
    assert f.spec() == "freeze=1-3:reverse:backlash=0.2:focal_true=800" and not Faults()
    with pytest.raises(SpecError, match="freeze"):
        parse("freeze=3-1", FAULT_KEYS, "x")


def _run(rig, spec: str, frames: int, latency: float = 0.0, fixations=None, seed: int = 0):
    faults = Faults.take(parse(spec, FAULT_KEYS, "test"))
    return list(closed_loop(rig, frames, None, ControlSettings(), None, 60.0, fixations=fixations,
                            timing=CameraTiming(latency), faults=faults, seed=seed))


LIES = [(lie, latency) for lie in ("freeze", "slip") for latency in (0.0, 0.066)]
if MIDDLEBURY.is_dir():
    for _lie in LIES:
        background.ahead(sweeps.teddy_lie, *_lie,
                         tests="test_a_frozen_or_slipping_slave_while_a_fixate_asks_a_move_is_held_and_found_again")


@needs_data
@pytest.mark.parametrize("lie,latency", LIES)
def test_a_frozen_or_slipping_slave_while_a_fixate_asks_a_move_is_held_and_found_again(lie, latency):
    """Teddy at 60 Hz, the fovea moved at 0.5 s to a point 0.8 degrees away while the slave lies from 0.4 to 2.4 s:
    diagnosed within 0.5 s, never more than 2 degrees past the pan the first decision asked for, within 1 px of
    the truth no later than 2 s after the camera is right again. (The loop's run is done ahead in the background
    where slow tests run too: tests/background.py.)"""
    rig = sweeps.teddy_rig(noise="1")
    steps = background.get(sweeps.teddy_lie, lie, latency)
    asked = steps[30].pan_deg + math.degrees(math.atan(steps[30].offset_px / rig.focal_px))
    first = next(s for s in steps if s.fault)
    assert first.fault == "slave_frozen" and first.t_s - 0.5 <= 0.5
    assert max(s.pan_deg for s in steps if 0.4 <= s.t_s < 2.4) <= asked + 2.0
    truth = truth_at(rig, 150, 200)[0]
    after = [s for s in steps if s.t_s >= 2.4]
    off = [abs(rig.focal_px * math.tan(math.radians(s.pan_deg) - truth)) for s in after]
    for_good = next(s.t_s for i, s in enumerate(after) if max(off[i:]) <= 1)
    assert for_good - 2.4 <= 2.0 and not any(s.fault for s in after[-60:])


@pytest.mark.parametrize("rate,latency,seed", [(60.0, 0.0, 12), (30.0, 0.066, 13)])
def test_a_slave_frozen_while_the_motor_holds_and_the_target_steps_is_named_and_found_again(rate, latency, seed):
    """The slave converged on a target 1.0 m ahead freezes at 0.7 s for 2 s; at 1.2 s the target steps to 0.65 m. The
    frozen image and the master's new one share nothing to match: the decisions abstain and nothing moves, so no
    motion tells the freeze (before: never named). Its bytes, which the sensor's noise changed every frame while the
    motor held, stay the same: `slave_frozen` named 0.3 s after the freeze began; the slave never 1 deg from where it
    was (probes only), and the target found within 1 px within 1 s of the thaw."""
    rig = MovingRig.from_options(motion="step:z0=1.0,z1=0.65,at=1.2", focal="500", seed=str(seed), noise="1")
    rig.start_pan_rad = rig.truth_pan(0.0)
    faults = Faults.take(parse("freeze=0.7-2.7", FAULT_KEYS, "test"))
    steps = list(closed_loop(rig, int(4.5 * rate), None, ControlSettings(), None, rate, timing=CameraTiming(latency),
                             faults=faults, seed=seed, focal_px=500.0))
    named = next(s for s in steps if s.fault)
    assert named.fault == "slave_frozen" and 0.9 <= named.t_s <= 1.1  # (1.0 s)
    p0 = [s.pan_deg for s in steps if s.t_s < 0.7][-1]
    assert max(abs(s.pan_deg - p0) for s in steps if 0.7 <= s.t_s < 2.7) <= 1.0  # (0.53 deg: a probe)
    found = next(s.t_s for s in steps if s.t_s >= 2.7 and not s.fault and abs(s.camera_error_px) <= 1.0)
    assert found <= 3.7 and not [s for s in steps if s.t_s > found and s.fault]  # (3.08 and 3.2 s)


def test_a_slip_in_pursuit_is_held_through_the_targets_turn_and_not_cleared_by_a_probe_there():
    """A sine of 0.4 Hz about 0.75 m at 45 Hz (seed 31), the coupling slipping from 3.3 to 5.3 s: named within 0.25 s,
    and the probe 1.2 s on, at the target's near turn, does not clear it (it did, read less a line through the turn:
    the chase then ran 4.7 deg past the asked pan); the slave within 2 deg of the pan asked before the slip, back
    within 1 px of the truth 0.5 s after it, and on it from then on: the background is read against no image from
    before the fault cleared, which the slipping camera took (it was, and named the slip again at 5.62 s: held 0.4 s
    while the target moved on, 7.6 px)."""
    rig = MovingRig.from_options(motion="sine:z=0.75,amp=0.25,hz=0.4", focal="500", seed="31", noise="1")
    rig.start_pan_rad = rig.truth_pan(0.0)
    faults = Faults.take(parse("slip=3.3-5.3", FAULT_KEYS, "test"))
    steps = list(closed_loop(rig, int(7 * 45), None, ControlSettings(), None, 45.0, faults=faults, seed=31,
                             focal_px=500.0))
    named = next(s for s in steps if s.fault and s.t_s >= 3.3)
    assert named.fault == "slave_frozen" and named.t_s - 3.3 <= 0.25  # (0.23 s)
    assert all(s.fault for s in steps if named.t_s <= s.t_s < 5.3)  # (before: cleared at 4.62 s)
    before = [s for s in steps if s.t_s < 3.3 and s.confident][-1]
    asked = before.pan_deg + math.degrees(math.atan(before.offset_px / 500.0))
    assert max(abs(s.pan_deg - asked) for s in steps if 3.3 <= s.t_s < 5.3) <= 2.0  # (1.60 deg; before 4.69)
    back = next(s.t_s for s in steps if s.t_s >= 5.3 and not s.fault and abs(s.camera_error_px) <= 1)
    assert back <= 5.8 and not any(s.fault for s in steps if s.t_s >= back)  # (5.6)
    assert max(abs(s.camera_error_px) for s in steps if s.t_s >= 6.0) <= 1.5  # (1.09 px)


def test_a_slip_while_a_fixate_asks_a_move_is_named_from_the_background_where_the_fovea_decides_little():
    """The still scene (seed 41) at 60 Hz with 66 ms of camera latency, the coupling slipping from 0.4 s, the fovea
    moved at frame 30 to (180, 300), where the network decides one frame in three (the others abstain, the window
    grown and back): each confident decision asked 2 deg more, too slowly to be judged between such sparse decisions,
    and the background's verdicts, which said the image did not move, were not heard from an undecided fovea and were
    taken for a late image's after each new band shape. Before: named after 1.2 s, 11.9 deg past the pan asked; now
    named within 0.5 s of the first decision there, within 2 deg of it (0.27 s, 1.83 deg)."""
    from vergence.sim import Rig

    rig = Rig.from_spec("focal=500:noise=1:seed=41")
    faults = Faults.take(parse("slip=0.4-2.4", FAULT_KEYS, "test"))
    steps = list(closed_loop(rig, 150, None, ControlSettings(), None, 60.0, fixations={30: (180, 300)},
                             timing=CameraTiming(0.066), faults=faults, seed=41, focal_px=500.0))
    first = next(s for s in steps if s.frame >= 30 and s.confident)
    asked = first.pan_deg + math.degrees(math.atan(first.offset_px / 500.0))
    named = next(s for s in steps if s.fault)
    assert named.fault == "slave_frozen" and named.t_s - first.t_s <= 0.5
    way = math.copysign(1.0, asked - first.pan_deg)
    assert max(way * (s.pan_deg - asked) for s in steps if s.t_s >= first.t_s) <= 2.0


@pytest.mark.parametrize("latency", [0.0, 0.066])
def test_a_reversed_camera_from_the_start_never_leaves_3_degrees_and_then_only_probes(latency):
    rig = MovingRig.from_options(motion="still:z=0.8", focal="500", seed="3")
    rig.start_pan_rad = rig.truth_pan(0.0) - 100 / 500  # 100 px off
    steps = _run(rig, "reverse", 180, latency)
    start = steps[0].pan_deg
    assert max(abs(s.pan_deg - start) for s in steps) <= 3.0
    first = next(s for s in steps if s.fault)
    assert first.fault == "reversed" and first.t_s <= 1.0
    moves = [s.target_deg for s in steps if s.frame > first.frame and s.target_deg is not None]
    assert all(abs(m - start) <= PROBE_DEG + 0.1 for m in moves)  # back to the start and probes


def test_a_reversed_cameras_probes_read_late_on_a_moving_target_never_clear_it():
    """A reversed camera from the start, 70 px off a sine of 0.89 Hz (0.89 +- 0.18 m), 66 ms, 30 Hz (session 48's draw
    4955). Named at once; then a probe's step fitted as a late image's (Lag.probe: the target's own motion a quadratic,
    r free) read r 0.67 at 150 ms where none read -0.52 almost as well, twice: the camera was named 145 ms late, which
    clears the fault, and the loop ran 17.7 deg from the start. A probe's lag counts only where no lag at which the
    image did not follow fits within LATE_NOISE_DEG as well."""
    rig = MovingRig.from_options(motion="sine:z=0.89,amp=0.18,hz=0.89", focal="500", seed="4955", noise="1")
    rig.start_pan_rad = rig.truth_pan(0.0) - math.atan(70 / 500)
    faults = Faults.take(parse("reverse", FAULT_KEYS, "test"))
    steps = list(closed_loop(rig, 240, None, ControlSettings(), None, 30.0, timing=CameraTiming(0.066),
                             faults=faults, seed=4955, focal_px=500.0))
    first = next(s for s in steps if s.fault)
    assert first.fault == "reversed" and first.t_s <= 0.2
    assert all(s.fault == "reversed" and s.late_ms is None for s in steps if s.t_s >= first.t_s)
    assert max(abs(s.pan_deg - steps[0].pan_deg) for s in steps) <= 3.0


def test_a_stall_is_named_within_a_second_and_commands_stop_but_probes():
    rig = MovingRig.from_options(motion="still:z=0.8", focal="500", seed="4")
    rig.start_pan_rad = rig.truth_pan(0.0) - 40 / 500
    steps = _run(rig, "stall=0-3", 150)
    first = next(s for s in steps if s.fault)
    assert first.fault == "stalled" and first.t_s <= 1.0
    moves = [s.target_deg for s in steps if s.fault and s.target_deg is not None]
    assert len(moves) <= 2 * 1.5 + 1  # the probes (one a second) and their way back


def test_a_frozen_master_holds_within_half_a_second():
    rig = MovingRig.from_options(motion="sine:z=0.8,amp=0.3,hz=0.5", focal="500", seed="5")
    rig.start_pan_rad = rig.truth_pan(0.0)
    steps = _run(rig, "freeze_master=1-2", 150)
    first = next(s for s in steps if s.fault)
    assert first.fault == "master_frozen" and 1.0 <= first.t_s <= 1.5
    assert not [s for s in steps if s.fault and s.target_deg is not None]
    assert not steps[-1].fault


@pytest.mark.parametrize("start_px,seed", [(0.0, 0), (-6.0, 8), (2.0, 11)])
def test_a_target_accelerating_640_deg_s2_is_pursued_at_30_hz_without_a_fault(start_px, seed):
    """A 2 Hz sine between 0.5 and 1.1 m (640 deg/s^2 at 0.5 m, 27 deg/s), 15 frames a period: at its turns the learnt
    rate lags it by 30 deg/s, and a correction of 1 deg a frame looked like a frozen camera (`vergence bench tracking`'s
    2 Hz, 30 Hz row: 69 frames in a fault, 17 px RMS, on two of these draws; 8.4 px on the third). Now such a pair is a
    doubt where the target's latest rate explains it: held, probed, nothing named. RMS over the last 4 s: 7.1, 7.0, 6.5
    px."""
    rig = MovingRig.from_options(motion="sine:z=0.8,amp=0.3,hz=2", focal="500", seed=str(seed))
    rig.start_pan_rad = rig.truth_pan(0.0) - math.atan(start_px / 500)
    steps = list(closed_loop(rig, 150, None, ControlSettings(mode="predictive"), None, 30.0, seed=seed))
    assert not [s for s in steps if s.fault]
    late = [s.error_px for s in steps[30:]]
    assert math.sqrt(sum(e * e for e in late) / len(late)) < 8.0


@pytest.mark.parametrize("seed", [0, 21])
def test_a_probe_that_the_targets_latest_rate_explains_names_nothing(seed):
    """`vergence bench tracking --camera --hz 2`'s row of 30 Hz, 8 ms of exposure, predictive (seed 0): a doubt at the
    sine's turn held the motor and its probes, judged against the learnt rate (-8 deg/s where the target went +21),
    named `slave_frozen` (37 frames, 12.8 px RMS). A probe's image that the target's latest rate explains is a doubt
    too: nothing named, 10.8 px (the loop tracking a 2 Hz target at 15 frames a period)."""
    rig = MovingRig.from_options(motion="sine:z=0.8,amp=0.3,hz=2", focal="500", seed=str(seed))
    steps = list(closed_loop(rig, 150, None, ControlSettings(mode="predictive"), None, 30.0,
                             timing=CameraTiming(0.0, exposure_s=0.008), seed=seed))
    assert not [s for s in steps if s.fault]
    late = [s.error_px for s in steps[30:]]
    assert math.sqrt(sum(e * e for e in late) / len(late)) < 12.0


@pytest.mark.parametrize("motion,latency,seed", [("sine:z=0.8,amp=0.3,hz=2", 0.1, 38),
                                                  ("sine:z=0.75,amp=0.3,hz=1.9", 0.09, 31)])
def test_one_pair_of_a_fast_target_read_past_any_targets_rate_is_no_jump(motion, latency, seed):
    """A target at up to 27-30 deg/s (2 Hz, 0.5-1.1 m; 1.9 Hz, 0.45-1.05 m) at 60 Hz with 90-100 ms of camera latency:
    one pair's rate read 31 deg/s where the target went 24, was taken for a jump (the rates 0), and the next fast
    correction, judged against a still target, named `slave_frozen` (these draws: at 1.85 and 0.53 s, 62 and 124
    frames in a fault, 9.2 and 20.5 px RMS; 57 of 120 such runs over seeds 30-59). Now such a pair's rate is the one
    over the last LONG_S (0.07 s) when that is a target's: no fault, 3.5 and 3.9 px RMS."""
    rig = MovingRig.from_options(motion=motion, focal="500", seed=str(seed), noise="1")
    rig.start_pan_rad = rig.truth_pan(0.0)
    steps = list(closed_loop(rig, 360, None, ControlSettings(mode="predictive"), None, 60.0,
                             timing=CameraTiming(latency), seed=seed))
    assert not [s for s in steps if s.fault]
    late = [s.error_px for s in steps[60:]]
    assert math.sqrt(sum(e * e for e in late) / len(late)) < 5.0


@pytest.mark.parametrize("motion", ["sine:z=0.8,amp=0.3,hz=1", "step:z0=1.2,z1=0.6,at=1"])
def test_the_moving_target_raises_no_fault_with_backlash_and_encoder_noise(motion):
    rig = MovingRig.from_options(motion=motion, focal="500", seed="6")
    rig.start_pan_rad = rig.truth_pan(0.0)
    steps = _run(rig, "backlash=0.2:encoder_noise=0.05", 240, 0.033, seed=6)
    assert not [s for s in steps if s.fault]


@pytest.mark.parametrize("rate,latency,seed", [(60.0, 0.0, 11), (30.0, 0.066, 12)])
def test_images_at_1_6_x_the_focal_length_told_are_named_and_the_steps_after_do_not_overshoot(rate, latency, seed):
    """focal_true 1.6 x the settings (the images rendered at f 800, the loop told 500), a target stepping between 0.6
    and 1.0 m every second: the first step overshoots (16-26 px: the move is 1.6 x what the offset asked), its fast
    moves' ratios name the focal length within 5 % by the third step (at 60 Hz a pair spans 1.5 deg of the move: a
    pair whose slack is a fifth of its motion counts; at a tenth, as before, 60 Hz never named it on one of four
    draws), and every step after overshoots at most 3 px (0.0-0.3 measured), no fault, no limit cycle."""
    rig = MovingRig.from_options(motion="square:z0=0.6,z1=1.0,hz=0.5", focal="800", seed=str(seed), noise="1")
    steps = list(closed_loop(rig, int(6 * rate), None, ControlSettings(), None, rate, timing=CameraTiming(latency),
                             seed=seed, focal_px=500.0))
    named = next(s for s in steps if s.focal_ratio is not None)
    assert named.t_s < 2.5 and steps[-1].focal_ratio == pytest.approx(1.6, rel=0.05)
    assert not [s for s in steps if s.fault]
    for k in range(int(named.t_s) + 1, 6):  # each step after the naming: its error never flips past 3 px
        seg = [s for s in steps if k <= s.t_s < k + 1]
        sign = math.copysign(1.0, seg[0].error_px)
        assert max(-sign * s.error_px for s in seg) <= 3.0, k
        assert max(abs(s.error_px) for s in seg[-10:]) < 0.5  # settled: no limit cycle
    clean = MovingRig.from_options(motion="square:z0=0.6,z1=1.0,hz=0.5", focal="500", seed=str(seed), noise="1")
    assert all(s.focal_ratio is None for s in closed_loop(clean, int(6 * rate), None, ControlSettings(), None, rate,
                                                           timing=CameraTiming(latency), seed=seed))


LATE = [("sine:z=0.8,amp=0.25,hz=0.4", 60.0, 0.066, 14), ("sine:z=0.9,amp=0.2,hz=0.3", 30.0, 0.1, 15)]
for _late in LATE:
    background.ahead(sweeps.late_camera, *_late,
                     tests="test_a_camera_later_than_its_frames_say_is_named_late_and_then_runs_without_faults")


@pytest.mark.parametrize("motion,rate,latency,seed", LATE)
def test_a_camera_later_than_its_frames_say_is_named_late_and_then_runs_without_faults(motion, rate, latency, seed):
    """The images `latency` older than the loop is told (`late=`, as an unstamped camera with [camera] latency_s
    unset): the check takes the first fast moves for a frozen camera (named, held), the probes' images follow late,
    and the lag fitted to them names the camera late within 20 % (fitted on the motor's own reports, vergence.head.lag)
    within 8 s. From then on each frame is taken at its image's instant: at most one more fault, and
    from a second after the last fault the slave tracks within 1.5 px RMS at 60 Hz (3 px at 30 Hz and 100 ms, where
    a told latency tracks at 1.0-1.7), with no fault to the end. (Done ahead in the background: tests/background.py.)"""
    steps = background.get(sweeps.late_camera, motion, rate, latency, seed)
    named = next((s for s in steps if s.late_ms is not None), None)
    assert named is not None and named.t_s <= 8.0
    assert abs(steps[-1].late_ms / 1e3 - latency) <= 0.2 * latency
    onsets = [b.t_s for a, b in zip(steps, steps[1:]) if b.fault and not a.fault]
    assert 1 <= len(onsets) and len([t for t in onsets if t > named.t_s]) <= 1
    cleared = max(b.t_s for a, b in zip(steps, steps[1:]) if a.fault and not b.fault)
    after = [s for s in steps if s.t_s > max(named.t_s, cleared) + 1.0]  # (a fault's hold, and the way back, over)
    rms = math.sqrt(sum(s.error_px ** 2 for s in after) / len(after))
    assert len(after) >= 2 * rate and rms <= (1.5 if rate == 60 else 3.0) and not any(s.fault for s in after)


@pytest.mark.parametrize("camera,r", [("follows", 1.0), ("reversed", -1.0), ("frozen", 0.0)])
def test_a_probes_step_is_read_through_a_late_image_and_a_target_moving_more_than_the_probe(camera, r):
    """A probe of 0.5 deg at 60 Hz, the image 90 ms late, the target turning (3.4 deg over the probe's frames, nearly
    seven probes): the probe's own level says nothing (r = -(a - a_ref) / p far outside the range where the image
    follows, for the camera that does), its step against the target's motion fitted as a constant, a rate and an
    acceleration says r, and where it followed its lag is noted."""
    lag, late = Lag(), 0.09

    def target(t):
        return 0.02 + math.radians(6.0) * t - math.radians(10.0) * t * t

    def pan(t):  # at rest, then the probe at 0.6 s
        return 0.0 if t < 0.6 else math.radians(0.5) * min(1.0, (t - 0.6) / 0.03)

    cam = {"follows": pan, "reversed": lambda t: -pan(t), "frozen": lambda t: 0.0}[camera]
    seen = []
    for k in range(58):
        t = k * DT
        lag.shift(t, pan(t))
        seen.append((t, target(t) - cam(t - late)))
        lag.saw(*seen[-1])
    t_ref, a_ref = seen[35]  # the last frame before the probe
    assert lag.probe(t_ref, a_ref) == pytest.approx(r, abs=0.1)
    assert lag.lags == ([pytest.approx(late, abs=0.01)] if camera == "follows" else [])
    level = -(seen[-1][1] - a_ref) / pan(seen[-1][0])
    assert camera != "follows" or not 0.5 <= level <= 2.2  # (the target's motion hides the probe)


def test_a_late_camera_whose_target_moves_fast_during_its_fault_is_cleared_by_a_probe_and_named():
    """A draw of its own: 0.85 +- 0.3 m at 0.5 Hz (up to 6 deg/s), 60 Hz, the images 90 ms older than the loop is
    told, the slave starting 4 deg off: the first move names a frozen camera (as it must); a probe's image shows the
    probe and the target's own motion meanwhile, and no probe's level ever said r near 1 (the fault held all 8 s,
    40 px RMS). Fitted with the lag and the target's motion (Lag.probe): cleared after 1.4 s, the camera named 89 ms
    late at 1.9 s, tracking within 0.7 px RMS over 5-8 s, never over 10 deg."""
    rig = MovingRig.from_options(motion="sine:z=0.85,amp=0.3,hz=0.5", focal="500", seed="48", noise="1")
    steps = list(closed_loop(rig, 480, None, ControlSettings(), None, 60.0, timing=CameraTiming(0.09),
                             faults=Faults.take(parse("late=0.09", FAULT_KEYS, "test")), seed=48))
    cleared = [b.t_s for a, b in zip(steps, steps[1:]) if a.fault and not b.fault]
    named = next(s for s in steps if s.late_ms is not None)
    assert cleared and cleared[0] < 2.0 and named.t_s < 3.0
    assert steps[-1].late_ms == pytest.approx(90, rel=0.2)
    late = [s.error_px for s in steps if s.t_s >= 5.0]
    assert math.sqrt(sum(e * e for e in late) / len(late)) < 1.5
    assert max(abs(s.pan_deg) for s in steps) < 10.0


@pytest.mark.parametrize("seed,fault", [(57, Fault.SLAVE_FROZEN), (58, Fault.SLAVE_FROZEN)])
def test_naming_a_camera_late_during_its_fault_clears_the_fault_at_once(caplog, seed, fault):
    """Draws of their own: a still scene at 0.7 m, 30 Hz, the images 66 ms older than the loop is told, the slave 3
    deg off. The first moves name a fault (frozen; on seed 58 it was named reversed before 2026-12-05, advising to
    flip a good camera's direction: its late image of the first correction's overshoot read as a turn against the
    motor, which the motor's own turn 66 ms earlier explains, Lag.unless_late); the lag fitted to the fault's
    moves names the camera late (within 20 %) during the fault, and that says its image follows: the fault is
    cleared in that frame, with a line that says why (it held to its next probe before), and none follows; from
    0.5 s after, within 0.5 px (0.2)."""
    rig = MovingRig.from_options(motion="still:z=0.7", focal="500", seed=str(seed), noise="1")
    rig.start_pan_rad = rig.truth_pan(0.0) + math.radians(3.0)
    with caplog.at_level(logging.WARNING, logger="vergence.doubt"):
        steps = list(closed_loop(rig, 240, None, ControlSettings(), None, 30.0, timing=CameraTiming(0.066),
                                 faults=Faults.take(parse("late=0.066", FAULT_KEYS, "test")), seed=seed))
    k = next(i for i, s in enumerate(steps) if s.late_ms is not None)
    assert steps[k - 1].fault == fault and steps[k].fault is None
    assert steps[k].late_ms == pytest.approx(66, rel=0.2)
    assert not any(s.fault for s in steps[k:])
    assert f"fault {fault} cleared (its image follows the motor" in caplog.text
    assert all(abs(s.camera_error_px) <= 0.5 for s in steps if s.t_s >= steps[k].t_s + 0.5)


def test_a_turn_against_the_motor_that_its_own_earlier_turn_explains_is_not_named_reversed():
    """Lag.unless_late: a pair whose image went against the motor is "reversed" only where no lag up to MAX_LAG_S
    explains it as following. The motor turned +1 deg over 0-50 ms and back -1 deg over 100-150 ms; an image that
    moved +1 deg between 100 and 200 ms shows the first turn 100 ms late: a late camera's pair ("frozen", held and
    fitted), not a reversed one. From rest, a first turn of +1 deg at 100-150 ms that the image shows as -1 deg has
    nothing earlier to explain it: reversed. A "frozen" kind passes as it is."""
    late, first = Lag(), Lag()
    for k in range(41):  # 5 ms apart, 0..200 ms
        t = k * 0.005
        late.motor(t, DEG * (min(t, 0.05) / 0.05 - min(max(t - 0.1, 0.0), 0.05) / 0.05))
        first.motor(t, DEG * min(max(t - 0.1, 0.0), 0.05) / 0.05)
    assert late.unless_late("reversed", 0.1, 0.2, 1.0 * DEG) == "frozen"
    assert first.unless_late("reversed", 0.1, 0.2, -1.0 * DEG) == "reversed"
    assert late.unless_late("frozen", 0.1, 0.2, 0.0) == "frozen"
    assert late.unless_late("reversed", 0.1, 0.2, 3.0 * DEG) == "reversed"  # r 3: no lag makes it follow


def test_a_probe_that_follows_late_is_fitted_and_two_that_agree_name_the_camera_late():
    """By hand, at 60 Hz: the image shows each probe 0.1 s after the frames' pans do. The first fit is noted, the
    second names the camera late (0.1 s, within the frames' sampling); the status and the note say it; a frame is
    then taken 0.1 s earlier, at the pan then."""
    d = Doubt()
    pans = []

    def frame(k, pan_deg, seen_pan_deg):
        t, pan = k * DT, pan_deg * DEG
        pans.append(pan)
        t, pan = d.shift(t, pan)
        d.observe(t, pan, (2.0 - seen_pan_deg) * DEG, k + 1, None, (320, 240))  # the target at 2 deg

    k = 0
    for _ in range(2):
        d.fault, d.anchor, d.t_probe, d.returned, d.ref = Fault.SLAVE_FROZEN, 0.0, k * DT, k * DT, None
        for i in range(40):  # at the anchor, then a probe of 0.5 deg at frame 10, seen 6 frames (0.1 s) later
            frame(k, 0.5 if i >= 10 else 0.0, 0.5 if i >= 16 else 0.0)
            k += 1
        assert d.fault is None
        for _ in range(10):  # back at the anchor (the fit was due 0.1 s after the probe cleared the fault)
            frame(k, 0.0, 0.0)
            k += 1
    assert d.lag.late_s == pytest.approx(0.1, abs=DT / 2)
    assert d.status()["late_ms"] == pytest.approx(100, abs=10) and "camera late" in d.note
    t, pan = d.shift(k * DT, 0.7 * DEG)
    assert t == pytest.approx(k * DT - d.lag.late_s) and pan == pytest.approx(0.0, abs=1e-9)
    assert type(pan) is float and type(d.status()["late_ms"]) is float  # (messages encode no numpy scalar)


def test_a_late_camera_is_read_against_the_motors_own_reports_not_the_frames_pans():
    """The motor reports its pan at 250 Hz through a 3 deg move of 60 ms (a cosine); the frames (30 Hz) carry pans
    told at their exposure that a late camera's capture guessed 1 deg off. Once the motor has reported, its reports
    are the pans kept, in time order whatever order they came in, and the frames' are not: a camera named 80 ms late
    is read at the pan the motor reported then (within 0.01 deg mid-move, its uncertainty half a report's step, 0.15
    deg, where the frames' pans read between frames are off by up to 1 deg and uncertain by 1.5), and a move's lag
    is fitted on them to the step (80 ms)."""
    def pan(t):
        return 0.0 if t < 0.3 else -3 * DEG if t > 0.36 else -1.5 * DEG * (1 - math.cos(math.pi * (t - 0.3) / 0.06))

    lag, k = Lag(), 0
    for i in range(20):
        t = i / 30
        reports = []
        while k * 0.004 <= t:
            reports.append(k * 0.004)
            k += 1
        for tr in reversed(reports):  # (newest first: kept in time order all the same)
            lag.motor(tr, pan(tr))
        lag.shift(t, pan(t) + 1.0 * DEG)  # a frame's pan, guessed 1 deg off: not kept
        lag.saw(t, -pan(t - 0.08))
    assert [p for _, p in lag.pans] == [pan(q) for q, _ in lag.pans] and [q for q, _ in lag.pans] == sorted(
        q for q, _ in lag.pans)
    assert lag.fit(7 / 30, -pan(7 / 30 - 0.08)) == pytest.approx(0.08, abs=0.003)
    lag.late_s = 0.08
    t = 0.413  # its image shows the motor at 0.333 s, mid-move
    ts, p, u = lag.shift(t, pan(t))
    assert ts == pytest.approx(0.333) and math.degrees(abs(p - pan(0.333))) < 0.01 and u < 0.2 * DEG  # (a report apart)


@pytest.mark.parametrize("motion,latency,rate_hz,seed", [("sine:z=0.6,amp=0.25,hz=0.4", 0.1, 45.0, 4612),
                                                          ("sine:z=0.7,amp=0.3,hz=0.3", 0.1, 60.0, 4701),
                                                          ("sine:z=0.77,amp=0.35,hz=0.92", 0.02, 60.0, 4728)])
def test_a_head_started_on_its_target_is_trusted_by_its_leashs_probe_at_a_turn(motion, latency, rate_hz, seed):
    """A sine whose near turn is 3.6-4 deg from where the slave starts, on the target: pursuit makes no decisive pair,
    so the untrusted leash holds the slave UNTRUSTED_DEG about its start at the turn, and probes back there. Read at
    the learnt rate, which a turning target outruns, the probe did not follow, the head was never trusted and every
    near turn ran 10-13 px off (draws of session 47: 12.9 px; the second draw named a false fault at its second turn,
    16.7 px). Read less the target's motion as its offsets at rest before the probe show it, the probe follows. The
    third turns back within BOUND_S (0.15 s past the leash at 0.92 Hz): no probe was sent and every near turn ran 6.5
    px off; the controller's own move back from the leash's end is now read as the probe. No fault, and from the
    second turn on within 3.5 px (1.5, 2.8 and 1.1)."""
    rig = MovingRig.from_options(motion=motion, focal="500", seed=str(seed), noise="1")
    rig.start_pan_rad = rig.truth_pan(0.0)
    steps = list(closed_loop(rig, int(7 * rate_hz), None, ControlSettings(), None, rate_hz, seed=seed,
                             focal_px=500.0, timing=CameraTiming(latency)))
    assert not [s for s in steps if s.fault]
    assert min(s.truth_pan_deg for s in steps) < math.degrees(rig.start_pan_rad) - UNTRUSTED_DEG - 0.5
    assert max(abs(s.camera_error_px) for s in steps if s.t_s >= 3.5) <= 3.5


@pytest.mark.parametrize("motion,seed", [("sine:z=0.66,amp=0.36,hz=1.07", 4732),
                                         ("sine:z=0.52,amp=0.22,hz=1.14", 4713)])
def test_a_target_turning_fast_near_the_head_names_nothing(motion, seed):
    """Sines that come within 0.3 m at over 1 Hz (35 deg/s of vergence, 600 deg/s^2 at the near turn), 100 ms late,
    60 Hz (draws of session 48). Their rate went past TARGET_RATE_DEG_S (30: a jump, the rates zeroed), and the pair
    after, the motor pursuing at 35 deg/s, was judged against a still target: the first named `slave_frozen` at 4.35
    s (43.6 px off). And the learnt rate lags such a target (5 deg/s where it moves at 35), so the fast pairs at its
    turns read r 0.6-1.4 where the image followed (the truth's r 0.95-1.1): both named the focal length off (1.21,
    then 0.74 x: the median of six spread over 0.58-1.40) and the loop ran on it, 14.5 and 2.2 px off at most. The
    pairs name it only where the middle half of them agree (focal_true's span 0.004-0.1 of their median). No fault,
    no focal length named, and from 2.5 s on within 2.5 px (1.7, 1.4)."""
    rig = MovingRig.from_options(motion=motion, focal="500", seed=str(seed), noise="1")
    rig.start_pan_rad = rig.truth_pan(0.0)
    steps = list(closed_loop(rig, int(5 * 60), None, ControlSettings(), None, 60.0, seed=seed, focal_px=500.0,
                             timing=CameraTiming(0.1)))
    assert not [s for s in steps if s.fault] and not [s for s in steps if s.focal_ratio is not None]
    assert max(abs(s.camera_error_px) for s in steps if s.t_s >= 2.5) <= 2.5  # (the predictor's start: 29-39 px)
