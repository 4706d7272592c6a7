"""The warm-up the worker and the reducer share: one synthetic textured frame through the kernels before the
first real one, so that frame does not pay for loading (compiling) them."""

from __future__ import annotations

import dataclasses

import numpy as np

from vergence import kernel
from vergence.frames import make_frame
from vergence.gather import Gatherer
from vergence.params import Params
from vergence.shards import compute_correlation

WIDTH = 128
WINDOW = 15


def warm_up(params: Params, control=None) -> None:
    """Run the kernel once on a small synthetic frame made with `params` (window 15, at most +-2 rows); given
    the controller's settings (the reducer), the frame and its correlation also go through a Gatherer, which
    decides on them (left-right check included)."""
    kernel.warm_up()
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (64, WIDTH), np.uint8)
    p = dataclasses.replace(params, window=WINDOW, vsearch=min(params.vsearch, 2))
    f = make_frame(img, img, rig="warm", frame=0, pan_rad=0.0, focal_px=100.0, params=p,
                   plan=[["w", 0, WIDTH - WINDOW + 1]])
    part = compute_correlation(f, "w")
    if control is not None:
        g = Gatherer(p, control)
        g.add_frame(f)
        g.add_correlation(part)
