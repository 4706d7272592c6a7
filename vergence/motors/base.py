"""The motor layer's contracts: per-motor settings, the driver interface, its faults, and the safety layer.

A driver moves one motor to an absolute pan (radians, positive toward increasing image x) and reports where
the motor is. Drivers know their wire protocol and nothing about commands; the safety layer (Safety) is the
only way a command becomes a goal: it drops what is not a number or is stale, and bounds what is left by
the soft limits and the step limit, counting what it clamped or ignored; its Ruling says what it made of
one command. Nothing here imports zenoh.

Safety is the one home of the motor's limits ([actuator.motor] min_deg, max_deg, max_step_deg,
dead_band_deg): the reducer's controller (vergence.head.control.Controller) asks a Safety built from the same
settings to bound each set-point it makes (inside, limit_step, dead_band_rad), and the actuator's own
Safety bounds whatever arrives (the last line: a message is a claim).
"""

from __future__ import annotations

import logging
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar

from ..ranges import Range, check

__all__ = ["MotorSettings", "Driver", "SerialDriver", "MotorError", "PortError", "Disconnected", "TransientError",
           "NoAnswer", "Safety", "Ruling"]

log = logging.getLogger("vergence.motors")


@dataclass(frozen=True)
class MotorSettings:
    """One pan motor, as wired ([actuator.motor] in the settings TOML).

    id: bus id (Dynamixel). baud: serial speed. ticks_per_rev: encoder ticks per turn (Dynamixel X: 4096).
    zero: the tick count at pan 0 (2048, the centre of an X-series). direction: +1, or -1 when the motor
    turns the camera the other way (toward decreasing image x for increasing ticks; the doubt's
    `reversed`): applied by vergence.motors.runner for every driver, which is given direction x pan.
    offset_deg: the slave camera's pan where the motor reads 0 (the pan zero's error, a float where zero is
    whole ticks; `vergence calibrate --distance` measures it): the pan the loop uses is direction x the
    motor's angle + offset, applied with direction for every driver (to_motor, from_motor); the limits below
    are of that pan.
    min_deg/max_deg: soft limits of the pan
    (the one home of the pan limits, max_step_deg and dead_band_deg: the reducer's controller reads them
    here too, through a Safety; [control] has none).
    max_speed_deg_s: the motor's top speed (the simulator's, and Dynamixel Profile Velocity when
    set_profile_velocity is true; 0 = the motor's own maximum). max_step_deg: the largest change of the goal
    per command. dead_band_deg: a target closer than this to the goal does not move the motor.
    watchdog_s: no valid command for this long -> hold the present position (0 = never).
    max_age_s: a command whose frame was captured longer ago than this is stale and ignored (0 = no check;
    needs the capture host's clock to agree with ours). max_skew_s: a command captured more than this
    ahead of our clock is implausible and ignored (a claim from the future would otherwise make every real
    command stale); 0 = no check. torque_off_on_stop: release the motor on exit.
    timeout_s: serial reply timeout; retries: attempts per transaction before it counts as failed.
    The simulated motor (vergence.motors.simulated), defaults of a Dynamixel X-series on a 1 Mbps bus:
    latency_s: from a goal written to the motor starting on it (the instruction and status packets, the
    return delay and one control period: about 2 ms). max_accel_deg_s2: the largest acceleration (0: none).
    tau_s: the position loop's time constant near the goal (the final approach is first order). quantise:
    the goal and the reported position are whole ticks (ticks_per_rev), as a Dynamixel's are. start_deg:
    its starting pan.
    """

    id: int = 1
    baud: int = 57600
    ticks_per_rev: int = 4096
    zero: int = 2048
    direction: int = 1
    offset_deg: float = 0.0
    min_deg: float = -45.0
    max_deg: float = 45.0
    max_speed_deg_s: float = 180.0
    max_step_deg: float = 10.0
    dead_band_deg: float = 0.0
    watchdog_s: float = 2.0
    max_age_s: float = 0.0
    max_skew_s: float = 2.0
    torque_off_on_stop: bool = True
    silent_s: float = 0.5
    absent_s: float = 2.0
    set_profile_velocity: bool = False
    timeout_s: float = 0.05
    retries: int = 3
    tau_s: float = 0.01
    start_deg: float = 0.0
    latency_s: float = 0.002
    max_accel_deg_s2: float = 5000.0
    quantise: bool = True

    RANGES: ClassVar[dict[str, Range]] = {
        "id": Range(0, 252, integer=True),
        "baud": Range(1200, 10_000_000, integer=True, note="bits per second"),
        "ticks_per_rev": Range(1, 1 << 24, integer=True),
        "zero": Range(-(1 << 31), (1 << 31) - 1, integer=True, note="ticks"),
        "direction": Range(-1, 1, integer=True, note="1 or -1"),
        "offset_deg": Range(-30, 30, note="degrees"),
        "min_deg": Range(-180, 180),
        "max_deg": Range(-180, 180),
        "max_speed_deg_s": Range(0, 1e6, note="0: the motor's own maximum"),
        "max_step_deg": Range(0, 360, lo_open=True),
        "dead_band_deg": Range(0, 10),
        "watchdog_s": Range(0, 3600, note="0: never"),
        "max_age_s": Range(0, 3600, note="0: no check"),
        "max_skew_s": Range(0, 3600, note="0: no check"),
        "silent_s": Range(0, 3600),
        "absent_s": Range(0, 3600),
        "timeout_s": Range(0, 10, lo_open=True),
        "retries": Range(1, 100, integer=True),
        "tau_s": Range(0, 10),
        "start_deg": Range(-180, 180),
        "latency_s": Range(0, 1),
        "max_accel_deg_s2": Range(0, 1e7, note="0: none"),
    }

    def __post_init__(self):
        check(self, self.RANGES)
        if self.direction not in (1, -1):
            raise ValueError(f"direction: must be 1 or -1, got {self.direction}")
        if self.min_deg > self.max_deg:
            raise ValueError(f"min_deg: must be at most max_deg ({self.max_deg:g}), got {self.min_deg}")

    @property
    def min_rad(self) -> float:
        return math.radians(self.min_deg)

    @property
    def max_rad(self) -> float:
        return math.radians(self.max_deg)

    @property
    def offset_rad(self) -> float:
        return math.radians(self.offset_deg)

    def to_motor(self, pan_rad: float) -> float:
        """The motor's own angle for a pan of the loop: direction x (pan - offset)."""
        return self.direction * (pan_rad - self.offset_rad)

    def from_motor(self, angle_rad: float) -> float:
        """The loop's pan for the motor's own angle: direction x angle + offset."""
        return self.direction * angle_rad + self.offset_rad

    def to_ticks(self, pan_rad: float) -> int:
        """Goal Position for the motor's angle (direction x pan, as MotorLoop gives it the driver): round(zero +
        angle * ticks_per_rev / 2 pi)."""
        return int(round(self.zero + pan_rad * self.ticks_per_rev / (2 * math.pi)))

    def from_ticks(self, ticks: int) -> float:
        return (ticks - self.zero) * 2 * math.pi / self.ticks_per_rev

    @property
    def tick_rad(self) -> float:
        """One tick of the encoder (rad; 0: a motor of any angle, `quantise` off)."""
        return 2 * math.pi / self.ticks_per_rev if self.quantise else 0.0

    def whole_ticks(self, angle_rad: float) -> float:
        """The motor's angle on its nearest whole tick, where it stops and what its encoder reads (`quantise`)."""
        tick = self.tick_rad
        return round(angle_rad / tick) * tick if tick else angle_rad


