"""The line protocol driver against its emulator on a pseudo-terminal: lines on the wire, faults, unplug."""

from __future__ import annotations

import math

import pytest
from emulators.line import LineEmulator
from emulators.pty import PtyDevice
from procs import wait_for
from samples import cmd

from vergence.motors import MotorSettings, PortError, TransientError
from vergence.motors.line import LineDriver
from vergence.motors.runner import MotorLoop


@pytest.fixture
def dev(tmp_path):
    emu = LineEmulator(position=2000)
    d = PtyDevice(emu, str(tmp_path / "ttyACM"))
    yield emu, d
    d.close()


def test_lines_on_the_wire(dev):
    emu, d = dev
    # (the emulator answers from a thread of this process: a loaded run starved it past 50 ms, three times)
    drv = LineDriver(MotorSettings(timeout_s=0.5), d.link)
    assert drv.open() == pytest.approx(-48 * 2 * math.pi / 4096)
    goal = round(2048 + 0.25 * 4096 / (2 * math.pi))
    drv.write_goal(0.25)
    wait_for(lambda: emu.goals == [2000, goal], 2, "the emulator taking the goal")
    drv.read_position()
    drv.close()
    assert bytes(d.rx) == f"Q\nP 2000\nE 1\nP {goal}\nQ\nE 0\n".encode()
    assert emu.goals == [2000, goal] and not emu.enabled


def test_faults_retried_and_counted(dev):
    emu, d = dev
    drv = LineDriver(MotorSettings(timeout_s=0.03, retries=3), d.link)
    drv.open()
    emu.garbage_next = 1  # a debug line before the answer: skipped, not an error
    drv.write_goal(0.0)
    assert drv.errors == 0 and drv.skipped == 1
    emu.err_next = 1
    drv.write_goal(0.01)
    assert drv.errors == 1
    emu.drop_next = 1
    drv.read_position()
    assert drv.errors == 2
    emu.drop_next = 3
    with pytest.raises(TransientError, match="3 times"):
        drv.read_position()
    drv.read_position()
    drv.close()


def test_device_without_enable(tmp_path):
    emu = LineEmulator(supports_enable=False, banner="stepper v1 ready\n")
    d = PtyDevice(emu, str(tmp_path / "tty"))
    try:
        drv = LineDriver(MotorSettings(timeout_s=0.5), d.link)
        drv.open()
        assert not drv.enable_supported
        drv.write_goal(-0.1)
        drv.close()
        assert emu.goals == [2048, round(2048 - 0.1 * 4096 / (2 * math.pi))]
    finally:
        d.close()


def test_missing_port():
    with pytest.raises(PortError, match="list_ports"):
        LineDriver(MotorSettings(), "/dev/ttyACM_NOPE").open()


def test_unplug_replug(dev):
    emu, d = dev
    emu.position, emu.goal = 0.0, 0  # a stepper: 3200 microsteps a turn, 0 at the centre
    ms = MotorSettings(timeout_s=0.03, watchdog_s=0, ticks_per_rev=3200, zero=0)
    loop = MotorLoop(LineDriver(ms, d.link), ms, backoff_s=(0.02, 0.1))
    loop.start()
    d.unplug()
    assert loop.tick().status == "disconnected"
    d.replug()
    wait_for(lambda: loop.tick().status == "ok", 3, "the loop to reconnect", interval=0.01)
    loop.command(cmd(0.1, frame=1))
    assert emu.goals[-1] == round(0.1 * 3200 / (2 * math.pi))
    loop.stop()
