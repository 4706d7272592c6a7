"""The real `vergence actuator` process, driven by Zenoh commands through a real router on 127.0.0.1.

The device emulators run in a thread of this test process on a pseudo-terminal; the actuator opens it
through a symlink, which the test re-points to a new pty to simulate unplugging and replugging an adapter
(a pty cannot be reopened once its master is closed, but the path the actuator knows stays the same)."""

from __future__ import annotations

import itertools
import json
import math
import re
import signal
import time

import pytest
import zenoh
from emulators.dynamixel import DynamixelEmulator
from emulators.line import LineEmulator
from emulators.pty import PtyDevice
from procs import Procs, run, wait_for

from vergence.wire.messages import Command, MotorState
from vergence.motors.dynamixel import Inst, instruction_packet

pytestmark = pytest.mark.slow  # every test here runs real processes


def command(rig: str, pan: float, frame: int) -> bytes:
    return Command(rig=rig, frame=frame, t_capture_ns=time.time_ns(), pan_rad=pan, correction_rad=0.0,
                   direction=0, magnitude_px=0.0, confidence=1.0).to_bytes()


def states(col) -> list[MotorState]:
    return [MotorState.from_bytes(b) for _, b, _ in col.snapshot()]


def wait_state(col, pred, timeout: float, what: str, logs, after: int = 0) -> MotorState:
    """The newest state (among those received after the first `after`) for which pred holds."""
    def found():
        return next((s for s in reversed(states(col)[after:]) if pred(s)), None)
    return wait_for(found, timeout, what, logs=logs)


def ticks(pan: float) -> int:
    return round(2048 + pan * 4096 / (2 * math.pi))


def test_sim_actuator(tmp_path):
    with Procs(tmp_path) as P:
        P.router()
        act = P.start("actuator", "actuator", "--driver", "sim")
        s = P.session()
        col = P.collect(s, P.key("motor_state"))
        P.wait_alive(s, "actuator")
        col.wait(1, 10)
        n0, t0 = len(col), time.monotonic()
        wait_for(lambda: len(col) >= n0 + 50, 5, "50 more motor states", logs=P.logs)
        rate = (len(col) - n0) / (time.monotonic() - t0)
        assert 40 <= rate <= 60, rate  # state_hz = 50
        pub = s.declare_publisher(P.key("command"))
        pub.put(command(P.rig, 0.1, 1))
        st = wait_state(col, lambda m: m.frame == 1, 5, "state of frame 1", P.logs)
        assert st.goal_rad == pytest.approx(0.1) and st.driver == "sim" and st.status == "ok"
        at = (ticks(0.1) - 2048) * 2 * math.pi / 4096  # the simulated servo reports whole ticks, as a Dynamixel
        st = wait_state(col, lambda m: abs(m.pan_rad - at) < 1e-9, 5, "the motor at 0.1 (its nearest tick)", P.logs)
        # one at a time, each counted before the next: a burst would be coalesced (see the flood test)
        for i, bad in enumerate([math.nan, math.inf, 1e300, -1e300]):
            pub.put(command(P.rig, bad, 2 + i))
            wait_state(col, lambda m, n=2 + i: m.commands >= n, 5, f"{2 + i} commands counted", P.logs)
        pub.put(b"\x00garbage")
        wait_state(col, lambda m: m.commands >= 6, 5, "6 commands counted", P.logs)
        pub.put(b"")
        st = wait_state(col, lambda m: m.commands == 7, 5, "7 commands counted", P.logs)
        assert (st.ignored, st.clamped, st.malformed) == (2, 2, 2)
        # +1e300 then -1e300: one step up (10 deg) then one step down, never past the limits
        assert st.goal_rad == pytest.approx(0.1)
        assert max(m.goal_rad for m in states(col)) == pytest.approx(0.1 + math.radians(10))
        act.signal(signal.SIGINT)
        assert act.wait(10) == 0
        # its last state, put before it exited, reaches the test through the router: waited for, with a deadline
        wait_for(lambda: states(col)[-1].status == "stopped", 5, "the last state: stopped", logs=P.logs)


def test_missing_port_exits_with_hint():
    r = run("actuator", "--driver", "dynamixel", "--port", "/dev/ttyUSB_NOPE9", "--connect", "tcp/127.0.0.1:9",
            timeout=20)
    assert r.returncode == 2
    assert "/dev/ttyUSB_NOPE9" in r.stderr and "python -m serial.tools.list_ports" in r.stderr


