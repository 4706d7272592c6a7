"""Winner-takes-all, layer 5 (direction and magnitude), the sub-pixel winner and the confidence, and every
check on a decision (correlation, left-right, halves: decide_scores, apply_checks).

Decision is the network's decision for one fovea, the one concept the others carry: vergence.network.match.Match
(one point, in one process), vergence.stages.gather.Reduced (one distributed frame, in the reducer),
messages.Decision (that on the wire, where Decision.v is called v_shift: `v` is the schema version) and
vergence.sim.loop.Step (one frame of the simulated loop). See docs/SERVICE.md, "One decision, five names"."""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

from . import kernel, retina
from .params import Params

__all__ = ["Decision", "decide", "centre_offset", "texture", "has_texture", "decide_scores", "apply_checks", "pearson",
           "lr_consistent", "halves_consistent", "HALVES_TOLERANCE"]


@dataclass(frozen=True)
class Decision:
    """One decision of the network for one fovea.

    k is the winning offset (integer, layer 4), k_sub the sub-pixel winner (k when sub-pixel is off),
    v the vertical shift of the winning window (0 without vertical search; v_shift in messages.Decision), k_centre
    the centre neuron,
    direction and magnitude the two layer-5 neurons: sign(k - k_centre) and |k - k_centre| pixels.
    offset_px = k_sub - k_centre: how far right of the fovea's column its match lies in the slave.
    confidence is the peak-to-rival margin in 0..1, confident says whether the camera may move."""

    k: int
    k_sub: float
    v: int
    k_centre: int
    direction: int
    magnitude: int
    offset_px: float
    score: float
    confidence: float
    texture: float
    confident: bool

    def to_dict(self) -> dict:
        return asdict(self)


def centre_offset(width: int, window: int) -> int:
    """k_c = W/2 - floor(w/2): the offset of the window centred on column W/2 (313 for 640 and 15)."""
    return width // 2 - window // 2


def _mean(a: np.ndarray) -> float:
    """float(a.mean()). Of a small array of 8-bit integers (the features) as the exact integer sum over the count,
    rounded once: numpy's float64 sum of such integers is exact, so its mean is that same double, without
    np.mean's wrapper."""
    if a.dtype.itemsize == 1 and a.dtype.kind in "ui" and 0 < a.size <= 2 ** 40:
        return int(a.sum(dtype=np.int64)) / a.size
    return float(a.mean())


def texture(fovea: np.ndarray) -> float:
    """Mean gradient magnitude G (0..255) of the fovea: near 0 for a flat or black fovea."""
    return _mean(fovea[1])


def has_texture(d: Decision, params: Params) -> bool:
    """Whether the fovea of a decision had texture to match: at least min_texture, and at least one grey level a pixel
    whatever the settings (a black or flat frame has none). An unconfident decision on a textured fovea is a lost
    target's (vergence.head.search searches), one on a black or flat frame holds."""
    return d.texture == d.texture and d.texture >= max(params.min_texture, 1.0)


def _parabola(ym: float, y0: float, yp: float) -> float:
    den = ym - 2.0 * y0 + yp
    if den >= 0.0:  # not a strict maximum: no refinement
        return 0.0
    return min(max(0.5 * (ym - yp) / den, -0.5), 0.5)  # np.clip's value, NaN included, without its call


