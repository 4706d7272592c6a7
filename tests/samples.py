"""Samples built the same way by several test files: a motor command (the motor tests under tests/vergence/motors),
a textured pair and its frame (the stages' tests: test_frames, test_shards, test_gather)."""

from __future__ import annotations

import cv2
import numpy as np

from vergence.stages.frames import make_frame, plan_shards
from vergence.wire.messages import Command


def cmd(pan, frame=1, t=0, **kw) -> Command:
    """A command for rig "head": go to pan `pan` (rad), nothing else said."""
    return Command(rig="head", frame=frame, t_capture_ns=t, pan_rad=pan, correction_rad=0.0, direction=0,
                   magnitude_px=0.0, confidence=1.0, **kw)


SHIFT = 12  # the slave sees the scene 12 px further left: the match lies 12 px right of the centre


def textured(h=120, w=200, seed=1, shift=SHIFT):
    rng = np.random.default_rng(seed)
    base = cv2.GaussianBlur(rng.integers(0, 256, (h, w + 40), np.uint8), (5, 5), 1.5)
    return np.ascontiguousarray(base[:, 20 : 20 + w]), np.ascontiguousarray(base[:, 20 - shift : 20 - shift + w])


def frame_of(master, slave, params, workers=("a",), fid=1, pan=0.0, focal=100.0, window=None):
    k = master.shape[1] - (window or params.window) + 1
    return make_frame(master, slave, rig="r", frame=fid, pan_rad=pan, focal_px=focal, params=params,
                      plan=plan_shards(workers, k), window=window)
