"""Byte-identical images (issue #35): a frozen camera's driver repeats its last image with fresh stamps. digest() is the
CRC-32 each Frame carries for its two images; Master watches the master camera's: images that used to change every
frame (MASTER_LIVE in a row at least: a live camera's noise) and have been the same for FROZEN_MASTER_S are a frozen
master. Slave watches the slave camera's against the motor: the same bytes after the motor moved IDENTICAL_MOVE_DEG
since they were first seen (more than a backlash or the encoder's noise) are a frozen slave (vergence.head.doubt);
so are the same bytes for FROZEN_MASTER_S while the master's changed MASTER_LIVE times or more (the scene, the
sensor's noise: what the slave would show too): a slave that freezes while the motor holds (a target that steps in
depth meanwhile leaves the match nothing to find). A still scene without noise changes neither.
"""

from __future__ import annotations

import math
import zlib

import numpy as np

__all__ = ["FROZEN_MASTER_S", "IDENTICAL_MOVE_DEG", "MASTER_LIVE", "Master", "Slave", "digest"]

FROZEN_MASTER_S = 0.3  # byte-identical master images for this long, where they used to change ...
MASTER_LIVE = 5  # ... every frame, this many in a row at least (a live camera's noise)
IDENTICAL_MOVE_DEG = 0.5  # a byte-identical slave image after the motor moved this much is frozen


def digest(img: np.ndarray, y: int | None = None, reach: int = 0) -> int:
    """The CRC-32 of an image's bytes (a frozen camera repeats them), or of its rows y - reach .. y + reach only
    (the band the network reads: a twentieth of a VGA image's, 4 us against 70); never 0, which says "not known"
    in a Frame, as it is for flat rows (a black frame repeats itself and is no frozen camera)."""
    if y is not None:
        img = img[max(0, y - reach):y + reach + 1]
    img = np.ascontiguousarray(img)
    if img.size == 0 or img.min() == img.max():
        return 0
    return zlib.crc32(img) or 1


class Master:
    """The master camera's digests, frame to frame."""

    def __init__(self):
        self.last: int | None = None
        self.same_since: float | None = None  # the exposure of the first image of the present run of the same bytes
        self.changes = 0  # the longest run of images that changed frame to frame
        self.run = 0  # the present run
        self.key = None  # the rows digested (the fovea's)

    def see(self, t: float, digest: int | None, key=None) -> str | None:
        """One master image (t its exposure, its digest of the rows `key` says, the fovea's; None: unknown):
        "changed" (unlike the last one), "frozen" (the same for FROZEN_MASTER_S where they used to change every
        frame) or None. Other rows' first digest is no change: their next one tells (a fovea moved 0.26 s into a
        freeze named it 0.56 s after it began, the issue's bound 0.5: Cones, seed 7210, docs/FAULTS.md)."""
        if digest is None:
            return None
        if key != self.key and self.last is not None:
            self.key, self.last = key, digest
            return None
        self.key = key
        if digest != self.last:
            # a run of MASTER_LIVE changes in a row says a live camera, where a few changes apart (the rows a
            # simulator renders as the window grows) do not
            self.run = self.run + 1 if self.last is not None else 0
            self.changes = max(self.changes, self.run)
            self.last, self.same_since = digest, t
            return "changed"
        self.run = 0
        if self.changes >= MASTER_LIVE and t - self.same_since >= FROZEN_MASTER_S:
            return "frozen"
        return None


class Slave:
    """The slave camera's digests, with the motor's pan when each was first seen."""

    def __init__(self):
        self.last: tuple[int, float] | None = None  # (digest, pan) when it was first seen
        self.since = 0.0  # its first exposure
        self.master_changes = 0  # the master's changes since

    def frozen(self, t: float, pan: float, digest: int | None, master_changed: bool = False) -> bool:
        """The slave's image (t its exposure, its digest; None: unknown) byte for byte what it was when first seen,
        though the motor moved IDENTICAL_MOVE_DEG since, or for FROZEN_MASTER_S while the master's images changed
        MASTER_LIVE times or more (master_changed: this frame's did)."""
        if digest is None:
            return False
        if self.last is None or self.last[0] != digest:
            self.last, self.since, self.master_changes = (digest, pan), t, 0
            return False
        self.master_changes += master_changed
        if self.master_changes >= MASTER_LIVE and t - self.since >= FROZEN_MASTER_S:
            return True
        return abs(pan - self.last[1]) >= math.radians(IDENTICAL_MOVE_DEG)
