"""The command line's shared value types (argparse `type=`): one X,Y parser for every command that takes a point
(capture and match --at, fixate's X,Y, sim --fixate-at FRAME:X,Y), the positive number, and number() / whole():
a number within a range (vergence.ranges.Range, the settings' own), so that every numeric option refuses
nonsense before anything starts: `argument --rate: must be from 0 to 1000 (0: as fast as possible), got '-5'`,
exit 2."""

from __future__ import annotations

import argparse
import math

from vergence.ranges import Range

__all__ = ["xy", "pixel", "master_point", "positive", "number", "whole", "PORT"]


def xy(text: str, conv=int, what: str = "X,Y in pixels") -> tuple:
    """X,Y as two conv (int or float) numbers, finite; argparse.ArgumentTypeError saying what was wanted."""
    try:
        x, y = (conv(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"want {what}, got {text!r}") from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise argparse.ArgumentTypeError(f"X,Y must be finite numbers, got {text!r}")
    return x, y


def pixel(text: str) -> tuple[int, int]:
    """argparse type for --at X,Y: a pixel of the master image (integers)."""
    try:
        return xy(text, int)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"--at wants X,Y in pixels, got {text!r}") from None


def master_point(text: str) -> tuple[float, float]:
    """argparse type for a point in master pixels, sub-pixel allowed (fixate's X,Y)."""
    return xy(text, float, "X,Y in master pixels")


def positive(text: str) -> float:
    """argparse type for a finite number > 0 (--baseline, --focal, --dscale)."""
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"want a positive number, got {text!r}")
    return v


def number(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False, hi_open: bool = False,
           note: str = "", integer: bool = False):
    """argparse type for a finite number from lo to hi (None: unbounded; *_open: the bound excluded); its error
    says the range (argparse puts the option's name first and exits 2). integer: a whole number (int)."""
    r = Range(lo, hi, lo_open=lo_open, hi_open=hi_open, integer=integer, note=note)

    def parse(text: str):
        try:
            v = int(text) if integer else float(text)
        except ValueError:
            v = math.nan
        if v not in r:
            raise argparse.ArgumentTypeError(f"must be {r.text()}, got {text!r}")
        return v

    parse.range = r  # for the tests and --help
    parse.__name__ = "whole number" if integer else "number"
    return parse


def whole(lo: int | None = None, hi: int | None = None, note: str = ""):
    """argparse type for a whole number (int) from lo to hi."""
    return number(lo, hi, note=note, integer=True)


PORT = whole(1, 65535)  # a TCP port
