"""The network's parameters (Params, FAITHFUL: the paper's own) and the dynamic-window rule, once."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import ClassVar

from ..ranges import Range, check
from ..choices import Photometric

PHOTOMETRIC = tuple(Photometric)  # retina.photometric's modes (vergence.choices)

__all__ = ["Params", "FAITHFUL", "WINDOW_STEP"]

WINDOW_STEP = 8  # px: the dynamic window grows (and shrinks back) by this much per step


@dataclass(frozen=True)
class Params:
    """Settings of the network. The defaults turn every extension on; Params.paper() is the paper's own.

    window: w, the fovea side in pixels (odd). vsearch: R, rows searched above and below (vertical search).
    vshift_cost: what each row of vertical shift costs a candidate, per pixel on layer 3's 0..255 scale
    (decide): under sensor noise the best row of a weakly textured fovea is otherwise often a random one.
    circular: compare the direction D on the circle. subpixel: parabola through the winner's neighbours.
    min_margin, min_texture: abstain below this peak-to-rival margin or this mean fovea gradient.
    min_correlation: abstain unless the winning slave window's intensities correlate with the fovea's (Pearson
    r, see pearson()) by at least this: two cameras' independent noise on a flat wall correlates weakly even at
    the best of all offsets, a real match strongly (the figures: docs/MEASUREMENTS.md, "Why min_correlation is
    0.35").
    lr_check: match the winning slave window back into the master band; abstain unless it lands within
    lr_tolerance px of the fovea. support: adaptive support weights (Yoon & Kweon) on the fovea, with
    support_gamma (intensity) and support_radius (distance, px, at the base window; it grows in proportion with
    the dynamic window, support_radius_at) as their two scales.
    halves_check: each half of the fovea (left, right, top, bottom; weighed by the support weights when they
    are on) must find its own best match, searched within halves_range px of the winner, within 2 px of it
    (halves_consistent): abstain at depth edges where one half of the window sees another surface.
    max_window: dynamic window; when not confident, grow w by WINDOW_STEP (8) px per try up to this size (0: off).
    photometric: before layer 1, map the slave band's intensities onto the master's over the same rows
    ("affine": mean and standard deviation, "histogram": quantiles, "none"; retina.photometric): two cameras
    never have the same gain and offset.
    clip_master: with a photometric mapping, where the slave's gain clipped (black or saturated over at least 1 %
    of the band), clip the master's fovea and rows to the same levels (retina.mapped_strips): those areas are
    then flat in both views instead of textured in one and flat in the other.
    clip_fallback: with clip_master, when every window abstains and the master was clipped, match() tries them
    all again with the master as it is (clip_master off) and takes the first confident answer; the service's
    dynamic window (frames.WindowControl, the capture) steps through the same unclipped windows after the
    clipped ones."""

    window: int = 15
    vsearch: int = 6
    vshift_cost: float = 0.5
    circular: bool = True
    subpixel: bool = True
    min_margin: float = 0.25
    min_texture: float = 1.5
    min_correlation: float = 0.35
    lr_check: bool = True
    lr_tolerance: float = 0.75
    support: bool = True
    support_gamma: float = 10.0
    support_radius: float = 5.0
    halves_check: bool = True
    halves_range: int = 12
    max_window: int = 47
    photometric: str = "affine"
    clip_master: bool = True
    clip_fallback: bool = True

    RANGES: ClassVar[dict[str, Range]] = {
        "window": Range(1, 501, integer=True, note="pixels, odd"),
        "vsearch": Range(0, 100, integer=True, note="rows"),
        "vshift_cost": Range(0, 255),
        "min_margin": Range(0, 1e6),
        "min_texture": Range(0, 10_000),
        "min_correlation": Range(-1, 1, note="Pearson r"),
        "lr_tolerance": Range(0, 100, note="pixels"),
        "support_gamma": Range(0, 1000, lo_open=True),
        "support_radius": Range(0, 1000, lo_open=True, note="pixels"),
        "halves_range": Range(0, 1000, integer=True, note="pixels"),
        "max_window": Range(0, 1001, integer=True, note="pixels; 0: no dynamic window"),
    }

    def __post_init__(self):
        check(self, self.RANGES)
        if self.window % 2 == 0:
            raise ValueError(f"window: must be odd, got {self.window}")
        if self.photometric not in PHOTOMETRIC:
            raise ValueError(f"photometric must be one of {', '.join(PHOTOMETRIC)}, got {self.photometric!r}")

    @classmethod
    def paper(cls, **overrides) -> "Params":
        """The paper's network: no extension (vertical search, circular D, sub-pixel, abstention...)."""
        base = dict(vsearch=0, vshift_cost=0.0, circular=False, subpixel=False, min_margin=0.0, min_texture=0.0,
                    min_correlation=0.0, lr_check=False, support=False, halves_check=False, max_window=0,
                    photometric="none", clip_master=False, clip_fallback=False)
        base.update(overrides)
        return cls(**base)

    @classmethod
    def build(cls, faithful: bool = False, **overrides) -> "Params":
        """Params from keyword overrides over the defaults (the paper's when faithful); see override()."""
        return (cls.paper() if faithful else cls()).override(**overrides)

    def override(self, **changes) -> "Params":
        """These Params with the named fields changed; None means "keep mine" (an option not given), an
        unknown name is rejected by name. Every merge of settings (file, command line, faithful) goes through
        here, so an option left out never brings a class default back over the base."""
        names = {f.name for f in fields(self)}
        bad = sorted(set(changes) - names)
        if bad:
            raise TypeError(f"unknown parameter(s) {', '.join(bad)}; known: {', '.join(sorted(names))}")
        return replace(self, **{k: v for k, v in changes.items() if v is not None})

    def support_radius_at(self, window: int) -> float:
        """The support weights' distance scale for a window of this size: support_radius at the base window,
        growing in proportion with the dynamic window (a grown window is there for its outer pixels)."""
        return self.support_radius * window / self.window

    def band_reach(self, window: int | None = None) -> int:
        """How many rows each side of the fovea's a frame reads for a window of this size (default the base one): the
        window's half, the vertical search and the Sobel kernels' one-row margin."""
        return (self.window if window is None else window) // 2 + self.vsearch + 1

    def windows(self) -> list[int]:
        """The dynamic window's sizes, smallest first: window, window + WINDOW_STEP, ... up to max_window (just
        window when max_window is 0). vergence.match() tries them in turn; the capture's WindowControl moves
        along them."""
        ws = [self.window]
        while self.max_window and ws[-1] + WINDOW_STEP <= self.max_window:
            ws.append(ws[-1] + WINDOW_STEP)
        return ws


FAITHFUL = Params.paper()
