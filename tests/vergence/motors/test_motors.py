"""Motor layer without serial ports: settings, the safety layer (property-based), the simulated motor, and
the actuator loop (MotorLoop) with a fake clock."""

from __future__ import annotations

import math
import re

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vergence.config import ConfigError, from_dict
from vergence.wire.messages import MotorState
from vergence.motors import Disconnected, MotorSettings, NoAnswer, PortError, Safety, TransientError, make_driver
from vergence.motors.base import Driver
from vergence.motors.runner import MotorLoop
from vergence.motors.simulated import SimMotor

from samples import cmd

DEG = math.pi / 180


class Clock:
    def __init__(self, t: float = 100.0):
        self.t = t

    def __call__(self) -> float:
        return self.t


# -- settings ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("pan, ticks", [(0.0, 2048), (math.pi / 2, 3072), (-math.pi / 2, 1024),
                                        (0.001, 2049), (0.0007, 2048), (math.radians(45), 2560),
                                        (math.radians(-45), 1536)])
def test_ticks_default(pan, ticks):
    m = MotorSettings()
    assert m.to_ticks(pan) == ticks == round(2048 + pan * 4096 / (2 * math.pi))


def test_whole_ticks_are_where_the_motor_stops_and_none_without_quantise():
    m, tick = MotorSettings(), 2 * math.pi / 4096
    assert m.tick_rad == tick and m.whole_ticks(2.4 * tick) == 2 * tick and m.whole_ticks(-2.6 * tick) == -3 * tick
    assert m.whole_ticks(0.3) == pytest.approx(m.from_ticks(m.to_ticks(0.3)), abs=1e-12)  # (a Dynamixel's goal)
    assert m.whole_ticks(0.3) == pytest.approx(0.3, abs=tick / 2)
    free = MotorSettings(quantise=False)
    assert free.tick_rad == 0.0 and free.whole_ticks(0.3) == 0.3


def test_ticks_zero_and_a_direction_every_driver_honours():
    """to_ticks takes the motor's own angle; MotorLoop gives every driver direction x pan (issue #35), so a
    Dynamixel's Goal Position for pan +90 deg with direction -1 and zero 1000 of 2000 is 500, as before, and the
    simulated motor's shaft turns the other way while the pans reported are the commanded ones."""
    m = MotorSettings(direction=-1, zero=1000, ticks_per_rev=2000)
    assert m.to_ticks(-math.pi / 2) == 500 and m.to_ticks(math.pi / 2) == 1500
    assert m.from_ticks(500) == pytest.approx(-math.pi / 2)
    clock = Clock()
    ms = MotorSettings(direction=-1, start_deg=3.0, tau_s=0.05, max_speed_deg_s=1000, max_step_deg=90, **IDEAL)
    motor = SimMotor(ms, clock=clock)
    loop = MotorLoop(motor, ms, clock=clock, wall_ns=lambda: 7)
    assert loop.start().pan_rad == pytest.approx(3 * DEG) and motor.shaft == pytest.approx(-3 * DEG)
    loop.command(cmd(0.05))
    assert motor.goal == pytest.approx(-0.05)
    clock.t += 0.5
    assert loop.tick().pan_rad == pytest.approx(0.05, abs=1e-4) and motor.shaft == pytest.approx(-0.05, abs=1e-4)
    loop.command(cmd(math.radians(60)))  # past max_deg 45: clamped in the pan's terms, then turned
    clock.t += 0.5
    assert loop.tick().pan_rad == pytest.approx(math.radians(45), abs=1e-3)
    assert motor.shaft == pytest.approx(-math.radians(45), abs=1e-3)


def test_an_offset_every_driver_honours():
    """[actuator.motor] offset_deg (issue #36, `vergence calibrate` writes it): the pans the loop commands and
    reports are the motor's angle (times direction) plus the offset; the limits are the pan's."""
    m = MotorSettings(direction=-1, offset_deg=0.3)
    assert m.to_motor(math.radians(1.0)) == pytest.approx(-math.radians(0.7))
    assert m.from_motor(-math.radians(0.7)) == pytest.approx(math.radians(1.0))
    clock = Clock()
    ms = MotorSettings(direction=-1, offset_deg=-1.5, start_deg=2.0, tau_s=0.05, max_speed_deg_s=1000,
                       max_step_deg=90, **IDEAL)
    motor = SimMotor(ms, clock=clock)
    loop = MotorLoop(motor, ms, clock=clock, wall_ns=lambda: 7)
    st = loop.start()
    assert st.pan_rad == pytest.approx(2 * DEG) and motor.shaft == pytest.approx(-3.5 * DEG) and st.offset_deg == -1.5
    loop.command(cmd(0.05))
    assert motor.goal == pytest.approx(-(0.05 + 1.5 * DEG))
    clock.t += 0.5
    assert loop.tick().pan_rad == pytest.approx(0.05, abs=1e-4)
    loop.command(cmd(math.radians(-60)))  # past min_deg -45: clamped in the pan's terms, then offset and turned
    clock.t += 0.5
    assert loop.tick().pan_rad == pytest.approx(-math.radians(45), abs=1e-3)
    assert motor.shaft == pytest.approx(math.radians(43.5), abs=1e-3)
    with pytest.raises(ConfigError, match="offset_deg"):
        from_dict({"actuator": {"motor": {"offset_deg": 31}}})


