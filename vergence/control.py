"""From the network's decision to a pan set-point: pixels -> angle, gain, dead band, rate limit, limits."""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["pixels_to_angle", "ControlSettings", "Controller"]


def pixels_to_angle(offset_px: float, focal_px: float, centre_px: float = 0.0) -> float:
    """The pan (radians) that brings the content at `offset_px` right of the principal point to it.

    With a rotating pinhole camera, a column u px right of the principal point lies atan(u / f) off the
    optical axis; centre_px is the fovea window's own offset from the principal point (0 at the centre)."""
    return math.atan((offset_px + centre_px) / focal_px) - math.atan(centre_px / focal_px)


@dataclass(frozen=True)
class ControlSettings:
    """gain: fraction of the measured correction applied per decision; dead_band_px: no move below it;
    max_step_deg: the largest change of the set-point per decision; min_deg/max_deg: the head's pan limits."""

    gain: float = 1.0
    dead_band_px: float = 0.25
    max_step_deg: float = 10.0
    min_deg: float = -45.0
    max_deg: float = 45.0


class Controller:
    """Turns decisions into absolute pan targets for the slave."""

    def __init__(self, settings: ControlSettings | None = None):
        self.s = settings or ControlSettings()

    def target(self, pan_at_capture: float, offset_px: float, focal_px: float, confident: bool = True,
               centre_px: float = 0.0) -> float | None:
        """The new absolute pan (radians) or None when the camera should not move (not confident, inside
        the dead band, or a non-finite input)."""
        if not confident or not all(math.isfinite(v) for v in (pan_at_capture, offset_px, focal_px)):
            return None
        if focal_px <= 0 or abs(offset_px) < self.s.dead_band_px:
            return None
        step = self.s.gain * pixels_to_angle(offset_px, focal_px, centre_px)
        lim = math.radians(self.s.max_step_deg)
        step = max(-lim, min(lim, step))
        return max(math.radians(self.s.min_deg), min(math.radians(self.s.max_deg), pan_at_capture + step))
