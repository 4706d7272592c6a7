"""A line protocol for custom motor controllers (an Arduino driving a stepper, say), over any pyserial URL.

ASCII lines ending in "\\n" (a "\\r" before it is ignored); positions are signed decimal integers in the
device's own units (steps), mapped to the pan by the motor settings exactly as Dynamixel ticks are:
pan = direction * (position - zero) * 2 pi / ticks_per_rev.

    host -> device       device -> host
    Q                    <position>          where the motor is now
    P <position>         OK <position>       go there (the device echoes the goal it took)
    E 1 | E 0            OK                  enable / release the motor (optional: a device that answers
                                             ERR ... to E still works; torque off then does nothing)
    anything else        ERR <text>

A device may print other lines (a banner after reset, debug output): lines that are not the expected answer
are skipped. A timeout, or an ERR answer to Q or P, is retried and counted.
"""

from __future__ import annotations

import logging
import re
import time


from .base import IO_ERRORS, Disconnected, MotorSettings, NoAnswer, SerialDriver, TransientError

__all__ = ["LineDriver"]

log = logging.getLogger("vergence.motors.line")

_INT = re.compile(r"^[+-]?\d+$")


class DeviceError(TransientError):
    """The device answered ERR."""


class LineDriver(SerialDriver):
    name = "line"

    def __init__(self, settings: MotorSettings, port: str):
        super().__init__(settings)
        self.url = port
        self.port = None
        self.buf = bytearray()
        self.skipped = 0  # unexpected lines
        self.enable_supported = True
        self.last_goal: int | None = None

    def describe(self) -> str:
        return f"line protocol on {self.url} at {self.settings.baud} baud"

    def _readline(self, deadline: float) -> str:
        while True:
            i = self.buf.find(b"\n")
            if i >= 0:
                line = bytes(self.buf[:i]).decode("ascii", "replace").strip()
                del self.buf[:i + 1]
                return line
            if time.monotonic() >= deadline:
                raise (TransientError if self.buf else NoAnswer)(f"timeout waiting for a line ({bytes(self.buf)!r} "
                                                                 "so far)")
            if len(self.buf) > 4096:
                self.buf.clear()
            self.buf += self.port.read(max(1, self.port.in_waiting))

    def _transact(self, line: str, accept, device_errors_fatal: bool = False) -> object:
        """Send a line; return accept(answer) for the first answer it does not reject with None."""
        if self.port is None:
            raise Disconnected(f"{self.url} is not open")
        last: Exception | None = None
        silent = True  # no try got a byte back
        for _ in range(self.settings.retries):
            try:
                self.port.reset_input_buffer()
                self.buf.clear()
                self.port.write(line.encode("ascii") + b"\n")
                deadline = time.monotonic() + self.settings.timeout_s
                while True:
                    answer = self._readline(deadline)
                    if answer.startswith("ERR"):
                        raise DeviceError(f"{line!r}: device answered {answer!r}")
                    value = accept(answer)
                    if value is not None:
                        return value
                    self.skipped += 1
            except IO_ERRORS as e:
                raise Disconnected(f"{self.url}: {e}") from e
            except TransientError as e:
                self.errors += 1
                last = e
                silent = silent and isinstance(e, NoAnswer)
                if device_errors_fatal and isinstance(e, DeviceError):
                    raise
        raise (NoAnswer if silent else TransientError)(f"{line!r} failed {self.settings.retries} times on "
                                                       f"{self.url}: {last}")

    def query(self) -> int:
        return self._transact("Q", lambda a: int(a) if _INT.match(a) else None)

    def goto(self, position: int) -> int:
        def ok(a: str):
            parts = a.split()
            if len(parts) == 2 and parts[0] == "OK" and _INT.match(parts[1]):
                return int(parts[1])
            return None
        return self._transact(f"P {position}", ok)

    def enable(self, on: bool) -> None:
        if not self.enable_supported:
            return
        try:
            self._transact(f"E {int(on)}", lambda a: a if a == "OK" else None, device_errors_fatal=True)
        except DeviceError as e:
            self.enable_supported = False
            log.warning("device does not take E (enable): %s; going on without it", e)

    def open(self) -> float:
        self.close(torque_off=False)
        self._open_port()
        try:
            try:
                present = self.query()
            except TransientError as e:
                raise TransientError(f"no answer to Q from the controller on {self.url} at "
                                     f"{self.settings.baud} baud ({e}); check the baud rate and the firmware")
            self.goto(present)  # hold where it is before enabling (the device may keep an old goal)
            self.enable(True)
            return self.settings.from_ticks(present)
        except BaseException:
            self.close(torque_off=False)
            raise

    def _release(self) -> None:
        self.enable(False)

    def write_goal(self, pan_rad: float) -> None:
        pos = self.settings.to_ticks(pan_rad)
        took = self.goto(pos)
        if took != pos:
            log.warning("controller took %d for goal %d (its own limit?)", took, pos)
        self.last_goal = took

    def read_position(self) -> float:
        return self.settings.from_ticks(self.query())
