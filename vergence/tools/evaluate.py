"""Accuracy of the network on any rectified pair with a ground-truth disparity (`vergence accuracy`), drawn as
tests/scenarios/test_accuracy.py and tests/vergence/sim/test_loop.py draw Middlebury's: the tests' visible() and
points() are these.

static(): per gain of the slave image (GAINS: as is, 1.3 * I + 20 and 0.7 * I - 15, clipped) and per seed, n
visible points STATIC_MARGIN px from the border: the share answered confidently (coverage) and the share of those
within 1 px of the ground truth (right), and right among confident apart for the answers near a depth edge of the
ground truth (depth_edges: within 3 px of a step of more than 1 px) and away from them. loop(): the closed loop
of tests/vergence/sim/test_loop.py (ideal motor, "p" controller, starts 10-40 px off drawn from seed + 1000, 8
frames; converged = within 1 px by frame 5 and staying there) at n points per seed LOOP_MARGIN px from the border,
the same points and starts at every gain, with each gain's paired difference to equal gain and its standard
error."""

from __future__ import annotations

import math
import os
import zipfile
from collections.abc import Callable
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from ..head.control import ControlSettings
from ..network.match import match
from ..motors.base import MotorSettings
from ..network.params import Params
from ..sim.loop import closed_loop, frames_to_converge
from ..sim.rig import Rig
from ..io.images import read_image

__all__ = ["GAINS", "STATIC_MARGIN", "LOOP_MARGIN", "STATIC_SEEDS", "LOOP_SEEDS", "STATIC_N", "LOOP_N",
           "EDGE_RADIUS", "EDGE_STEP", "load_disparity", "visible", "depth_edges", "points", "gained",
           "started_off", "SeedFigures", "StaticGain", "LoopGain", "static", "loop"]

# slave = gain * I + offset, clipped: the slave camera as is, brighter, darker
GAINS: dict[str, tuple[float, float]] = {"equal": (1.0, 0.0), "bright": (1.3, 20.0), "dark": (0.7, -15.0)}
STATIC_MARGIN = 40  # px from the border (tests/scenarios/test_accuracy.py)
LOOP_MARGIN = 60  # px (tests/vergence/sim/test_loop.py: the slave pans, the fovea must stay inside)
STATIC_SEEDS, STATIC_N = (0, 1, 2, 3, 4), 500
LOOP_SEEDS, LOOP_N = (3, 4, 5), 100
LOOP_FRAMES, LOOP_BY = 8, 5  # frames run; converged = within 1 px by this frame and staying there
EDGE_RADIUS, EDGE_STEP = 3, 1.0  # px: near a depth edge = within EDGE_RADIUS of a step of more than EDGE_STEP
IDEAL_MOTOR = MotorSettings(tau_s=0.02, latency_s=0.0, max_accel_deg_s2=0.0, quantise=False)
P_CONTROL = ControlSettings(mode="p")


def load_disparity(path: str, scale: float = 1.0) -> np.ndarray:
    """The left image's disparity in px as float64, 0 = unknown: a .npz (its arr_0) or an image (value / scale).
    inf, NaN and values < 0 become 0. ValueError naming the file when it is missing or unreadable."""
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"disparity scale must be a positive number, got {scale!r}")
    if not os.path.isfile(path):
        raise ValueError(f"cannot read disparity {path!r}: no such file")
    if path.endswith(".npz"):
        try:
            with np.load(path) as z:
                d = np.asarray(z["arr_0"]).astype(np.float64)
        except KeyError:
            raise ValueError(f"cannot read disparity {path!r}: no arr_0 in it (np.savez(path, disp))") from None
        except (OSError, ValueError, zipfile.BadZipFile) as e:
            raise ValueError(f"cannot read disparity {path!r}: not a .npz numpy can read ({e})") from None
    else:
        try:
            d = read_image(path, cv2.IMREAD_UNCHANGED).astype(np.float64) / scale
        except ValueError:
            raise ValueError(f"cannot read disparity {path!r}: not an image OpenCV can decode") from None
    if d.ndim != 2:
        raise ValueError(f"disparity {path!r} has shape {d.shape}: want one value per pixel (2-D)")
    d[~np.isfinite(d) | (d < 0)] = 0
    return d


def visible(disp: np.ndarray) -> np.ndarray:
    """True where the left pixel's disparity is known AND the point is seen by the right camera.

    A left pixel at x with disparity d lands on right column x - d. If some pixel further right lands on or
    left of that column, it is nearer (larger d) and hides our point from the right camera: the point is
    occluded, its content absent from the slave image, and no matcher can be right there. Middlebury's own
    evaluation ("nonocc") excludes such points the same way."""
    h, w = disp.shape
    vis = disp > 0
    xr = np.arange(w)[None, :] - disp
    xr = np.where(disp > 0, xr, np.inf)
    # running minimum of the right-image column over the pixels to the right of each x
    right_min = np.minimum.accumulate(xr[:, ::-1], axis=1)[:, ::-1]
    shifted = np.concatenate([right_min[:, 1:], np.full((h, 1), np.inf)], axis=1)
    return vis & ~(shifted < xr + 0.5)