def decide(scores: np.ndarray, window: int, *, k_centre: int | None = None, subpixel: bool = Params.subpixel,
           tex: float | None = None, min_texture: float = Params.min_texture, min_margin: float = Params.min_margin,
           rival_radius: int | None = None, vshift_cost: float = Params.vshift_cost) -> Decision:
    """Winner-takes-all over layer 4 and the two output neurons (layer 5), with the confidence.

    The confidence is the margin between the winner and the best rival more than rival_radius offsets away, as a
    fraction of the rival's dissimilarity (255 * w * w - y). The defaults are Params' (vergence.match's); the
    checks that need the images (decide_scores) are not here. min_margin=0 and min_texture=0 give the paper's
    behaviour: always confident.

    Args:
        scores: y(k) (1-D) or y(v, k) with vertical search (row v is the shift v - R); the band is W = K + w - 1
            wide.
        window: w. k_centre: the centred window's offset, W/2 - floor(w/2) by default. subpixel: parabola
            through the winner's neighbours.
        tex, min_texture: the fovea's mean gradient (when given) must be at least min_texture.
        min_margin: the confidence needed. rival_radius: w // 2 by default.
        vshift_cost: with vertical search, what each row of shift |v| costs per pixel (layer 3's 0..255 scale) in
            the winner-takes-all and the margin, so that a shifted row wins only where it is clearly better
            (the decision's score stays the row's own y).

    Returns:
        A Decision: the winner k (sub-pixel k_sub, vertical shift v), the layer-5 direction and magnitude,
        offset_px, the confidence and whether it is confident.

    Raises:
        ValueError: no offsets to decide between."""
    y2 = np.atleast_2d(np.asarray(scores, dtype=np.float64))
    nv, kk = y2.shape
    if kk < 1:
        raise ValueError("no offsets to decide between")
    raw = y2
    if vshift_cost and nv > 1:
        y2 = y2 - (vshift_cost * window * window) * np.abs(np.arange(nv) - (nv - 1) // 2)[:, None]
    flat = int(np.argmax(y2))
    vi, k = divmod(flat, kk)
    row = y2[vi]
    if k_centre is None:
        k_centre = centre_offset(kk + window - 1, window)
    best = float(row[k])
    k_sub = float(k)
    if subpixel and 0 < k < kk - 1:
        k_sub = k + _parabola(float(row[k - 1]), best, float(row[k + 1]))
    # The rival: best score over all rows at offsets more than rival_radius away from the winner.
    r = window // 2 if rival_radius is None else rival_radius
    prof = y2.max(axis=0)
    lo, hi = max(0, k - r), min(kk, k + r + 1)
    rival = max(prof[:lo].max(initial=-np.inf), prof[hi:].max(initial=-np.inf))
    top = 255.0 * window * window
    if np.isfinite(rival):
        dis_rival = top - rival
        margin = (best - rival) / dis_rival if dis_rival > 0 else 0.0
    else:
        margin = 1.0
    margin = float(min(max(margin, 0.0), 1.0))
    confident = margin >= min_margin
    if tex is not None and tex < min_texture:
        confident = False
    d = k - k_centre
    return Decision(k=k, k_sub=k_sub, v=vi - (nv - 1) // 2, k_centre=k_centre, direction=int(np.sign(d)),
                    magnitude=abs(d), offset_px=k_sub - k_centre, score=float(raw[vi, k]), confidence=margin,
                    texture=float(tex) if tex is not None else float("nan"), confident=bool(confident))


def decide_scores(scores: np.ndarray, fovea: np.ndarray, x: int, params: Params,
                  master_rows: np.ndarray | None = None, slave_band: np.ndarray | None = None,
                  weights: np.ndarray | None = None) -> Decision:
    """Layer 4's scores -> a Decision for the fovea (planes (3, w, w)) centred on master column x.

    With params.min_correlation, a confident decision's slave window must correlate with the fovea
    (correlation); with params.lr_check, it must also pass the left-right check (lr_consistent), given
    the master's rows of the fovea as a gray strip with its margin ((w + 2, W + 2), retina.band_strip with
    no vertical search) and the slave band's planes ((3, w + 2R, W)); with params.halves_check, it must also
    pass halves_consistent, which reads the slave band's columns k - halves_range .. k + halves_range + w - 1
    only. This is the one decision step of both match() and the reducer. weights: the fovea's support weights
    when the caller has them already (kernel.support_weights with params' scales), else computed when needed."""
    w = fovea.shape[1]
    d = decide(scores, w, k_centre=x - w // 2, subpixel=params.subpixel, tex=texture(fovea),
               min_texture=params.min_texture, min_margin=params.min_margin, vshift_cost=params.vshift_cost)
    return apply_checks(d, fovea, x, params, master_rows, slave_band, weights)


def apply_checks(d: Decision, fovea: np.ndarray, x: int, params: Params, master_rows: np.ndarray | None = None,
                 slave_band: np.ndarray | None = None, weights: np.ndarray | None = None) -> Decision:
    """decide_scores' second half: the correlation, left-right and halves checks on a decision (only a
    confident one can change), for a caller that gets the bands only once it knows the decision (the reducer).
    The first check that fails makes it not confident, and the later ones are not asked."""
    if not d.confident or slave_band is None:
        return d
    if params.min_correlation > 0 and not pearson(fovea, slave_band, d) >= params.min_correlation:
        return replace(d, confident=False)
    if params.lr_check and master_rows is not None and not lr_consistent(master_rows, slave_band, x, d, params):
        return replace(d, confident=False)
    if params.halves_check and not halves_consistent(fovea, slave_band, d, params, weights):
        return replace(d, confident=False)
    return d


def pearson(fovea: np.ndarray, slave_band: np.ndarray, d: Decision) -> float:
    """Pearson correlation of the fovea's intensities with those of the winning slave window (rows shifted
    by v, columns k..k+w-1 of the band): near 1 for a real match, near 0 for two fields of independent
    noise; 0 when either is flat."""
    w = fovea.shape[1]
    r = (slave_band.shape[1] - w) // 2
    f, s = fovea[0], slave_band[0, r + d.v : r + d.v + w, d.k : d.k + w]
    f, s = f.astype(np.float64) - _mean(f), s.astype(np.float64) - _mean(s)
    den = float(np.sqrt((f * f).sum() * (s * s).sum()))
    return float((f * s).sum()) / den if den > 0 else 0.0


def lr_consistent(master_rows: np.ndarray, slave_band: np.ndarray, x: int, d: Decision, params: Params) -> bool:
    """Left-right consistency: the winning slave window (rows shifted by v), matched back along the fovea's
    own rows of the master, lands within params.lr_tolerance px of where the forward match says it should.
    master_rows: those rows as a gray strip with its margin, or its planes (retina.planes of it, 3-D) when the
    caller has them (the reducer makes them before the correlations come: vergence.stages.gather.prepare)."""
    half = x - d.k_centre
    w = 2 * half + 1
    r = (slave_band.shape[1] - w) // 2  # R
    sf = np.ascontiguousarray(slave_band[:, r + d.v : r + d.v + w, d.k : d.k + w])
    master = master_rows if master_rows.ndim == 3 else retina.planes(master_rows)
    back = kernel.correlate(sf, master, circular=params.circular)
    expected = x - (d.k_sub - d.k)
    return abs((_winner_sub(back, params.subpixel) + half) - expected) <= params.lr_tolerance


def _winner_sub(scores: np.ndarray, subpixel: bool) -> float:
    """decide(scores, ...).k_sub of 1-D scores, without the rest of the decision (the left-right check's)."""
    k = int(np.argmax(scores))
    if subpixel and 0 < k < scores.shape[0] - 1:
        return k + _parabola(float(scores[k - 1]), float(scores[k]), float(scores[k + 1]))
    return float(k)


CLIPPED_HALF = 0.5  # a half with less of its weight on pixels the slave did not clip is not asked
HALVES_TOLERANCE = 2  # px: how far a half's own best offset may lie from the winner (1 abstains at too many points)


def halves_consistent(fovea: np.ndarray, slave_band: np.ndarray, d: Decision, params: Params,
                      weights: np.ndarray | None = None) -> bool:
    """The halves check: the left, right, top and bottom halves of the fovea (the centre row or column in
    each), weighed by the fovea's support weights when params.support, each matched alone along the winning
    row v at offsets within params.halves_range of the winner k, must each find their best offset within
    HALVES_TOLERANCE (2) px of k. At a depth edge the half on the other surface finds that surface's offset:
    the fovea straddles two surfaces and the winner may be the wrong one's (foreground fattening), so abstain.
    The pixels the slave camera clipped (in the winning window, at the band's darkest or brightest level) are
    left out of every half, and a half left with under CLIPPED_HALF (half) of its weight is not asked: with the
    slave at gain 0.7, -15, a fifth of tsukuba's pixels go black, and a half on them found its best anywhere.
    Exact integers (kernel.half_sads, the four halves in one pass); reads the band's columns
    k - halves_range .. k + halves_range + w - 1 of the winning rows only. weights: the fovea's support weights
    when the caller has them (kernel.support_weights with params' scales; read, never written)."""
    w = fovea.shape[1]
    r = (slave_band.shape[1] - w) // 2  # the vertical search R
    kk = slave_band.shape[2] - w + 1
    k0, k1 = max(0, d.k - params.halves_range), min(kk, d.k + params.halves_range + 1)
    rows = slave_band[:, r + d.v : r + d.v + w, :]
    if not params.support:
        wts = np.ones((w, w), np.uint8)
    elif weights is not None:
        wts = weights
    else:
        wts = kernel.support_weights(fovea, params.support_gamma, params.support_radius_at(w))
    # Pixels the slave camera clipped (its band's darkest or brightest level, in the winning window) carry no
    # texture: a half mostly on them would find its best offset anywhere. They are left out of the halves, and
    # a half left with under CLIPPED_HALF of its weight is not asked.
    band_i = slave_band[0]
    win = band_i[r + d.v : r + d.v + w, d.k : d.k + w]
    clipped = (win == band_i.min()) | (win == band_i.max())
    asked = np.ones(4, bool)
    if clipped.any():
        kept = np.where(clipped, 0, wts).astype(np.uint8)
        c = w // 2
        full = [wts[:, : c + 1].sum(), wts[:, c:].sum(), wts[: c + 1].sum(), wts[c:].sum()]
        left = [kept[:, : c + 1].sum(), kept[:, c:].sum(), kept[: c + 1].sum(), kept[c:].sum()]
        asked = np.array([lf >= CLIPPED_HALF * fu for lf, fu in zip(left, full)])
        wts = kept
    s = kernel.half_sads(fovea, rows, k0, k1, circular=params.circular, weights=wts)
    best = np.argmin(s, axis=1)
    return all(abs(k0 + int(best[h]) - d.k) <= HALVES_TOLERANCE or not asked[h] for h in range(4))