def test_config_motor_table_and_errors():
    s = from_dict({"actuator": {"driver": "dynamixel", "port": "loop://",
                                "motor": {"id": 7, "min_deg": -20, "max_step_deg": 2.5}}})
    assert s.actuator.motor.id == 7 and s.actuator.motor.min_rad == pytest.approx(-20 * DEG)
    with pytest.raises(ConfigError, match="actuator.motor.speed"):
        from_dict({"actuator": {"motor": {"speed": 3}}})
    with pytest.raises(ConfigError, match="direction"):
        from_dict({"actuator": {"motor": {"direction": 2}}})
    with pytest.raises(ConfigError, match="min_deg"):
        from_dict({"actuator": {"motor": {"min_deg": 10, "max_deg": -10}}})


def test_make_driver_needs_port():
    with pytest.raises(PortError, match="list_ports"):
        make_driver("dynamixel", MotorSettings(), "")
    with pytest.raises(ValueError, match="unknown driver"):
        make_driver("stepper", MotorSettings(), "x")


# -- safety --------------------------------------------------------------------------------------------------

def test_safety_clamps_and_ignores():
    s = Safety(MotorSettings(max_step_deg=10))
    assert s.command(5 * DEG).goal == pytest.approx(5 * DEG)
    v = s.command(1e9)
    assert v.clamped and v.goal == pytest.approx(15 * DEG)
    for bad in (math.nan, math.inf, -math.inf, "1", None, True):
        assert s.command(bad).goal is None
    assert (s.accepted, s.clamped, s.ignored) == (2, 1, 6)
    for _ in range(10):
        s.command(-1e300)
    assert s.goal == pytest.approx(-45 * DEG)


def test_safety_stale_frames():
    s = Safety(MotorSettings(max_age_s=0.5))
    assert s.command(0.01, frame=5, t_capture_ns=2_000_000_000, now_ns=2_100_000_000).goal is not None
    assert s.command(0.02, frame=4, t_capture_ns=1_900_000_000, now_ns=2_100_000_000).goal is None  # older
    assert s.command(0.02, frame=9, t_capture_ns=2_200_000_000, now_ns=2_800_000_000).goal is None  # too old
    assert s.command(0.03, frame=6, t_capture_ns=2_300_000_000, now_ns=2_400_000_000).goal == 0.03
    assert s.ignored == 2


def test_safety_dead_band():
    s = Safety(MotorSettings(dead_band_deg=0.5))
    assert s.command(0.3 * DEG).goal is None and s.held == 1 and s.ignored == 0
    assert s.command(0.6 * DEG).goal == pytest.approx(0.6 * DEG)


targets = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-10**400, 10**400),
                    st.sampled_from([math.nan, math.inf, -math.inf, 1e308, -1e308, 0.785, -0.786, 5e-324]))
motor_settings = st.builds(
    MotorSettings,
    min_deg=st.floats(-90, 0), max_deg=st.floats(0, 90),
    max_step_deg=st.floats(0.01, 30), dead_band_deg=st.floats(0, 1))


@settings(max_examples=300, deadline=None)
@given(motor_settings, st.floats(-10, 10), st.lists(st.tuples(targets, st.integers(-5, 2**40),
                                                               st.integers(-5, 2**62)), max_size=60))
def test_safety_property(ms, start, stream):
    """Whatever arrives, the goal stays inside the soft limits and never moves more than max_step."""
    s = Safety(ms, start)
    lo, hi, step = ms.min_rad, ms.max_rad, math.radians(ms.max_step_deg)
    assert lo <= s.goal <= hi
    prev = s.goal
    n = 0
    for pan, frame, t in stream:
        v = s.command(pan, frame, t, now_ns=2**62)
        n += 1
        assert lo <= s.goal <= hi
        assert abs(s.goal - prev) <= step * (1 + 1e-12)
        if v.goal is not None:
            assert v.goal == s.goal and math.isfinite(v.goal)
            assert v.goal == s.limit_step(prev, float(pan))  # the bound the reducer's controller asks for
        else:
            assert s.goal == prev
        prev = s.goal
    assert s.accepted + s.ignored + s.held == n
    assert s.clamped <= s.accepted