def _dynamixel_actuator(P, dev):
    """A router and `vergence actuator --driver dynamixel` on the emulator's port, at status ok: (its Proc, the
    test's session, a collector of its motor states)."""
    P.router()
    act = P.start("actuator", "actuator", "--driver", "dynamixel", "--port", dev.link, "--id", "1",
                  "--baud", "1000000")
    s = P.session()
    col = P.collect(s, P.key("motor_state"))
    P.wait_alive(s, "actuator")
    wait_state(col, lambda m: m.status == "ok", 10, "status ok", P.logs)
    return act, s, col


def test_dynamixel_actuator_bytes_state_and_replug(tmp_path):
    emu = DynamixelEmulator(present=2048 + 100)
    dev = PtyDevice(emu, str(tmp_path / "ttyDXL"))
    try:
        with Procs(tmp_path) as P:
            act, s, col = _dynamixel_actuator(P, dev)
            # start-up: ping, mode read, present read, goal = present, torque on
            insts = [(inst, bytes(p)) for _, inst, p in emu.packets[:6]]
            assert insts[0] == (Inst.PING, b"")
            assert (Inst.WRITE, bytes.fromhex("40 00 01")) in insts
            assert emu.get("torque_enable") == 1 and emu.goal_writes[0] == 2148
            pub = s.declare_publisher(P.key("command"))
            for i, pan in enumerate([0.05, 0.1, -0.02], start=1):
                pub.put(command(P.rig, pan, i))
                st = wait_state(col, lambda m, i=i: m.frame == i, 5, f"state of frame {i}", P.logs)
                assert st.goal_rad == pytest.approx(pan)
            wait_for(lambda: emu.goal_writes[-1] == ticks(-0.02), 5, "the last goal written")
            assert emu.goal_writes == [2148, ticks(0.05), ticks(0.1), ticks(-0.02)]
            # the goal on the wire, byte for byte (Goal Position 116, 4 bytes, little-endian)
            assert instruction_packet(1, Inst.WRITE, bytes([116, 0]) + ticks(0.1).to_bytes(4, "little")) \
                in bytes(dev.rx)
            st = wait_state(col, lambda m: abs(m.pan_rad + 0.02) < 2 * math.pi / 4096, 5, "present = goal",
                            P.logs)
            assert st.driver == "dynamixel" and st.errors == 0
            # a corrupted reply and a lost one: retried and counted
            emu.corrupt_next, emu.drop_next = 1, 1
            st = wait_state(col, lambda m: m.errors >= 2, 5, "2 errors counted", P.logs)
            assert st.status == "ok"
            # unplug the adapter, then plug it back: same path, a new pty
            dev.unplug()
            wait_state(col, lambda m: m.status == "disconnected", 5, "status disconnected", P.logs)
            time.sleep(0.3)  # time under test: unplugged for a while, through the actuator's reconnect attempts
            n = len(col)
            dev.replug()
            wait_state(col, lambda m: m.status == "ok", 10, "status ok again", P.logs, after=n)
            pub.put(command(P.rig, 0.03, 10))
            wait_state(col, lambda m: m.frame == 10, 5, "state of frame 10", P.logs)
            wait_for(lambda: emu.goal_writes[-1] == ticks(0.03), 5, "the goal after the replug")
            act.signal(signal.SIGINT)
            assert act.wait(10) == 0
            assert emu.get("torque_enable") == 0  # torque off on stop (the default)
    finally:
        dev.close()



