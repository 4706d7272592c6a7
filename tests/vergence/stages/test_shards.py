"""vergence.stages.shards, the worker side: shards of layer 4 concatenate to the whole correlation."""

from __future__ import annotations

import numpy as np
import pytest
from samples import frame_of, textured

from vergence.network import kernel, retina
from vergence.head.control import ControlSettings
from vergence.stages.gather import Gatherer
from vergence.wire.messages import Frame, Correlation
from vergence.network.params import Params
from vergence.stages.shards import compute_correlation


def clipping_pair():
    """A textured pair whose slave is at gain 1.6, +40: a quarter of its band saturates (clip_master clips)."""
    m, s = textured()
    return m, np.clip(s * 1.6 + 40, 0, 255).astype(np.uint8)


def gather(params=Params(max_window=0), deadline=0.05):
    return Gatherer(params, ControlSettings(), deadline)


@pytest.mark.parametrize("params", [Params(), Params.paper(), Params(vsearch=0, circular=False),
                                    Params(support=True), Params(photometric="affine")],
                         ids=["default", "paper", "flat", "support", "affine"])
@pytest.mark.parametrize("nworkers", [1, 2, 3])
@pytest.mark.parametrize("gain", [1.0, 0.7])
def test_shards_concatenate_to_correlate(params, nworkers, gain):
    m, s = textured()
    s = np.clip(s * gain + (-15 if gain != 1 else 0), 0, 255).astype(np.uint8)  # the slave camera's gain
    f = Frame.from_bytes(frame_of(m, s, params, workers=[f"w{i}" for i in range(nworkers)]).to_bytes())
    parts = [Correlation.from_bytes(compute_correlation(f, f"w{i}").to_bytes()) for i in range(nworkers)]
    got = np.concatenate([p.array() for p in parts], axis=1)
    fovea, band = retina.features(m, s, window=params.window, vsearch=params.vsearch, photometric=params.photometric)
    w = kernel.support_weights(fovea, params.support_gamma, params.support_radius_at(params.window)) \
        if params.support else None
    want = np.atleast_2d(kernel.correlate(fovea, band, circular=params.circular, weights=w))
    assert got.shape == want.shape == (2 * params.vsearch + 1, m.shape[1] - params.window + 1)
    assert np.array_equal(got, want)
    assert compute_correlation(f, "nobody") is None
