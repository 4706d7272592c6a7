"""Messages built the same way by several test files (the motor tests under tests/vergence/motors)."""

from __future__ import annotations

from vergence.messages import Command


def cmd(pan, frame=1, t=0, **kw) -> Command:
    """A command for rig "head": go to pan `pan` (rad), nothing else said."""
    return Command(rig="head", frame=frame, t_capture_ns=t, pan_rad=pan, correction_rad=0.0, direction=0,
                   magnitude_px=0.0, confidence=1.0, **kw)