def test_safety_inside_and_limit_step_values():
    """The stateless bounds the controller asks for: inside the limits, then at most max_step from start."""
    s = Safety(MotorSettings(min_deg=-10, max_deg=20, max_step_deg=5, dead_band_deg=0.25))
    assert [s.inside(x * DEG) / DEG for x in (-30, 0, 15, 25)] == pytest.approx([-10, 0, 15, 20])
    assert s.limit_step(0.0, 3 * DEG) / DEG == pytest.approx(3)
    assert s.limit_step(0.0, 30 * DEG) / DEG == pytest.approx(5)
    assert s.limit_step(18 * DEG, 30 * DEG) / DEG == pytest.approx(20)
    assert s.limit_step(-8 * DEG, -90 * DEG) / DEG == pytest.approx(-10)
    assert s.limit_step(40 * DEG, 50 * DEG) / DEG == pytest.approx(20)  # from outside: to the nearest limit
    assert s.dead_band_rad == pytest.approx(0.25 * DEG) and s.goal == 0.0  # stateless: the goal is unmoved


@settings(max_examples=100, deadline=None)
@given(st.lists(st.one_of(targets.map(lambda p: ("cmd", p)), st.binary(max_size=40).map(lambda b: ("raw", b)),
                          st.floats(0, 5).map(lambda dt: ("wait", dt))), max_size=60))
def test_loop_property(stream):
    """The whole loop with the simulated motor: garbage, NaN, floods and pauses; goal and position stay in
    the limits, the goal never jumps more than max_step, every message is accounted for."""
    clock = Clock()
    ms = MotorSettings(max_step_deg=3, watchdog_s=1.0)
    loop = MotorLoop(SimMotor(ms, clock=clock), ms, clock=clock, wall_ns=lambda: int(clock.t * 1e9))
    loop.start()
    prev = loop.safety.goal
    frame = 0
    for kind, x in stream:
        if kind == "wait":
            clock.t += x
            st_ = loop.tick()
        elif kind == "raw":
            st_ = loop.command(x)
        else:
            frame += 1
            pan = x if isinstance(x, float) else 1e300 if x > 0 else -1e300 if x < 0 else 0.0
            st_ = loop.command(cmd(pan, frame=frame))
        assert isinstance(st_, MotorState)
        assert st_.min_rad <= st_.goal_rad <= st_.max_rad
        assert abs(st_.goal_rad - prev) <= 3 * DEG + 1e-12
        assert st_.min_rad - 1e-9 <= st_.pan_rad <= st_.max_rad + 1e-9
        prev = st_.goal_rad
    st_ = loop.state()
    assert st_.commands == sum(k != "wait" for k, _ in stream)
    assert st_.malformed + loop.safety.accepted + loop.safety.ignored + loop.safety.held == st_.commands


# -- simulated motor -----------------------------------------------------------------------------------------

IDEAL = dict(latency_s=0.0, max_accel_deg_s2=0.0, quantise=False)  # the servo's imperfections off


def test_sim_first_order_and_speed():
    clock = Clock()
    m = SimMotor(MotorSettings(tau_s=0.1, max_speed_deg_s=1000, **IDEAL), clock=clock)
    m.open()
    m.write_goal(0.1)
    clock.t += 0.1
    assert m.read_position() == pytest.approx(0.1 * (1 - math.exp(-1)))
    clock.t += 1.0
    assert m.read_position() == pytest.approx(0.1, abs=1e-5)
    m2 = SimMotor(MotorSettings(tau_s=0.0, max_speed_deg_s=90, **IDEAL), clock=clock)
    m2.open()
    m2.write_goal(math.radians(40))
    clock.t += 0.2
    assert m2.read_position() == pytest.approx(math.radians(18))
    clock.t += 1.0
    assert m2.read_position() == pytest.approx(math.radians(40))


def test_sim_integration_independent_of_polling():
    c1, c2 = Clock(), Clock()
    ms = MotorSettings(tau_s=0.05, max_speed_deg_s=60)
    a, b = SimMotor(ms, clock=c1), SimMotor(ms, clock=c2)
    for m in (a, b):
        m.open()
        m.write_goal(math.radians(30))
    for _ in range(100):
        c1.t += 0.003
        a.read_position()
    c2.t += 0.3
    assert a.read_position() == pytest.approx(b.read_position(), abs=1e-12)


# -- the loop ------------------------------------------------------------------------------------------------

