"""Test access to ../shared/data/middlebury (tests may read it; the product never does)."""

from __future__ import annotations

import functools
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2] / "shared" / "data" / "middlebury"
SCENES = ["cones", "teddy", "tsukuba", "venus"]

needs_data = pytest.mark.skipif(not (ROOT / "scenes.json").is_file(), reason=f"no Middlebury data at {ROOT}")


@functools.lru_cache(maxsize=None)
def load(name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(left gray, right gray, disparity in px as float, 0 = unknown)."""
    s = json.loads((ROOT / "scenes.json").read_text())[name]
    left = cv2.imread(str(ROOT / s["left"]), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(ROOT / s["right"]), cv2.IMREAD_GRAYSCALE)
    disp = cv2.imread(str(ROOT / s["disparity"]), cv2.IMREAD_UNCHANGED).astype(np.float64) / s["disparity_scale"]
    return left, right, disp


@functools.lru_cache(maxsize=None)
def visible(name: str) -> np.ndarray:
    """True where the left pixel's disparity is known AND the point is seen by the right camera.

    A left pixel at x with disparity d lands on right column x - d. If some pixel further right lands on or
    left of that column, it is nearer (larger d) and hides our point from the right camera: the point is
    occluded, its content absent from the slave image, and no matcher can be right there. Middlebury's own
    evaluation ("nonocc") excludes such points the same way."""
    d = load(name)[2]
    h, w = d.shape
    vis = d > 0
    xr = np.arange(w)[None, :] - d
    xr = np.where(d > 0, xr, np.inf)
    # running minimum of the right-image column over the pixels to the right of each x
    right_min = np.minimum.accumulate(xr[:, ::-1], axis=1)[:, ::-1]
    shifted = np.concatenate([right_min[:, 1:], np.full((h, 1), np.inf)], axis=1)
    return vis & ~(shifted < xr + 0.5)


def points(name: str, n: int = 100, seed: int = 0, margin: int = 40, mask: np.ndarray | None = None):
    """n random (x, y) with valid ground truth, fixed seed, at least `margin` px from the border."""
    left, _, disp = load(name)
    ok = disp > 0 if mask is None else mask
    rng = np.random.default_rng(seed)
    h, w = left.shape
    out = []
    while len(out) < n:
        x, y = int(rng.integers(margin, w - margin)), int(rng.integers(margin, h - margin))
        if ok[y, x]:
            out.append((x, y))
    return out
