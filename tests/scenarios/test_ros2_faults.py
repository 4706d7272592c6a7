"""Issue #35 on a ROS 2 head, as its Why measured it: the test's own rclpy node plays a stereo camera whose slave
driver freezes (repeats its last image with fresh stamps, a common USB/V4L2 fault) while a look_at asks the head for
a move, or slips, or turns against its encoder from the start, or lags its joint by a second, and a joint that jams;
`vergence up --source ros2:LEFT,RIGHT --ros2` with the sim actuator (the jam: `--driver ros2` against a forward
command controller). The slave never runs off (before issue #35 it ran to its 45 degree limit in under a second and
stayed there), the reducer's status and /diagnostics name the fault at ERROR, and once the camera thaws the loop
finds the look_at point by itself."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

import rosnode
from procs import Procs, free_port, wait_for
from vergence.wire.messages import Decision, MotorState
from vergence.wire.status import decode_status

pytestmark = [pytest.mark.slow, pytest.mark.alone]  # (alone: tests/split.py)

F, CX = 256.0, 160


class Freezable:
    """render(pan) of a rig, whose slave image, while `frozen` is set, repeats byte for byte ("freeze": the master goes
    on) or is rendered at the pan it had when it was set, with fresh noise ("slip": the coupling slips, the encoder
    moves, the camera does not)."""

    def __init__(self, rig, lie: str = "freeze"):
        self.rig, self.lie, self.frozen, self.last, self.held = rig, lie, threading.Event(), None, None

    def __call__(self, pan: float):
        if not self.frozen.is_set():
            self.held = pan
        master, slave = self.rig.render(pan if self.lie == "freeze" else self.held, 0.0)
        if self.lie == "freeze" and self.frozen.is_set() and self.last is not None:
            return master, self.last
        self.last = slave
        return master, slave


HEAR_S = 0.15  # the test's camera waits this long at most for the joint state of its exposure


def _joint_pan_at(t, P, behind_ns: int = 0):
    """The slave's pan behind_ns before t_ns, from the rig's /vergence/<rig>/joint_states as the test's node heard
    them (interpolated between two; before the first heard, None, or with behind_ns the first). A camera on the shaft
    sees where the shaft is: so it waits (up to HEAR_S) for a state stamped at or after that instant, else a loaded
    machine's late joint states had it render the pan of tens of ms before (a reversed camera's image then moved
    half the motor's turn, r -0.5, and was named slave_frozen in a CI run)."""
    from sensor_msgs.msg import JointState
    from vergence.ros2.convert import pan_at as interpolate

    joints = t.collect(JointState, f"/vergence/{P.rig}/joint_states")

    def stamp(m) -> int:
        return m.header.stamp.sec * 10**9 + m.header.stamp.nanosec

    def pan_at(t_ns: int) -> float | None:
        with t.cond:
            t.cond.wait_for(lambda: joints and stamp(joints[-1][1]) >= t_ns - behind_ns, HEAR_S)
            states = [(stamp(m), m.position[0]) for _, m in joints[-99:]]
        t_ns -= behind_ns
        if not states or (t_ns < states[0][0] and not behind_ns):
            return None
        return interpolate(states, max(t_ns, states[0][0]), 0.0)

    return pan_at


def _up(P, cam, *more: str):
    """`vergence up` on the test's camera, bridged to ROS 2 (the sim actuator unless `more` says another driver): a
    session of the test's on its router."""
    P.start("up", "up", "--listen", P.endpoint, "--source", f"ros2:{cam.LEFT},{cam.RIGHT}:wait=60", "--ros2",
            "--workers", "2", "--rate", "0", "--no-standby", *more, connect=False)
    return P.session(60)


def _on_the_target(P, s, rig, ctl):
    """Wait for the forward controller's joint within 1 px of the target, a decision in, and then 1 s more: the
    decisions' collector."""
    decisions = P.collect(s, P.key("decision"))
    wait_for(lambda: abs(rig.error_px(ctl.position())) <= 1.0 and len(decisions.snapshot()) > 0, 90,
             "converged on the target", logs=P.logs)
    t_conv = time.time_ns()
    wait_for(lambda: time.time_ns() - t_conv >= 1e9, 5, "1 s on the target", interval=0.05)
    return decisions