def test_loop_tracks_commands_and_watchdog():
    clock = Clock()
    ms = MotorSettings(watchdog_s=0.5, tau_s=0.05, max_speed_deg_s=1000, **IDEAL)
    loop = MotorLoop(SimMotor(ms, clock=clock), ms, rig="r", clock=clock, wall_ns=lambda: 7)
    s0 = loop.start()
    assert s0.status == "ok" and s0.pan_rad == 0.0 and s0.driver == "sim"
    s1 = loop.command(cmd(0.05, frame=3, t=11).to_bytes())
    assert (s1.goal_rad, s1.frame, s1.t_capture_ns, s1.rig) == (0.05, 3, 11, "r")
    clock.t += 0.4
    s2 = loop.tick()
    assert s2.pan_rad == pytest.approx(0.05, abs=1e-4) and s2.status == "ok"
    loop.command(cmd(0.2, frame=4))
    clock.t += 0.01
    s3 = loop.tick()
    assert 0.05 < s3.pan_rad < 0.2
    clock.t += 0.6  # watchdog: hold where it is
    s4 = loop.tick()
    assert s4.status == "hold" and "watchdog" in s4.note
    assert s4.goal_rad == pytest.approx(s4.pan_rad, abs=1e-9)
    assert loop.command(cmd(0.1, frame=5)).status == "ok"
    s5 = loop.command(b"\x93\x01\x02")
    assert s5.malformed == 1 and s5.commands == 4
    assert loop.stop().status == "stopped"


class FlakyDriver(Driver):
    """A driver whose faults the test switches on and off."""

    name = "flaky"

    def __init__(self, ms, clock=None):
        super().__init__(ms)
        self.clock, self.tries = clock or (lambda: 0.0), []
        self.present, self.goals, self.mode, self.opens = 0.1, [], "ok", 0

    def open(self):
        self.tries.append(self.clock())
        if self.mode == "gone":
            raise PortError("no such port 'x'")
        if self.mode == "silent":
            raise NoAnswer("no answer from motor 1 (timeout: 0 of 7 bytes)")
        self.opens += 1
        return self.present

    def close(self, torque_off=True):
        pass

    def write_goal(self, pan):
        self._io()
        self.goals.append(pan)
        self.present = pan

    def read_position(self):
        self._io()
        return self.present

    def _io(self):
        if self.mode == "gone":
            raise Disconnected("port x vanished")
        if self.mode == "crc":
            self.errors += 3
            raise TransientError("bad CRC, 3 attempts")
        if self.mode == "silent":
            self.errors += 3
            raise NoAnswer("read failed 3 times: timeout: 0 of 7 bytes")


def test_loop_reconnects_with_backoff():
    clock = Clock()
    ms = MotorSettings(watchdog_s=0, absent_s=0)  # (absent_s: the test below)
    drv = FlakyDriver(ms, clock)
    loop = MotorLoop(drv, ms, clock=clock, backoff_s=(0.1, 0.4))
    assert loop.start().goal_rad == pytest.approx(0.1)  # goal starts at the present position
    drv.mode = "crc"
    s = loop.command(cmd(0.12, frame=1))
    assert s.status == "ok" and s.errors == 6 and "CRC" in s.note
    drv.mode = "gone"
    assert loop.tick().status == "disconnected"
    assert loop.command(cmd(0.2, frame=2)).ignored == 1
    drv.tries = []
    t_lost = clock.t
    for _ in range(40):
        clock.t += 0.05
        assert loop.tick().status == "disconnected"
    # first try 0.1 s after the loss, then 0.2, 0.4, 0.4 ... s apart (ticks every 0.05 s)
    gaps = [b - a for a, b in zip([t_lost] + drv.tries, drv.tries)][:5]
    for gap, want in zip(gaps, [0.1, 0.2, 0.4, 0.4, 0.4]):
        assert want - 1e-9 <= gap <= want + 0.05 + 1e-9
    drv.mode = "ok"
    clock.t += 0.5
    st_ = loop.tick()
    assert st_.status == "ok" and loop.reconnects == 1
    assert loop.command(cmd(0.15, frame=3)).goal_rad == pytest.approx(0.15)
    assert drv.goals[-1] == pytest.approx(0.15)


