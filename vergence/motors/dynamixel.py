"""ROBOTIS Dynamixel Protocol 2.0 for one X-series motor in position mode, over any pyserial URL.

Packets (ROBOTIS e-Manual, "Protocol 2.0"):

    instruction: FF FF FD 00 | ID | LEN_L LEN_H | INST | PARAMS ... | CRC_L CRC_H
    status:      FF FF FD 00 | ID | LEN_L LEN_H | 55   | ERR | PARAMS ... | CRC_L CRC_H

LEN counts the bytes after it (instruction, [error,] parameters, CRC) after byte stuffing; stuffing inserts an
extra FD after every FF FF FD inside instruction+parameters so that the header never appears in the body;
the CRC (CRC-16, polynomial 0x8005, initial 0, not reflected: ROBOTIS' table) covers everything from the
first FF to the last parameter, stuffed. ERR: bit 7 is the hardware alert, bits 0-6 an error number
(ERRORS). Multi-byte values are little-endian.

At open: ping, check the operating mode (set position mode when it is not, which needs torque off: that is
EEPROM), torque on. Then Goal Position writes and Present Position reads. Torque off at close, if asked.
"""

from __future__ import annotations

import logging
import struct
import time


from .base import IO_ERRORS, Disconnected, MotorSettings, NoAnswer, SerialDriver, TransientError

__all__ = ["crc16", "stuff", "unstuff", "instruction_packet", "status_packet", "parse_status", "StatusError",
           "PacketError", "XSERIES", "Inst", "ERRORS", "DynamixelDriver"]

log = logging.getLogger("vergence.motors.dynamixel")

HEADER = b"\xff\xff\xfd\x00"
BROADCAST = 0xFE


class Inst:
    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    REG_WRITE = 0x04
    ACTION = 0x05
    FACTORY_RESET = 0x06
    REBOOT = 0x08
    STATUS = 0x55
    SYNC_READ = 0x82
    SYNC_WRITE = 0x83


# Status packet error numbers (bits 0-6 of ERR); bit 7 (0x80) is the hardware alert.
ALERT = 0x80
ERRORS = {
    1: "result fail",
    2: "instruction error",
    3: "CRC error",
    4: "data range error",
    5: "data length error",
    6: "data limit error",
    7: "access error",
}

# The X-series control table as plain data: name -> (address, size in bytes, area, access).
# area: "eeprom" (writable only while torque is off) or "ram". access: "r" or "rw".
XSERIES: dict[str, tuple[int, int, str, str]] = {
    "model_number": (0, 2, "eeprom", "r"),
    "model_information": (2, 4, "eeprom", "r"),
    "firmware_version": (6, 1, "eeprom", "r"),
    "id": (7, 1, "eeprom", "rw"),
    "baud_rate": (8, 1, "eeprom", "rw"),
    "return_delay_time": (9, 1, "eeprom", "rw"),
    "drive_mode": (10, 1, "eeprom", "rw"),
    "operating_mode": (11, 1, "eeprom", "rw"),
    "secondary_id": (12, 1, "eeprom", "rw"),
    "protocol_type": (13, 1, "eeprom", "rw"),
    "homing_offset": (20, 4, "eeprom", "rw"),
    "moving_threshold": (24, 4, "eeprom", "rw"),
    "temperature_limit": (31, 1, "eeprom", "rw"),
    "max_voltage_limit": (32, 2, "eeprom", "rw"),
    "min_voltage_limit": (34, 2, "eeprom", "rw"),
    "pwm_limit": (36, 2, "eeprom", "rw"),
    "current_limit": (38, 2, "eeprom", "rw"),
    "velocity_limit": (44, 4, "eeprom", "rw"),
    "max_position_limit": (48, 4, "eeprom", "rw"),
    "min_position_limit": (52, 4, "eeprom", "rw"),
    "shutdown": (63, 1, "eeprom", "rw"),
    "torque_enable": (64, 1, "ram", "rw"),
    "led": (65, 1, "ram", "rw"),
    "status_return_level": (68, 1, "ram", "rw"),
    "registered_instruction": (69, 1, "ram", "r"),
    "hardware_error_status": (70, 1, "ram", "r"),
    "velocity_i_gain": (76, 2, "ram", "rw"),
    "velocity_p_gain": (78, 2, "ram", "rw"),
    "position_d_gain": (80, 2, "ram", "rw"),
    "position_i_gain": (82, 2, "ram", "rw"),
    "position_p_gain": (84, 2, "ram", "rw"),
    "bus_watchdog": (98, 1, "ram", "rw"),
    "goal_pwm": (100, 2, "ram", "rw"),
    "goal_current": (102, 2, "ram", "rw"),
    "goal_velocity": (104, 4, "ram", "rw"),
    "profile_acceleration": (108, 4, "ram", "rw"),
    "profile_velocity": (112, 4, "ram", "rw"),
    "goal_position": (116, 4, "ram", "rw"),
    "realtime_tick": (120, 2, "ram", "r"),
    "moving": (122, 1, "ram", "r"),
    "moving_status": (123, 1, "ram", "r"),
    "present_pwm": (124, 2, "ram", "r"),
    "present_current": (126, 2, "ram", "r"),
    "present_velocity": (128, 4, "ram", "r"),
    "present_position": (132, 4, "ram", "r"),
    "velocity_trajectory": (136, 4, "ram", "r"),
    "position_trajectory": (140, 4, "ram", "r"),
    "present_input_voltage": (144, 2, "ram", "r"),
    "present_temperature": (146, 1, "ram", "r"),
}
POSITION_MODE = 3
POSITION_MODES = (3, 4, 5)  # position, extended position, current-based position
PROFILE_VELOCITY_UNIT_RPM = 0.229


