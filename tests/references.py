"""Plain reference implementations written from ALGORITHM.md (slow, obvious), shared by several test files."""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np

from middlebury import load


def ref_features(img: np.ndarray) -> np.ndarray:
    """I, G, D of a whole gray image, as ALGORITHM.md states them (float64 maths, OpenCV's default border)."""
    gx = cv2.Sobel(img, cv2.CV_64F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_64F, 0, 1, ksize=3)
    g = np.sqrt(gx**2 + gy**2)
    gq = np.minimum(255, np.floor(g / 4 + 0.5))
    ang = np.arctan2(gy, gx) % (2 * math.pi)
    dq = np.floor(ang * 256 / (2 * math.pi) + 0.5) % 256
    dq[g == 0] = 0
    return np.stack([img, gq, dq]).astype(np.uint8)


@functools.lru_cache(maxsize=None)
def whole_features(name):
    left, right, _ = load(name)
    return ref_features(left), ref_features(right)


def ref_winner(name: str, x: int, y: int, w: int = 15) -> int:
    """The paper's winner k* on a Middlebury scene for the fovea at master pixel (x, y): the whole images'
    features, the argmax of layer 4, no row searched."""
    fm, fs = whole_features(name)
    h = w // 2
    fov = fm[:, y - h : y + h + 1, x - h : x + h + 1].astype(np.int64)
    band = fs[:, y - h : y + h + 1, :].astype(np.int64)
    kk = band.shape[2] - w + 1
    # y(k) = sum(255 - (|dI| + |dG| + |dD|) / 3); argmax y = argmin of the integer sum of differences
    s = [np.abs(fov - band[:, :, k : k + w]).sum() for k in range(kk)]
    return int(np.argmin(s))
