"""The simulator lies too (issue #35), so that the loop's doubt is tested without hardware: the faults of real heads
as spec keys, the same for the sim source (`--source sim:freeze=1-3`) and `vergence sim --faults freeze=1-3`.

Camera side (the images): freeze=T0-T1 (the slave camera repeats its last image, byte for byte, as a driver does),
freeze_master=T0-T1, black=T0-T1 (both cameras black), reverse (the camera turns against the encoder), slip=T0-T1
(the encoder moves, the camera does not; after T1 it follows again, off by what slipped), backlash=DEG (the camera
lags the shaft within a dead zone of DEG), focal_true=F (images rendered at focal length F px, while the settings
say the spec's focal), zero=DEG (the slave camera sits DEG further than its encoder says: a pan zero that is off,
which `vergence calibrate --distance` measures and [actuator.motor] offset_deg corrects). Motor side: stall=T0-T1
(nothing moves; the encoder says so), encoder_noise=DEG (Gaussian noise on each encoder reading): in `vergence up`
the sim actuator's (`vergence actuator --faults`, which `up` gives a sim source's two keys; the sim source knows
them too, for its frames' pans and its replica of the motor; their times count from the exposure of the first frame
commanded); and late=S (`vergence sim` only: the loop is told each image is S younger than it is, as an unstamped
camera's latency that [camera] latency_s does not say; S at most --camera-latency. The sim source has it as
latency=S:stamps=no with latency_s unset). Times are seconds from the first exposure."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from ..spec import Key, parse

__all__ = ["Faults", "Lies", "FAULT_KEYS", "MOTOR_KEYS", "motor_lies"]

FAULT_KEYS = [Key("freeze", "range", lo=0, unit="s"), Key("freeze_master", "range", lo=0, unit="s"),
              Key("black", "range", lo=0, unit="s"), Key("reverse", "flag"), Key("slip", "range", lo=0, unit="s"),
              Key("stall", "range", lo=0, unit="s"), Key("backlash", lo=0, hi=10, unit="deg"),
              Key("focal_true", above=0, hi=1e5, unit="px"), Key("encoder_noise", lo=0, hi=5, unit="deg"),
              Key("zero", lo=-30, hi=30, unit="deg"), Key("late", lo=0, hi=1, unit="s")]
MOTOR_KEYS = [k for k in FAULT_KEYS if k.name in ("stall", "encoder_noise")]  # the sim actuator's lies


@dataclass(frozen=True)
class Faults:
    """The faults of one run (FAULT_KEYS' values; None or 0: not there)."""

    freeze: tuple[float, float] | None = None
    freeze_master: tuple[float, float] | None = None
    black: tuple[float, float] | None = None
    reverse: bool = False
    slip: tuple[float, float] | None = None
    stall: tuple[float, float] | None = None
    backlash: float | None = None
    focal_true: float | None = None
    encoder_noise: float | None = None
    zero: float | None = None
    late: float | None = None

    @classmethod
    def take(cls, items: dict) -> Faults:
        """The faults among a parsed spec's items (vergence.spec.parse with FAULT_KEYS), removed from `items`."""
        return cls(**{f.name: items.pop(f.name) for f in fields(cls) if f.name in items})

    def motor(self) -> Faults:
        """The motor's lies alone (stall, encoder_noise): what the sim actuator takes in `vergence up`."""
        return Faults(stall=self.stall, encoder_noise=self.encoder_noise)

    def __bool__(self) -> bool:
        return any(getattr(self, f.name) for f in fields(self))

    def spec(self) -> str:
        """The spec these faults were read from (in FAULT_KEYS' order)."""
        out = []
        for f in fields(self):
            v = getattr(self, f.name)
            if v is True:
                out.append(f.name)
            elif isinstance(v, tuple):
                out.append(f"{f.name}={v[0]:g}-{v[1]:g}")
            elif v:
                out.append(f"{f.name}={v:g}")
        return ":".join(out)


def motor_lies(spec: str) -> dict:
    """The sim motor's keywords (vergence.motors.simulated.SimMotor: stall, noise_deg) for `vergence actuator --faults
    SPEC` (MOTOR_KEYS); SpecError naming the key."""
    f = Faults.take(parse(spec, MOTOR_KEYS, "--faults"))
    return {"stall": f.stall, "noise_deg": f.encoder_noise or 0.0}


def within(span: tuple[float, float] | None, t: float) -> bool:
    return span is not None and span[0] <= t < span[1]


class Lies:
    """Applies Faults to a rig's cameras and encoder, in time order: camera() for the slave camera's pan at an
    instant of its exposure, slave_inputs() / master_inputs() for what a frozen camera renders, images() for the
    pair as the cameras give it, encoder() for a reading."""

    def __init__(self, faults: Faults, seed: int = 0):
        self.f = faults
        self.cam: float | None = None  # the camera's pan (backlash, slip)
        self.slipped = 0.0  # how far the camera is behind the shaft after a slip
        self.slip_at: float | None = None  # the shaft's pan when the slip began
        self.held_inputs: dict[str, object] = {}  # the inputs a frozen camera keeps rendering
        self.held: dict[tuple, np.ndarray] = {}  # (camera, key) -> the image it repeats
        self.rng = np.random.default_rng(seed)

    def camera(self, shaft: float, t: float) -> float:
        """The slave camera's pan when the motor's shaft is at `shaft` (its own sense: direction x pan) at time t;
        `reverse` mounts the camera the other way about the pan zero (a motor that turns the other way than
        [actuator.motor] direction says); `zero` turns it that much further than the encoder says."""
        f = self.f
        if within(f.slip, t):
            if self.slip_at is None:
                self.slip_at = shaft - self.slipped
            pan = self.slip_at
        else:
            if self.slip_at is not None:
                self.slipped = shaft - self.slip_at
                self.slip_at = None
            pan = shaft - self.slipped
        if f.reverse:
            pan = -pan
        if f.backlash:
            half = math.radians(f.backlash) / 2
            if self.cam is None:
                self.cam = pan
            self.cam = min(max(self.cam, pan - half), pan + half)
            pan = self.cam
        if f.zero:
            pan += math.radians(f.zero)
        return pan

    def inputs(self, which: str, t: float, now):
        """What camera `which` ("slave" or "master") renders at t: `now` unless it is frozen then, when the inputs of
        its last image before the freeze."""
        span = self.f.freeze if which == "slave" else self.f.freeze_master
        if within(span, t):
            return self.held_inputs.setdefault(which, now)
        self.held_inputs[which] = now
        self.held = {k: v for k, v in self.held.items() if k[0] != which}
        return now

    def images(self, t: float, key, master: np.ndarray, slave: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The pair as the cameras give it at t: black, or a frozen camera's image repeated byte for byte (`key`:
        what was rendered, e.g. the rows of a band)."""
        if within(self.f.black, t):
            return np.zeros_like(master), np.zeros_like(slave)
        if within(self.f.freeze, t):
            slave = self.held.setdefault(("slave", key), slave)
        if within(self.f.freeze_master, t):
            master = self.held.setdefault(("master", key), master)
        return master, slave

    def stalled(self, t: float) -> bool:
        return within(self.f.stall, t)

    def encoder(self, pan: float) -> float:
        """An encoder reading with the noise of encoder_noise."""
        if self.f.encoder_noise:
            return pan + float(self.rng.normal(0.0, math.radians(self.f.encoder_noise)))
        return pan