class MotorError(Exception):
    """Base of the motor faults."""


class PortError(MotorError):
    """The port cannot be opened (missing, busy, no permission): the message names it and the fix."""


class Disconnected(MotorError):
    """The port went away while running (unplugged): reconnect with backoff."""


class TransientError(MotorError):
    """A transaction failed after its retries (timeout, bad CRC, a status error): counted, never fatal."""


class NoAnswer(TransientError):
    """A transaction that got no reply at all, every retry timed out: the motor is silent (unpowered, a cut
    bus). The loop takes a silence of [actuator.motor] silent_s for a lost motor (vergence.motors.runner)."""


try:  # pyserial's posix backend lets termios.error (not an OSError) out of flush/reconfigure on a dead tty
    import termios as _termios
    _TERMIOS_ERRORS: tuple[type[BaseException], ...] = (_termios.error,)
except ImportError:  # pragma: no cover - windows
    _TERMIOS_ERRORS = ()
# serial.SerialException is an OSError
IO_ERRORS: tuple[type[BaseException], ...] = (OSError,) + _TERMIOS_ERRORS


def port_hint(port: str, err: object) -> str:
    return (f"cannot open serial port {port!r}: {err}. List the ports with "
            f"`python -m serial.tools.list_ports -v` (or `ls /dev/serial/by-id/`), then pass --port or set "
            f"[actuator] port in the settings")


