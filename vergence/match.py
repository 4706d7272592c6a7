"""The whole network for one fixation point of an image pair: retina -> kernel -> decision."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace

import numpy as np

from . import kernel, retina
from .decide import Decision, decide, texture

__all__ = ["Params", "Match", "match", "decide_scores", "apply_checks", "correlation", "lr_consistent",
           "halves_consistent", "FAITHFUL"]


@dataclass(frozen=True)
class Params:
    """Settings of the network. The defaults turn every extension on; Params.paper() is the paper's own.

    window: w, the fovea side in pixels (odd). vsearch: R, rows searched above and below (vertical search).
    vshift_cost: what each row of vertical shift costs a candidate, per pixel on layer 3's 0..255 scale
    (decide): under sensor noise the best row of a weakly textured fovea is otherwise often a random one.
    circular: compare the direction D on the circle. subpixel: parabola through the winner's neighbours.
    min_margin, min_texture: abstain below this peak-to-rival margin or this mean fovea gradient.
    min_correlation: abstain unless the winning slave window's intensities correlate with the fovea's (Pearson
    r, see correlation()) by at least this: the independent sensor noise of two cameras looking at a flat
    wall correlates by less than 0.25 even at the best of all offsets (a black wall, its noise clipped at 0, once
    by 0.31), a real match mostly by 0.6 to 1.
    lr_check: match the winning slave window back into the master band; abstain unless it lands within
    lr_tolerance px of the fovea. support: adaptive support weights (Yoon & Kweon) on the fovea, with
    support_gamma (intensity) and support_radius (distance, px) as their two scales.
    halves_check: each half of the fovea (left, right, top, bottom; weighed by the support weights when they
    are on) must find its own best match, searched within halves_range px of the winner, within 2 px of it
    (halves_consistent): abstain at depth edges where one half of the window sees another surface.
    max_window: dynamic window; when not confident, grow w by 8 px per try up to this size (0: off).
    photometric: before layer 1, map the slave band's intensities onto the master's over the same rows
    ("affine": mean and standard deviation, "histogram": quantiles, "none"; retina.photometric): two cameras
    never have the same gain and offset."""

    window: int = 15
    vsearch: int = 6
    vshift_cost: float = 0.5
    circular: bool = True
    subpixel: bool = True
    min_margin: float = 0.03
    min_texture: float = 1.5
    min_correlation: float = 0.35
    lr_check: bool = True
    lr_tolerance: float = 0.75
    support: bool = True
    support_gamma: float = 8.0
    support_radius: float = 7.0
    halves_check: bool = True
    halves_range: int = 12
    max_window: int = 47
    photometric: str = "affine"

    def __post_init__(self):
        if self.photometric not in retina.PHOTOMETRIC:
            raise ValueError(f"photometric must be one of {', '.join(retina.PHOTOMETRIC)}, got {self.photometric!r}")

    @classmethod
    def paper(cls, **overrides) -> "Params":
        """The paper's network: no extension (vertical search, circular D, sub-pixel, abstention...)."""
        base = dict(vsearch=0, vshift_cost=0.0, circular=False, subpixel=False, min_margin=0.0, min_texture=0.0,
                    min_correlation=0.0, lr_check=False, support=False, halves_check=False, max_window=0,
                    photometric="none")
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
    scores: np.ndarray | None = field(default=None, repr=False, compare=False)  # layer 4, as decided on

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


def decide_scores(scores: np.ndarray, fovea: np.ndarray, x: int, params: Params,
                  master_rows: np.ndarray | None = None, slave_band: np.ndarray | None = None) -> Decision:
    """Layer 4's scores -> a Decision for the fovea (planes (3, w, w)) centred on master column x.

    With params.min_correlation, a confident decision's slave window must correlate with the fovea
    (correlation); with params.lr_check, it must also pass the left-right check (lr_consistent), given
    the master's rows of the fovea as a gray strip with its margin ((w + 2, W + 2), retina.band_strip with
    no vertical search) and the slave band's planes ((3, w + 2R, W)); with params.halves_check, it must also
    pass halves_consistent, which reads the slave band's columns k - halves_range .. k + halves_range + w - 1
    only. This is the one decision step of both match() and the reducer."""
    w = fovea.shape[1]
    d = decide(scores, w, k_centre=x - w // 2, subpixel=params.subpixel, tex=texture(fovea),
               min_texture=params.min_texture, min_margin=params.min_margin, vshift_cost=params.vshift_cost)
    return apply_checks(d, fovea, x, params, master_rows, slave_band)


