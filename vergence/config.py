"""Typed settings for every process, loaded from one TOML file; errors name the offending field.

The settings are frozen dataclasses (vergence.network.params.Params, vergence.head.control.ControlSettings and
vergence.motors.MotorSettings among them); msgspec checks a parsed file against them (types, unknown keys,
each class's __post_init__), its errors giving the path (network.window: expected `int`, got `str`).
A setting that moved is an error naming where it lives now (MOVED): [control] min_deg, max_deg and
max_step_deg are [actuator.motor]'s since the motor's limits got one home (no deprecation period: two
values for one limit would leave the reader guessing which one holds).

    rig = "head"          # the rig's name (the key prefix vergence/<rig>/), or name = "head" in [rig]
    [rig]       # the rig's geometry: baseline_m, focal_px, master, gimbal (vergence.head.depth)
    [network]   # vergence.network.params.Params: window, vsearch, circular, subpixel, min_margin, ...
    [capture]   # source, rate_hz, preview_hz, focal_px, master
    [camera]    # latency_s, skew_s: the cameras' timing where a source does not stamp its images
    [reducer]   # deadline_ms
    [control]   # mode, gain, dead_band_px, the predictive filter (vergence.head.control.ControlSettings)
    [actuator]  # driver, port, and the motor (see vergence.motors): [actuator.motor] min_deg, max_deg,
                # max_step_deg, dead_band_deg are the one home of the pan limits (the reducer's controller
                # and the actuator both read them there)
    [supervise] # `vergence up`: heartbeat_s, start_grace_s, stall_s (liveness by heartbeat, issue #29);
                # restart_s, restart_max_s (the back-off before a restart)
    [limits]    # what a message may claim before it is believed (clock skew, frame window, sizes, membership)
    [ros2]      # the ROS 2 bridge: look_at (unset: on unless a deployed ACL is in force), discovery (localhost)
"""

from __future__ import annotations

import dataclasses
import re
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path

import msgspec

from .head.control import ControlSettings
from .choices import Gimbal, Side
from .network.params import Params
from .motors import DRIVERS
from .motors.base import MotorSettings
from .ranges import Range, check
from .head.timing import CameraTiming

__all__ = ["ConfigError", "MOVED", "RigSettings", "CaptureSettings", "CameraSettings", "ReducerSettings",
           "ActuatorSettings", "LimitSettings", "SuperviseSettings", "Ros2Settings", "DISCOVERY", "Settings", "load",
           "from_dict"]


class ConfigError(ValueError):
    """A settings file or value that is wrong; the message names the field."""


@dataclass(frozen=True)
class RigSettings:
    """The `[rig]` table, the head's geometry (vergence.head.depth): baseline_m, the distance between the two
    cameras' optical centres in metres; focal_px, the focal length in pixels of the views the capture reads
    (0: [capture] focal_px, else the source's own, else 0.8 x width); master, which camera is the fixed one,
    left or right ("": [capture] master, left); gimbal, helmholtz (both cameras pan on one tilting
    platform) or fick (each camera tilts on its own pan joint); pan_axis_m, how far behind the slave's optical
    centre its pan axis is (metres; `vergence calibrate` measures it from points at several pans). The rig's
    name is the top-level `rig = "head"` (or `name` in this table)."""

    baseline_m: float = 0.06
    focal_px: float = 0.0
    master: str = ""
    gimbal: str = "helmholtz"
    pan_axis_m: float = 0.0

    RANGES: typing.ClassVar[dict[str, Range]] = {
        "baseline_m": Range(0, 10, lo_open=True, note="metres"),
        "focal_px": Range(0, 100_000, note="pixels; 0: the capture's"),
        "pan_axis_m": Range(-0.5, 0.5, note="metres behind the slave's optical centre"),
    }

    def __post_init__(self):
        check(self, self.RANGES)
        if self.master not in ("", "left", "right"):
            raise ValueError(f"master={self.master!r}: must be left or right")
        if self.gimbal not in tuple(Gimbal):
            raise ValueError(f"gimbal={self.gimbal!r}: must be helmholtz or fick")


