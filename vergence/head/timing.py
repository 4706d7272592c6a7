"""The camera's time model: when each image was exposed, and the slave's pan at that instant.

A frame's time is when its light reached the sensor, not when a process read it. A real camera hands over an
image tens of milliseconds after its exposure (driver and device buffers), and two cameras are not exposed at
the same instant; meanwhile the slave motor moves. So every frame carries two exposure times (master and
slave, each the middle of its exposure) beside the time it was read, and the slave's pan at the slave's
exposure, interpolated in the motor's own position history:

- CameraTiming: a camera's timing as the simulator models it and as the settings state it when a source does
  not stamp its images (latency: exposure to read; skew: the slave's exposure after the master's; exposure:
  the integration time, for motion blur; jitter: exposure times off their schedule).
- Stamper: the exposure times of one pair: the source's own stamps where it has them and they are
  believable, else the read time minus the configured latency. A stamp in the future, older than a second, or
  going backwards is counted (per reason) and replaced by the configured one: it never reaches the motor.
- PanHistory: the motor's recent positions with the motor's own times; at(t) is the pan at t, or None where
  the history cannot tell (older than it, across a gap in it, or too far past its newest sample).
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass
from typing import ClassVar

from ..ranges import Range, check

__all__ = ["CameraTiming", "Stamper", "PanHistory", "MAX_AGE_S", "MAX_AHEAD_S"]

MAX_AGE_S = 1.0  # a source's exposure stamp older than this, when read, is not believed
MAX_AHEAD_S = 0.002  # nor one ahead of the read by more than this (clock granularity)
RATE_SPAN_S = 0.015  # past its newest sample, the history extrapolates at the rate over at least this long


@dataclass(frozen=True)
class CameraTiming:
    """latency_s: from the exposure of the later of the two images to the read of the pair (the image is that
    old when the capture gets it); skew_s: the slave's exposure minus the master's (negative: the slave
    first); exposure_s: each image integrates the scene over this long (motion blur; its stamp is the
    middle); jitter_s: the standard deviation of the exposure times off their schedule (the simulator's)."""

    latency_s: float = 0.0
    skew_s: float = 0.0
    exposure_s: float = 0.0
    jitter_s: float = 0.0

    RANGES: ClassVar[dict[str, Range]] = {
        "latency_s": Range(0, MAX_AGE_S, note="seconds"),
        "skew_s": Range(-0.5, 0.5, note="seconds; negative: the slave first"),
        "exposure_s": Range(0, MAX_AGE_S, note="seconds"),
        "jitter_s": Range(0, MAX_AGE_S, note="seconds"),
    }

    def __post_init__(self):
        check(self, self.RANGES)

    @property
    def age_s(self) -> float:
        """How old the later image is when read: latency_s, but at least half the exposure (an image is read
        after its exposure ends, and its time is the exposure's middle)."""
        return max(self.latency_s, self.exposure_s / 2)

    def exposures(self, t_read: float) -> tuple[float, float]:
        """(master, slave) exposure times of a pair read at t_read (seconds, any epoch): the later one is
        age_s old."""
        later = t_read - self.age_s
        return (later - self.skew_s, later) if self.skew_s > 0 else (later, later + self.skew_s)

    def read_time(self, t_master: float) -> float:
        """When a pair whose master was exposed at t_master is read."""
        return t_master + max(0.0, self.skew_s) + self.age_s


class Stamper:
    """The exposure times (ns, time.time_ns's epoch) of each pair the capture reads.

    stamp(t_read_ns, claimed) -> (t_master_ns, t_slave_ns, reason): `claimed` is the source's own pair of
    stamps or None; a claim that is not believable is replaced by the configured timing, and its reason
    ("future", "old", "backwards") is counted in `rejected` and returned (None: believed or none claimed)."""

    def __init__(self, timing: CameraTiming | None = None):
        self.timing = timing or CameraTiming()
        self.rejected = {"future": 0, "old": 0, "backwards": 0}
        self.last_ns = 0  # the newest master stamp handed out

    def judge(self, t_read_ns: int, claimed: tuple[int, int]) -> str | None:
        """Why a claimed pair of stamps is not believed, or None."""
        newest, oldest = max(claimed), min(claimed)
        if newest > t_read_ns + MAX_AHEAD_S * 1e9:
            return "future"
        if oldest < t_read_ns - MAX_AGE_S * 1e9:
            return "old"
        if claimed[0] <= self.last_ns:
            return "backwards"
        return None

    def stamp(self, t_read_ns: int, claimed: tuple[int, int] | None = None) -> tuple[int, int, str | None]:
        why = None
        if claimed is not None:
            claimed = (int(claimed[0]), int(claimed[1]))
            why = self.judge(t_read_ns, claimed)
            if why is None:
                self.last_ns = claimed[0]
                return claimed[0], claimed[1], None
            self.rejected[why] += 1
        tm, ts = self.timing.exposures(t_read_ns / 1e9)
        tm_ns = t_read_ns + round((tm - t_read_ns / 1e9) * 1e9)
        ts_ns = t_read_ns + round((ts - t_read_ns / 1e9) * 1e9)
        tm_ns = max(tm_ns, self.last_ns + 1)  # never backwards, even after a believed stamp ahead of it
        self.last_ns = tm_ns
        return tm_ns, ts_ns, why


class PanHistory:
    """The slave motor's recent positions (t seconds in the motor's own clock, pan radians), oldest first.

    add(t, pan) appends a sample newer than the newest (an older or equal one is counted in `refused` and
    dropped: a history goes forward). at(t): the pan at t, interpolated linearly between the two samples
    around it; past the newest sample, extrapolated at the rate of the last two for at most max_gap_s; None
    where it cannot tell: before the oldest sample (`older` counted), between two samples more than max_gap_s
    apart or more than max_gap_s past the newest (`gaps` counted). keep_s: how much history is kept."""

    def __init__(self, max_gap_s: float = 0.1, keep_s: float = 2.0):
        if not (max_gap_s > 0 and keep_s > max_gap_s):
            raise ValueError(f"max_gap_s={max_gap_s}, keep_s={keep_s}: want 0 < max_gap_s < keep_s")
        self.max_gap_s, self.keep_s = max_gap_s, keep_s
        self.t: deque[float] = deque()
        self.pan: deque[float] = deque()
        self.refused = self.older = self.gaps = 0

    def __len__(self) -> int:
        return len(self.t)

    def add(self, t: float, pan: float) -> bool:
        if not (math.isfinite(t) and math.isfinite(pan)) or (self.t and t <= self.t[-1]):
            self.refused += 1
            return False
        self.t.append(t)
        self.pan.append(pan)
        while self.t[-1] - self.t[0] > self.keep_s:
            self.t.popleft()
            self.pan.popleft()
        return True

    def clear(self) -> None:
        self.t.clear()
        self.pan.clear()

    def newest(self) -> float | None:
        return self.pan[-1] if self.pan else None

    def at(self, t: float) -> float | None:
        ts, ps = self.t, self.pan
        if not ts or not math.isfinite(t):
            return None
        if t < ts[0]:
            self.older += 1
            return None
        if t >= ts[-1]:
            if t - ts[-1] > self.max_gap_s:
                self.gaps += 1
                return None
            # the rate over at least RATE_SPAN_S (two readings a millisecond apart, a tick apart, are no rate)
            j = bisect.bisect_right(ts, ts[-1] - RATE_SPAN_S) - 1
            if j < 0 or ts[-1] - ts[j] > self.max_gap_s + RATE_SPAN_S:
                return ps[-1]
            rate = (ps[-1] - ps[j]) / (ts[-1] - ts[j])
            return ps[-1] + rate * (t - ts[-1])
        i = bisect.bisect_right(ts, t)  # ts[i-1] <= t < ts[i]
        t0, t1 = ts[i - 1], ts[i]
        if t1 - t0 > self.max_gap_s:
            self.gaps += 1
            return None
        return ps[i - 1] + (ps[i] - ps[i - 1]) * (t - t0) / (t1 - t0)
