"""Trajectories of the target's distance Z(t) in metres, from a short text spec.

    still:z=Z                      Z(t) = Z
    step:z0=Z0,z1=Z1,at=SECONDS    Z0 before `at`, Z1 from `at` on
    ramp:z0=Z0,z1=Z1,speed=M_PER_S from Z0 to Z1 at constant speed (from t = 0), then Z1
    sine:z=Z,amp=A,hz=F            Z(t) = Z + A sin(2 pi F t)
    square:z0=Z0,z1=Z1,hz=F        Z0 and Z1 in turn, a step every 1 / (2 F) s (Z0 first)

Every distance must stay positive (Z - A > 0 for a sine). A bad spec raises ValueError naming the item.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..spec import Key, SpecError, parse

__all__ = ["Motion", "parse_motion", "KINDS"]

KINDS = {"still": ("z",), "step": ("z0", "z1", "at"), "ramp": ("z0", "z1", "speed"), "sine": ("z", "amp", "hz"),
         "square": ("z0", "z1", "hz")}


@dataclass(frozen=True)
class Motion:
    """A parsed trajectory: kind and its numbers (metres, seconds, hertz)."""

    kind: str
    p: tuple[tuple[str, float], ...]

    def __getitem__(self, key: str) -> float:
        return dict(self.p)[key]

    @property
    def spec(self) -> str:
        return f"{self.kind}:" + ",".join(f"{k}={v:g}" for k, v in self.p)

    def z(self, t: float) -> float:
        """The target's distance at time t (seconds)."""
        q = dict(self.p)
        if self.kind == "still":
            return q["z"]
        if self.kind == "step":
            return q["z0"] if t < q["at"] else q["z1"]
        if self.kind == "ramp":
            z0, z1 = q["z0"], q["z1"]
            travel = q["speed"] * max(0.0, t)
            return z1 if travel >= abs(z1 - z0) else z0 + math.copysign(travel, z1 - z0)
        if self.kind == "square":
            return q["z1"] if math.floor(2 * q["hz"] * max(0.0, t)) % 2 else q["z0"]
        return q["z"] + q["amp"] * math.sin(2 * math.pi * q["hz"] * t)

    @property
    def z_range(self) -> tuple[float, float]:
        """The nearest and the farthest distance the target reaches."""
        q = dict(self.p)
        if self.kind == "still":
            return q["z"], q["z"]
        if self.kind == "sine":
            return q["z"] - abs(q["amp"]), q["z"] + abs(q["amp"])
        return min(q["z0"], q["z1"]), max(q["z0"], q["z1"])


def _keys(kind: str) -> list[Key]:
    """The keys of a kind (vergence.spec), all required: metres, seconds, hertz."""
    limits = {"speed": dict(above=0.0, unit="m/s"), "hz": dict(lo=0.0, unit="Hz"), "at": dict(lo=0.0, unit="s")}
    if kind == "square":
        limits["hz"] = dict(above=0.0, unit="Hz")
    return [Key(k, required=True, **limits.get(k, {})) for k in KINDS[kind]]


def parse_motion(spec: str) -> Motion:
    """A Motion from 'kind:key=value,...' (see the module's docstring); ValueError (vergence.spec.SpecError)
    naming the item."""
    kind, _, rest = (spec or "").strip().partition(":")
    kind = kind.strip()
    if kind not in KINDS:
        raise SpecError(f"motion {spec!r}: unknown kind {kind!r}; want one of "
                        + ", ".join(f"{k}:{','.join(v + '=' for v in keys)}" for k, keys in KINDS.items()))
    vals = parse(rest, _keys(kind), f"motion {spec!r}", sep=",")
    m = Motion(kind, tuple((k, vals[k]) for k in KINDS[kind]))
    if not m.z_range[0] > 0:
        raise SpecError(f"motion {spec!r}: the target comes to {m.z_range[0]:g} m; every distance must be > 0")
    return m
