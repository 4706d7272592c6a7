"""The warm-up the worker and the reducer share: one synthetic textured frame through the kernels before the
first real one, so that frame does not pay for loading (compiling) them.

numba keeps what it compiles in a cache (the package's __pycache__, or NUMBA_CACHE_DIR): the first start on a
machine compiles, some 10 s of one core, and every later one loads, a fraction of a second. compiled() says
whether the cache holds the kernels; `python -m services.runtime.warm` compiles everything every process uses
(the worker's, the reducer's and the capture's), once, which `vergence up` runs on a first start before its
children, rather than have them all compile the same functions at once on the same cores."""

from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from vergence.network.params import Params

WIDTH = 128
WINDOW = 15


def warm_up(params: Params, control=None) -> None:
    """Run the kernel once on a small synthetic frame made with `params` (window 15, at most +-2 rows); given
    the controller's settings (the reducer), the frame and its correlation also go through a Gatherer, which
    decides on them (left-right check included). (The kernels are imported here: `vergence up` imports this
    module for compiled() and loads no numba.)"""
    import numpy as np

    from vergence.network import kernel
    from vergence.stages.frames import make_frame
    from vergence.stages.gather import Gatherer
    from vergence.stages.shards import compute_correlation

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
        for r in g.add_correlation(part):
            _ = r.command  # the controller's code too (it runs when the command is first asked for)


def preload(settings) -> None:
    """What each child of `vergence up` would load at its start, loaded once in up: the modules of the services it
    runs (numpy, numba, OpenCV, zenoh) and the kernels (from numba's cache, as the warm-ups of the workers, the
    reducer and the capture do). Every child and standby is forked from up with them (services.ops.launch.Proc,
    fork=True): a worker then starts in about 0.1-0.3 s of CPU, not 1-1.5 s, and a restart is back that much
    sooner."""
    import importlib

    from vergence.network import retina

    for name in ("services.ops.router", "services.pipeline.actuator", "services.pipeline.worker",
                 "services.pipeline.reducer", "services.pipeline.capture", "services.ops.cli"):
        importlib.import_module(name)
    warm_up(settings.network, settings.control)
    retina.warm_up()


def cache_dirs() -> list[Path]:
    """Where numba's cache of vergence's kernels may be: NUMBA_CACHE_DIR when set, else the __pycache__ of the
    kernels' package (vergence/network/) and, for a read-only install, the user's cache (~/.cache/numba)."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return [Path(os.environ["NUMBA_CACHE_DIR"])]
    package = Path(__file__).resolve().parents[2] / "vergence" / "network"
    return [package / "__pycache__", Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "numba"]


def compiled() -> bool:
    """Whether numba's cache holds the kernel (a first start on this machine, or after an upgrade, has not)."""
    return any(next(d.rglob("kernel*.nbi"), None) is not None for d in cache_dirs() if d.is_dir())


def main() -> int:
    """Compile (or load) every kernel the pipeline's processes use (`vergence up` says how long it took)."""
    from vergence.head.control import ControlSettings
    from vergence.network import retina
    from vergence.network.params import Params

    retina.warm_up()
    warm_up(Params(), ControlSettings())
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except KeyboardInterrupt:  # up stopped by Ctrl-C during the compile: its SIGINT, no traceback
        sys.exit(130)
