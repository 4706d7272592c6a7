"""The whole network for one fixation point of an image pair: retina -> kernel -> decision."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace

import numpy as np

from . import kernel, retina
from .decide import Decision, decide, texture

__all__ = ["Params", "Match", "match", "FAITHFUL"]


@dataclass(frozen=True)
class Params:
    """Settings of the network. The defaults turn every extension on; Params.paper() is the paper's own.

    window: w, the fovea side in pixels (odd). vsearch: R, rows searched above and below (vertical search).
    circular: compare the direction D on the circle. subpixel: parabola through the winner's neighbours.
    min_margin, min_texture: abstain below this peak-to-rival margin or this mean fovea gradient.
    lr_check: match the winning slave window back into the master band; abstain unless it lands within
    lr_tolerance px of the fovea. support: adaptive support weights (Yoon & Kweon) on the fovea.
    max_window: dynamic window; when not confident, grow w by 8 px per try up to this size (0: off)."""

    window: int = 15
    vsearch: int = 2
    circular: bool = True
    subpixel: bool = True
    min_margin: float = 0.04
    min_texture: float = 4.0
    lr_check: bool = True
    lr_tolerance: float = 1.0
    support: bool = False
    support_gamma: float = 12.0
    max_window: int = 31

    @classmethod
    def paper(cls, **overrides) -> "Params":
        """The paper's network: no extension (vertical search, circular D, sub-pixel, abstention...)."""
        base = dict(vsearch=0, circular=False, subpixel=False, min_margin=0.0, min_texture=0.0,
                    lr_check=False, support=False, max_window=0)
        base.update(overrides)
        return cls(**base)

    @classmethod
    def build(cls, faithful: bool = False, **overrides) -> "Params":
        """Params from keyword overrides (None values ignored), unknown names rejected by name."""
        names = {f.name for f in fields(cls)}
        bad = sorted(set(overrides) - names)
        if bad:
            raise TypeError(f"unknown parameter(s) {', '.join(bad)}; known: {', '.join(sorted(names))}")
        overrides = {k: v for k, v in overrides.items() if v is not None}
        return cls.paper(**overrides) if faithful else cls(**overrides)

    def windows(self) -> list[int]:
        """The window sizes tried in turn (the dynamic window)."""
        ws = [self.window]
        while self.max_window and ws[-1] + 8 <= self.max_window:
            ws.append(ws[-1] + 8)
        return ws


FAITHFUL = Params.paper()


@dataclass(frozen=True)
class Match:
    """A decision for the fovea at (x, y) of the master, with the window that produced it."""

    x: int
    y: int
    window: int
    decision: Decision

    @property
    def confident(self) -> bool:
        return self.decision.confident

    @property
    def offset_px(self) -> float:
        return self.decision.offset_px

    def to_dict(self) -> dict:
        d = {"x": self.x, "y": self.y, "window": self.window}
        d.update(asdict(self.decision))
        return d


def _one(master, slave, x, y, w, p: Params) -> Decision:
    fovea, band = retina.features(master, slave, (x, y), w, p.vsearch)
    weights = kernel.support_weights(fovea, p.support_gamma) if p.support else None
    scores = kernel.correlate(fovea, band, circular=p.circular, weights=weights)
    tex = texture(fovea)
    d = decide(scores, w, k_centre=x - w // 2, subpixel=p.subpixel, tex=tex, min_texture=p.min_texture,
               min_margin=p.min_margin)
    if p.lr_check and d.confident:
        d = replace(d, confident=_back_ok(master, slave, x, y, w, d, p))
    return d


def _back_ok(master, slave, x, y, w, d: Decision, p: Params) -> bool:
    """Left-right consistency: the winning slave window, matched back into the master, lands on x."""
    xs, ys = d.k + w // 2, y + d.v
    try:
        sf, mb = retina.features(slave, master, (xs, ys), w, p.vsearch)
    except retina.BorderError:
        return False
    back = kernel.correlate(sf, mb, circular=p.circular)
    bd = decide(back, w, k_centre=xs - w // 2, subpixel=p.subpixel, min_margin=0.0, min_texture=0.0)
    return abs((bd.k_sub + w // 2) - (x + (d.k_sub - d.k))) <= p.lr_tolerance


def match(master: np.ndarray, slave: np.ndarray, at: tuple[int, int] | None = None,
          params: Params | None = None, **overrides) -> Match:
    """Decide where the master fovea at `at` = (x, y) (default: the image centre) lies in the slave band.

    Images: uint8 gray or BGR of the same size. Keyword overrides are Params fields (faithful=True for the
    paper's network). Raises retina.BorderError when the window does not fit, ValueError on bad images."""
    if params is None:
        params = Params.build(**overrides)
    elif overrides:
        params = replace(params, **overrides)
    if master.shape[:2] != slave.shape[:2]:
        raise ValueError(f"master and slave differ in size: {master.shape[1]} x {master.shape[0]} and "
                         f"{slave.shape[1]} x {slave.shape[0]}")
    x, y = at if at is not None else (master.shape[1] // 2, master.shape[0] // 2)
    retina.check_point(master.shape, x, y, params.window, params.vsearch)
    first = None
    for w in params.windows():
        try:
            retina.check_point(master.shape, x, y, w, params.vsearch)
        except retina.BorderError:
            break
        d = _one(master, slave, x, y, w, params)
        first = first or Match(x, y, w, d)
        if d.confident:
            return Match(x, y, w, d)
    return first