def test_loop_takes_a_silent_motor_for_lost_then_absent_and_resumes_holding(caplog):
    """Issue #29: a motor that answers nothing for silent_s is lost (nothing more written to it), absent after
    absent_s (an error logged, again every 30 s), and back by itself within the backoff's 1 s of answering,
    holding where it is until a new command."""
    import logging

    from vergence.motors import runner

    clock = Clock()
    ms = MotorSettings(watchdog_s=2.0, silent_s=0.5, absent_s=2.0)
    drv = FlakyDriver(ms, clock)
    loop = MotorLoop(drv, ms, clock=clock)
    loop.start()
    assert loop.command(cmd(0.12, frame=1)).status == "ok" and drv.goals == [pytest.approx(0.12)]
    drv.mode = "silent"
    clock.t += 0.2
    s = loop.command(cmd(0.13, frame=2))
    assert s.status == "ok" and "fault" in s.note  # 0.2 s of silence: a transient fault so far
    clock.t += 0.4
    with caplog.at_level(logging.INFO, logger="vergence.actuator"):
        s = loop.tick()
        assert s.status == "disconnected" and "no answer for 0.6 s" in s.note
        t_lost, frame, states = clock.t, 3, []
        while clock.t - t_lost < 40.0:  # commands at 10 Hz into the silence
            clock.t += 0.1
            states.append((clock.t - t_lost, loop.command(cmd(0.2, frame=frame)).status, loop.tick().status))
            frame += 1
    assert drv.goals == [pytest.approx(0.12)]  # nothing written while lost
    first_absent = min(t for t, a, b in states if b == "absent")
    assert 2.0 <= first_absent < 2.0 + 0.1 + 1e-9
    assert all(b == "disconnected" for t, a, b in states if t < first_absent)
    assert loop.state().ignored == len(states) and loop.state().status == "absent"
    errors = [r.getMessage() for r in caplog.records if r.levelno == logging.ERROR]
    assert len(errors) == 2 and re.match(r"motor absent for 2\.[01] s \(lost: no answer for 0\.6 s: read failed 3 "
                                         r"times: timeout: 0 of 7 bytes\); commands are ignored", errors[0]), errors
    assert errors[1].startswith("motor still absent after 32 s (lost: no answer")  # again ABSENT_REPEAT_S later
    assert runner.ABSENT_REPEAT_S == 30.0
    assert max(b - a for a, b in zip(drv.tries, drv.tries[1:])) <= 1.0 + 0.1 + 1e-9  # probed every 1 s at most
    drv.mode = "ok"
    drv.present = 0.05  # where it is when it answers again
    t_back = clock.t
    while loop.tick().status != "ok":
        clock.t += 0.05
        assert clock.t - t_back <= 1.1
    s = loop.state()
    assert s.goal_rad == pytest.approx(0.05) and loop.reconnects == 1  # holds where it is, no old target
    assert drv.goals == [pytest.approx(0.12)]
    assert loop.command(cmd(0.06, frame=frame)).goal_rad == pytest.approx(0.06)  # a new command moves it
    assert drv.goals[-1] == pytest.approx(0.06)


def test_loop_port_missing_at_start_is_fatal():
    ms = MotorSettings()
    drv = FlakyDriver(ms)
    drv.mode = "gone"
    with pytest.raises(PortError):
        MotorLoop(drv, ms).start()


def test_loop_brings_a_motor_found_outside_the_limits_back():
    ms = MotorSettings(watchdog_s=0)
    drv = FlakyDriver(ms)
    drv.present = math.radians(60)
    st_ = MotorLoop(drv, ms).start()
    assert st_.goal_rad == pytest.approx(math.radians(45)) and st_.at_limit
    assert drv.goals == [pytest.approx(math.radians(45))]


# -- the sim motor's replica (the capture's, for a source that renders the slave) -------------------------

WALL_NS = 1_764_000_000 * 10**9  # the states' wall clock: a real epoch (seconds there as floats lose 0.2 us)


def _drive(ms: MotorSettings, seconds: float, delay, seed: int = 0, period: float = 0.02):
    """The sim actuator (MotorLoop and SimMotor on one fake clock) under random commands every 3-12 ms and its
    periodic states, each state handed to a Replica `delay(i)` s after it was published (in order, as one
    Zenoh key keeps them). Yields (t, the true shaft as a pan (direction x it), the replica) every 0.25 ms."""
    import numpy as np

    from vergence.motors.simulated import Replica

    rng = np.random.default_rng(seed)
    clock = Clock(50.0)
    wall = lambda: WALL_NS + round(clock.t * 1e9)  # noqa: E731
    motor = SimMotor(ms, clock_ns=wall)
    loop = MotorLoop(motor, ms, clock=clock, wall_ns=wall)
    rep = Replica(ms)
    inbox: list[tuple[float, MotorState]] = []

    def publish(st):
        after = inbox[-1][0] if inbox else 0.0
        inbox.append((max(after, clock.t + delay(len(inbox))), st))

    publish(loop.start())
    next_cmd, next_tick, goal = clock.t + 0.1, clock.t, 0.0
    while clock.t < 50.0 + seconds:
        clock.t = round(clock.t + 0.00025, 9)
        if clock.t >= next_cmd:
            goal = float(np.clip(goal + rng.normal(0, 2) * DEG, -20 * DEG, 20 * DEG))
            publish(loop.command(cmd(goal, frame=int(clock.t * 1000))))
            next_cmd = clock.t + rng.uniform(0.003, 0.012)
        if clock.t >= next_tick:
            publish(loop.tick())
            next_tick += period
        while inbox and inbox[0][0] <= clock.t:
            st = inbox.pop(0)[1]
            rep.observe(st.t_ns, st.pan_rad, st.goal_rad, torque=st.status != "stopped")
        yield clock.t, ms.from_motor(motor.shaft), rep