def test_the_actuator_status_counts_what_it_did(tmp_path):
    """The actuator runs on services.runtime.node.Node: a status every second on
    vergence/<rig>/status/actuator/<id> whose counters say what came and what went (and one at exit)."""
    emu = DynamixelEmulator(present=2048)
    dev = PtyDevice(emu, str(tmp_path / "ttyDXL"))
    try:
        with Procs(tmp_path) as P:
            act, s, col = _dynamixel_actuator(P, dev)
            stats = P.collect(s, P.key("status/actuator/*"))
            pub = s.declare_publisher(P.key("command"))
            # one at a time, each counted before the next: 3 applied, 1 refused (not finite), 1 malformed
            for i, pan in enumerate([0.05, 0.1, math.nan, -0.02], start=1):
                pub.put(command(P.rig, pan, i))
                wait_state(col, lambda m, i=i: m.commands >= i, 5, f"{i} commands counted", P.logs)
            pub.put(b"\x00garbage")
            wait_state(col, lambda m: m.commands >= 5, 5, "5 commands counted", P.logs)

            def counted():
                for _, b, _ in reversed(stats.snapshot()):
                    st = json.loads(b)
                    if st["counters"].get("commands") == 5:
                        return st
                return None

            st = wait_for(counted, 5, "a status with 5 commands", logs=P.logs)
            c = st["counters"]
            assert st["role"] == "actuator" and st["id"] == P.wait_alive(s, "actuator")[0]
            assert (c["commands"], c["applied"], c["refused"], c.get("clamped", 0)) == (5, 3, 1, 0)
            assert st["bad"] == {"command": 1}
            assert c["motor_states"] >= 5 and st["motor"] == "ok" and st["driver"] == "dynamixel"
            act.signal(signal.SIGINT)
            assert act.wait(10) == 0
            last = wait_for(lambda: next((d for d in (json.loads(b) for _, b, _ in stats.snapshot())
                                          if d.get("exiting")), None), 5, "the status at exit", logs=P.logs)
            assert last["counters"]["commands"] == 5 and last["motor"] == "stopped"
            # every state it published counted: the start, one per command, the ticks and the stop
            assert last["counters"]["motor_states"] >= len(states(col))
    finally:
        dev.close()

def test_line_actuator(tmp_path):
    emu = LineEmulator(position=0)
    dev = PtyDevice(emu, str(tmp_path / "ttyACM"))
    conf = tmp_path / "head.toml"
    conf.write_text('[actuator]\ndriver = "line"\nport = "%s"\n[actuator.motor]\nticks_per_rev = 3200\n'
                    'zero = 0\ndirection = -1\n' % dev.link)
    try:
        with Procs(tmp_path) as P:
            P.router()
            act = P.start("actuator", "actuator", "--config", str(conf))
            s = P.session()
            col = P.collect(s, P.key("motor_state"))
            wait_state(col, lambda m: m.status == "ok", 10, "status ok", P.logs)
            pub = s.declare_publisher(P.key("command"))
            pub.put(command(P.rig, 0.15, 1))
            st = wait_state(col, lambda m: m.frame == 1 and abs(m.pan_rad - 0.15) < 0.002, 5, "at 0.15",
                            P.logs)
            assert st.driver == "line"
            want = round(-0.15 * 3200 / (2 * math.pi))
            assert emu.goals == [0, want]
            assert f"P {want}\n".encode() in bytes(dev.rx)
            dev.unplug()
            wait_state(col, lambda m: m.status == "disconnected", 5, "status disconnected", P.logs)
            n = len(col)
            dev.replug()
            wait_state(col, lambda m: m.status == "ok", 10, "ok again", P.logs, after=n)
            pub.put(command(P.rig, 0.1, 2))
            wait_for(lambda: emu.goals[-1] == round(-0.1 * 3200 / (2 * math.pi)), 5, "goal after replug")
            act.signal(signal.SIGINT)
            assert act.wait(10) == 0
            assert bytes(dev.rx).endswith(b"E 0\n")
    finally:
        dev.close()


def test_flood_keeps_goal_safe(tmp_path):
    """Thousands of commands in a burst, garbage among them: the actuator keeps up by taking the newest,
    counts the rest, and no goal leaves the limits or jumps more than max_step (1 deg here)."""
    conf = tmp_path / "a.toml"
    conf.write_text("[actuator.motor]\nmax_step_deg = 1.0\nmin_deg = -20\nmax_deg = 20\n")
    with Procs(tmp_path) as P:
        P.router()
        P.start("actuator", "actuator", "--driver", "sim", "--config", str(conf))
        s = P.session()
        col = P.collect(s, P.key("motor_state"))
        P.wait_alive(s, "actuator")
        col.wait(1, 10)
        # BLOCK: the burst must reach the actuator whole (what is counted is the actuator's coalescing, not
        # messages a loaded machine's network layer dropped)
        pub = s.declare_publisher(P.key("command"), congestion_control=zenoh.CongestionControl.BLOCK)
        import random
        rnd = random.Random(5)
        n = 3000
        for i in range(n):
            r = rnd.random()
            if r < 0.1:
                pub.put(bytes(rnd.randrange(256) for _ in range(rnd.randrange(20))))
            else:
                pan = rnd.choice([math.nan, math.inf, -math.inf, 1e9, -1e9, rnd.uniform(-1, 1)])
                pub.put(command(P.rig, pan, i))
        st = wait_state(col, lambda m: m.commands == n, 15, f"{n} commands accounted for", P.logs)
        assert st.ignored + st.malformed > 0
        goals = [m.goal_rad for m in states(col)]
        assert all(-math.radians(20) - 1e-12 <= g <= math.radians(20) + 1e-12 for g in goals)
        assert max(abs(b - a) for a, b in zip(goals, goals[1:])) <= math.radians(1.0) + 1e-9