class Driver(ABC):
    """One motor on one port. Positions are pan angles in radians; conversion to device units is the
    driver's business (MotorSettings.to_ticks). Drivers retry transient faults themselves and count them in
    `errors`; they raise Disconnected when the port is gone and TransientError when retries ran out."""

    name = "driver"

    def __init__(self, settings: MotorSettings):
        self.settings = settings
        self.errors = 0  # failed attempts (timeouts, bad CRC, status errors), retried or not

    @abstractmethod
    def open(self) -> float:
        """Connect and enable the motor; returns the present pan. Raises PortError or Disconnected."""

    @abstractmethod
    def close(self, torque_off: bool = True) -> None:
        """Release the port (and the motor, when torque_off). Never raises."""

    @abstractmethod
    def write_goal(self, pan_rad: float) -> None:
        """Send an absolute goal (already made safe)."""

    @abstractmethod
    def read_position(self) -> float:
        """The present pan in radians."""

    def first_exposure(self, t_ns: int) -> None:
        """The exposure (wall ns) of the first frame the motor is commanded for (MotorLoop, once): the sim
        motor's lies count from it, as the sim source's from its first exposure. A real motor ignores it."""

    def describe(self) -> str:
        return self.name


class SerialDriver(Driver):
    """A driver on a pyserial port (self.port, opened from self.url): closing releases the motor, best
    effort since the port may be gone, then the port."""

    port = None
    url = ""

    def _release(self) -> None:
        """Let the motor go (torque off): the driver's own command."""

    def _open_port(self) -> None:
        """Open self.url at the motor's baud rate; PortError (naming the port and how to list ports)."""
        import serial  # pyserial: only the serial drivers need it

        try:
            self.port = serial.serial_for_url(self.url, baudrate=self.settings.baud,
                                              timeout=self.settings.timeout_s / 4,
                                              write_timeout=max(0.5, self.settings.timeout_s))
        except IO_ERRORS + (ValueError,) as e:
            raise PortError(port_hint(self.url, e)) from e

    def close(self, torque_off: bool = True) -> None:
        if self.port is None:
            return
        if torque_off:
            try:
                self._release()
            except Exception as e:  # best effort: the port may be gone
                log.warning("releasing the motor failed on %s: %s", self.url, e)
        try:
            self.port.close()
        except Exception:
            pass
        self.port = None


@dataclass
class Ruling:
    """What the safety layer ruled on one command: goal is the motor's new goal (radians), None when the motor
    must not move (ignored, or inside the dead band); clamped, whether the target was bounded; reason, why it
    was ignored or clamped. (Not messages.Decision, the network's decision on a frame.)"""

    goal: float | None
    clamped: bool = False
    reason: str = ""  # why it was ignored or clamped ("" when taken as is)