@dataclass(frozen=True)
class CaptureSettings:
    """source: sim[:...] | files:L,R | video:L,R | camera:0,1 | ros2:LEFT,RIGHT (vergence.io.sources). rate_hz:
    frames per second (0: as fast as the source gives them). preview_hz: rate of the downscaled preview.
    focal_px: focal length in pixels (0: the source's own, else 0.8 x width). master: which camera is the fixed
    one, left or right."""

    source: str = "sim:motion=sine:z=0.8,amp=0.3,hz=0.2"  # the demo: a target moving in depth; "sim": still
    rate_hz: float = 30.0
    preview_hz: float = 2.0
    preview_width: int = 160
    focal_px: float = 0.0
    master: str = "left"

    RANGES: typing.ClassVar[dict[str, Range]] = {
        "rate_hz": Range(0, 1000, note="0: as fast as the source gives them"),
        "preview_hz": Range(0, 100, note="0: no preview"),
        "preview_width": Range(0, 8192, integer=True, note="pixels; 0: the full width"),
        "focal_px": Range(0, 100_000, note="pixels; 0: the source's"),
    }

    def __post_init__(self):
        check(self, self.RANGES)
        if self.master not in tuple(Side):
            raise ValueError(f"master={self.master!r}: must be left or right")


@dataclass(frozen=True)
class CameraSettings:
    """The `[camera]` table: the cameras' timing where the source does not stamp its images (or its stamps
    are not believable): latency_s, from the exposure of the later image to its read (the image is this old
    when the capture gets it; `vergence latency` measures it); skew_s, the slave's exposure after the master's
    (negative: before). Both in seconds (vergence.head.timing.CameraTiming). cx, cy, slave_cx, slave_cy: each
    camera's principal point in pixels (-1: the source's, a camera_info's, else the image centre; issue #36). k1, k2,
    p1, p2, k3: both cameras' lens distortion, OpenCV's plumb_bob (all 0: the source's, a camera_info's, else none):
    the capture removes it from the rows a frame reads (vergence.io.lens)."""

    latency_s: float = 0.0
    skew_s: float = 0.0
    cx: float = -1.0
    cy: float = -1.0
    slave_cx: float = -1.0
    slave_cy: float = -1.0
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0

    RANGES: typing.ClassVar[dict[str, Range]] = {
        **{k: CameraTiming.RANGES[k] for k in ("latency_s", "skew_s")},
        **{k: Range(-1, 100_000, note="pixels; -1: the source's, else the image centre")
           for k in ("cx", "cy", "slave_cx", "slave_cy")},
        **{k: Range(-10, 10, note="OpenCV's plumb_bob; all 0: the source's, else none")
           for k in ("k1", "k2", "p1", "p2", "k3")}}

    @property
    def distortion(self) -> dict[str, float]:
        """The distortion coefficients set ({}: none)."""
        d = {k: getattr(self, k) for k in ("k1", "k2", "p1", "p2", "k3")}
        return d if any(d.values()) else {}

    def __post_init__(self):
        self.timing()  # its checks (CameraTiming.RANGES), with their messages
        check(self, {k: r for k, r in self.RANGES.items() if k not in ("latency_s", "skew_s")})

    def timing(self) -> CameraTiming:
        return CameraTiming(latency_s=self.latency_s, skew_s=self.skew_s)


@dataclass(frozen=True)
class ReducerSettings:
    """deadline_ms: a frame whose shards are not all in by then is dropped and counted. summary_s: how often the
    reducer logs what the loop is doing (one line: frames, commands, the offset, the pans)."""

    deadline_ms: float = 50.0
    summary_s: float = 5.0

    RANGES: typing.ClassVar[dict[str, Range]] = {"deadline_ms": Range(0, 10_000, lo_open=True),
                                                 "summary_s": Range(0.5, 3600, note="seconds")}

    def __post_init__(self):
        check(self, self.RANGES)


