"""Dynamixel Protocol 2.0: packets byte for byte (the e-Manual's examples), CRC, stuffing, and the driver
against the emulator on a pseudo-terminal: start-up sequence, goals, faults, unplug and replug."""

from __future__ import annotations

import math
import os
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from emulators.dynamixel import DynamixelEmulator, add_stuffing, crc16_bitwise, remove_stuffing
from emulators.pty import PtyDevice
from procs import wait_for
from samples import cmd
from vergence.motors import Disconnected, MotorSettings, PortError, TransientError
from vergence.motors.dynamixel import (CRC_TABLE, XSERIES, DynamixelDriver, Inst, PacketError, crc16,
                                       instruction_packet, parse_status, status_packet, stuff, unstuff)
from vergence.motors.runner import MotorLoop


def hx(s: str) -> bytes:
    return bytes.fromhex(s)


# -- packets -------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("packet, built", [
    # e-Manual, Protocol 2.0: ping id 1; read 4 bytes at 132 (Present Position); write 512 to 116 (Goal)
    ("FF FF FD 00 01 03 00 01 19 4E", lambda: instruction_packet(1, Inst.PING)),
    ("FF FF FD 00 01 07 00 02 84 00 04 00 1D 15",
     lambda: instruction_packet(1, Inst.READ, hx("84 00 04 00"))),
    ("FF FF FD 00 01 09 00 03 74 00 00 02 00 00 CA 89",
     lambda: instruction_packet(1, Inst.WRITE, hx("74 00 00 02 00 00"))),
    # the status of a ping: model 1030 (0x0406), firmware 0x26
    ("FF FF FD 00 01 07 00 55 00 06 04 26 65 5D", lambda: status_packet(1, 0, hx("06 04 26"))),
], ids=["ping", "read-present", "write-goal", "ping-status"])
def test_known_packets(packet, built):
    assert built() == hx(packet)


def test_crc_table_is_robotis():
    assert CRC_TABLE[:4] == [0x0000, 0x8005, 0x800F, 0x000A]
    assert CRC_TABLE[64] == 0x8183 and CRC_TABLE[255] == 0x0202


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=64))
def test_crc_matches_bitwise(data):
    assert crc16(data) == crc16_bitwise(data)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.sampled_from([0xFF, 0xFD, 0x00, 0x55]), max_size=40).map(bytes))
def test_stuffing_roundtrip_and_agrees_with_emulator(body):
    s = stuff(body)
    assert s == add_stuffing(body)
    assert unstuff(s) == body == remove_stuffing(s)
    # no header can appear inside: every FF FF FD is followed by the stuffed FD
    assert all(s[i + 3:i + 4] == b"\xfd" for i in range(len(s)) if s[i:i + 3] == b"\xff\xff\xfd")


def test_stuffed_packet_bytes():
    # a goal whose bytes contain FF FF FD: 0xFDFFFF00 little-endian = 00 FF FF FD
    pkt = instruction_packet(1, Inst.WRITE, hx("74 00 00 FF FF FD"))
    assert pkt[:7] == hx("FF FF FD 00 01 0A 00")  # length counts the stuffed byte
    assert pkt[7:-2] == hx("03 74 00 00 FF FF FD FD")
    assert int.from_bytes(pkt[-2:], "little") == crc16_bitwise(pkt[:-2])


def test_parse_status_errors():
    good = status_packet(3, 0, b"\x01\x02")
    assert parse_status(good) == (3, 0, b"\x01\x02")
    bad = bytearray(good)
    bad[-1] ^= 1
    with pytest.raises(PacketError, match="CRC"):
        parse_status(bytes(bad))
    with pytest.raises(PacketError, match="status"):
        parse_status(instruction_packet(3, Inst.PING))
    assert parse_status(status_packet(1, 0x87)) == (1, 0x87, b"")


def test_control_table_addresses():
    assert XSERIES["operating_mode"][:2] == (11, 1)
    assert XSERIES["torque_enable"][:2] == (64, 1)
    assert XSERIES["goal_position"][:2] == (116, 4)
    assert XSERIES["present_position"][:2] == (132, 4)


