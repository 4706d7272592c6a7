"""Winner-takes-all, layer 5 (direction and magnitude), the sub-pixel winner and the confidence."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

__all__ = ["Decision", "decide", "centre_offset", "texture"]


@dataclass(frozen=True)
class Decision:
    """One decision of the network for one fovea.

    k is the winning offset (integer, layer 4), k_sub the sub-pixel winner (k when sub-pixel is off),
    v the vertical shift of the winning window (0 without vertical search), k_centre the centre neuron,
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


def texture(fovea: np.ndarray) -> float:
    """Mean gradient magnitude G (0..255) of the fovea: near 0 for a flat or black fovea."""
    return float(fovea[1].mean())


def _parabola(ym: float, y0: float, yp: float) -> float:
    den = ym - 2.0 * y0 + yp
    if den >= 0.0:  # not a strict maximum: no refinement
        return 0.0
    return float(np.clip(0.5 * (ym - yp) / den, -0.5, 0.5))


def decide(scores: np.ndarray, window: int, *, k_centre: int | None = None, subpixel: bool = True,
           tex: float | None = None, min_texture: float = 4.0, min_margin: float = 0.04,
           rival_radius: int | None = None, back_ok: bool | None = None, vshift_cost: float = 0.0) -> Decision:
    """Winner-takes-all over layer 4 and the two output neurons.

    scores: y(k) (1-D) or y(v, k) with vertical search (row v is the shift v - R). The band is
    W = K + w - 1 wide; k_centre defaults to W/2 - floor(w/2). The confidence is the margin between the
    winner and the best rival more than rival_radius (default w // 2) offsets away, as a fraction of the
    rival's dissimilarity (255 * w * w - y); confident needs that margin >= min_margin, the fovea's texture
    (when given) >= min_texture, and the left-right check (when given) to agree. min_margin=0 and
    min_texture=0 with no check give the paper's behaviour: always confident. vshift_cost: with vertical
    search, each row of shift |v| costs this much per pixel (the 0..255 scale of layer 3) in the
    winner-takes-all and the margin, so that a shifted row wins only where it is clearly better; the
    decision's score stays the row's own y."""
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
    if back_ok is False:
        confident = False
    d = k - k_centre
    return Decision(k=k, k_sub=k_sub, v=vi - (nv - 1) // 2, k_centre=k_centre, direction=int(np.sign(d)),
                    magnitude=abs(d), offset_px=k_sub - k_centre, score=float(raw[vi, k]), confidence=margin,
                    texture=float(tex) if tex is not None else float("nan"), confident=bool(confident))