@dataclass(frozen=True)
class ActuatorSettings:
    """driver: one of vergence.motors.DRIVERS (sim | dynamixel | line | ros2). port: a pyserial URL (/dev/ttyUSB0,
    socket://host:port, loop://), or the ros2 driver's CONTROLLER[:key=value...]. state_hz: rate of
    vergence/<rig>/motor_state. motor: the motor ([actuator.motor], vergence.motors)."""

    driver: str = "sim"
    port: str = ""
    state_hz: float = 50.0
    motor: MotorSettings = field(default_factory=MotorSettings)

    RANGES: typing.ClassVar[dict[str, Range]] = {"state_hz": Range(0, 1000, lo_open=True)}

    def __post_init__(self):
        check(self, self.RANGES)
        if self.driver not in DRIVERS:
            raise ValueError(f"driver: must be one of {', '.join(DRIVERS)}, got {self.driver!r}")


@dataclass(frozen=True)
class LimitSettings:
    """What a message may claim before it moves any state (a message is a claim, not a fact).

    max_skew_s: a capture time more than this ahead of or behind the receiver's clock (time.time_ns: same
    host, or an NTP'd cluster) is implausible. frame_window: a frame id more than this ahead of the newest
    completed frame is implausible. reanchor_s: when no frame completed for this long, the reducer forgets
    its newest frame and takes any plausible one again (self-recovery). max_frame_bytes, max_frame_ops: the
    largest frame a worker computes (its bytes; rows x offsets x window^2 of layer 4). miss_s: a worker in
    the plan that the reducer has not heard from for this long, and whose shards missed miss_frames frames in a
    row, leaves the plan; probation_s: when it is
    tried again (doubling on each miss, up to 32 x)."""

    max_skew_s: float = 2.0
    frame_window: int = 1000
    reanchor_s: float = 1.0
    max_frame_bytes: int = 4 * 1024 * 1024
    max_frame_ops: int = 200_000_000
    miss_s: float = 0.25
    miss_frames: int = 3
    probation_s: float = 4.0

    RANGES: typing.ClassVar[dict[str, Range]] = {
        "max_skew_s": Range(0, 3600, lo_open=True),
        "frame_window": Range(1, 1_000_000_000, integer=True),
        "reanchor_s": Range(0, 3600, lo_open=True),
        "max_frame_bytes": Range(1, 1 << 30, integer=True),
        "max_frame_ops": Range(1, 1e12, integer=True),
        "miss_s": Range(0, 3600, lo_open=True),
        "miss_frames": Range(1, 1_000_000, integer=True),
        "probation_s": Range(0, 3600, lo_open=True),
    }

    def __post_init__(self):
        check(self, self.RANGES)


@dataclass(frozen=True)
class SuperviseSettings:
    """How `vergence up` tells a hung child from a busy one (services/runtime/heartbeat.py, services/ops/up.py).

    heartbeat_s: a child (or standby) whose heartbeat, a byte every 0.1 s from a thread of its own, has been
    missing this long is hung (SIGSTOP, a debugger, swapped out): it is SIGKILLed and handled as an exit (its
    standby takes over, or it is restarted). start_grace_s: the time a fresh child has for its first beat (its
    interpreter starting; the thread starts before any heavy import, so it beats through a numba compile).
    stall_s: a child whose own loop (its status, the actuator's motor loop) has not turned for this long stops
    beating, so a deadlocked loop is hung too (0: not checked).

    restart_s: the wait before restarting a child that died (with no standby to take over), doubled at each
    death that comes before the child has run 10 s, up to restart_max_s; back to restart_s after a longer run."""

    heartbeat_s: float = 1.5
    start_grace_s: float = 30.0
    stall_s: float = 10.0
    restart_s: float = 0.2
    restart_max_s: float = 5.0

    RANGES: typing.ClassVar[dict[str, Range]] = {
        "heartbeat_s": Range(0, 3600, lo_open=True, note="seconds"),
        "start_grace_s": Range(0, 3600, lo_open=True, note="seconds"),
        "stall_s": Range(0, 3600, note="seconds; 0: not checked"),
        "restart_s": Range(0, 3600, lo_open=True, note="seconds"),
        "restart_max_s": Range(0, 3600, lo_open=True, note="seconds"),
    }

    def __post_init__(self):
        check(self, self.RANGES)
        if 0 < self.stall_s <= self.heartbeat_s:
            raise ValueError(f"stall_s: must exceed heartbeat_s ({self.heartbeat_s:g}) or be 0, got {self.stall_s}")
        if self.restart_max_s < self.restart_s:
            raise ValueError(f"restart_max_s: must be at least restart_s ({self.restart_s:g}), got "
                             f"{self.restart_max_s}")