def _crc_table() -> list[int]:
    table = []
    for i in range(256):
        c = i << 8
        for _ in range(8):
            c = ((c << 1) ^ 0x8005) if c & 0x8000 else (c << 1)
        table.append(c & 0xFFFF)
    return table


CRC_TABLE = _crc_table()  # the ROBOTIS table: CRC_TABLE[1] == 0x8005, CRC_TABLE[255] == 0x0202


def crc16(data: bytes, crc: int = 0) -> int:
    """ROBOTIS CRC-16 (poly 0x8005, init 0, MSB first) of data."""
    for b in data:
        crc = ((crc << 8) ^ CRC_TABLE[((crc >> 8) ^ b) & 0xFF]) & 0xFFFF
    return crc


def stuff(body: bytes) -> bytes:
    """Insert FD after every FF FF FD of body (instruction + parameters)."""
    out = bytearray()
    for b in body:
        out.append(b)
        if b == 0xFD and len(out) >= 3 and out[-3] == 0xFF and out[-2] == 0xFF:
            out.append(0xFD)
    return bytes(out)


def unstuff(body: bytes) -> bytes:
    """Remove the FD inserted after every FF FF FD."""
    out = bytearray()
    i = 0
    while i < len(body):
        b = body[i]
        out.append(b)
        if b == 0xFD and len(out) >= 3 and out[-3] == 0xFF and out[-2] == 0xFF and i + 1 < len(body) \
                and body[i + 1] == 0xFD:
            i += 1  # skip the stuffed FD
        i += 1
    return bytes(out)


def _packet(dxl_id: int, body: bytes) -> bytes:
    body = stuff(body)
    head = HEADER + bytes([dxl_id]) + struct.pack("<H", len(body) + 2)
    crc = crc16(head + body)
    return head + body + struct.pack("<H", crc)


def instruction_packet(dxl_id: int, inst: int, params: bytes = b"") -> bytes:
    """A complete instruction packet, stuffed, with its CRC."""
    return _packet(dxl_id, bytes([inst]) + bytes(params))


def status_packet(dxl_id: int, error: int, params: bytes = b"") -> bytes:
    """A complete status packet (what a motor answers)."""
    return _packet(dxl_id, bytes([Inst.STATUS, error]) + bytes(params))


class PacketError(TransientError):
    """A reply that is not a valid status packet (bad CRC, wrong id, truncated): retried."""


class StatusError(TransientError):
    """The motor answered with an error number in its status packet: retried."""

    def __init__(self, error: int, what: str = ""):
        self.error = error
        name = ERRORS.get(error & 0x7F, f"error {error & 0x7F}")
        super().__init__(f"{what}: motor reports {name} (status error byte 0x{error:02X})")


def parse_status(packet: bytes) -> tuple[int, int, bytes]:
    """(id, error, params) of one complete status packet; PacketError when it is not one."""
    if len(packet) < 11 or packet[:4] != HEADER:
        raise PacketError(f"not a status packet: {packet.hex(' ')}")
    length = packet[5] | packet[6] << 8
    if len(packet) != 7 + length:
        raise PacketError(f"length field {length} does not match {len(packet) - 7} bytes")
    crc = packet[-2] | packet[-1] << 8
    if crc16(packet[:-2]) != crc:
        raise PacketError(f"bad CRC 0x{crc:04X}, expected 0x{crc16(packet[:-2]):04X}")
    body = unstuff(packet[7:-2])
    if body[0] != Inst.STATUS:
        raise PacketError(f"instruction 0x{body[0]:02X} where a status (0x55) was expected")
    return packet[4], body[1], body[2:]


def read_packet(port, deadline: float) -> bytes:
    """Read one packet (FF FF FD 00 ... CRC) from port before the monotonic deadline, skipping any noise
    before the header. Raises TransientError on timeout (NoAnswer when not one byte came); serial errors
    propagate."""
    buf = bytearray()
    while True:
        i = buf.find(HEADER)
        if i > 0:
            del buf[:i]
        elif i < 0 and len(buf) > 3:
            del buf[:-3]
        if len(buf) >= 7 and buf[:4] == HEADER:
            need = 7 + (buf[5] | buf[6] << 8)
            if len(buf) >= need:
                return bytes(buf[:need])
        else:
            need = 7
        left = deadline - time.monotonic()
        if left <= 0:
            raise (TransientError if buf else NoAnswer)(f"timeout: {len(buf)} of {need} bytes of a status packet")
        buf += port.read(max(1, need - len(buf)))  # port.timeout is a fraction of the deadline