@pytest.mark.slow
def test_reducer_and_actuator_bound_the_pan_by_one_motor_table(tmp_path):
    """One settings file, one [actuator.motor]: the reducer's controller bounds every command by its limits
    (max_step_deg 0.5 from the pan at capture, min_deg -1), before the actuator bounds it again. The simulated
    rig's slave converges at -5.4 degrees, beyond the limit: each command is the pan at capture - 0.5 degrees,
    until the pan sits at the -1 degree limit, where the scene still asks for more."""
    conf = tmp_path / "v.toml"
    conf.write_text('[network]\nmax_window = 0\n[capture]\npreview_hz = 0\n[control]\nmode = "p"\n'
                    "[actuator.motor]\nmin_deg = -1.0\nmax_deg = 1.0\nmax_step_deg = 0.5\n")
    cfg = str(conf)
    with Procs(tmp_path) as P:
        P.router()
        P.start("actuator", "actuator", "--driver", "sim", "--config", cfg)
        P.start("reducer", "reducer", "--config", cfg)
        P.start("w1", "worker", "--name", "w1", "--config", cfg)
        s = P.session()
        P.wait_alive(s, "worker", 1)
        P.wait_alive(s, "actuator")
        commands = P.collect(s, P.key("command"))
        motor = P.collect(s, P.key("motor_state"))
        P.start("capture", "capture", "--source", "sim:size=320x240", "--rate", "20", "--config", cfg)
        wait_state(motor, lambda m: abs(m.goal_rad + math.radians(1.0)) < 1e-12, 30, "the goal at min_deg",
                   P.logs)
        cmds = [Command.from_bytes(b) for _, b, _ in commands.snapshot()]
        assert cmds and all(c.pan_rad >= -math.radians(1.0) - 1e-12 for c in cmds)
        assert all(abs(c.correction_rad) <= math.radians(0.5) + 1e-12 for c in cmds)
        # the controller's own bound, not the actuator's: a command is exactly its pan at capture - 0.5 deg
        # (or the limit), where an unbounded one would be up to 5.4 deg past it
        assert any(c.correction_rad == pytest.approx(-math.radians(0.5), abs=1e-12) for c in cmds)
        assert cmds[-1].pan_rad == pytest.approx(-math.radians(1.0), abs=1e-12)
        assert all(-math.radians(1.0) - 1e-12 <= m.goal_rad <= math.radians(1.0) + 1e-12 for m in states(motor))