@pytest.mark.parametrize("seed, direction, offset", [(1, 1, 0.0), (2, 1, 0.0), (3, -1, 0.0), (4, -1, 0.3137)])
def test_replica_is_within_a_tick_of_the_shaft_without_waiting_for_reports(seed, direction, offset):
    """States arrive 0.2-1.5 ms after they are published: the replica's shaft at every instant up to now (and
    30 ms back: a camera's latency) is the sim motor's (well within the issue's one encoder tick), and it is
    trusted from its first 20 ms on (two states on the goal at rest)."""
    import numpy as np

    # -1: the shaft turns the other way, the pans reported do not; offset: the pans reported are the shaft's plus it
    ms = MotorSettings(direction=direction, offset_deg=offset)
    rng = np.random.default_rng(seed + 100)
    errs, past, untrusted = [], [], 0
    history: list[tuple[float, float]] = []
    for t, shaft, rep in _drive(ms, 3.0, lambda i: rng.uniform(0.0002, 0.0015), seed=seed):
        history.append((t, shaft))
        if t < 50.05:
            continue
        got = rep.at(WALL_NS + round(t * 1e9))
        if got is None:
            untrusted += 1
            continue
        errs.append(abs(got - shaft))
        t_old, shaft_old = history[-121]  # 30 ms back
        if t_old >= 50.05:
            past.append(abs(rep.at(WALL_NS + round(t_old * 1e9)) - shaft_old))
    tick = 2 * math.pi / ms.ticks_per_rev
    assert untrusted == 0 and rep.mismatches == 0
    assert len(errs) > 10_000 and max(errs) <= tick, max(errs) / tick
    assert max(past) <= tick
    assert max(errs) <= 0.01 * tick  # the same grid, the same instants: exact but for rounding (one step off: 0.5)


def test_replica_puts_a_late_goal_in_its_place():
    """Every tenth state 6 ms late (after its goal took effect): the replica rewinds and stays within a tick
    from the moment the state arrives (before, it cannot know)."""
    import numpy as np

    ms = MotorSettings()
    late = 0.006
    errs = []
    for t, shaft, rep in _drive(ms, 2.0, lambda i: late if i % 10 == 5 else 0.0003, seed=3):
        if t < 50.05:
            continue
        # an instant the replica has been told everything about: before the latest goal known to be late
        got = rep.at(WALL_NS + round(t * 1e9))
        assert got is not None
        errs.append(abs(got - shaft))
    tick = 2 * math.pi / ms.ticks_per_rev
    assert rep.mismatches == 0
    assert np.percentile(errs, 99) <= tick


def test_replica_distrusts_other_settings_until_the_motor_rests():
    """A replica of a faster motor than the actuator's fails its check (counted), answers None, and is trusted
    again once the motor rests on a goal."""
    from vergence.motors.simulated import Replica

    ms = MotorSettings()
    clock = Clock(50.0)
    wall = lambda: WALL_NS + round(clock.t * 1e9)  # noqa: E731
    motor = SimMotor(ms, clock_ns=wall)
    loop = MotorLoop(motor, ms, clock=clock, wall_ns=wall)
    rep = Replica(MotorSettings(max_speed_deg_s=900, tau_s=0.002))

    def feed(st):
        rep.observe(st.t_ns, st.pan_rad, st.goal_rad)

    feed(loop.start())
    for _ in range(3):
        clock.t += 0.01
        feed(loop.tick())
    assert rep.trusted
    feed(loop.command(cmd(10 * DEG)))
    for _ in range(5):
        clock.t += 0.01
        feed(loop.tick())
    assert rep.mismatches >= 1 and not rep.trusted
    assert rep.at(wall()) is None
    for _ in range(30):
        clock.t += 0.01
        feed(loop.tick())
    assert rep.trusted
    now = wall()
    assert rep.at(now) == pytest.approx(motor.shaft, abs=2 * math.pi / ms.ticks_per_rev)


