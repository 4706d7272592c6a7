"""Test access to ../shared/data/middlebury (tests may read it; the product never does)."""

from __future__ import annotations

import functools
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from vergence.tools import evaluate

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
    """True where the left pixel's disparity is known AND the point is seen by the right camera
    (vergence.tools.evaluate.visible, which says why)."""
    return evaluate.visible(load(name)[2])


def points(name: str, n: int = 100, seed: int = 0, margin: int = 40, mask: np.ndarray | None = None):
    """n random (x, y) with valid ground truth (mask: where, default every known disparity), fixed seed, at least
    `margin` px from the border: vergence.tools.evaluate.points, the draw `vergence accuracy` makes."""
    disp = load(name)[2]
    return evaluate.points(disp > 0 if mask is None else mask, n, seed, margin)