def test_a_silent_dynamixel_is_a_visible_fault_and_control_resumes_by_itself(tmp_path):
    """Issue #29: the emulated motor answers nothing for 5 s, then comes back, under a stream of fresh commands
    (20 Hz). The real actuator (default settings: silent_s 0.5, absent_s 2, watchdog_s 2) reports
    "disconnected" within silent_s and "absent" absent_s later, in its state, its log and a real `vergence
    monitor`; while lost it writes nothing but pings; once the motor answers it holds where it is and the
    commands move it again within 2 s; no goal it writes comes from a command older than the watchdog's 2 s (a goal is
    a fresh command's, or a step of max_step_deg, 10 deg, from the goal before it towards a fresh command: the sine
    has moved on while the motor was silent)."""
    import threading

    emu = DynamixelEmulator(present=2048)
    dev = PtyDevice(emu, str(tmp_path / "ttyDXL"))
    sent: list[tuple[float, int]] = []  # (time.monotonic(), goal ticks) of each command
    quit_ = threading.Event()
    try:
        with Procs(tmp_path) as P:
            act, s, col = _dynamixel_actuator(P, dev)
            mon = P.start("monitor", "monitor", "--timeout", "60", "--refresh", "0.2", "--color", "never")
            pub = s.declare_publisher(P.key("command"))

            def commander():  # the reducer's part: a fresh command every 50 ms, a slow sine of 0.3 rad
                k = 0
                while not quit_.wait(0.05):
                    k += 1
                    pan = 0.3 * math.sin(2 * math.pi * k / 400)
                    sent.append((time.monotonic(), ticks(pan)))
                    pub.put(command(P.rig, pan, k))

            th = threading.Thread(target=commander, daemon=True)
            th.start()
            wait_for(lambda: len(emu.goal_writes) > 10, 10, "goals written")
            t_quiet = time.monotonic()
            emu.silence(5.0)
            n = len(col)
            lost = wait_state(col, lambda m: m.status == "disconnected", 5, "disconnected", P.logs, after=n)
            t_lost = time.monotonic()
            absent = wait_state(col, lambda m: m.status == "absent", 10, "absent", P.logs, after=n)
            t_absent = time.monotonic()
            wait_for(lambda: "MOTOR ABSENT: commands are not executed" in mon.text(), 5, "the monitor's fault line",
                     logs=P.logs)
            t_monitor = time.monotonic()
            assert re.search(r"motor absent for 2\.\d s \(lost: no answer for 0\.\d s: ", act.text()), act.text()
            t_back = emu.silent_until
            n = len(col)
            wait_state(col, lambda m: m.status == "ok", 10, "ok again", P.logs, after=n)
            t_ok = time.monotonic()
            wait_for(lambda: [v for t, v in emu.goal_log if t > t_back][1:], 5, "a command executed after the return")
            quit_.set()
            th.join(5)
            after = [(t, v) for t, v in emu.goal_log if t > t_back]
            t_moved = after[1][0]
            print(f"silent for 5 s: disconnected after {t_lost - t_quiet:.2f} s, absent after "
                  f"{t_absent - t_quiet:.2f} s, on the monitor after {t_monitor - t_quiet:.2f} s; back: ok after "
                  f"{t_ok - t_back:.2f} s, a command executed after {t_moved - t_back:.2f} s")
            assert "no answer for" in lost.note and absent.ignored > 0
            assert t_lost - t_quiet < 0.5 + 0.5 and t_absent - t_quiet < 0.5 + 2.0 + 0.6
            assert t_moved - t_back < 2.0
            # while lost: nothing but pings on the bus (the probes); before it, the transactions of silent_s
            assert {inst for t, _, inst in emu.unheard if t > t_lost} == {Inst.PING}
            # back: the first goal is the hold at its present position, then only fresh commands
            hold = after[0][1]
            assert hold == emu.goal_log[len(emu.goal_log) - len(after) - 1][1]  # where it was when it went silent
            step = 4096 * 10.0 / 360  # [actuator.motor] max_step_deg in ticks
            for (_, before), (t, v) in itertools.pairwise(after):
                fresh = [tv for ts, tv in sent if t - 2.0 < ts <= t]
                src = [ts for ts, tv in sent if tv == v and ts <= t]
                clamped = abs(abs(v - before) - step) <= 1 and any((tv - v) * (v - before) > 0 for tv in fresh)
                assert (src and t - src[-1] < 2.0) or clamped, (t, v, before)
            assert re.search(r"motor reconnected \(1\) after [45]\.\d s absent", act.text()), act.text()
            act.signal(signal.SIGINT)
            assert act.wait(10) == 0
            mon.signal(signal.SIGINT)
    finally:
        quit_.set()
        dev.close()


def test_a_port_given_to_the_sim_driver_is_refused_not_ignored():
    r = run("actuator", "--port", "/dev/ttyUSB9", "--connect", "tcp/127.0.0.1:9", timeout=20)
    assert r.returncode == 2
    assert r.stderr.strip() == ("vergence actuator: --port applies to a real driver (dynamixel, line, ros2); the sim "
                                "driver has no port")


@pytest.mark.parametrize("argv,says", [
    (["--faults", "stall=1-2", "--driver", "dynamixel", "--port", "loop://"],
     "--faults makes the sim motor lie; the dynamixel driver drives a real one"),
    (["--faults", "freeze=1-2"], "--faults: unknown key 'freeze' (item 'freeze=1-2'); keys: stall=A-B, encoder_noise"),
    (["--faults", "encoder_noise=9"], "--faults: encoder_noise='9' must be <= 5 deg"),
])
def test_the_sim_motors_lies_are_refused_where_they_do_not_apply(argv, says):
    r = run("actuator", *argv, "--connect", "tcp/127.0.0.1:9", timeout=20)
    assert r.returncode == 2 and r.stderr.strip().startswith("vergence actuator: " + says), r.stderr