class DynamixelDriver(SerialDriver):
    """One Dynamixel X-series motor in position mode (Protocol 2.0)."""

    name = "dynamixel"

    def __init__(self, settings: MotorSettings, port: str, table: dict | None = None):
        super().__init__(settings)
        self.url = port
        self.table = table or XSERIES
        self.port = None
        self.model = None
        self.firmware = None
        self.alerts = 0  # status packets with the hardware alert bit
        self.last_goal_ticks: int | None = None

    def describe(self) -> str:
        return f"dynamixel id {self.settings.id} on {self.url} at {self.settings.baud} baud"

    # -- transport ----------------------------------------------------------------------------------------
    def _txrx(self, inst: int, params: bytes, what: str) -> bytes:
        """Send one instruction and return the parameters of its status packet; retried."""
        if self.port is None:
            raise Disconnected(f"{self.url} is not open")
        pkt = instruction_packet(self.settings.id, inst, params)
        last: Exception | None = None
        silent = True  # no try got a byte back
        for _ in range(self.settings.retries):
            try:
                self.port.reset_input_buffer()
                self.port.write(pkt)
                deadline = time.monotonic() + self.settings.timeout_s
                while True:
                    reply = read_packet(self.port, deadline)
                    dxl_id, error, data = parse_status(reply)
                    if dxl_id == self.settings.id:
                        break  # another id's status (a shared bus): keep reading
                if error & ALERT:
                    self.alerts += 1
                    log.warning("%s: hardware alert bit set (read hardware_error_status, address 70)", what)
                if error & 0x7F:
                    raise StatusError(error, what)
                return data
            except IO_ERRORS as e:
                raise Disconnected(f"{self.url}: {e}") from e
            except TransientError as e:
                self.errors += 1
                last = e
                silent = silent and isinstance(e, NoAnswer)
        raise (NoAnswer if silent else TransientError)(f"{what} failed {self.settings.retries} times on {self.url}: "
                                                       f"{last}")

    def read(self, name: str, signed: bool = False) -> int:
        addr, size, _, _ = self.table[name]
        data = self._txrx(Inst.READ, struct.pack("<HH", addr, size), f"read {name}")
        if len(data) != size:
            self.errors += 1
            raise PacketError(f"read {name}: {len(data)} bytes instead of {size}")
        return int.from_bytes(data, "little", signed=signed)

    def write(self, name: str, value: int) -> None:
        addr, size, _, _ = self.table[name]
        data = int(value).to_bytes(size, "little", signed=value < 0)
        self._txrx(Inst.WRITE, struct.pack("<H", addr) + data, f"write {name}={value}")

    def ping(self) -> tuple[int, int]:
        data = self._txrx(Inst.PING, b"", "ping")
        if len(data) != 3:
            raise PacketError(f"ping: {len(data)} parameter bytes instead of 3")
        return data[0] | data[1] << 8, data[2]

    # -- Driver -------------------------------------------------------------------------------------------
    def open(self) -> float:
        self.close(torque_off=False)
        self._open_port()
        try:
            try:
                self.model, self.firmware = self.ping()
            except TransientError as e:
                raise type(e)(f"no answer from Dynamixel id {self.settings.id} on {self.url} at "
                                     f"{self.settings.baud} baud ({e}); check power, id and baud rate "
                                     "(Dynamixel Wizard can scan for them)") from e
            mode = self.read("operating_mode")
            if mode not in POSITION_MODES:
                if self.read("torque_enable"):
                    self.write("torque_enable", 0)
                self.write("operating_mode", POSITION_MODE)
                log.info("operating mode %d -> %d (position)", mode, POSITION_MODE)
            if self.settings.set_profile_velocity and self.settings.max_speed_deg_s > 0:
                rpm = self.settings.max_speed_deg_s / 6.0
                self.write("profile_velocity", max(1, round(rpm / PROFILE_VELOCITY_UNIT_RPM)))
            present = self.read("present_position", signed=True)
            # hold where it is before enabling torque (the goal register may hold an old target)
            self.write("goal_position", present)
            self.write("torque_enable", 1)
            log.info("Dynamixel model %d firmware %d, id %d: torque on at %d ticks", self.model,
                     self.firmware, self.settings.id, present)
            return self.settings.from_ticks(present)
        except BaseException:
            self.close(torque_off=False)
            raise

    def _release(self) -> None:
        self.write("torque_enable", 0)

    def write_goal(self, pan_rad: float) -> None:
        ticks = self.settings.to_ticks(pan_rad)
        self.write("goal_position", ticks)
        self.last_goal_ticks = ticks

    def read_position(self) -> float:
        return self.settings.from_ticks(self.read("present_position", signed=True))