def test_replica_counts_the_commands_seen_against_the_motors_own_count():
    """A command seen is out until a state's `commands` counts it (the state may come first: it answers the next
    command seen); one that no state counts within ANSWER_NS is let go, counted in unheard; a count that went down
    is a restarted actuator's."""
    from vergence.motors.simulated import Replica

    rep = Replica(MotorSettings())
    ms = 1_000_000
    rep.counted(7, 0)  # the first state: its count is the reference
    assert rep.unanswered(0) is None
    rep.commanded(1 * ms)
    rep.commanded(2 * ms)
    assert rep.unanswered(2 * ms) == 1 * ms
    rep.counted(7, 3 * ms)  # a periodic state: nothing new counted
    assert rep.unanswered(3 * ms) == 1 * ms
    rep.counted(8, 4 * ms)
    assert rep.unanswered(4 * ms) == 2 * ms
    rep.counted(9, 5 * ms)
    assert rep.unanswered(5 * ms) is None
    rep.counted(10, 6 * ms)  # the state before the command (another path through the network)
    rep.commanded(7 * ms)
    assert rep.unanswered(7 * ms) is None
    rep.commanded(8 * ms)  # never counted: out until ANSWER_NS, then let go
    assert rep.unanswered(8 * ms + rep.ANSWER_NS) == 8 * ms
    assert rep.unanswered(8 * ms + rep.ANSWER_NS + 1) is None and rep.unheard == 1
    rep.counted(1, 90 * ms)  # a restarted actuator, one command since its start: answers the next one seen
    rep.commanded(91 * ms)
    assert rep.unanswered(91 * ms) is None and rep.unheard == 1
    rep.counted(2, 100 * ms)  # an early answer older than ANSWER_NS answers nothing
    late = 101 * ms + rep.ANSWER_NS
    rep.commanded(late)
    assert rep.unanswered(late) == late
    rep.counted(3, late + ms)
    assert rep.unanswered(late + ms) is None and rep.unheard == 1


# -- the sim motor's lies (issue #35: `vergence actuator --faults`, which `vergence up` gives a sim source's) ---------

def test_sim_stall_stops_the_shaft_where_it_is_and_drops_the_goals_until_it_ends():
    """stall=(1, 2) s from the first commanded frame's exposure (0.5 s): a move under way at 1.5 s stops there, a goal
    written in the stall is never taken, the first one after it is; the encoder tells the truth throughout."""
    clock = Clock(0.0)
    m = SimMotor(MotorSettings(tau_s=0.0, max_speed_deg_s=20, **IDEAL), clock=clock, stall=(1.0, 2.0))
    m.open()
    m.first_exposure(round(0.5e9))
    m.first_exposure(round(0.9e9))  # (once: the first command's)
    clock.t = 1.3
    m.write_goal(10 * DEG)
    clock.t = 1.6
    at_stall = m.read_position()
    assert at_stall == pytest.approx(4 * DEG, abs=1e-6) and m.shaft == at_stall  # 0.2 s at 20 deg/s
    m.write_goal(-5 * DEG)
    clock.t = 2.45
    assert m.read_position() == at_stall
    m.write_goal(1 * DEG)  # (2 ms before the stall's end: it would take it after)
    clock.t = 2.55
    assert m.read_position() == at_stall
    m.write_goal(2 * DEG)
    clock.t = 2.7
    assert m.read_position() == pytest.approx(2 * DEG, abs=1e-6)


def test_sim_encoder_noise_scatters_the_readings_not_the_shaft():
    clock = Clock(0.0)
    m = SimMotor(MotorSettings(), clock=clock, noise_deg=0.05, seed=3)
    m.open()
    m.write_goal(3 * DEG)
    clock.t = 1.0
    tick = 360 / MotorSettings().ticks_per_rev
    shaft = m.shaft / DEG
    assert shaft == pytest.approx(3, abs=tick)
    reads = [m.read_position() / DEG - shaft for _ in range(4000)]
    assert abs(sum(reads) / len(reads)) < 0.005 and 0.045 <= math.sqrt(sum(r * r for r in reads) / len(reads)) <= 0.065
    assert all(abs(r / tick - round(r / tick)) < 1e-6 for r in reads)  # whole ticks, as an encoder gives


