"""Capture side of one frame: two images -> a messages.Frame carrying only what layer 1 needs, the shard plan
(membership -> who computes which k-range: plan_shards, Roster), the dynamic window driven by the decisions
coming back (WindowControl), and a Frame's bounds every receiver applies (frame_cost, frame_too_large)."""

from __future__ import annotations

import threading
import time

import numpy as np

from ..head.frozen import digest
from ..network import retina
from ..config import LimitSettings
from ..wire.messages import Frame, MessageError
from ..network.params import Params
from ..wire.status import WorkersReport

__all__ = ["plan_shards", "make_frame", "Roster", "WindowControl", "frame_cost", "frame_too_large"]


def plan_shards(workers, k_count: int) -> list[list]:
    """Split offsets 0..k_count-1 into contiguous ranges, one per worker (sorted by id, so every process
    computes the same plan), sizes differing by at most one: [[id, k0, k1], ...]. More workers than offsets:
    the extra ones get nothing. No worker: []."""
    ids = sorted(set(workers))[: max(k_count, 0)]
    n = len(ids)
    plan = []
    for i, wid in enumerate(ids):
        k0 = i * k_count // n
        k1 = (i + 1) * k_count // n
        plan.append([wid, k0, k1])
    return plan


def make_frame(master: np.ndarray, slave: np.ndarray, *, rig: str, frame: int, pan_rad: float, focal_px: float,
               params: Params, plan: list[list], at: tuple[int, int] | None = None, window: int | None = None,
               t_capture_ns: int | None = None, clip: bool = True, clipped: list | None = None) -> Frame:
    """A Frame for the fovea at `at` (default: the image centre) of the master, window w (default
    params.window): the fovea and band gray strips with their Sobel margins, and the master band too when
    params.lr_check needs it. The slave band is mapped onto the master's intensities here (params.photometric),
    and the master clipped like the slave where its gain clipped (params.clip_master, unless clip is False:
    the dynamic window's clip_fallback states, WindowControl), so the workers and the reducer see the same
    strips as vergence.match() with that clip_master; `clipped` (a list) gets whether it was clipped
    (retina.master_clipped's answer, found on the way). Raises retina.BorderError when the window does not fit."""
    if t_capture_ns is None:
        t_capture_ns = time.time_ns()
    h, wd = master.shape[:2]
    if slave.shape[:2] != (h, wd):
        raise ValueError(f"master and slave differ in size: {wd} x {h} and {slave.shape[1]} x {slave.shape[0]}")
    x, y = at if at is not None else (wd // 2, h // 2)
    w = params.window if window is None else window
    retina.check_point(master.shape, x, y, w, params.vsearch)
    fovea, band, mband, lims = retina.mapped_strips(master, slave, x, y, w, params.vsearch, params.photometric,
                                                 params.lr_check, params.clip_master and clip)
    if clipped is not None:
        clipped.append(lims is not None)
    reach = params.band_reach()  # the digests': the base window's band (within a grown one's)
    return Frame(rig=rig, frame=frame, t_capture_ns=t_capture_ns, pan_rad=float(pan_rad), width=wd, height=h,
                 x=x, y=y, window=w, vsearch=params.vsearch, focal_px=float(focal_px), fovea=fovea.tobytes(),
                 band=band.tobytes(), plan=plan, circular=params.circular, support=params.support,
                 master_band=b"" if mband is None else mband.tobytes(), support_gamma=params.support_gamma,
                 support_radius=params.support_radius_at(w), master_digest=digest(master, y, reach),
                 slave_digest=digest(slave, y, reach))


def frame_cost(frame: Frame) -> int:
    """Layer 4's work on a frame: rows x offsets x window^2 (what LimitSettings.max_frame_ops bounds)."""
    return (2 * frame.vsearch + 1) * frame.k_count * frame.window * frame.window


def frame_too_large(frame: Frame | None, size: int, limits: LimitSettings) -> str | None:
    """Why a frame (or its message of `size` bytes, before decoding when frame is None) is beyond the
    settings' bounds, or None."""
    if size > limits.max_frame_bytes:
        return f"frame of {size} bytes, more than max_frame_bytes {limits.max_frame_bytes}"
    if frame is not None and frame_cost(frame) > limits.max_frame_ops:
        return (f"frame {frame.width} px wide, w {frame.window}, +-{frame.vsearch} rows: {frame_cost(frame)} "
                f"operations, more than max_frame_ops {limits.max_frame_ops}")
    return None



def check_frame(data: bytes, limits: LimitSettings, now_ns: int | None = None) -> Frame:
    """The frame in a message, if it is within the settings' bounds (frame_too_large, before decoding and
    after) and, given now_ns, captured within [limits] max_skew_s of that clock; MessageError says why not.
    The worker checks all three, the reducer the bounds (the worker and the reducer share this check)."""
    why = frame_too_large(None, len(data), limits)
    if why is None:
        frame = Frame.from_bytes(data)
        why = frame_too_large(frame, len(data), limits)
        if why is None and now_ns is not None and abs(frame.t_capture_ns - now_ns) > limits.max_skew_s * 1e9:
            why = f"frame {frame.frame} captured {(frame.t_capture_ns - now_ns) / 1e9:+.3g} s from our clock"
    if why is not None:
        raise MessageError(why)
    return frame

class Roster:
    """The workers the capture plans with: the live liveliness tokens (an invitation, not a guarantee),
    minus those the reducer's evidence (Gatherer.report) shows missing.

    A worker in the plan for at least miss_s that a report shows with at least miss_frames expired frames in a
    row without its correlation, and no correlation for miss_s (or none ever), leaves the plan for probation_s,
    doubling on each exclusion in a row (up to 32 x); it is then tried again. One that answers is back to a clean
    record. Without reports (no reducer), the plan is the tokens, as before. The defaults are the settings'
    ([limits]). counters: excluded, readmitted, reports."""

    def __init__(self, miss_s: float = LimitSettings.miss_s, probation_s: float = LimitSettings.probation_s,
                 miss_frames: int = LimitSettings.miss_frames, clock=time.monotonic):
        self.miss_s, self.probation_s, self.miss_frames = miss_s, probation_s, miss_frames
        self.clock = clock
        self.lock = threading.Lock()
        self.tokens: set[str] = set()
        self.joined: dict[str, float] = {}  # when each planned worker entered the plan
        self.out: dict[str, float] = {}  # excluded until (monotonic)
        self.strikes: dict[str, int] = {}
        self.changes = 0
        self.counters = dict(excluded=0, readmitted=0, reports=0)

    def token(self, wid: str, alive: bool) -> None:
        now = self.clock()
        with self.lock:
            if alive and wid not in self.tokens:
                self.tokens.add(wid)
                self.joined[wid] = now
            elif not alive and wid in self.tokens:
                self.tokens.discard(wid)
                self.joined.pop(wid, None)
                self.out.pop(wid, None)
                self.strikes.pop(wid, None)
            else:
                return
            self.changes += 1

    def on_report(self, report: WorkersReport) -> list[str]:
        """Apply one reducer report (vergence.wire.status.decode_report's); returns the workers it excluded."""
        now = self.clock()
        gone = []
        with self.lock:
            self.counters["reports"] += 1
            for wid in list(self.joined):
                w = report.workers.get(wid)
                if w is None:
                    continue
                if w.age_s is not None and w.age_s < self.miss_s:
                    self.strikes[wid] = 0
                    continue
                if now - self.joined[wid] >= self.miss_s and w.misses >= self.miss_frames:
                    k = self.strikes.get(wid, 0)
                    self.out[wid] = now + self.probation_s * 2 ** min(k, 5)
                    self.strikes[wid] = k + 1
                    del self.joined[wid]
                    self.counters["excluded"] += 1
                    self.changes += 1
                    gone.append(wid)
        return gone

    def snapshot(self) -> tuple[int, list[str]]:
        """(a change counter, the sorted ids to plan with): excluded workers whose probation ended come back."""
        now = self.clock()
        with self.lock:
            for wid in [w for w, t in self.out.items() if now >= t]:
                del self.out[wid]
                if wid in self.tokens:
                    self.joined[wid] = now
                    self.counters["readmitted"] += 1
                    self.changes += 1
            return self.changes, sorted(self.joined)

    def excluded(self) -> list[str]:
        with self.lock:
            return sorted(self.out)


class WindowControl:
    """The dynamic window of the service, driven by the decisions coming back to the capture.

    It moves along states (window, clip): params.windows() (the one dynamic-window rule, shared with
    vergence.match()) with the master clipped as params.clip_master says (clip True), then, with
    params.clip_fallback, the same windows with the master as it is (clip False), which the capture reaches
    only when the master was clipped (clipped(): make_frame's frames at a clipped state since the last
    confident decision), as match() tries them. Only a decision made in the current state counts (frames in
    flight with an older one are ignored). Not confident: one step on, to at most the last state. Confident
    `patience` times in a row: one step back toward the base, so a scene that needs the larger window does not
    flip every frame. params.max_window = 0 and no clip_fallback keeps params.window."""

    def __init__(self, params: Params, patience: int = 30):
        self.sizes = params.windows()
        fallback = params.clip_fallback and params.clip_master and params.photometric != "none"
        self.states = [(w, True) for w in self.sizes] + ([(w, False) for w in self.sizes] if fallback else [])
        self.step = 0  # index into states
        self.patience = patience
        self.streak = 0
        self.was_clipped = False  # the master clipped in a frame of this sweep (since the last confident one)
        self.lock = threading.Lock()

    @property
    def window(self) -> int:
        return self.states[self.step][0]

    @property
    def clip(self) -> bool:
        return self.states[self.step][1]

    @property
    def state(self) -> tuple[int, bool]:
        with self.lock:
            return self.states[self.step]

    def clipped(self, clipped: bool = True) -> None:
        """A frame of the current state went out with the master clipped (master_clipped)."""
        if clipped:
            with self.lock:
                self.was_clipped = True

    def reset(self) -> None:
        """Back to the base window (a grown one that no longer fits the image at the fixation point). From the
        clipped windows, where the master was clipped and there are fallback states: to the first of those,
        as match() tries the unclipped windows after the clipped ones that fit."""
        with self.lock:
            last = len(self.sizes)
            if self.step < last and last < len(self.states) and self.was_clipped:
                self.step = last
            else:
                self.step = 0
                self.was_clipped = False
            self.streak = 0

    def update(self, window: int, confident: bool, clip: bool = True) -> int:
        with self.lock:
            if (window, clip) != self.states[self.step]:
                return self.window
            if not confident:
                self.streak = 0
                last = len(self.sizes) - 1
                if self.step != last or self.was_clipped:  # the unclipped windows only where the master clipped
                    self.step = min(self.step + 1, len(self.states) - 1)
            else:
                self.was_clipped = False
                self.streak += 1
                if self.streak >= self.patience and self.step > 0:
                    self.step -= 1
                    self.streak = 0
            return self.window
