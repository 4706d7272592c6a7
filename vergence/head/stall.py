"""A motor that does not follow its commands (issue #35): stalled, jammed, its torque off by an overload. A command
STALL_ARM_DEG or more away from the motor's pan (and past twice its dead band: a goal that near its last moves
nothing) starts a clock unless one runs; the motor moving STALL_MOVE_DEG (or half that command's move) stops it, and
so does a command nearer than half STALL_MOVE_DEG (one between keeps it running: the loop's goals scatter about the
move it asks); STALL_S on it, the motor is stalled (vergence.head.doubt names it and holds). A search's commands
count too: a motor that never moves while it searches is stalled. (Armed at 0.6 deg, MIN_MOVE_DEG, and stopped by
any nearer goal, a loop that asked 0.4 deg, 4 px, of a stalled motor every frame for seconds was never named; kept
running by goals 0.1-0.3 deg away, a motor that moved 0.17 deg of a 0.3 deg goal the next goal took back was
named stalled: docs/FAULTS.md.)"""

from __future__ import annotations

import math

__all__ = ["Stall", "STALL_S", "STALL_MOVE_DEG", "STALL_ARM_DEG"]

STALL_S = 0.5  # no move for this long after a command far away: stalled
STALL_MOVE_DEG = 0.2  # ... a move of this much (or half the move asked): it follows
STALL_ARM_DEG = 0.3  # ... a command at least this far away (and past twice the dead band) starts the clock


class Stall:
    """The clock: commanded() every command, stalled() every pan the motor reports at a frame."""

    def __init__(self, dead_band: float = 0.0):
        self.dead_band = dead_band  # the motor's, rad ([actuator.motor] dead_band_deg)
        self.since: tuple[float, float, float] | None = None  # (t, pan, the move that says it follows) since when a
        # command far away has not moved it

    def commanded(self, pan: float, goal: float, t_now: float) -> None:
        """A command to `goal` at the present `pan` (rad) at t_now (s)."""
        ask = abs(goal - pan)
        if ask >= max(math.radians(STALL_ARM_DEG), 2 * self.dead_band):
            if self.since is None:
                self.since = (t_now, pan, min(math.radians(STALL_MOVE_DEG), ask / 2))
        elif ask < math.radians(STALL_MOVE_DEG) / 2:
            self.since = None

    def stalled(self, t: float, pan: float) -> float | None:
        """The seconds the motor has not moved since a command far away, where that is STALL_S or more (None: it
        moves, or no such command)."""
        if self.since is None:
            return None
        t0, p0, moved = self.since
        if abs(pan - p0) >= moved:
            self.since = None
            return None
        return t - t0 if t - t0 >= STALL_S else None

    def reset(self) -> None:
        self.since = None