@pytest.mark.parametrize("lie,look_px,finds", [("freeze", (40, 120), True), ("freeze", (88, 150), False),
                                              ("slip", (40, 120), True)], ids=["background", "edge", "slip"])
def test_a_frozen_ros2_slave_camera_while_look_at_asks_a_move_is_named_held_and_found_again(tmp_path, monkeypatch,
                                                                                            lie, look_px, finds):
    """A still target 0.3 m wide 0.55 m ahead (its own texture, seed 7; master columns 90-230, rows 50-190) before a
    background 2.5 m away, f 256 px, sensor noise 1.5; 1 s after converging on the target, the slave camera freezes
    and a look_at asks for a background point 5.2 deg of pan away (22 px): well off the target, or 2 px off its
    edge, where the fovea's window holds both and the network abstains. The Must of issue #35 for a frozen slave:
    named `slave_frozen` within 0.5 s, at ERROR on /diagnostics; the slave never past the pan the last consistent
    decision asked for (the look_at point's: the frozen image's first decision there is true), never near a limit;
    the fault cleared no later than 2 s after the 2 s freeze ends (at the edge by the probes' background: the fovea
    decides nothing there) and, off the edge, converged on the look_at point (five converged decisions in a row, the
    slave within 1 px of its truth) by then. The edge point is occluded in the slave's view (the near target hides
    the 22 px left of its edge there): nothing can find it; the search sweeps once and goes back to the pan it last
    converged at, and rests there (before, it swept +-41 deg for as long as the look_at lasted). "slip": the same
    Must with the coupling slipping instead (the slave rendered at the pan it had when the slip began, with fresh
    noise: no repeated bytes to tell it)."""
    rosnode.require()
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from geometry_msgs.msg import PointStamped
    from vergence.sim.moving import Head, MovingRig

    domain = rosnode.ros_env(monkeypatch)
    rig = MovingRig("still:z=0.55", Head(0.06, F, (320, 240)), target_m=0.3, bg_m=2.5, noise=1.5, seed=7)
    truth_look = rig.truth_at(*look_px)
    with Procs(tmp_path) as P, rosnode.TestNode(domain) as t:
        P.endpoint = f"tcp/127.0.0.1:{free_port()}"
        diags = t.collect(DiagnosticArray, "/diagnostics")
        render = Freezable(rig, lie)
        cam = rosnode.StereoCamera(t, render, _joint_pan_at(t, P), F, hz=30.0)
        try:
            s = _up(P, cam)
            states = P.collect(s, P.key("motor_state"))
            statuses = P.collect(s, P.key("status/reducer/*"))
            decisions = P.collect(s, P.key("decision"))

            def pans(after_ns: int = 0) -> list[tuple[int, float]]:
                return [(m.t_ns, m.pan_rad) for _, b, _ in states.snapshot()
                        if (m := MotorState.from_bytes(b)).t_ns >= after_ns]

            def faults(after_ns: int = 0) -> list[tuple[int, object]]:
                return [(a, decode_status(b).fault()) for a, b, _ in statuses.snapshot() if a >= after_ns]

            def settled() -> bool:
                """Within 1 px of the target, and no fault in the reducer's statuses of the last second: on a loaded
                machine the test's camera node can render its first frames at joint states that reached it late,
                which the check rightly names (a slave image that does not follow the motor) and clears by itself."""
                fs, now = faults(), time.time_ns()
                old = [k for k, (a, _) in enumerate(fs) if a <= now - 1e9]
                return bool(pans() and abs(rig.error_px(pans()[-1][1])) <= 1.0 and old
                            and all(f is None for _, f in fs[old[-1]:]))

            decisions.wait(1, 90)
            wait_for(settled, 30, "converged on the target, no fault for 1 s", logs=P.logs)
            t_conv = time.time_ns()
            wait_for(lambda: time.time_ns() - t_conv >= 1e9, 5, "1 s on the target", interval=0.05)
            limits = MotorState.from_bytes(states.snapshot()[-1][1])
            limit = min(-limits.min_rad, limits.max_rad)
            look = t.publisher(PointStamped, f"/vergence/{P.rig}/look_at", logs=P.logs)
            z = rig.bg_m
            target = PointStamped()
            target.header.frame_id = "left_optical_frame"
            target.point.x, target.point.y, target.point.z = (look_px[0] - CX) * z / F, (look_px[1] - 120) * z / F, z
            render.frozen.set()
            t_freeze = time.time_ns()
            look.publish(target)
            named = wait_for(lambda: next((a for a, f in faults(t_freeze) if f and f[0] == "slave_frozen"), None), 5,
                             "slave_frozen named", logs=P.logs)
            t.wait_until(lambda: next((d for _, arr in diags for d in arr.status if d.level == DiagnosticStatus.ERROR
                                       and "slave_frozen" in d.message), None), 10, "slave_frozen at ERROR", P.logs)
            wait_for(lambda: time.time_ns() - t_freeze >= 2e9, 5, "the 2 s freeze", interval=0.05)
            render.frozen.clear()
            t_thaw = time.time_ns()
            during = [p for _, p in pans(t_freeze)]
            tol = math.atan(1.0 / F)

            def cleared():
                return next((a for a, f in faults(t_thaw) if f is None), None)

            def found():
                """Five converged decisions in a row at the look_at point, the slave within 1 px of its truth (not a
                search's sweep passing it): the first one's arrival."""
                ds = [(a, d) for a, b, _ in decisions.snapshot() if a > t_thaw
                      and ((d := Decision.from_bytes(b)).x, d.y) == look_px][-5:]
                ps = pans(t_thaw)
                return (len(ds) == 5 and all(d.converged for _, d in ds) and ps and cleared() is not None
                        and abs(ps[-1][1] - truth_look) <= tol and ds[0][0])

            def rests():
                """A point the slave cannot see: a sweep that went 10 deg or more from the target's pan (the last one
                converged at), then back there for 1.2 s (the search's rest, 2 s from its last stop): when it came
                back."""
                ps = pans(t_cleared)
                k = len(ps)
                while k and abs(ps[k - 1][1] - start) <= math.radians(0.5):
                    k -= 1
                swept = any(abs(p - start) > math.radians(10) for _, p in ps[:k])
                return swept and k < len(ps) and ps[-1][0] - ps[k][0] >= 1.2e9 and ps[k][0]

            start = rig.truth_pan_rad
            t_cleared = wait_for(cleared, 10, "the fault cleared after the thaw", logs=P.logs)
            t_found = wait_for(found, 10, "converged on the look_at point", logs=P.logs) if finds else None
            t_rest = None if finds else wait_for(rests, 20, "a sweep, then resting where it converged", logs=P.logs)
            if not finds:  # the status says the sweep found nothing (`vergence monitor` asks if the slave can see it)
                wait_for(lambda: any((decode_status(b).search() or 0) >= 1 for _, b, _ in statuses.snapshot()), 5,
                         "a status with an empty sweep", logs=P.logs)
                t.wait_until(lambda: next((d for _, arr in diags for d in arr.status if d.level == DiagnosticStatus.WARN
                                           and "found nothing: is the point visible to the slave" in d.message), None),
                             5, "the empty sweep at WARN on /diagnostics", P.logs)
        finally:
            cam.close()
    past = max((p - truth_look) * np.sign(truth_look - start) for p in during)
    print(f"\nnamed {(named - t_freeze) / 1e9:.2f} s after the freeze; pans during it "
          f"{math.degrees(min(during)):.2f} to {math.degrees(max(during)):.2f} deg (look_at truth "
          f"{math.degrees(truth_look):.2f}, the target's {math.degrees(start):.2f}): {math.degrees(past):.2f} deg "
          f"past; cleared {(t_cleared - t_thaw) / 1e9:.2f} s after the thaw"
          + ("" if t_found is None else f", converged there {(t_found - t_thaw) / 1e9:.2f} s after")
          + ("" if t_rest is None else f", back where it converged, swept, {(t_rest - t_thaw) / 1e9:.2f} s after"))
    assert (named - t_freeze) / 1e9 <= 0.5
    assert math.degrees(past) <= 2.0
    assert max(abs(p) for p in during) < limit - math.radians(5)
    assert (t_cleared - t_thaw) / 1e9 <= 2.0
    assert t_found is None or (t_found - t_thaw) / 1e9 <= 2.0


