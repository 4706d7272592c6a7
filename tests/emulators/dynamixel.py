"""A Dynamixel X-series motor (XM430-W350 defaults) speaking Protocol 2.0 byte for byte.

Written from the ROBOTIS e-Manual independently of vergence.motors.dynamixel (its own bitwise CRC, its own
stuffing and parsing), so that tests of the driver against it check two readings of the spec against each
other, and the known packets of the e-Manual pin both.

What it does: finds packets in the byte stream (skipping noise), checks the CRC (a bad one is answered with
the CRC error), removes stuffing, answers PING, READ and WRITE for its id (PING also for the broadcast id),
keeps the control table as bytes, refuses writes to read-only fields and to the EEPROM area while torque
is on (access error), checks values (data range / data limit errors), and moves Present Position toward
Goal Position at a finite speed while torque is on. Faults can be injected for the next replies, and
silence(s) makes it answer nothing for s seconds (a motor unpowered, or its bus cut), then come back.
"""

from __future__ import annotations

import struct
import threading
import time

HEADER = b"\xff\xff\xfd\x00"
PING, READ, WRITE, STATUS = 0x01, 0x02, 0x03, 0x55
ERR_RESULT, ERR_INSTRUCTION, ERR_CRC, ERR_RANGE, ERR_LENGTH, ERR_LIMIT, ERR_ACCESS = 1, 2, 3, 4, 5, 6, 7

# address: (name, size, eeprom, writable, default)
TABLE = {
    0: ("model_number", 2, True, False, 1020),
    2: ("model_information", 4, True, False, 0),
    6: ("firmware_version", 1, True, False, 46),
    7: ("id", 1, True, True, 1),
    8: ("baud_rate", 1, True, True, 1),
    9: ("return_delay_time", 1, True, True, 250),
    10: ("drive_mode", 1, True, True, 0),
    11: ("operating_mode", 1, True, True, 3),
    12: ("secondary_id", 1, True, True, 255),
    13: ("protocol_type", 1, True, True, 2),
    20: ("homing_offset", 4, True, True, 0),
    24: ("moving_threshold", 4, True, True, 10),
    31: ("temperature_limit", 1, True, True, 80),
    32: ("max_voltage_limit", 2, True, True, 160),
    34: ("min_voltage_limit", 2, True, True, 95),
    36: ("pwm_limit", 2, True, True, 885),
    38: ("current_limit", 2, True, True, 1193),
    44: ("velocity_limit", 4, True, True, 200),
    48: ("max_position_limit", 4, True, True, 4095),
    52: ("min_position_limit", 4, True, True, 0),
    63: ("shutdown", 1, True, True, 52),
    64: ("torque_enable", 1, False, True, 0),
    65: ("led", 1, False, True, 0),
    68: ("status_return_level", 1, False, True, 2),
    69: ("registered_instruction", 1, False, False, 0),
    70: ("hardware_error_status", 1, False, False, 0),
    98: ("bus_watchdog", 1, False, True, 0),
    104: ("goal_velocity", 4, False, True, 0),
    108: ("profile_acceleration", 4, False, True, 0),
    112: ("profile_velocity", 4, False, True, 0),
    116: ("goal_position", 4, False, True, 2048),
    120: ("realtime_tick", 2, False, False, 0),
    122: ("moving", 1, False, False, 0),
    128: ("present_velocity", 4, False, False, 0),
    132: ("present_position", 4, False, False, 2048),
    144: ("present_input_voltage", 2, False, False, 120),
    146: ("present_temperature", 1, False, False, 30),
}
ADDR = {v[0]: k for k, v in TABLE.items()}
SIZE = 147
OPERATING_MODES = {0, 1, 3, 4, 5, 16}


def crc16_bitwise(data: bytes) -> int:
    """CRC-16/BUYPASS (poly 0x8005, init 0, MSB first), bit by bit: the ROBOTIS CRC."""
    crc = 0
    for b in data:
        crc ^= b << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


