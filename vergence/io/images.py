"""Image files: read_image, the one reader of an image path (the sources, the simulator's scenes, the ground
truth of an evaluation); SourceError, what it and the sources raise; and Source, the base class of every source
(vergence.io.sources' and vergence.ros2.source's: here, so that neither imports the other)."""

from __future__ import annotations

import abc
import os

import cv2
import numpy as np

from ..choices import Side

__all__ = ["Source", "SourceError", "read_image"]


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


class Source(abc.ABC):
    """What the capture reads a pair from (every source subclasses it, the ROS 2 one too): size, focal_px,
    start_pan_rad, follows_pan, read(pan_at) -> (master, slave), close(). `master` ("left" or "right") says which
    camera is the fixed one: the base class checks it and _order puts the master first."""

    size: tuple[int, int] = (0, 0)
    focal_px: float = 0.0
    start_pan_rad: float = 0.0
    truth_pan_rad: float | None = None
    follows_pan: bool = True
    renders: bool = False  # the slave image is rendered at the pan it is asked for (the simulator)
    on_reject = None  # a source that refuses images of its own (ros2) calls it at each: the capture's status goes out
    rows: tuple[int, int] | None = None  # the rows the capture reads of the next pair (None: all); a source that
    # renders may leave the others black (the simulator: a band is a tenth of the cost of a view)
    exposure_ns: tuple[int, int] | None = None
    fovea: tuple[int, int] | None = None  # where the capture's fovea is (None: the centre); the truth's point
    frame_id: str = ""  # the master image's own name of its optical frame, where the source has one (ros2)
    # (master's, slave's) principal point (cx, cy) where the source knows it (a camera_info, the simulator's cx=, cy=);
    # -1: not known (the capture takes [camera] cx, cy where set, else the image centre)
    principal: tuple = ((-1.0, -1.0), (-1.0, -1.0))
    # (master's, slave's) vergence.io.lens.Lens where the source knows its cameras' distortion (a camera_info, the
    # simulator's k1=, k2=): the capture removes it from the rows a frame reads; None: none known
    lenses: tuple | None = None

    def __init__(self, master: str = "left"):
        if master not in tuple(Side):
            raise SourceError(f"capture.master must be 'left' or 'right', got {master!r}")
        self.swap = master == "right"

    def _order(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (right, left) if self.swap else (left, right)

    @abc.abstractmethod
    def read(self, pan_at=0.0) -> tuple[np.ndarray, np.ndarray]:
        """The next pair (master, slave), uint8 gray; pan_at: the slave's pan, a number or a function of a time."""

    def close(self) -> None:
        """Release the device or files (a no-op by default)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
