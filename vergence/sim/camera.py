"""The simulated cameras' timing: when each frame is exposed, over how long, and what the image integrates.

vergence.head.timing.CameraTiming says the numbers (latency, skew, exposure, jitter); this module turns them into
the simulator's schedule (Schedule: frame i's master exposure at i / rate off its schedule by the jitter,
the slave's skew later, read latency after the later one) and into images (expose: each view the mean of
sub-views rendered across its exposure, so that a moving target or a turning slave blurs, then the sensor's
noise once). Times are seconds on whatever clock the caller keeps (virtual in `vergence sim`, the wall clock
in the capture's sim source)."""

from __future__ import annotations

import math

import numpy as np

from ..head.timing import CameraTiming
from .optics import Region

__all__ = ["Schedule", "sub_times", "expose", "SUB_S"]

SUB_S = 0.002  # one sub-view per this much exposure (at least two for any exposure > 0)


def sub_times(t_mid: float, exposure_s: float) -> list[float]:
    """The instants an exposure of exposure_s centred on t_mid is sampled at (one: t_mid, for no exposure)."""
    if exposure_s <= 0:
        return [t_mid]
    n = max(2, math.ceil(exposure_s / SUB_S))
    return [t_mid + exposure_s * ((k + 0.5) / n - 0.5) for k in range(n)]


def _mean(views: list[np.ndarray]) -> np.ndarray:
    if len(views) == 1:
        return views[0]
    return np.rint(np.mean(np.stack(views), axis=0, dtype=np.float32)).astype(np.uint8)


def expose(rig, master_times: list[float], slave_samples: list[tuple[float, float]],
           region: Region | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(master, slave) images: the master's view averaged over master_times, the slave's over
    slave_samples [(pan, t), ...] (its pan at each instant), each with its camera's sensor noise once.
    rig: a vergence.sim Rig or MovingRig (master_view, slave_view, noisy). region: only that part of the
    views (vergence.sim.optics.Region): a band gets the noise those rows get in the whole view, a scaled
    view (a preview) none."""
    if region is None:
        master = _mean([rig.master_view(t) for t in master_times])
        slave = _mean([rig.slave_view(pan, t) for pan, t in slave_samples])
        return rig.noisy(master, 0), rig.noisy(slave, 1)
    master = _mean([rig.master_view(t, region) for t in master_times])
    slave = _mean([rig.slave_view(pan, t, region) for pan, t in slave_samples])
    if region.scale:
        return master, slave
    return rig.noisy(master, 0, region.y0), rig.noisy(slave, 1, region.y0)


class Schedule:
    """Frame i's exposure times (the middle of each exposure) and its read time, from a rate and a
    CameraTiming: the master at i / rate_hz plus its jitter (Gaussian of sigma jitter_s, cut at 0.4 of a
    frame so the frames keep their order; none for frame 0), the slave skew_s after it, the pair read
    latency_s after the later of the two."""

    def __init__(self, rate_hz: float, timing: CameraTiming | None = None, seed: int = 0):
        if not (rate_hz > 0 and math.isfinite(rate_hz)):
            raise ValueError(f"rate {rate_hz}: must be a positive number of frames per second")
        self.rate_hz, self.timing = rate_hz, timing or CameraTiming()
        self.rng = np.random.default_rng(seed + 7919)

    def frame(self, i: int) -> tuple[float, float, float]:
        """(t_master, t_slave, t_read) of frame i (call it for i = 0, 1, 2 ... in order)."""
        tm = self.timing
        cut = 0.4 / self.rate_hz
        jitter = 0.0 if i == 0 or tm.jitter_s <= 0 else float(np.clip(self.rng.normal(0.0, tm.jitter_s), -cut, cut))
        t_master = i / self.rate_hz + jitter
        return t_master, t_master + tm.skew_s, tm.read_time(t_master)