def apply_checks(d: Decision, fovea: np.ndarray, x: int, params: Params, master_rows: np.ndarray | None = None,
                 slave_band: np.ndarray | None = None) -> Decision:
    """decide_scores' second half: the correlation, left-right and halves checks on a decision (only a
    confident one can change), for a caller that gets the bands only once it knows the decision (the reducer)."""
    if params.min_correlation > 0 and d.confident and slave_band is not None:
        d = replace(d, confident=correlation(fovea, slave_band, d) >= params.min_correlation)
    if params.lr_check and d.confident and master_rows is not None and slave_band is not None:
        d = replace(d, confident=lr_consistent(master_rows, slave_band, x, d, params))
    if params.halves_check and d.confident and slave_band is not None:
        d = replace(d, confident=halves_consistent(fovea, slave_band, d, params))
    return d


def correlation(fovea: np.ndarray, slave_band: np.ndarray, d: Decision) -> float:
    """Pearson correlation of the fovea's intensities with those of the winning slave window (rows shifted
    by v, columns k..k+w-1 of the band): near 1 for a real match, near 0 for two fields of independent
    noise; 0 when either is flat."""
    w = fovea.shape[1]
    r = (slave_band.shape[1] - w) // 2
    f = fovea[0].astype(np.float64)
    s = slave_band[0, r + d.v : r + d.v + w, d.k : d.k + w].astype(np.float64)
    f -= f.mean()
    s -= s.mean()
    den = float(np.sqrt((f * f).sum() * (s * s).sum()))
    return float((f * s).sum()) / den if den > 0 else 0.0


def lr_consistent(master_rows: np.ndarray, slave_band: np.ndarray, x: int, d: Decision, params: Params) -> bool:
    """Left-right consistency: the winning slave window (rows shifted by v), matched back along the fovea's
    own rows of the master, lands within params.lr_tolerance px of where the forward match says it should."""
    half = x - d.k_centre
    w = 2 * half + 1
    r = (slave_band.shape[1] - w) // 2  # R
    sf = np.ascontiguousarray(slave_band[:, r + d.v : r + d.v + w, d.k : d.k + w])
    back = kernel.correlate(sf, retina.planes(master_rows), circular=params.circular)
    bd = decide(back, w, k_centre=0, subpixel=params.subpixel)
    expected = x - (d.k_sub - d.k)
    return abs((bd.k_sub + half) - expected) <= params.lr_tolerance


HALVES_TOLERANCE = 2  # px: how far a half's own best offset may lie from the winner (1 abstains at too many points)


def halves_consistent(fovea: np.ndarray, slave_band: np.ndarray, d: Decision, params: Params) -> bool:
    """The halves check: the left, right, top and bottom halves of the fovea (the centre row or column in
    each), weighed by the fovea's support weights when params.support, each matched alone along the winning
    row v at offsets within params.halves_range of the winner k, must each find their best offset within
    HALVES_TOLERANCE (2) px of k. At a depth edge the half on the other surface finds that surface's offset:
    the fovea straddles two surfaces and the winner may be the wrong one's (foreground fattening), so abstain.
    Exact integers (kernel.half_sads, the four halves in one pass); reads the band's columns
    k - halves_range .. k + halves_range + w - 1 of the winning rows only."""
    w = fovea.shape[1]
    r = (slave_band.shape[1] - w) // 2  # the vertical search R
    kk = slave_band.shape[2] - w + 1
    k0, k1 = max(0, d.k - params.halves_range), min(kk, d.k + params.halves_range + 1)
    rows = slave_band[:, r + d.v : r + d.v + w, :]
    wts = kernel.support_weights(fovea, params.support_gamma, params.support_radius) if params.support else None
    s = kernel.half_sads(fovea, rows, k0, k1, circular=params.circular, weights=wts)
    return bool(np.all(np.abs(k0 + np.argmin(s, axis=1) - d.k) <= HALVES_TOLERANCE))


def _one(master, slave, x, y, w, p: Params) -> Match:
    fovea, band = retina.features(master, slave, (x, y), w, p.vsearch, p.photometric)
    weights = kernel.support_weights(fovea, p.support_gamma, p.support_radius) if p.support else None
    scores = kernel.correlate(fovea, band, circular=p.circular, weights=weights)
    mrows = retina.band_strip(master, y, w) if p.lr_check else None
    return Match(x, y, w, decide_scores(scores, fovea, x, p, mrows, band), scores)


def match(master: np.ndarray, slave: np.ndarray, at: tuple[int, int] | None = None,
          params: Params | None = None, **overrides) -> Match:
    """Decide where the master fovea at `at` = (x, y) (default: the image centre) lies in the slave band.

    Images: uint8 gray or BGR of the same size. Keyword overrides are Params fields (faithful=True for the
    paper's network). Raises retina.BorderError when the window does not fit, ValueError on bad images."""
    if params is None:
        params = Params.build(**overrides)
    elif overrides:
        params = params.override(**overrides)
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
        m = _one(master, slave, x, y, w, params)
        first = first or m
        if m.confident:
            return m
    return first