# -- the emulator alone --------------------------------------------------------------------------------------

def test_emulator_eeprom_locked_while_torque_on():
    emu = DynamixelEmulator()
    assert emu.feed(instruction_packet(1, Inst.WRITE, hx("0B 00 04"))) == status_packet(1, 0)  # mode 4
    emu.feed(instruction_packet(1, Inst.WRITE, hx("40 00 01")))  # torque on
    assert emu.feed(instruction_packet(1, Inst.WRITE, hx("0B 00 03"))) == status_packet(1, 7)  # access error
    assert emu.get("operating_mode") == 4
    assert emu.feed(instruction_packet(1, Inst.WRITE, hx("84 00 00 00 00 00"))) == status_packet(1, 7)  # r/o
    assert emu.feed(instruction_packet(1, Inst.WRITE, hx("74 00 00"))) == status_packet(1, 5)  # length
    assert emu.feed(instruction_packet(1, 0x7F)) == status_packet(1, 2)  # instruction error
    bad = bytearray(instruction_packet(1, Inst.PING))
    bad[-2] ^= 0xFF
    assert emu.feed(b"\x00\x13" + bytes(bad)) == status_packet(1, 3)  # noise skipped, CRC error answered
    assert emu.feed(instruction_packet(2, Inst.PING)) == b""  # another id: silence


def test_emulator_goal_limit_in_position_mode():
    emu = DynamixelEmulator()
    emu.feed(instruction_packet(1, Inst.WRITE, hx("40 00 01")))
    goal_5000 = (116).to_bytes(2, "little") + (5000).to_bytes(4, "little")
    assert emu.feed(instruction_packet(1, Inst.WRITE, goal_5000)) == status_packet(1, 6)
    assert emu.get("goal_position") == 2048


# -- the driver on a pseudo-terminal -------------------------------------------------------------------------

@pytest.fixture
def dxl(tmp_path):
    emu = DynamixelEmulator(present=2100)
    dev = PtyDevice(emu, str(tmp_path / "ttyDXL"))
    yield emu, dev
    dev.close()


def test_driver_start_sequence_and_goals(dxl):
    emu, dev = dxl
    emu.set("operating_mode", 1)  # velocity mode: the driver must switch to position mode (torque is off)
    drv = DynamixelDriver(MotorSettings(), dev.link)
    assert drv.open() == pytest.approx((2100 - 2048) * 2 * math.pi / 4096)
    assert drv.model == 1020 and emu.get("operating_mode") == 3 and emu.get("torque_enable") == 1
    assert [inst for _, inst, _ in emu.packets[:1]] == [Inst.PING]
    assert emu.writes_to("operating_mode") == [3] and emu.writes_to("torque_enable") == [1]
    for pan in (0.0, 0.1, -0.3, math.radians(45)):
        drv.write_goal(pan)
    assert emu.goal_writes == [2100, 2048, round(2048 + 0.1 * 4096 / (2 * math.pi)),
                               round(2048 - 0.3 * 4096 / (2 * math.pi)), 2560]
    # the last goal on the wire, byte for byte
    assert instruction_packet(1, Inst.WRITE, hx("74 00 00 0A 00 00")) in bytes(dev.rx)
    # the emulated motor travels at 20000 ticks/s: read until it is there
    wait_for(lambda: drv.read_position() == pytest.approx(math.radians(45), abs=2 * math.pi / 4096), 2,
             "the motor at its goal")
    drv.close(torque_off=True)
    assert emu.get("torque_enable") == 0


def test_driver_keeps_position_mode_with_torque_on(dxl):
    emu, dev = dxl
    emu.set("torque_enable", 1)
    emu.set("operating_mode", 4)  # extended position: fine as it is
    drv = DynamixelDriver(MotorSettings(torque_off_on_stop=False), dev.link)
    drv.open()
    assert emu.writes_to("operating_mode") == [] and emu.get("operating_mode") == 4
    drv.close(torque_off=False)
    assert emu.get("torque_enable") == 1