def _held_near_start(fault: str, got: list[tuple[int, float]], named: int, t_first: int) -> None:
    """What a head whose image never followed must do from its start pan (0), got its motor's (t_ns, pan): the fault
    named within 1 s of the first decision, the slave never past the untrusted leash (2.9 deg), and from 0.3 s after
    the naming on within a probe of its start (0.5 deg; each to the sim motor's tick)."""
    tick = 360 / 4096
    after = [p for ts, p in got if ts >= named + 300_000_000]
    print(f"\n{fault} named {(named - t_first) / 1e9:.2f} s after the first decision; the slave within "
          f"{math.degrees(max(abs(p) for _, p in got)):.2f} deg of its start, {math.degrees(max(map(abs, after))):.2f}"
          f" deg from 0.3 s after ({len(after)} states)")
    assert (named - t_first) / 1e9 <= 1.0
    assert max(abs(p) for _, p in got) <= math.radians(2.9 + tick)
    assert after and max(map(abs, after)) <= math.radians(0.5 + tick)


def test_a_ros2_camera_turning_against_its_encoder_is_named_within_1_s_and_the_slave_stays_within_3_degrees(
        tmp_path, monkeypatch):
    """The issue's second Why: a camera that turns the other way than the encoder says (a motor wired or configured
    backwards), from the first frame. The test's camera node renders the slave at minus the pan its joint_states say
    (a target 0.35 m wide at 0.7 m before a background at 3 m, f 256 px, noise 1, seed 11: its own scene). Must:
    named `reversed` within 1 s of the first decision, at ERROR on /diagnostics, the note saying which setting to
    flip; |pan - start| never over 3 deg; after it, no command but back to the start pan and probes (within 0.5 deg
    of it). Before issue #35 such a head ran to its limit from the first frame."""
    rosnode.require()
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from vergence.sim.moving import Head, MovingRig

    domain = rosnode.ros_env(monkeypatch)
    rig = MovingRig("still:z=0.7", Head(0.06, F, (320, 240)), target_m=0.35, bg_m=3.0, noise=1.0, seed=11)
    with Procs(tmp_path) as P, rosnode.TestNode(domain) as t:
        P.endpoint = f"tcp/127.0.0.1:{free_port()}"
        diags = t.collect(DiagnosticArray, "/diagnostics")
        cam = rosnode.StereoCamera(t, lambda pan: rig.render(-pan, 0.0), _joint_pan_at(t, P), F, hz=30.0)
        try:
            s = _up(P, cam)
            states = P.collect(s, P.key("motor_state"))
            statuses = P.collect(s, P.key("status/reducer/*"))
            decisions = P.collect(s, P.key("decision"))

            def pans() -> list[tuple[int, float]]:
                return [(m.t_ns, m.pan_rad) for _, b, _ in states.snapshot() for m in [MotorState.from_bytes(b)]]

            t_first = decisions.wait(1, 90)[0][0]
            named, note = wait_for(lambda: next(((a, f[1]) for a, b, _ in statuses.snapshot()
                                                 if (f := decode_status(b).fault()) and f[0] == "reversed"), None),
                                   5, "reversed named", logs=P.logs)
            t.wait_until(lambda: next((d for _, arr in diags for d in arr.status if d.level == DiagnosticStatus.ERROR
                                       and "reversed" in d.message), None), 10, "reversed at ERROR", P.logs)
            wait_for(lambda: time.time_ns() - named >= 2.5e9, 5, "2.5 s more", interval=0.05)  # two probes at least
            got = pans()
        finally:
            cam.close()
    _held_near_start("reversed", got, named, t_first)
    assert "flip [actuator.motor] direction" in note


