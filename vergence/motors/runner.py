"""The actuator's logic without the network: command bytes in, motor goals and MotorState messages out.

services/pipeline/actuator.py only subscribes, hands the newest command to `MotorLoop.command`, calls `tick` at the
state rate and publishes what they return. Everything that decides something lives here, so it is tested
with the simulated motor and a fake clock:
- malformed messages are counted and skipped (logged once per kind of fault);
- targets go through the safety layer (limits, step, stale, dead band);
- the watchdog holds the present position when commands stop;
- a port lost while running gives status "disconnected", reconnection attempts with exponential backoff (up to
  1 s), and resumes without a restart; transient faults (timeouts, bad CRC, status errors) are counted, never
  fatal;
- a motor that answers nothing for [actuator.motor] silent_s (every transaction timed out: unpowered, a cut
  bus) is lost the same way: nothing more is written to it, it is probed until it answers (issue #29);
- lost for absent_s, the status turns "absent" and an error is logged, repeated every ABSENT_REPEAT_S; the
  commands meanwhile are ignored (counted); when it answers again it holds where it is (its goal register is
  rewritten with its present position, vergence.motors.dynamixel) until a new command;
- [actuator.motor] direction and offset_deg are applied here, for every driver (issues #35, #36): a driver is
  given direction x (pan - offset) and its reading r is taken as direction x r + offset, so a motor that turns
  the other way (the doubt's `reversed`), or a camera whose pan zero is off its encoder's, is fixed by one
  setting whatever drives it (sim, ROS 2, Dynamixel, line).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable

from ..wire.messages import Command, MessageError, MotorState
from .base import Disconnected, Driver, MotorError, MotorSettings, NoAnswer, PortError, Safety, TransientError

__all__ = ["MotorLoop", "ABSENT_REPEAT_S"]

log = logging.getLogger("vergence.actuator")
ABSENT_REPEAT_S = 30.0  # an absent motor's error is logged again this often
AWAY = ("disconnected", "absent")  # the statuses of a motor that is not written to


class MotorLoop:
    """One motor driven by commands. Not thread-safe: call it from one thread."""

    def __init__(self, driver: Driver, settings: MotorSettings, rig: str = "head",
                 clock: Callable[[], float] = time.monotonic, wall_ns: Callable[[], int] = time.time_ns,
                 backoff_s: tuple[float, float] = (0.1, 1.0)):
        self.driver = driver
        self.s = settings
        self.rig = rig
        self.clock = clock
        self.wall_ns = wall_ns
        self.backoff = backoff_s
        self.safety = Safety(settings)
        self.pan = math.nan
        self.status = "starting"
        self.frame = -1
        self.t_capture_ns = 0
        self.commands = 0
        self.malformed = 0
        self.reconnects = 0
        self.note = ""
        self._last_cmd = clock()
        self._held = False
        self._retry_at = 0.0
        self._delay = backoff_s[0]
        self._answered = clock()  # the latest transaction the motor answered (or its connection)
        self._lost_at = 0.0  # when it was lost (status disconnected or absent)
        self._said_absent = 0.0  # when its absence was last logged
        self._why_lost = ""  # what lost it (no answer for silent_s, the port gone)
        self._logged: set[str] = set()
        self._exposed = False  # the driver was told the first commanded frame's exposure

    # -- lifecycle ----------------------------------------------------------------------------------------
    def start(self) -> MotorState:
        """Open the driver; a PortError here is fatal (the caller prints it). Disconnected is retried."""
        try:
            present = self.s.from_motor(self.driver.open())
        except PortError:
            raise
        except MotorError as e:
            self._lost(e)
            return self.state()
        self._connected(present)
        return self.state()

    def stop(self) -> MotorState:
        self.driver.close(torque_off=self.s.torque_off_on_stop)
        self.status = "stopped"
        return self.state()

    # -- inputs -------------------------------------------------------------------------------------------
    def command(self, data: bytes | Command) -> MotorState | None:
        """One command message (bytes from the wire, or decoded). Returns the state to publish."""
        self.commands += 1
        if not isinstance(data, Command):
            try:
                data = Command.from_bytes(data)
            except MessageError as e:
                self.malformed += 1
                self._once("malformed", f"skipping a malformed command: {e}")
                self.note = f"malformed command: {e}"[:200]
                return self.state()
        if self.status in AWAY:
            self.safety.ignored += 1
            self.note = (f"command ignored: motor {self.status} for {self.clock() - self._lost_at:.1f} s "
                         f"({self._why_lost})")[:200]
            return self.state()
        self._last_cmd = self.clock()
        self._held = False
        v = self.safety.command(data.pan_rad, data.frame, data.t_capture_ns, self.wall_ns())
        if not self._exposed and self.safety.last_t_capture > 0:  # (a plausible command's exposure)
            self._exposed = True
            self.driver.first_exposure(self.safety.last_t_capture)
        if v.goal is None:
            if v.reason and v.reason != "dead band":
                self.note = f"ignored: {v.reason}"
                self._once("ignored:" + v.reason.split(":")[0], f"command ignored: {v.reason}")
        else:
            self.frame, self.t_capture_ns = data.frame, data.t_capture_ns
            if v.clamped:
                self.note = f"clamped: {v.reason}"
                self._once("clamped", f"command clamped: {v.reason}")
            if self._io(self._write, v.goal) is not _FAILED:
                if self.status in ("hold", "starting", "error"):
                    self.status = "ok"
        self._read()
        return self.state()

    def superseded(self, n: int) -> None:
        """n commands were replaced by a newer one before the motor thread took them (a flood): they count
        as received and ignored."""
        if n > 0:
            self.commands += n
            self.safety.ignored += n
            self.note = f"{n} command(s) superseded by newer ones"
            self._once("superseded", "commands arrive faster than the motor takes them: the newest is used")

    def tick(self) -> MotorState:
        """The periodic step: reconnect when due, watchdog, read the position. Returns the state."""
        now = self.clock()
        if self.status in AWAY:
            self._absent(now)
            if now >= self._retry_at:
                self._reconnect()
            return self.state()
        wd = self.s.watchdog_s
        if wd > 0 and not self._held and now - self._last_cmd > wd:
            self._read()
            goal = self.safety.reset(self.pan)
            self._io(self._write, goal)
            self._held = True
            self.status = "hold"
            self.note = f"watchdog: no command for {wd:g} s, holding {math.degrees(goal):.2f} deg"
            # normal once the gaze has converged (the reducer sends nothing inside its dead band): not a warning
            log.info("%s", self.note)
        self._read()
        return self.state()

    # -- internals ----------------------------------------------------------------------------------------
    def _once(self, kind: str, text: str) -> None:
        if kind not in self._logged:
            self._logged.add(kind)
            log.warning("%s (logged once)", text)

    def _absent(self, now: float) -> None:
        """Lost for absent_s: status "absent", an error logged (again every ABSENT_REPEAT_S)."""
        away = now - self._lost_at
        if self.s.absent_s <= 0 or away < self.s.absent_s:
            return
        if self.status != "absent":
            self.status = "absent"
            log.error("motor absent for %.1f s (lost: %s); commands are ignored until it answers, probed every "
                      "%.1f s at most", away, self._why_lost, self.backoff[1])
            self._said_absent = now
        elif now - self._said_absent >= ABSENT_REPEAT_S:
            log.error("motor still absent after %.0f s (lost: %s; latest try: %s)", away, self._why_lost, self.note)
            self._said_absent = now

    def _read(self) -> None:
        if self.status in AWAY:
            return
        p = self._io(self.driver.read_position)
        if p is not _FAILED and math.isfinite(p):
            self.pan = self.s.from_motor(p)

    def _write(self, pan: float) -> None:
        """A goal (already made safe) to the driver, in the motor's own sense of rotation."""
        self.driver.write_goal(self.s.to_motor(pan))

    def _io(self, fn, *args):
        try:
            out = fn(*args)
            self._answered = self.clock()
            return out
        except NoAnswer as e:
            self.note = f"fault: {e}"[:200]
            silent = self.clock() - self._answered
            if self.s.silent_s > 0 and silent >= self.s.silent_s:
                self._lost(Disconnected(f"no answer for {silent:.1f} s: {e}"))
            else:
                self._once("transient:" + type(e).__name__, f"motor fault (retried, counted): {e}")
            return _FAILED
        except TransientError as e:
            self.note = f"fault: {e}"[:200]
            self._once("transient:" + type(e).__name__, f"motor fault (retried, counted): {e}")
            return _FAILED
        except (Disconnected, PortError) as e:
            self._lost(e)
            return _FAILED

    def _lost(self, e: Exception) -> None:
        if self.status not in AWAY:
            log.warning("motor disconnected: %s; retrying with backoff", e)
            self._lost_at = self.clock()
            self._why_lost = str(e)[:200]
        if self.status != "absent":
            self.status = "disconnected"
        self.note = f"disconnected: {e}"[:200]
        self.driver.close(torque_off=False)
        self._delay = self.backoff[0]
        self._retry_at = self.clock() + self._delay

    def _reconnect(self) -> None:
        try:
            present = self.s.from_motor(self.driver.open())
        except MotorError as e:
            self._delay = min(self.backoff[1], self._delay * 2)
            self._retry_at = self.clock() + self._delay
            self.note = f"disconnected: {e}; next try in {self._delay:.2f} s"[:200]
            return
        self.reconnects += 1
        log.warning("motor reconnected (%d) after %.1f s %s", self.reconnects, self.clock() - self._lost_at,
                    self.status)
        self._connected(present)

    def _connected(self, present: float) -> None:
        self.pan = present
        if self.safety.reset(present) != present:  # found outside the soft limits: bring it back in
            self._io(self._write, self.safety.goal)
        self.status = "ok"
        self.note = ""
        self._last_cmd = self._answered = self.clock()
        self._held = False

    def state(self) -> MotorState:
        s, g = self.safety, self.safety.goal
        at_limit = g <= s.lo + 1e-12 or g >= s.hi - 1e-12
        pan = self.pan if math.isfinite(self.pan) else g
        t_ns = getattr(self.driver, "position_ns", None) or self.wall_ns()  # ros2: the joint state's own stamp
        return MotorState(rig=self.rig, t_ns=t_ns, pan_rad=pan,
                          goal_rad=g, min_rad=s.lo, max_rad=s.hi, status=self.status, driver=self.driver.name,
                          frame=self.frame, t_capture_ns=self.t_capture_ns, at_limit=at_limit,
                          clamped=s.clamped, ignored=s.ignored, errors=self.driver.errors, note=self.note,
                          malformed=self.malformed, commands=self.commands, offset_deg=self.s.offset_deg)


_FAILED = object()
