"""The command line's shared value types (argparse `type=`): one X,Y parser for every command that takes a point
(capture and match --at, fixate's X,Y, sim --fixate-at FRAME:X,Y) and the positive number."""

from __future__ import annotations

import argparse
import math

__all__ = ["xy", "pixel", "master_point", "positive"]


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