def test_driver_retries_faults(dxl):
    emu, dev = dxl
    drv = DynamixelDriver(MotorSettings(timeout_s=0.03, retries=3), dev.link)
    drv.open()
    emu.corrupt_next = 1
    emu.noise_next = b"\x00\xff\x42"
    drv.write_goal(0.01)
    assert drv.errors == 1 and emu.goal_writes[-2:] == [2055, 2055]
    emu.drop_next = 2
    drv.read_position()
    assert drv.errors == 3
    emu.error_next = 1  # result fail
    drv.write_goal(0.02)
    assert drv.errors == 4
    emu.drop_next = 3
    with pytest.raises(TransientError, match="3 times"):
        drv.read_position()
    assert drv.errors == 7
    drv.read_position()  # and it goes on
    drv.close()


def test_driver_no_answer_is_transient(tmp_path):
    emu = DynamixelEmulator(dxl_id=5)
    dev = PtyDevice(emu, str(tmp_path / "tty"))
    try:
        drv = DynamixelDriver(MotorSettings(id=1, timeout_s=0.02, retries=1), dev.link)
        with pytest.raises(TransientError, match="id 1 .* baud"):
            drv.open()
    finally:
        dev.close()


def test_driver_missing_port_names_it():
    drv = DynamixelDriver(MotorSettings(), "/dev/ttyNOPE42")
    with pytest.raises(PortError) as e:
        drv.open()
    assert "/dev/ttyNOPE42" in str(e.value) and "python -m serial.tools.list_ports" in str(e.value)


@pytest.mark.realtime  # times a thread or a wake-up: kept in the main process of a split run
def test_loop_survives_unplug_and_replug(dxl):
    emu, dev = dxl
    ms = MotorSettings(timeout_s=0.03, watchdog_s=0)
    loop = MotorLoop(DynamixelDriver(ms, dev.link), ms, backoff_s=(0.02, 0.1))
    assert loop.start().status == "ok"
    loop.command(cmd(0.05, frame=1))
    dev.unplug()
    assert loop.tick().status == "disconnected"
    for _ in range(5):
        time.sleep(0.03)  # time under test: unplugged, the loop stays disconnected through its back-off
        assert loop.tick().status == "disconnected"
    with pytest.raises(Disconnected):
        loop.driver.read_position()
    dev.replug()
    wait_for(lambda: loop.tick().status == "ok", 3, "the loop to reconnect", interval=0.01)
    loop.command(cmd(0.06, frame=2))
    assert emu.goal_writes[-1] == round(2048 + 0.06 * 4096 / (2 * math.pi))
    assert loop.reconnects == 1 and dev.plugs == 2
    loop.stop()
    assert emu.get("torque_enable") == 0
    assert os.path.islink(dev.link)


def test_profile_velocity_from_max_speed(dxl):
    emu, dev = dxl
    drv = DynamixelDriver(MotorSettings(set_profile_velocity=True, max_speed_deg_s=180), dev.link)
    drv.open()
    assert emu.get("profile_velocity") == round(180 / 6 / 0.229) == 131  # 0.229 rpm per unit
    drv.close()


def test_driver_over_socket_url():
    """socket:// (a serial-to-TCP bridge such as ser2net) works like a tty: serial_for_url."""
    import socket
    import threading

    emu = DynamixelEmulator()
    srv = socket.create_server(("127.0.0.1", 0))
    port = srv.getsockname()[1]

    def serve():
        conn, _ = srv.accept()
        with conn:
            while data := conn.recv(4096):
                conn.sendall(emu.feed(data))

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    try:
        drv = DynamixelDriver(MotorSettings(), f"socket://127.0.0.1:{port}")
        assert drv.open() == 0.0
        drv.write_goal(-0.1)
        assert emu.goal_writes[-1] == round(2048 - 0.1 * 4096 / (2 * math.pi))
        drv.close()
        assert emu.get("torque_enable") == 0
    finally:
        srv.close()
        t.join(5)