def depth_edges(disp: np.ndarray, radius: int = EDGE_RADIUS, step: float = EDGE_STEP) -> np.ndarray:
    """True within `radius` px (a square) of a depth edge of the ground truth: two neighbouring pixels (across or
    down) whose disparities differ by more than `step` px, an unknown (0) beside a known one included (the border
    of an occlusion). Middlebury's own evaluation reports such pixels apart ("disc"): there the fovea holds two
    surfaces and a window method's answer is often the other one's."""
    e = np.zeros(disp.shape, bool)
    across = np.abs(np.diff(disp, axis=1)) > step
    down = np.abs(np.diff(disp, axis=0)) > step
    e[:, 1:] |= across
    e[:, :-1] |= across
    e[1:] |= down
    e[:-1] |= down
    if radius > 0:
        e = cv2.dilate(e.astype(np.uint8), np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)) > 0
    return e


def points(ok: np.ndarray, n: int, seed: int, margin: int) -> list[tuple[int, int]]:
    """n random (x, y) where ok is True, at least `margin` px from the border, drawn from seed: x in
    [margin, w - margin), then y in [margin, h - margin), again until ok. ValueError when no such pixel exists
    (the draw would never end)."""
    h, w = ok.shape
    if w <= 2 * margin or h <= 2 * margin:
        raise ValueError(f"image {w} x {h} too small for points {margin} px from the border")
    if n > 0 and not ok[margin:h - margin, margin:w - margin].any():
        raise ValueError(f"no pixel with a visible ground truth {margin} px from the border")
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        x, y = int(rng.integers(margin, w - margin)), int(rng.integers(margin, h - margin))
        if ok[y, x]:
            out.append((x, y))
    return out


def gained(img: np.ndarray, gain: float, offset: float) -> np.ndarray:
    """gain * img + offset, clipped to 0..255, as uint8 (img itself at gain 1, offset 0)."""
    if gain == 1.0 and offset == 0.0:
        return img
    return np.clip(img.astype(np.float32) * np.float32(gain) + np.float32(offset), 0, 255).astype(np.uint8)


def _check(left: np.ndarray, right: np.ndarray, disp: np.ndarray, gains, seeds, n: int) -> None:
    if n < 1 or not seeds or not gains:
        raise ValueError(f"want at least 1 point, 1 seed and 1 gain, got n={n}, seeds={list(seeds)}, "
                         f"gains={list(gains)}")
    if left.shape != right.shape or left.shape != disp.shape:
        raise ValueError(f"sizes differ: left {left.shape}, right {right.shape}, disparity {disp.shape}")
    bad = [g for g in gains if g not in GAINS]
    if bad:
        raise ValueError(f"unknown gain(s) {', '.join(bad)}; known: {', '.join(GAINS)}")


@dataclass(frozen=True)
class SeedFigures:
    """One seed's draw: coverage = % of the n points answered confidently, right = % of those within 1 px;
    near = how many of the confident answers are near a depth edge (depth_edges), right_near and right_away =
    right among the confident answers near one and away from them, in %."""

    seed: int
    coverage: float
    right: float
    near: int
    right_near: float
    right_away: float


@dataclass(frozen=True)
class StaticGain:
    gain: str
    n: int
    seeds: list[SeedFigures]

    @property
    def mean(self) -> tuple[float, float]:
        return (float(np.mean([s.coverage for s in self.seeds])), float(np.mean([s.right for s in self.seeds])))

    @property
    def worst(self) -> tuple[float, float]:
        return min(s.coverage for s in self.seeds), min(s.right for s in self.seeds)

    @property
    def away_worst(self) -> float:
        """Right among the confident answers away from depth edges, on the worst seed."""
        return min(s.right_away for s in self.seeds)

    @property
    def near_pooled(self) -> tuple[int, float]:
        """The confident answers near a depth edge over every seed, and the % of them right."""
        n = sum(s.near for s in self.seeds)
        right = sum(round(s.near * s.right_near / 100) for s in self.seeds)  # whole answers
        return n, 100 * right / max(1, n)

    def to_dict(self) -> dict:
        return {**asdict(self), "mean": list(self.mean), "worst": list(self.worst), "away_worst": self.away_worst,
                "near_pooled": list(self.near_pooled)}

    def line(self) -> str:
        (mc, mr), (wc, wr) = self.mean, self.worst
        nn, nr = self.near_pooled
        return (f"{self.gain}: confident / right among confident, per seed {[s.seed for s in self.seeds]}: "
                + ", ".join(f"{s.coverage:.1f}/{s.right:.1f}" for s in self.seeds)
                + f"; mean {mc:.1f}/{mr:.1f}, worst {wc:.1f}/{wr:.1f} %; right away from depth edges (worst seed) "
                f"{self.away_worst:.1f} %, within {EDGE_RADIUS} px of one {nr:.1f} % of {nn} answers")