class Safety:
    """Turns untrusted targets into goals: within [min, max], at most max_step from the previous goal.

    A target that is not finite, or comes from a frame captured before the last accepted one (stale), or
    older than max_age_s, or more than max_skew_s ahead of the clock (implausible), is ignored; the
    remembered capture time is never ahead of the clock, so no command locks the later ones out. One
    outside the soft limits or too far from the goal is clamped. The
    goal starts at the present position clamped into the limits. Counters: accepted, clamped, ignored, held
    (inside the dead band).
    """

    def __init__(self, settings: MotorSettings, start_rad: float = 0.0):
        self.s = settings
        self.lo, self.hi = settings.min_rad, settings.max_rad
        self.step = math.radians(settings.max_step_deg)
        self.dead = math.radians(settings.dead_band_deg)
        self.goal = self.inside(start_rad if math.isfinite(start_rad) else 0.0)
        self.last_t_capture = -1
        self.last_frame = -1
        self.accepted = self.clamped = self.ignored = self.held = 0
        self.last_reason = ""

    def inside(self, x: float) -> float:
        """x (radians) clamped into the soft limits [min_deg, max_deg]."""
        return min(self.hi, max(self.lo, x))

    def limit_step(self, start: float, x: float) -> float:
        """The pan nearest x (radians) that is inside the soft limits and at most max_step_deg from start
        (a goal, or the pan a set-point is made from); stateless, the same bounds as command()'s."""
        x = self.inside(x)
        if abs(x - start) > self.step:
            x = self.inside(start + math.copysign(self.step, x - start))
        return x

    @property
    def dead_band_rad(self) -> float:
        """dead_band_deg in radians: a target closer than this to the goal does not move the motor."""
        return self.dead

    def reset(self, present_rad: float) -> float:
        """At (re)connection, or when the watchdog fires: the goal becomes the present position clamped into
        the limits, so the motor stays where it is (or, found outside the limits, comes back to the nearest
        one at the motor's own speed). The only goal change not bounded by max_step."""
        if math.isfinite(present_rad):
            self.goal = self.inside(present_rad)
        return self.goal

    def _ignore(self, reason: str) -> Ruling:
        self.ignored += 1
        self.last_reason = reason
        return Ruling(None, reason=reason)

    def command(self, pan_rad: object, frame: int = -1, t_capture_ns: int = 0, now_ns: int | None = None
                ) -> Ruling:
        """The goal for one target, or Ruling(None) when the motor keeps its goal."""
        if isinstance(pan_rad, bool) or not isinstance(pan_rad, (int, float)):
            return self._ignore(f"target {pan_rad!r} is not a number")
        try:
            x = float(pan_rad)
        except OverflowError:
            x = math.inf
        if not math.isfinite(x):
            return self._ignore(f"target {x} is not finite")
        if t_capture_ns > 0:
            if self.s.max_skew_s > 0 and now_ns is not None and t_capture_ns - now_ns > self.s.max_skew_s * 1e9:
                return self._ignore(f"implausible: frame {frame} captured {(t_capture_ns - now_ns) / 1e9:.3g} s "
                                    f"in the future")
            if t_capture_ns < self.last_t_capture:
                return self._ignore(f"stale: frame {frame} captured before frame {self.last_frame}")
            if self.s.max_age_s > 0 and now_ns is not None and now_ns - t_capture_ns > self.s.max_age_s * 1e9:
                return self._ignore(f"stale: frame {frame} is {(now_ns - t_capture_ns) / 1e9:.3f} s old")
            self.last_t_capture = t_capture_ns if now_ns is None else min(t_capture_ns, now_ns)
            self.last_frame = frame
        reasons = []
        if x < self.lo or x > self.hi:
            reasons.append(f"target {math.degrees(x):.3g} deg outside "
                           f"[{self.s.min_deg:g}, {self.s.max_deg:g}]")
            x = self.inside(x)
        if abs(x - self.goal) > self.step:
            reasons.append(f"step {math.degrees(x - self.goal):+.3g} deg beyond {self.s.max_step_deg:g}")
            x = self.limit_step(self.goal, x)
        if abs(x - self.goal) < self.dead and not reasons:
            self.held += 1
            return Ruling(None, reason="dead band")
        self.accepted += 1
        if reasons:
            self.clamped += 1
            self.last_reason = "; ".join(reasons)
        self.goal = x
        return Ruling(x, clamped=bool(reasons), reason="; ".join(reasons))
