"""One parser for the `key=value:key=value` options of a spec (issue #34): the simulator's (`sim:noise=2:...`),
its motions (`sine:z=0.8,amp=0.3,hz=0.5`, items separated by commas), the ROS 2 source's and the ROS 2 driver's.

A caller declares its keys (Key: a name, a kind, a default, a range or the choices) and parse() gives a dict of
typed values, or raises SpecError (a ValueError) naming the spec, the item or key, what it wants and the keys
there are. Kinds: "float" (finite), "int", "str", "choice" (one of `choices`), "flag" (given bare, e.g. `reverse`:
True; absent: False), "list" (comma-separated words), "pair" (two numbers, `sep` between: 320,240 or 640x480),
"range" (two numbers T0-T1, the first not past the second) and "spec" (a nested spec whose own items may follow
its first: `motion=sine:z=0.8,...` takes the items after it that are not keys of this spec).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["Key", "SpecError", "parse", "split"]

KINDS = ("float", "int", "str", "choice", "flag", "list", "pair", "range", "spec")


class SpecError(ValueError):
    """A spec that cannot be read: the message names the key (or item) and what it wants."""


@dataclass(frozen=True)
class Key:
    """One key of a spec. lo/hi bound a number (inclusive), above bounds it from below (exclusive); unit is said in
    the refusals (s, m, px, deg); required: parse() refuses a spec without it; whole: a pair or range of whole
    numbers."""

    name: str
    kind: str = "float"
    default: object = None
    lo: float | None = None
    hi: float | None = None
    above: float | None = None
    choices: tuple[str, ...] = ()
    sep: str = ","
    unit: str = ""
    required: bool = False
    whole: bool = False  # a pair or range of whole numbers

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"key {self.name}: kind {self.kind!r} is not one of {', '.join(KINDS)}")

    def wants(self) -> str:
        """What the key takes, for a refusal: `noise=X`, `mode=forward|trajectory`, `size=AxB`."""
        if self.kind == "flag":
            return self.name
        if self.kind == "choice":
            return f"{self.name}={'|'.join(self.choices)}"
        if self.kind in ("pair", "range"):
            sep = "-" if self.kind == "range" else self.sep
            return f"{self.name}=A{sep}B"
        return f"{self.name}={'A,B' if self.kind == 'list' else 'X'}"


def split(text: str, sep: str = ":") -> list[tuple[str, bool, str]]:
    """The items of a spec as (key, has '=', value), stripped, empty items left out."""
    out = []
    for item in (text or "").split(sep):
        if not item.strip():
            continue
        key, eq, value = item.partition("=")
        out.append((key.strip(), bool(eq), value.strip()))
    return out


def parse(text: str, keys: list[Key] | tuple[Key, ...], what: str, sep: str = ":") -> dict:
    """The typed values of every key (its default where the spec does not give it); SpecError naming what is
    wrong. `what` starts each refusal (e.g. "sim source", "motion 'sine:z=1'")."""
    table = {k.name: k for k in keys}
    names = ", ".join(k.wants() for k in keys)
    out = {k.name: (False if k.kind == "flag" else k.default) for k in keys}
    given: set[str] = set()
    items = split(text, sep)
    while items:
        name, eq, raw = items.pop(0)
        key = table.get(name)
        shown = f"{name}={raw}" if eq else name
        if key is None:
            raise SpecError(f"{what}: unknown key {name!r} (item {shown!r}); keys: {names}")
        if key.kind == "flag":
            if eq:
                raise SpecError(f"{what}: {name} is a flag: give it bare, without a value")
            out[name] = True
        elif not eq:
            raise SpecError(f"{what}: item {shown!r} is not key=value; keys: {names}")
        else:
            if key.kind == "spec":  # its own items follow it, up to the next key of this spec
                while items and items[0][0] not in table:
                    k2, eq2, v2 = items.pop(0)
                    raw += sep + (f"{k2}={v2}" if eq2 else k2)
            out[name] = value(key, raw, what)
        given.add(name)
    missing = [k.name for k in keys if k.required and k.name not in given]
    if missing:
        raise SpecError(f"{what}: missing {', '.join(missing)}; keys: {names}")
    return out


def value(key: Key, raw: str, what: str):
    """One item's value, typed and checked (SpecError naming the key)."""
    name = key.name
    if key.kind in ("str", "spec"):
        if not raw:
            raise SpecError(f"{what}: {name}= is empty")
        return raw
    if key.kind == "choice":
        if raw not in key.choices:
            raise SpecError(f"{what}: {name}={raw!r}: want one of {', '.join(key.choices)}")
        return raw
    if key.kind == "list":
        return [w.strip() for w in raw.split(",") if w.strip()]
    if key.kind in ("pair", "range"):
        sep = "-" if key.kind == "range" else key.sep
        conv = int if key.whole else float
        parts = raw.lower().split(sep)
        try:
            a, b = (_number(p, conv) for p in parts) if len(parts) == 2 else (None, None)
        except ValueError:
            a = b = None
        if a is None or b is None:
            raise SpecError(f"{what}: {name}={raw!r} must be two numbers as A{sep}B")
        if key.kind == "range" and a > b:
            raise SpecError(f"{what}: {name}={raw!r}: the range's start is past its end")
        for v in (a, b):
            _bounds(key, v, raw, what)
        return a, b
    conv = int if key.kind == "int" else float
    try:
        v = _number(raw, conv)
    except ValueError:
        kind = "a whole number" if conv is int else "a number"
        raise SpecError(f"{what}: {name}={raw!r} is not {kind}{_of(key)}") from None
    _bounds(key, v, raw, what)
    return v


def _number(text: str, conv):
    v = conv(text.strip())
    if not math.isfinite(v):
        raise ValueError(text)
    return v


def _of(key: Key) -> str:
    return {"s": " of seconds", "m": " of metres", "px": " of pixels", "deg": " of degrees"}.get(key.unit, "")


def _bounds(key: Key, v: float, raw: str, what: str) -> None:
    unit = f" {key.unit}" if key.unit else ""
    if key.above is not None and not v > key.above:
        raise SpecError(f"{what}: {key.name}={raw!r} must be > {key.above:g}{unit}")
    if key.lo is not None and not v >= key.lo:
        raise SpecError(f"{what}: {key.name}={raw!r} must be >= {key.lo:g}{unit}")
    if key.hi is not None and not v <= key.hi:
        raise SpecError(f"{what}: {key.name}={raw!r} must be <= {key.hi:g}{unit}")