DISCOVERY = ("localhost", "subnet", "environment")


@dataclass(frozen=True)
class Ros2Settings:
    """The `[ros2]` table, the ROS 2 bridge's (`vergence ros2`, `up --ros2`; docs/ROS2.md, docs/CLUSTER.md).

    look_at: whether a look_at from the ROS 2 graph moves the fovea. Unset: on where the bridge's Zenoh session
    is not authenticated (a plain `vergence up --ros2`), off where it is (a client config of deploy/make-certs.sh:
    a deployed ACL is in force, and look_at would let any node in reach of the bridge move the fovea that the
    ACL lets only the fixate role move); true or false wins. While off, a look_at moves nothing: it is counted
    (look_at_off), logged at most once a second and shown as a WARN on /diagnostics.
    discovery: the range the bridge's own ROS 2 node discovers in: localhost (this host only: the default), subnet
    (ROS 2 Jazzy's default range), environment (ROS_AUTOMATIC_DISCOVERY_RANGE and ROS_STATIC_PEERS as the
    environment sets them). The ros2 source's and the ros2 driver's nodes always keep the environment's range
    (cameras and controllers may be on other hosts)."""

    look_at: bool | None = None
    discovery: str = "localhost"

    def __post_init__(self):
        if self.discovery not in DISCOVERY:
            raise ValueError(f"discovery: must be one of {', '.join(DISCOVERY)}, got {self.discovery!r}")


@dataclass(frozen=True)
class Settings:
    rig: str = "head"
    geometry: RigSettings = field(default_factory=RigSettings)  # the TOML's [rig] table
    network: Params = field(default_factory=Params)
    capture: CaptureSettings = field(default_factory=CaptureSettings)
    camera: CameraSettings = field(default_factory=CameraSettings)
    reducer: ReducerSettings = field(default_factory=ReducerSettings)
    control: ControlSettings = field(default_factory=ControlSettings)
    actuator: ActuatorSettings = field(default_factory=ActuatorSettings)
    limits: LimitSettings = field(default_factory=LimitSettings)
    supervise: SuperviseSettings = field(default_factory=SuperviseSettings)
    ros2: Ros2Settings = field(default_factory=Ros2Settings)


_CHECKS: dict[type, type] = {}


def _check_type(cls):
    """A msgspec.Struct with the settings dataclass cls's fields and types (nested settings too) that forbids
    unknown keys: msgspec.convert into it checks a table's keys and types, naming the path; made once per class.
    Its defaults are never used (the dataclass's are)."""
    check = _CHECKS.get(cls)
    if check is None:
        hints = typing.get_type_hints(cls)
        spec = [(f.name, _check_type(hints[f.name]) if dataclasses.is_dataclass(hints[f.name]) else hints[f.name],
                 None) for f in dataclasses.fields(cls) if f.init]
        check = _CHECKS[cls] = msgspec.defstruct(f"{cls.__name__}Check", spec, forbid_unknown_fields=True)
    return check


def _rig_table(data: dict) -> dict:
    """The TOML's [rig] table (with its optional name) as Settings' rig (the name) and geometry."""
    if "geometry" in data:  # Settings' field, not a table's name: one name per table
        raise ConfigError("geometry: unknown setting; the rig's geometry is the [rig] table")
    table = data.get("rig")
    if not isinstance(table, dict):
        return data
    table = dict(table)
    data = dict(data)
    name = table.pop("name", "head")
    if not isinstance(name, str):
        raise ConfigError(f"rig.name: expected str, got {name!r}")
    data["rig"] = name
    data["geometry"] = table
    return data


