"""The whole network for one fixation point of an image pair: retina -> kernel -> decision.

Match is one point's vergence.network.decide.Decision in one process, with where (x, y), the window that made it
and its scores; its distributed counterpart, one frame's Decision in the reducer, is
vergence.stages.gather.Reduced (docs/SERVICE.md, "One decision, five names")."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from . import kernel, retina
from .decide import Decision, decide_scores
from .params import FAITHFUL, Params

__all__ = ["Match", "match", "Params", "FAITHFUL"]


@dataclass(frozen=True)
class Match:
    """A decision (vergence.network.decide.Decision) for the fovea at (x, y) of the master, with the window that
    produced it and its layer-4 scores."""

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


def _one(master, slave, x, y, w, p: Params) -> tuple[Match, bool]:
    """The match at window w, and whether clip_master clipped the master for it (retina.master_clipped)."""
    fstrip, bstrip, mrows, lims = retina.mapped_strips(master, slave, x, y, w, p.vsearch, p.photometric, p.lr_check,
                                                       p.clip_master)
    fovea, band = retina.planes(fstrip), retina.planes(bstrip)
    weights = kernel.support_weights(fovea, p.support_gamma, p.support_radius_at(w)) if p.support else None
    scores = kernel.correlate(fovea, band, circular=p.circular, weights=weights)
    return Match(x, y, w, decide_scores(scores, fovea, x, p, mrows, band, weights), scores), lims is not None


def match(master: np.ndarray, slave: np.ndarray, at: tuple[int, int] | None = None,
          params: Params | None = None, **overrides) -> Match:
    """Decide where the master fovea at `at` = (x, y) (default: the image centre) lies in the slave band.

    With params.clip_fallback, where every window abstains with the master clipped like the slave (clip_master),
    every window is tried again with the master as it is.

    Args:
        master, slave: uint8 images, gray or BGR, of the same size.
        at: the fixation point (x, y) in the master image.
        params: the network's settings (Params(): every extension on). overrides: Params fields by keyword
            (faithful=True for the paper's network).

    Returns:
        A Match: the point, the window that decided and its Decision, and the layer-4 scores decided on.

    Raises:
        BorderError: the window does not fit around `at`.
        ValueError: the images differ in size or are not images."""
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
    clipped = False  # whether clip_master clipped the master at any window tried (retina.master_clipped)
    for w in params.windows():
        try:
            retina.check_point(master.shape, x, y, w, params.vsearch)
        except retina.BorderError:
            break
        m, clipped_w = _one(master, slave, x, y, w, params)
        clipped = clipped or clipped_w
        first = first or m
        if m.confident:
            return m
    if params.clip_master and params.clip_fallback and clipped:
        # where the slave's gain clipped, the master clipped alike can leave too little texture (a bright fovea
        # just under the estimated clip level, flattened): the master as it is, every window again
        second = match(master, slave, at, params.override(clip_master=False))
        if second.confident:
            return second
    return first
