"""Worker side: a Frame and this worker's k-range of its plan -> one messages.Correlation (layer 4 on that range)."""

from __future__ import annotations

import time

import numpy as np

from ..network import kernel, retina
from ..wire.messages import Frame, Correlation

__all__ = ["compute_correlation"]


def compute_correlation(frame: Frame, worker: str, t_done: bool = True) -> Correlation | None:
    """Layer 4 on this worker's k-range of the frame (None when the plan gives it nothing).

    Only the band columns the range reads are turned into features (planes are local, so the result is
    bit-identical to the unsharded computation)."""
    rng = frame.shard(worker)
    if rng is None:
        return None
    k0, k1 = rng
    w = frame.window
    fovea = retina.planes(frame.fovea_strip())
    # planes column j is strip column j + 1: offsets k0..k1-1 read plane columns k0 .. k1 + w - 2
    sub = frame.band_strip()[:, k0 : k1 + w + 1]
    band = retina.planes(sub)
    weights = kernel.support_weights(fovea, frame.support_gamma, frame.support_radius) if frame.support else None
    scores = np.atleast_2d(kernel.correlate(fovea, band, circular=frame.circular, weights=weights))
    return Correlation(rig=frame.rig, frame=frame.frame, t_capture_ns=frame.t_capture_ns, worker=worker, k0=k0, k1=k1,
                   rows=scores.shape[0], scores=scores.astype("<f8", copy=False).tobytes(),
                   t_done_ns=time.time_ns() if t_done else 0)
