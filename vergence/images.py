"""Image files: read_image, the one reader of an image path (the sources, the simulator's scenes, the ground
truth of an evaluation), and SourceError, what it and the sources raise."""

from __future__ import annotations

import os

import cv2
import numpy as np

__all__ = ["SourceError", "read_image"]


class SourceError(ValueError):
    """A source that cannot be opened or read; the message names it and says how to fix it."""


def read_image(path: str, flags: int = cv2.IMREAD_GRAYSCALE) -> np.ndarray:
    """An image file (gray by default); SourceError that says whether it is missing or undecodable."""
    if not os.path.isfile(path):
        raise SourceError(f"cannot read image {path!r}: no such file")
    img = cv2.imread(path, flags)
    if img is None:
        raise SourceError(f"cannot read image {path!r}: not an image OpenCV can decode")
    return img