def static(left: np.ndarray, right: np.ndarray, disp: np.ndarray, params: Params | None = None,
           seeds=STATIC_SEEDS, n: int = STATIC_N, gains=tuple(GAINS),
           each: Callable[[StaticGain], None] | None = None) -> list[StaticGain]:
    """Per gain (in the order given), per seed: coverage and right among confident, in %. each: called with
    every gain's figures as soon as they are in (a long run shows its progress)."""
    params = params or Params()
    _check(left, right, disp, gains, seeds, n)
    vis, edges = visible(disp), depth_edges(disp)
    out = []
    for gname in gains:
        slave = gained(right, *GAINS[gname])
        rows = []
        for seed in seeds:
            pts = points(vis, n, seed, STATIC_MARGIN)
            res = [(match(left, slave, p, params), disp[p[1], p[0]], edges[p[1], p[0]]) for p in pts]
            conf = [(abs(m.offset_px + d) <= 1.0, e) for m, d, e in res if m.confident]
            near = [ok for ok, e in conf if e]
            away = [ok for ok, e in conf if not e]
            rows.append(SeedFigures(int(seed), 100 * len(conf) / n,
                                    100 * sum(ok for ok, _ in conf) / max(1, len(conf)), len(near),
                                    100 * sum(near) / max(1, len(near)), 100 * sum(away) / max(1, len(away))))
        out.append(StaticGain(gname, n, rows))
        if each is not None:
            each(out[-1])
    return out


@dataclass(frozen=True)
class LoopGain:
    """converged: % of `points` runs converged; paired / stderr: the difference to equal gain on the same points
    and starts, in percentage points, and its standard error (None for equal gain itself, or without it)."""

    gain: str
    points: int
    converged: float
    paired: float | None = None
    stderr: float | None = None

    def to_dict(self) -> dict:
        return asdict(self)

    def line(self) -> str:
        s = f"{self.gain}: converged {self.converged:.1f} % of {self.points} points"
        if self.paired is not None:
            err = "n/a" if self.stderr is None else f"{self.stderr:.1f}"
            s += f"; paired against equal gain {self.paired:+.1f} points, standard error {err}"
        return s


def started_off(left: np.ndarray, right: np.ndarray, disp: np.ndarray, x: int, y: int, rng: np.random.Generator,
                **kw) -> Rig:
    """A rig fixating (x, y), its slave started 10-40 px (drawn from rng, either side) off the converged pan;
    kw: more Rig settings (gain, offset...)."""
    px = float(rng.uniform(10, 40)) * rng.choice([-1, 1])
    base = Rig(left, right, disparity=disp, fixate=(x, y))
    return Rig(left, right, disparity=disp, fixate=(x, y), start_pan_deg=math.degrees(base.pan_off_truth(px)), **kw)


def _converged(left, right, disp, vis, params, seeds, n, gain, offset) -> np.ndarray:
    out = []
    for seed in seeds:
        rng = np.random.default_rng(seed + 1000)
        for x, y in points(vis, n, seed, LOOP_MARGIN):
            rig = started_off(left, right, disp, x, y, rng, gain=gain, offset=offset)
            k = frames_to_converge(list(closed_loop(rig, LOOP_FRAMES, params, motor=IDEAL_MOTOR, control=P_CONTROL)))
            out.append(float(k is not None and k <= LOOP_BY))
    return np.array(out)


def loop(left: np.ndarray, right: np.ndarray, disp: np.ndarray, params: Params | None = None,
         seeds=LOOP_SEEDS, n: int = LOOP_N, gains=tuple(GAINS),
         each: Callable[[LoopGain], None] | None = None) -> list[LoopGain]:
    """Per gain, equal gain first when it is among them, then the others in the order given: the share of
    closed-loop runs converged, in %, and each other gain's paired difference to equal gain. each: as static()'s."""
    params = params or Params()
    _check(left, right, disp, gains, seeds, n)
    order = list(dict.fromkeys(sorted(gains, key=lambda g: g != "equal")))
    vis = visible(disp)
    equal = None
    out = []
    for gname in order:
        r = _converged(left, right, disp, vis, params, seeds, n, *GAINS[gname])
        if gname == "equal":
            equal = r
        paired = stderr = None
        if equal is not None and gname != "equal":
            diff = r - equal
            paired = float(100 * diff.mean())
            stderr = float(100 * diff.std(ddof=1) / math.sqrt(diff.size)) if diff.size > 1 else None
        out.append(LoopGain(gname, int(r.size), float(100 * r.mean()), paired, stderr))
        if each is not None:
            each(out[-1])
    return out
