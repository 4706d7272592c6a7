"""A custom controller speaking the line protocol of vergence.motors.line: Q, P <n>, E 0|1.

The position follows the goal at a finite speed (steps per second) while enabled; P outside [lo, hi] is
answered ERR; faults can be injected for the next answers (drop, garbage line, ERR)."""

from __future__ import annotations

import threading
import time


class LineEmulator:
    def __init__(self, position: int = 2048, speed_steps_s: float = 20000.0, lo: int = -10**6,
                 hi: int = 10**6, supports_enable: bool = True, banner: str = "", clock=time.monotonic):
        self.lock = threading.Lock()
        self.position = float(position)
        self.goal = position
        self.speed = speed_steps_s
        self.lo, self.hi = lo, hi
        self.enabled = not supports_enable  # a controller without E is always enabled
        self.supports_enable = supports_enable
        self.clock = clock
        self.t = clock()
        self.buf = bytearray()
        self.lines: list[str] = []  # every line received
        self.goals: list[int] = []  # every P accepted
        self.drop_next = 0
        self.garbage_next = 0
        self.err_next = 0
        self.pending = banner.encode() if banner else b""

    def _advance(self) -> None:
        now = self.clock()
        dt, self.t = now - self.t, now
        if self.enabled:
            step = self.speed * dt
            d = self.goal - self.position
            self.position = self.goal if abs(d) <= step else self.position + (step if d > 0 else -step)

    def feed(self, data: bytes) -> bytes:
        with self.lock:
            self.buf += data
            out = bytearray(self.pending)
            self.pending = b""
            while b"\n" in self.buf:
                i = self.buf.index(b"\n")
                line = bytes(self.buf[:i]).decode("ascii", "replace").strip()
                del self.buf[:i + 1]
                self.lines.append(line)
                answer = self._answer(line)
                if self.drop_next:
                    self.drop_next -= 1
                    continue
                if self.garbage_next:
                    self.garbage_next -= 1
                    out += b"#debug: \xff\x00 noise\n"
                if self.err_next:
                    self.err_next -= 1
                    answer = "ERR injected"
                out += answer.encode() + b"\n"
            return bytes(out)

    def _answer(self, line: str) -> str:
        self._advance()
        parts = line.split()
        if parts == ["Q"]:
            return str(int(round(self.position)))
        if len(parts) == 2 and parts[0] == "P":
            try:
                n = int(parts[1])
            except ValueError:
                return "ERR bad number"
            if not self.lo <= n <= self.hi:
                return "ERR out of range"
            self.goal = n
            self.goals.append(n)
            return f"OK {n}"
        if len(parts) == 2 and parts[0] == "E" and parts[1] in ("0", "1") and self.supports_enable:
            self.enabled = parts[1] == "1"
            return "OK"
        return "ERR unknown command"