def test_a_ros2_slave_camera_a_second_behind_its_joint_is_held_not_chased(tmp_path, monkeypatch):
    """The issue's third Why, seen by accident: the camera node's slave images lagged the joint by a second (rendered
    at the pan the joint had 1 s before each exposure), and 18 commands took the slave from 0 to -45 deg in 0.6 s,
    every decision reading the same offset. Must: named within 1 s of the first decision (`slave_frozen`: a lag that
    long is past the lags vergence.head.lag fits, 0.25 s, so it is not named late), the slave never past the
    untrusted leash (2.9 deg) and, 0.3 s after the naming on, only back at its start and probing (within 0.5 deg),
    for 5 s."""
    rosnode.require()
    from vergence.sim.moving import Head, MovingRig

    domain = rosnode.ros_env(monkeypatch)
    rig = MovingRig("still:z=0.7", Head(0.06, F, (320, 240)), target_m=0.35, bg_m=3.0, noise=1.0, seed=11)
    with Procs(tmp_path) as P, rosnode.TestNode(domain) as t:
        P.endpoint = f"tcp/127.0.0.1:{free_port()}"
        cam = rosnode.StereoCamera(t, lambda pan: rig.render(pan, 0.0), _joint_pan_at(t, P, 10**9), F, hz=30.0)
        try:
            s = _up(P, cam)
            states = P.collect(s, P.key("motor_state"))
            statuses = P.collect(s, P.key("status/reducer/*"))
            t_first = P.collect(s, P.key("decision")).wait(1, 90)[0][0]
            named = wait_for(lambda: next((a for a, b, _ in statuses.snapshot()
                                           if (f := decode_status(b).fault()) and f[0] == "slave_frozen"), None),
                             5, "slave_frozen named", logs=P.logs)
            wait_for(lambda: time.time_ns() - t_first >= 5e9, 10, "5 s", interval=0.1)
            got = [(m.t_ns, m.pan_rad) for _, b, _ in states.snapshot() for m in [MotorState.from_bytes(b)]]
            last = decode_status(statuses.snapshot()[-1][1]).fault()
        finally:
            cam.close()
    _held_near_start("slave_frozen", got, named, t_first)
    assert last is not None and last[0] == "slave_frozen"  # held, not chased
    assert "images more than 0.25 s later than their stamps" in last[1]  # what to check names this case too