def add_stuffing(body: bytes) -> bytes:
    out = bytearray()
    for i, b in enumerate(body):
        out.append(b)
        if b == 0xFD and i >= 2 and body[i - 2] == 0xFF and body[i - 1] == 0xFF:
            out.append(0xFD)
    return bytes(out)


def remove_stuffing(body: bytes) -> bytes:
    out = bytearray()
    skip = False
    for i, b in enumerate(body):
        if skip:
            skip = False
            continue
        out.append(b)
        if b == 0xFD and i >= 2 and body[i - 2:i] == b"\xff\xff" and body[i + 1:i + 2] == b"\xfd":
            skip = True
    return bytes(out)


def build(dxl_id: int, body: bytes) -> bytes:
    body = add_stuffing(body)
    head = HEADER + bytes([dxl_id]) + struct.pack("<H", len(body) + 2)
    return head + body + struct.pack("<H", crc16_bitwise(head + body))


class DynamixelEmulator:
    """feed(bytes) -> reply bytes. Thread-safe (the pty thread feeds, the test inspects)."""

    def __init__(self, dxl_id: int = 1, speed_ticks_s: float = 20000.0, present: int = 2048,
                 clock=time.monotonic):
        self.lock = threading.Lock()
        self.mem = bytearray(SIZE)
        for addr, (_, size, _, _, default) in TABLE.items():
            self.mem[addr:addr + size] = default.to_bytes(size, "little", signed=default < 0)
        self.set("id", dxl_id)
        self.set("present_position", present)
        self.set("goal_position", present)
        self.speed = speed_ticks_s
        self.clock = clock
        self.t = clock()
        self.buf = bytearray()
        self.packets: list[tuple[int, int, bytes]] = []  # (id, instruction, params) of every valid packet
        self.goal_writes: list[int] = []
        self.goal_log: list[tuple[float, int]] = []  # (clock(), value) of each goal write it took
        self.silent_until = 0.0  # clock() before which it hears and answers nothing (silence())
        self.unheard: list[tuple[float, int, int]] = []  # (clock(), id, instruction) of packets sent while silent
        self.errors_sent: list[int] = []
        self.bad_crc = 0
        # fault injection for the next replies
        self.corrupt_next = 0
        self.drop_next = 0
        self.error_next = 0
        self.noise_next = b""

    # -- table --------------------------------------------------------------------------------------------
    def get(self, name: str, signed: bool = True) -> int:
        addr = ADDR[name]
        size = TABLE[addr][1]
        return int.from_bytes(self.mem[addr:addr + size], "little", signed=signed)

    def set(self, name: str, value: int) -> None:
        addr = ADDR[name]
        size = TABLE[addr][1]
        self.mem[addr:addr + size] = int(value).to_bytes(size, "little", signed=value < 0)

    def _advance(self) -> None:
        now = self.clock()
        dt, self.t = now - self.t, now
        if not self.get("torque_enable"):
            return
        pos, goal = self.get("present_position"), self.get("goal_position")
        step = self.speed * dt
        pos = goal if abs(goal - pos) <= step else pos + (step if goal > pos else -step)
        self.set("present_position", int(round(pos)))
        self.set("moving", int(pos != goal))

    def silence(self, seconds: float) -> None:
        """Answer nothing, and take nothing in, for `seconds` from now (an unpowered motor, or a cut bus)."""
        with self.lock:
            self.silent_until = self.clock() + seconds

    def silent(self) -> bool:
        return self.clock() < self.silent_until

    def _unheard(self, data: bytes) -> None:
        """Note the packets in data (their id and instruction) that a silent motor does not hear."""
        i = 0
        while (i := data.find(HEADER, i)) >= 0 and i + 7 < len(data):
            self.unheard.append((self.clock(), data[i + 4], data[i + 7]))
            i += 4

    # -- bytes --------------------------------------------------------------------------------------------
    def feed(self, data: bytes) -> bytes:
        with self.lock:
            if self.silent():
                self._unheard(data)
                self.buf.clear()
                return b""
            self.buf += data
            out = bytearray()
            while True:
                i = self.buf.find(HEADER)
                if i < 0:
                    del self.buf[:max(0, len(self.buf) - 3)]
                    break
                del self.buf[:i]
                if len(self.buf) < 7:
                    break
                need = 7 + (self.buf[5] | self.buf[6] << 8)
                if need < 10:  # shorter than instruction + CRC: not a packet, resync
                    del self.buf[:1]
                    continue
                if len(self.buf) < need:
                    break
                pkt, self.buf = bytes(self.buf[:need]), self.buf[need:]
                out += self._packet(pkt)
            return bytes(out)

    def _packet(self, pkt: bytes) -> bytes:
        dxl_id = pkt[4]
        me = self.get("id")
        crc = pkt[-2] | pkt[-1] << 8
        if crc16_bitwise(pkt[:-2]) != crc:
            self.bad_crc += 1
            return self._reply(ERR_CRC, b"") if dxl_id == me else b""
        body = remove_stuffing(pkt[7:-2])
        inst, params = body[0], body[1:]
        self.packets.append((dxl_id, inst, params))
        if dxl_id not in (me, 0xFE):
            return b""
        self._advance()
        if inst == PING:
            return self._reply(0, struct.pack("<HB", self.get("model_number"), self.get("firmware_version")))
        if dxl_id == 0xFE:
            return b""
        if inst == READ:
            if len(params) != 4:
                return self._reply(ERR_LENGTH)
            addr, n = struct.unpack("<HH", params)
            if n == 0 or addr + n > SIZE:
                return self._reply(ERR_ACCESS)
            return self._reply(0, bytes(self.mem[addr:addr + n]))
        if inst == WRITE:
            if len(params) < 3:
                return self._reply(ERR_LENGTH)
            addr = params[0] | params[1] << 8
            return self._reply(self._write(addr, params[2:]))
        return self._reply(ERR_INSTRUCTION)

    def _write(self, addr: int, data: bytes) -> int:
        if addr not in TABLE:
            return ERR_ACCESS
        name, size, eeprom, writable, _ = TABLE[addr]
        if len(data) != size:
            return ERR_LENGTH
        if not writable:
            return ERR_ACCESS
        if eeprom and self.get("torque_enable"):
            return ERR_ACCESS  # EEPROM is locked while torque is on
        value = int.from_bytes(data, "little", signed=True)
        if name == "operating_mode" and value not in OPERATING_MODES:
            return ERR_RANGE
        if name == "torque_enable" and value not in (0, 1):
            return ERR_RANGE
        if name == "goal_position":
            self.goal_writes.append(value)
            self.goal_log.append((self.clock(), value))
            if self.get("operating_mode") == 3 and not (
                    self.get("min_position_limit") <= value <= self.get("max_position_limit")):
                return ERR_LIMIT
        self.mem[addr:addr + size] = data
        return 0

    def _reply(self, error: int, params: bytes = b"") -> bytes:
        if self.drop_next:
            self.drop_next -= 1
            return b""
        if self.error_next:
            error, params = self.error_next, b""
            self.error_next = 0
        self.errors_sent.append(error)
        pkt = bytearray(build(self.get("id"), bytes([STATUS, error]) + params))
        if self.corrupt_next:
            self.corrupt_next -= 1
            pkt[-1] ^= 0x5A
        noise, self.noise_next = self.noise_next, b""
        return noise + bytes(pkt)

    def writes_to(self, name: str) -> list[int]:
        """Values written to a field, in order (from the packets received)."""
        addr = ADDR[name]
        with self.lock:
            return [int.from_bytes(p[2:], "little", signed=True) for i, inst, p in self.packets
                    if inst == WRITE and len(p) >= 2 and p[0] | p[1] << 8 == addr]
