"""Typed settings for every process, loaded from one TOML file; errors name the offending field.

    rig = "head"          # the rig's name (the key prefix vergence/<rig>/), or name = "head" in [rig]
    [rig]       # the rig's geometry: baseline_m, focal_px, master, gimbal (vergence.depth)
    [network]   # vergence.match.Params: window, vsearch, circular, subpixel, min_margin, ...
    [capture]   # source, rate_hz, preview_hz, focal_px, master
    [reducer]   # deadline_ms
    [control]   # gain, dead_band_px, max_step_deg, min_deg, max_deg
    [actuator]  # driver, port, and the motor (see vergence.motors)
    [limits]    # what a message may claim before it is believed (clock skew, frame window, sizes, membership)
"""

from __future__ import annotations

import dataclasses
import re
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path

from .control import ControlSettings
from .match import Params
from .motors.base import MotorSettings

__all__ = ["ConfigError", "RigSettings", "CaptureSettings", "ReducerSettings", "ActuatorSettings", "LimitSettings",
           "Settings", "load", "from_dict"]


class ConfigError(ValueError):
    """A settings file or value that is wrong; the message names the field."""


@dataclass(frozen=True)
class RigSettings:
    """The `[rig]` table, the head's geometry (vergence.depth): baseline_m, the distance between the two
    cameras' optical centres in metres; focal_px, the focal length in pixels of the views the capture reads
    (0: [capture] focal_px, else the source's own, else 0.8 x width); master, which camera is the fixed one,
    left or right ("": [capture] master, left); gimbal, helmholtz (both cameras pan on one tilting
    platform) or fick (each camera tilts on its own pan joint). The rig's name is the top-level `rig = "head"`
    (or `name` in this table)."""

    baseline_m: float = 0.06
    focal_px: float = 0.0
    master: str = ""
    gimbal: str = "helmholtz"

    def __post_init__(self):
        import math

        if not (math.isfinite(self.baseline_m) and self.baseline_m > 0):
            raise ValueError(f"baseline_m={self.baseline_m}: must be a positive number of metres")
        if not (math.isfinite(self.focal_px) and self.focal_px >= 0):
            raise ValueError(f"focal_px={self.focal_px}: must be a number of pixels >= 0 (0: the capture's)")
        if self.master not in ("", "left", "right"):
            raise ValueError(f"master={self.master!r}: must be left or right")
        if self.gimbal not in ("helmholtz", "fick"):
            raise ValueError(f"gimbal={self.gimbal!r}: must be helmholtz or fick")


@dataclass(frozen=True)
class CaptureSettings:
    """source: sim[:...] | files:L,R | video:L,R | camera:0,1. rate_hz: frames per second (0: as fast as
    the source gives them). preview_hz: rate of the downscaled preview. focal_px: focal length in pixels
    (0: the source's own, else 0.8 x width). master: which camera is the fixed one, left or right."""

    source: str = "sim"
    rate_hz: float = 30.0
    preview_hz: float = 2.0
    preview_width: int = 160
    focal_px: float = 0.0
    master: str = "left"


@dataclass(frozen=True)
class ReducerSettings:
    """deadline_ms: a frame whose shards are not all in by then is dropped and counted."""

    deadline_ms: float = 50.0


@dataclass(frozen=True)
class ActuatorSettings:
    """driver: sim | dynamixel | line. port: a pyserial URL (/dev/ttyUSB0, socket://host:port, loop://).
    state_hz: rate of vergence/<rig>/motor/state. motor: the motor ([actuator.motor], vergence.motors)."""

    driver: str = "sim"
    port: str = ""
    state_hz: float = 50.0
    motor: MotorSettings = field(default_factory=MotorSettings)


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

    def __post_init__(self):
        for name in ("max_skew_s", "reanchor_s", "miss_s", "probation_s"):
            v = getattr(self, name)
            if not (v > 0 and v < float("inf")):
                raise ValueError(f"{name} must be a positive number, got {v}")
        for name in ("frame_window", "max_frame_bytes", "max_frame_ops", "miss_frames"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")


@dataclass(frozen=True)
class Settings:
    rig: str = "head"
    geometry: RigSettings = field(default_factory=RigSettings)  # the TOML's [rig] table
    network: Params = field(default_factory=Params)
    capture: CaptureSettings = field(default_factory=CaptureSettings)
    reducer: ReducerSettings = field(default_factory=ReducerSettings)
    control: ControlSettings = field(default_factory=ControlSettings)
    actuator: ActuatorSettings = field(default_factory=ActuatorSettings)
    limits: LimitSettings = field(default_factory=LimitSettings)


def _coerce(path: str, value, tp):
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        tp = args[0]
        origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        return _build(path, value, tp)
    if tp is bool:
        if isinstance(value, bool):
            return value
    elif tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
    elif tp is str:
        if isinstance(value, str):
            return value
    elif origin in (list, tuple):
        (inner, *_) = typing.get_args(tp)
        if isinstance(value, (list, tuple)):
            return type(value)(_coerce(f"{path}[{i}]", v, inner) for i, v in enumerate(value))
    else:
        return value
    raise ConfigError(f"{path}: expected {getattr(tp, '__name__', tp)}, got {value!r}")


def _rig_table(data: dict) -> dict:
    """The TOML's [rig] table (with its optional name) as Settings' rig (the name) and geometry."""
    table = data.get("rig")
    if not isinstance(table, dict):
        return data
    if "geometry" in data:
        raise ConfigError("geometry: unknown setting; the rig's geometry is the [rig] table")
    table = dict(table)
    data = dict(data)
    name = table.pop("name", "head")
    if not isinstance(name, str):
        raise ConfigError(f"rig.name: expected str, got {name!r}")
    data["rig"] = name
    data["geometry"] = _build("rig", table, RigSettings)
    return data


def _build(path: str, data, cls):
    if dataclasses.is_dataclass(data) and isinstance(data, cls):
        return data
    if not isinstance(data, dict):
        raise ConfigError(f"{path or 'settings'}: expected a table, got {data!r}")
    if cls is Settings:
        data = _rig_table(data)
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - names)
    if unknown:
        where = f"{path}." if path else ""
        raise ConfigError(f"{where}{unknown[0]}: unknown setting; known here: {', '.join(sorted(names))}")
    kw = {k: _coerce(f"{path}.{k}" if path else k, v, hints[k]) for k, v in data.items()}
    try:
        return cls(**kw)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{path or 'settings'}: {e}") from None


def from_dict(data: dict, cls=Settings):
    """Settings (or any settings dataclass) from a plain dict, checked field by field."""
    return _build("", data, cls)


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
        return _build("", data, cls)
    except ConfigError as e:
        raise ConfigError(f"{p}: {e}") from None


def replace(settings, **changes):
    """dataclasses.replace that checks types like the loader (section.field=value overrides)."""
    data = dataclasses.asdict(settings)
    for dotted, value in changes.items():
        d = data
        *parents, leaf = dotted.split(".")
        for part in parents:
            d = d.setdefault(part, {})
        d[leaf] = value
    return _build("", data, type(settings))