def test_loop_tells_its_driver_the_first_plausible_commands_exposure_once():
    clock = Clock()
    wall = lambda: 10**18 + round(clock.t * 1e9)  # noqa: E731
    ms = MotorSettings()
    m = SimMotor(ms, clock_ns=wall, stall=(0.0, 1.0))
    loop = MotorLoop(m, ms, clock=clock, wall_ns=wall)
    loop.start()
    loop.command(cmd(5 * DEG, frame=1, t=wall() + 3 * 10**9))  # 3 s ahead (past max_skew_s): not believed
    assert m.stall_ns is None
    loop.command(cmd(5 * DEG, frame=2, t=wall() - 30_000_000))
    assert m.stall_ns == (wall() - 30_000_000, wall() + 970_000_000)
    clock.t += 0.5
    assert loop.tick().pan_rad == 0.0  # the goal came in the stall: dropped
    loop.command(cmd(6 * DEG, frame=3, t=wall() - 30_000_000))
    assert m.stall_ns[0] == 10**18 + round(100.0 * 1e9) - 30_000_000


def test_make_driver_refuses_lies_for_a_real_motor():
    sim = make_driver("sim", MotorSettings(), lies={"stall": (1.0, 2.5), "noise_deg": 0.1})
    assert sim.noise_rad == 0.1 * DEG and make_driver("sim", MotorSettings()).describe() == "sim"
    assert sim.describe() == ("sim (stalled 1-2.5 s from the first commanded frame, encoder noise 0.1 deg, as --faults "
                              "says)")  # (the actuator's first log line)
    with pytest.raises(ValueError, match="--faults makes the sim motor lie; the dynamixel driver drives a real one"):
        make_driver("dynamixel", MotorSettings(), "/dev/ttyUSB0", lies={"stall": (1.0, 2.0)})


def _replica_run(rep_kw: dict, motor_kw: dict, seconds: float = 3.0):
    """The sim actuator (MotorLoop, SimMotor with motor_kw's lies) at 50 Hz of states and a command every 0.25 s
    (alternately 4 and 0 deg), each state handed at once to a Replica(**rep_kw) told the same first exposure: yields
    (t, the shaft, the replica's pan or None) every 5 ms."""
    from vergence.motors.simulated import Replica

    ms = MotorSettings()
    clock = Clock(50.0)
    wall = lambda: WALL_NS + round(clock.t * 1e9)  # noqa: E731
    motor = SimMotor(ms, clock_ns=wall, **motor_kw)
    loop = MotorLoop(motor, ms, clock=clock, wall_ns=wall)
    rep = Replica(ms, **rep_kw)

    def feed(st):
        rep.observe(st.t_ns, st.pan_rad, st.goal_rad)

    feed(loop.start())
    for k in range(round(seconds / 0.005)):
        clock.t = round(50.0 + k * 0.005, 9)
        if k % 50 == 10:
            c = cmd((4 if k // 50 % 2 == 0 else 0) * DEG, frame=k, t=wall())
            rep.first_exposure(c.t_capture_ns) if k == 10 else None
            feed(loop.command(c))
        if k % 4 == 0:
            feed(loop.tick())
        yield clock.t, motor.shaft, rep.at(wall()), rep


def test_replica_knows_the_stall_it_is_told_and_trusts_again_after_it():
    """Told the stall (stall=0.5-1.5 from the first command's exposure at 50.05 s), the replica renders nothing from
    its model within it (None: the capture takes the motor's own states), never mismatches, and is trusted again
    after it, on the shaft; untold, it would have claimed the goals the motor dropped."""
    out = list(_replica_run({"stall": (0.5, 1.5)}, {"stall": (0.5, 1.5)}))
    inside = [p for t, _, p, _ in out if 50.56 <= t < 51.55]
    assert inside and all(p is None for p in inside)
    after = [(s, p) for t, s, p, _ in out if t >= 51.9]
    assert after and all(p is not None and abs(p - s) <= 2 * math.pi / 4096 for s, p in after)
    assert out[-1][3].mismatches == 0
    untold = list(_replica_run({}, {"stall": (0.5, 1.5)}))
    assert untold[-1][3].mismatches >= 1


def test_replica_of_a_noisy_encoder_stays_trusted_on_the_shaft():
    """encoder_noise 0.05 deg on the sim actuator's readings: the replica told it stays trusted throughout (its checks
    widened by 5 deviations) and gives the exact shaft once the first command has moved it (before, it rests where the
    motor's first noisy reading put its goal); untold, each check fails within the first second."""
    out = list(_replica_run({"noise_deg": 0.05}, {"noise_deg": 0.05}))
    got = [(s, p) for t, s, p, _ in out if t >= 50.3]
    assert all(p is not None and abs(p - s) <= 1e-9 for s, p in got) and out[-1][3].mismatches == 0
    untold = list(_replica_run({}, {"noise_deg": 0.05}, seconds=1.0))
    assert untold[-1][3].mismatches >= 1