def test_a_jammed_ros2_joint_is_named_stalled_within_1_s_probed_and_resumed(tmp_path, monkeypatch):
    """A stall through the ROS 2 driver: `--driver ros2` against the test's forward command controller (its joint
    heads for each command at 170 deg/s and says where it is on /joint_states, truthfully). Converged on the target of
    the first test's scene, the joint jams (speed 0) and a fixate asks for the background point 5.2 deg away. Must:
    named `stalled` within 1 s; from then on the commands the joint receives are probes, within 0.5 deg of where it
    stands and at most about one a second; 3 s later the joint is freed: a probe moves it, the fault clears by itself
    and the loop converges on the point (five converged decisions there within 3 s)."""
    rosnode.require()
    from vergence.sim.moving import Head, MovingRig
    from vergence.wire.messages import Fixate

    domain = rosnode.ros_env(monkeypatch)
    rig = MovingRig("still:z=0.55", Head(0.06, F, (320, 240)), target_m=0.3, bg_m=2.5, noise=1.5, seed=7)
    look_px = (40, 120)
    with Procs(tmp_path) as P, rosnode.TestNode(domain) as t:
        P.endpoint = f"tcp/127.0.0.1:{free_port()}"
        ctl = rosnode.ForwardController(t)
        cam = rosnode.StereoCamera(t, lambda p: rig.render(p, 0.0), ctl.pan_at, F, hz=30.0)
        try:
            s = _up(P, cam, "--driver", "ros2", "--port", "forward_position_controller:joint=slave_pan")
            statuses = P.collect(s, P.key("status/reducer/*"))
            decisions = _on_the_target(P, s, rig, ctl)
            stand = ctl.position()
            ctl.speed = 0.0  # jammed: its joint states still say where it is
            t_jam = time.time_ns()
            s.put(P.key("fixate"), Fixate(x=look_px[0], y=look_px[1], t_ns=t_jam).to_bytes())

            def faults(after_ns: int) -> list[tuple[int, object]]:
                return [(a, decode_status(b).fault()) for a, b, _ in statuses.snapshot() if a >= after_ns]

            named = wait_for(lambda: next((a for a, f in faults(t_jam) if f and f[0] == "stalled"), None), 5,
                             "stalled named", logs=P.logs)
            wait_for(lambda: time.time_ns() - t_jam >= 3e9, 5, "3 s jammed", interval=0.05)
            held = [(ts, g) for ts, g in ctl.commands if ts >= named]
            ctl.speed = 3.0
            t_free = time.time_ns()
            wait_for(lambda: any(f is None for _, f in faults(t_free)), 5, "the fault cleared", logs=P.logs)
            wait_for(lambda: sum(d.converged for a, b, _ in decisions.snapshot() if a > t_free
                                 and ((d := Decision.from_bytes(b)).x, d.y) == look_px) >= 5, 5,
                     "converged on the point", logs=P.logs)
            t_found = time.time_ns()
        finally:
            cam.close()
            ctl.close()
    probes = [g for _, g in held]
    moves = [ts for (ts, g), (_, g0) in zip(held[1:], held) if g != g0]
    print(f"\nstalled named {(named - t_jam) / 1e9:.2f} s after the jam; {len(held)} commands held, "
          f"{math.degrees(max(abs(g - stand) for g in probes)):.2f} deg from where it stood at most, "
          f"{len(moves)} changes of goal in {(t_free - named) / 1e9:.1f} s; converged there "
          f"{(t_found - t_free) / 1e9:.2f} s after it was freed")
    assert (named - t_jam) / 1e9 <= 1.0
    assert probes and max(abs(g - stand) for g in probes) <= math.radians(0.5 + 360 / 4096)
    assert len(moves) <= 2 * (t_free - named) / 1e9 + 1  # a probe and its return, about one a second


