"""The slave's pan while its motor rests: the mean of the encoder's readings since it came to rest, not one reading.

A frame's pan at exposure is one encoder reading (or the line between two). A noisy encoder (0.05 deg of noise is
0.44 px at f 500) puts that noise into every target pan the controller measures (the pan plus the image's offset);
converged on a still target, the loop then chased it: a command every few frames (76 in 3 s), each moving a camera
that was on the target (and, with backlash, leaving it elsewhere in the play). While the motor rests, its shaft
does not move, so every reading since it came to rest is a reading of the same pan: their mean is that pan, its
noise shrunk by the square root of their number. Rest: no command for SETTLE_S (the motor's latency and its
final approach, a few of its time constants), up to the next command, and readings that say so (their two halves'
means within REST_DEG: a shaft still moving, pushed or drifting is left as read). A clean encoder's readings at
rest are all one tick, so their mean is that reading: the loop is unchanged there, to the digit. The mean is
used only within NEAR_DEG of the frame's own pan, so a reading that is no claim of the shaft (the caller's checks
let only plausible reports in) moves no pan by more than that. Both bounds widen with the encoder's own scatter
(SIGMAS of it, from successive readings, which a drift barely moves; NEAR_MAX_DEG at most): an encoder noisier than
0.05 deg failed them often, and each frame that fell back to its one reading sent a command that the next frames'
single readings chased. Measured: docs/FAULTS.md, "The encoder's noise at rest"."""

from __future__ import annotations

import bisect
import itertools
import math
from collections import deque

__all__ = ["Rest", "SETTLE_S", "REST_DEG", "NEAR_DEG", "NEAR_MAX_DEG", "SIGMAS"]

SETTLE_S = 0.06  # a command's motor at rest this long after it (2 ms latency, 10 ms time constant, a move's travel)
REST_DEG = 0.1  # the first and second halves of the readings since then agree within this: the shaft did not move
NEAR_DEG = 0.25  # the mean moves a frame's pan by at most this (5 x the encoder noise the simulator's bench uses),
NEAR_MAX_DEG = 1.0  # or SIGMAS x the readings' scatter, up to this
SIGMAS = 4.0  # the halves' means apart by more than this many standard errors (or REST_DEG): the shaft moved
KEEP_S = 2.0  # readings and commands kept this long
MIN_READINGS = 3


class Rest:
    """The motor's readings (motor()) and the instants of the commands sent (commanded()); at() gives a frame's
    pan as the readings of the rest it falls in say it. Times on the frames' clock, pans in radians."""

    def __init__(self):
        self.t: deque[float] = deque()
        self.pan: deque[float] = deque()
        self.commands: deque[float] = deque()

    def motor(self, t: float, pan: float) -> None:
        """One encoder reading (in time order; an older one, or a non-finite one, is not kept)."""
        if not (math.isfinite(t) and math.isfinite(pan)) or (self.t and t <= self.t[-1]):
            return
        self.t.append(t)
        self.pan.append(pan)
        while self.t[-1] - self.t[0] > KEEP_S:
            self.t.popleft()
            self.pan.popleft()

    def commanded(self, t: float) -> None:
        """A command sent at t (the motor may move from then)."""
        if not math.isfinite(t):
            return
        if self.commands and t < self.commands[-1]:
            self.commands.clear()  # a clock that went back: what was kept says nothing of the new times
        self.commands.append(t)
        while self.commands[-1] - self.commands[0] > KEEP_S:
            self.commands.popleft()

    def at(self, t: float, pan: float) -> float:
        """The slave's pan at t: `pan` (the frame's), or where the motor rests at t, the mean of its readings
        since it came to rest (to the next command)."""
        if not (math.isfinite(t) and math.isfinite(pan)) or not self.t:
            return pan
        cs = self.commands
        i = bisect.bisect_right(cs, t)  # cs[i-1] <= t < cs[i]
        t0 = cs[i - 1] + SETTLE_S if i else self.t[0]
        t1 = cs[i] if i < len(cs) else math.inf
        if t < t0:
            return pan
        ts = self.t
        a, b = bisect.bisect_left(ts, t0), bisect.bisect_left(ts, t1)
        n = b - a
        if n < MIN_READINGS:
            return pan
        p0 = self.pan[a]
        ds = [p - p0 for p in itertools.islice(self.pan, a, b)]  # (about the first: equal readings' mean is exact)
        half = n // 2
        m = sum(ds) / n
        # the encoder's scatter, from successive readings (a drift barely moves them; 0: a clean one's tick)
        sd = math.sqrt(sum((ds[k + 1] - ds[k]) ** 2 for k in range(n - 1)) / (2 * (n - 1)))
        drift = abs(sum(ds[:half]) / half - sum(ds[half:]) / (n - half))
        if drift > max(math.radians(REST_DEG), SIGMAS * sd * math.sqrt(1 / half + 1 / (n - half))):
            return pan
        near = min(max(math.radians(NEAR_DEG), SIGMAS * sd), math.radians(NEAR_MAX_DEG))
        return p0 + m if abs(p0 + m - pan) <= near else pan
