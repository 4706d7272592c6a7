"""The one range check of every numeric setting (issue #28): Range says what a setting may be, check() refuses
anything else with a message that names the setting and the range.

    RANGES = {"rate_hz": Range(0, 1000, note="0: as fast as the source")}
    def __post_init__(self):
        check(self, RANGES)      # ValueError "rate_hz: must be from 0 to 1000 (0: as fast as the source), got -5"

A settings class lists every numeric field of its own in its RANGES (a test enumerates the fields and fails on a
number without one). The message starts with the field's name, which vergence.config prefixes with its table
(capture.rate_hz: ...). NaN and the infinities are never in a range with finite bounds.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

__all__ = ["Range", "check", "numeric_fields"]


def _num(v: float) -> str:
    """A bound as written: 10000000, not 1e+07; 0.5."""
    return str(int(v)) if float(v).is_integer() else f"{v:g}"


@dataclass(frozen=True)
class Range:
    """lo <= v <= hi (None: unbounded on that side); lo_open / hi_open: the bound itself excluded; integer: a
    whole number (an int setting; a bool is not one); note: what a special value means, said in the message."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    integer: bool = False
    note: str = ""

    def __contains__(self, v) -> bool:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            return False
        if self.integer and not float(v).is_integer():
            return False
        if not math.isfinite(v):
            return False
        if self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo):
            return False
        return not (self.hi is not None and (v >= self.hi if self.hi_open else v > self.hi))

    def text(self) -> str:
        """'from 0 to 1000', 'above 0 and at most 1000', 'at least 1', ... (and the note)."""
        lo = None if self.lo is None else f"{'above' if self.lo_open else 'at least'} {_num(self.lo)}"
        hi = None if self.hi is None else f"{'below' if self.hi_open else 'at most'} {_num(self.hi)}"
        if lo and hi and not (self.lo_open or self.hi_open):
            out = f"from {_num(self.lo)} to {_num(self.hi)}"
        else:
            out = " and ".join(s for s in (lo, hi) if s) or "a finite number"
        out = ("a whole number " if self.integer else "") + out
        return out + (f" ({self.note})" if self.note else "")

    def check(self, name: str, v) -> None:
        if v not in self:
            raise ValueError(f"{name}: must be {self.text()}, got {v!r}")

    def outside(self) -> list:
        """Values just outside the range (for the tests): past each bound, and NaN for a float."""
        out = []
        for bound, open_, sign in ((self.lo, self.lo_open, -1), (self.hi, self.hi_open, 1)):
            if bound is not None:
                out.append(bound if open_ else bound + sign * (1 if self.integer else max(1e-6, abs(bound) * 1e-6)))
        return [int(v) for v in out] if self.integer else [float(v) for v in out] + [math.nan]


def check(obj, ranges: dict[str, Range]) -> None:
    """Each field of obj named in ranges within its range; ValueError naming the first that is not."""
    for name, r in ranges.items():
        r.check(name, getattr(obj, name))


def numeric_fields(cls) -> list[str]:
    """The names of a settings dataclass's int and float fields (bools excluded)."""
    hints = {f.name: f.type for f in dataclasses.fields(cls)}
    return [n for n, t in hints.items() if t in ("int", "float", int, float)]