def test_a_noisy_ros2_joint_raises_no_fault_and_stays_on_the_target(tmp_path, monkeypatch):
    """A joint whose /joint_states carry 0.1 deg of noise (a noisy encoder: 0.45 px at f 256, twice the issue's 0.05
    deg; the joint and the camera are where they are), `--driver ros2` against the test's forward command
    controller, the first test's still target: the reducer names no fault, and over the 3 s after the first second
    converged the joint stays within 2 px of the truth (a frame right after a command has one reading, 0.45 px of
    noise, and the decision's own; 2 px is over 3.5 of their joint sigma). Measured: 0.11-1.25 px (2026-12-06, 14
    runs), 0.01-1.20 (2026-12-07, 10 runs), 0.30-1.21 with two busy processes beside (8 runs), 1.57 once in CI;
    the commands in those 3 s 1-9 (the reducer taking a resting motor's pan as the mean of its readings,
    vergence.head.rest), 11-20 with each frame's one reading (rest bypassed, 3 runs, 0.48-0.64 px): fewer, but the
    motor states at 50 Hz leave the frames right after a command on single readings, so the counts overlap too much
    to assert."""
    rosnode.require()
    from vergence.sim.moving import Head, MovingRig

    domain = rosnode.ros_env(monkeypatch)
    rig = MovingRig("still:z=0.55", Head(0.06, F, (320, 240)), target_m=0.3, bg_m=2.5, noise=1.5, seed=7)
    with Procs(tmp_path) as P, rosnode.TestNode(domain) as t:
        P.endpoint = f"tcp/127.0.0.1:{free_port()}"
        ctl = rosnode.ForwardController(t, noise=math.radians(0.1))
        cam = rosnode.StereoCamera(t, lambda p: rig.render(p, 0.0), ctl.pan_at, F, hz=30.0)
        try:
            s = _up(P, cam, "--driver", "ros2", "--port", "forward_position_controller:joint=slave_pan")
            statuses = P.collect(s, P.key("status/reducer/*"))
            _on_the_target(P, s, rig, ctl)
            t0 = time.time_ns()
            errors = []
            wait_for(lambda: errors.append(abs(rig.error_px(ctl.position()))) or time.time_ns() - t0 >= 3e9, 5,
                     "3 s on the target", interval=0.05)
            sent = [g for ts, g in ctl.commands if ts >= t0]
            faults = [f for _, b, _ in statuses.snapshot() if (f := decode_status(b).fault())]
        finally:
            cam.close()
            ctl.close()
    print(f"\n{len(sent)} commands in the 3 s after the first second on the target; the joint at most "
          f"{max(errors):.2f} px off the truth; {len(statuses.snapshot())} statuses, faults {faults}")
    assert statuses.snapshot() and not faults
    assert max(errors) <= 2.0
