"""A motor that does not follow its commands (issue #35): stalled, jammed, its torque off by an overload. A command
STALL_ARM_DEG or more away from the motor's pan (and past twice its dead band: a goal that near its last moves nothing)
starts a clock unless one runs; the motor moving STALL_MOVE_DEG (or half that command's move) stops it. A command nearer
than half STALL_MOVE_DEG pauses it (the next one further on resumes it; one between keeps it running: the loop's goals
scatter about the move it asks), and a pause of STALL_S stops it; STALL_S on it, not paused, the motor is stalled
(vergence.head.doubt names it and holds). (Stopped by a near command, a stall in pursuit of a sine at 0.93 Hz went
unnamed for 1.8 s: the target passed the stuck motor's pan every 0.5 s, docs/FAULTS.md.) A search's commands count too:
a motor that never moves while it searches is stalled. (Armed at 0.6 deg, MIN_MOVE_DEG, and stopped by any nearer goal,
a loop that asked 0.4 deg, 4 px, of a stalled motor every frame for seconds was never named; kept running by goals
0.1-0.3 deg away, a motor that moved 0.17 deg of a 0.3 deg goal the next goal took back was named stalled:
docs/FAULTS.md.) A noisy encoder: once the readings since the clock started go both up and down (the motor did not move,
so that is its noise), a move is measured from their median, and one reading that far is no move (two in a row are):
each noisy reading 0.2 deg off stopped the clock, and a stall with 0.1 deg of noise went unnamed in half the bench's
pursuits (docs/FAULTS.md, "A stall on a noisy encoder")."""

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
        self.still: list[float] = []  # the pans since, while it did not move (they differ: a noisy encoder's)
        self.away = False  # the previous pan was that move away (a noisy encoder's: confirmed by the next)
        self.near: float | None = None  # since when the goals have been near the pan (the clock paused), and
        self.paused = 0.0  # the seconds it was paused so (none of them count)

    def commanded(self, pan: float, goal: float, t_now: float) -> None:
        """A command to `goal` at the present `pan` (rad) at t_now (s)."""
        ask = abs(goal - pan)
        near = ask < math.radians(STALL_MOVE_DEG) / 2
        if self.near is not None and (not near or t_now - self.near > STALL_S):
            if t_now - self.near > STALL_S:
                self.since = None  # content where it is for long: the clock stops
            self.paused, self.near = self.paused + t_now - self.near, None
        if ask >= max(math.radians(STALL_ARM_DEG), 2 * self.dead_band):
            if self.since is None:
                self.since = (t_now, pan, min(math.radians(STALL_MOVE_DEG), ask / 2))
                self.still, self.away, self.paused = [pan], False, 0.0
        elif near and self.since is not None and self.near is None:
            self.near = t_now  # a goal where it is pauses the clock (a target passing the stuck motor's pan)

    def stalled(self, t: float, pan: float) -> float | None:
        """The seconds the motor has not moved since a command far away, where that is STALL_S or more (None: it
        moves, or no such command)."""
        if self.since is None:
            return None
        t0, p0, moved = self.since
        still = self.still
        steps = [b - a for a, b in zip(still, still[1:])]  # of a motor that did not move: up and down, noise (one way:
        noisy = any(d > 0 for d in steps) and any(d < 0 for d in steps)  # a move that ends, at 66 ms of latency)
        away, self.away = self.away, abs(pan - (sorted(still)[len(still) // 2] if noisy else p0)) >= moved
        if self.away and (away or not noisy):  # (a noisy encoder's one reading that far is no move; two in a row are)
            self.since = self.near = None
            return None
        if not self.away:
            still.append(pan)
            del still[:-32]
        asked = t - t0 - self.paused
        return asked if asked >= STALL_S and self.near is None else None

    def reset(self) -> None:
        self.since = self.near = None