# settings that moved: (the class of the table they were in, their name) -> where they are now
MOVED: dict[tuple[type, str], str] = {
    (ControlSettings, "min_deg"): "[actuator.motor] min_deg",
    (ControlSettings, "max_deg"): "[actuator.motor] max_deg",
    (ControlSettings, "max_step_deg"): "[actuator.motor] max_step_deg",
}


def _table(cls, path: list[str]):
    """The settings class of the table at path."""
    for part in path:
        cls = typing.get_type_hints(cls)[part]
    return cls


def _known(cls, path: list[str]) -> list[str]:
    """The setting names of the table at path (the dataclass fields there)."""
    return sorted(f.name for f in dataclasses.fields(_table(cls, path)) if f.init)


def _error(e: msgspec.ValidationError, cls) -> ConfigError:
    """msgspec's "what - at `$.a.b`" as "a.b: what" (the [rig] table's fields by their TOML name, rig.x)."""
    what, _, at = str(e).partition(" - at `$")
    path = [p for p in at.rstrip("`").split(".") if p]
    if cls is Settings and path[:1] == ["geometry"]:
        path[0] = "rig"
    unknown = re.fullmatch(r"Object contains unknown field `(.*)`", what)
    if unknown:
        where = ["geometry" if p == "rig" and cls is Settings else p for p in path]
        moved = MOVED.get((_table(cls, where), unknown[1]))
        if moved:
            return ConfigError(f"{'.'.join(path + [unknown[1]])}: moved to {moved} (the motor's limits have one "
                               "home, which the reducer's controller and the actuator both read)")
        names = sorted({"rig" if n == "geometry" and cls is Settings and not where else n for n in _known(cls, where)})
        return ConfigError(f"{'.'.join(path + [unknown[1]])}: unknown setting; known here: {', '.join(names)}")
    what = what.replace("Expected `object`", "expected a table").replace("Expected", "expected")
    what = what.replace("`bool | null`", "`bool` (true or false; left out: the default)")  # TOML has no null
    # a table's own check (__post_init__, vergence.ranges) names its field first: capture.rate_hz: must be ...
    named = re.match(r"(\w+)[:= ]", what)
    table = _table(cls, ["geometry" if p == "rig" and cls is Settings else p for p in path]) if path else None
    if named and dataclasses.is_dataclass(table) and named[1] in _known(table, []):
        return ConfigError(f"{'.'.join(path)}.{what}")
    return ConfigError(f"{'.'.join(path) or 'settings'}: {what}")


def from_dict(data: dict, cls=Settings):
    """Settings (or any settings dataclass) from a plain dict (a parsed TOML), checked by msgspec: types, unknown
    keys and each class's own value checks, the error naming the field's path (network.window)."""
    if cls is Settings and isinstance(data, dict):
        data = _rig_table(data)
    try:
        msgspec.convert(data, _check_type(cls))  # the keys and the types
        return msgspec.convert(data, cls)  # the values, each settings class's __post_init__
    except msgspec.ValidationError as e:
        raise _error(e, cls) from None


def load(path: str | Path | None = None, cls=Settings):
    """Settings from a TOML file (defaults when path is None). A missing file, bad TOML or a bad field
    raises ConfigError that says which."""
    if path is None:
        return cls()
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as e:
        raise ConfigError(f"cannot read settings file {p}: {e.strerror}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        hint = ""
        if re.search(r"^\s*rig\s*=", text, re.M) and re.search(r"^\s*\[rig\]", text, re.M):
            hint = ' (rig = "..." and a [rig] table cannot both be there: write name = "..." in [rig])'
        raise ConfigError(f"{p}: not valid TOML: {e}{hint}") from None
    try:
        return from_dict(data, cls)
    except ConfigError as e:
        raise ConfigError(f"{p}: {e}") from None
