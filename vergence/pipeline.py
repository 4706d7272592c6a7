"""The distributed pipeline's per-step logic, free of any network code.

capture: make_frame (two images -> a messages.Frame carrying only what layer 1 needs, and the shard plan);
workers: plan_shards (membership -> who computes which k-range), compute_partial (a Frame -> one worker's
messages.Partial); reducer: Gatherer (Partials -> a complete profile, or a dropped frame at its deadline)
and reduce (a complete profile -> messages.Profile and messages.Command through vergence.match.decide_scores
and vergence.control.Controller, the very steps of vergence.match()). The services in services/ only
subscribe, call these, and publish.
"""

from __future__ import annotations

import math
import os
import threading
import time
from dataclasses import dataclass, field, replace

import msgspec
import numpy as np

from . import kernel, retina
from .control import ControlSettings, Controller
from .config import LimitSettings
from .decide import Decision
from .match import Params, apply_checks, decide_scores
from .messages import Command, Frame, Partial, Profile, Verdict

__all__ = ["plan_shards", "make_frame", "frame_params", "compute_partial", "reduce", "make_profile", "make_verdict",
           "Gatherer", "Roster", "Result", "WindowControl", "Health", "frame_cost"]


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
               t_capture_ns: int | None = None) -> Frame:
    """A Frame for the fovea at `at` (default: the image centre) of the master, window w (default
    params.window): the fovea and band gray strips with their Sobel margins, and the master band too when
    params.lr_check needs it. The slave band is mapped onto the master's intensities here (params.photometric),
    so the workers and the reducer see the same band as vergence.match(). Raises retina.BorderError when the
    window does not fit."""
    if t_capture_ns is None:
        t_capture_ns = time.time_ns()
    h, wd = master.shape[:2]
    if slave.shape[:2] != (h, wd):
        raise ValueError(f"master and slave differ in size: {wd} x {h} and {slave.shape[1]} x {slave.shape[0]}")
    x, y = at if at is not None else (wd // 2, h // 2)
    w = params.window if window is None else window
    retina.check_point(master.shape, x, y, w, params.vsearch)
    fovea = retina.fovea_strip(master, x, y, w)
    band = retina.slave_band_strip(master, slave, y, w, params.vsearch, params.photometric)
    mband = retina.band_strip(master, y, w) if params.lr_check else None
    return Frame(rig=rig, frame=frame, t_capture_ns=t_capture_ns, pan_rad=float(pan_rad), width=wd, height=h,
                 x=x, y=y, window=w, vsearch=params.vsearch, focal_px=float(focal_px), fovea=fovea.tobytes(),
                 band=band.tobytes(), plan=plan, circular=params.circular, support=params.support,
                 master_band=b"" if mband is None else mband.tobytes(), support_gamma=params.support_gamma,
                 support_radius=params.support_radius)


def frame_params(frame: Frame, params: Params) -> Params:
    """The network settings a frame was computed with: the frame's own window, vertical search, direction
    comparison and support weights over the reducer's decision settings."""
    return replace(params, window=frame.window, vsearch=frame.vsearch, circular=frame.circular,
                   support=frame.support, support_gamma=frame.support_gamma, support_radius=frame.support_radius)


def compute_partial(frame: Frame, worker: str, t_done: bool = True) -> Partial | None:
    """Layer 4 on this worker's k-range of the frame (None when the plan gives it nothing).

    Only the band columns the range reads are turned into features (planes are local, so the result is
    bit-identical to the unsharded computation)."""
    rng = frame.shard(worker)
    if rng is None:
        return None
    k0, k1 = rng
    w = frame.window
    fovea = retina.planes(frame.fovea_strip())
    # planes column j is strip column j + 1: offsets k0..k1-1 read plane columns k0 .. k1 + w - 2
    sub = frame.band_strip()[:, k0 : k1 + w + 1]
    band = retina.planes(sub)
    weights = kernel.support_weights(fovea, frame.support_gamma, frame.support_radius) if frame.support else None
    scores = np.atleast_2d(kernel.correlate(fovea, band, circular=frame.circular, weights=weights))
    return Partial(rig=frame.rig, frame=frame.frame, t_capture_ns=frame.t_capture_ns, worker=worker, k0=k0, k1=k1,
                   rows=scores.shape[0], scores=scores.astype("<f8", copy=False).tobytes(),
                   t_done_ns=time.time_ns() if t_done else 0)


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


def decide_frame(frame: Frame, scores: np.ndarray, params: Params) -> Decision:
    """vergence.match.decide_scores on a frame's complete scores: the decision of vergence.match() itself.

    The slave band's features (for the left-right check, with the master band's gray strip, and the halves
    check) are computed only when the checks can change the result, i.e. when the decision without them is
    confident; apply_checks then runs the checks on that decision."""
    p = frame_params(frame, params)
    fovea = retina.planes(frame.fovea_strip())
    y = scores[0] if scores.shape[0] == 1 else scores
    d = decide_scores(y, fovea, frame.x, p)
    mstrip = frame.master_band_strip()
    if ((p.lr_check and mstrip is not None) or p.halves_check or p.min_correlation > 0) and d.confident:
        # The checks read the slave band's features at the winning window's columns k..k+w-1 (correlation and
        # left-right checks) and k-R..k+R+w-1 (halves check, R = halves_range) only: compute those (all rows),
        # not the whole band. tests/test_pipeline.py holds this equal to match().
        w = frame.window
        band = frame.band_strip()
        sband = np.zeros((3, band.shape[0] - 2, band.shape[1] - 2), np.uint8)
        reach = p.halves_range if p.halves_check else 0
        c0, c1 = max(0, d.k - reach), min(sband.shape[2], d.k + reach + w)
        sband[:, :, c0:c1] = retina.planes(band[:, c0 : c1 + 2])
        d = apply_checks(d, fovea, frame.x, p, mstrip, sband)
    return d


def make_verdict(frame: Frame, d: Decision, t_reduced_ns: int) -> Verdict:
    """The Verdict message of a reduced frame: its decision, without the scores."""
    return Verdict(rig=frame.rig, frame=frame.frame, t_capture_ns=frame.t_capture_ns, t_reduced_ns=t_reduced_ns,
                   window=frame.window, k=d.k, k_sub=d.k_sub, v_shift=d.v, k_centre=d.k_centre,
                   direction=d.direction, magnitude=d.magnitude, offset_px=d.offset_px, confidence=d.confidence,
                   confident=d.confident, texture=d.texture if math.isfinite(d.texture) else 0.0,
                   pan_rad=frame.pan_rad)


def make_profile(frame: Frame, scores: np.ndarray, d: Decision, t_reduced_ns: int) -> Profile:
    """The Profile message of a reduced frame: its Verdict with the whole layer-4 vector."""
    return Profile(**msgspec.structs.asdict(make_verdict(frame, d, t_reduced_ns)), width=frame.width,
                   rows=scores.shape[0], scores=np.ascontiguousarray(scores, "<f8").tobytes(),
                   workers=[str(e[0]) for e in frame.plan])


def _command(frame: Frame, d: Decision, controller: Controller) -> Command | None:
    target = controller.target(frame.pan_rad, d.offset_px, frame.focal_px, d.confident,
                               centre_px=frame.x - frame.width // 2, t_s=frame.t_capture_ns / 1e9)
    if target is None:
        return None
    return Command(rig=frame.rig, frame=frame.frame, t_capture_ns=frame.t_capture_ns, pan_rad=target,
                   correction_rad=target - frame.pan_rad, direction=d.direction, magnitude_px=abs(d.offset_px),
                   confidence=d.confidence, t_sent_ns=time.time_ns())


def reduce(frame: Frame, scores: np.ndarray, params: Params, controller: Controller,
           t_reduced_ns: int | None = None) -> tuple[Profile, Command | None]:
    """A complete profile -> (Profile, Command or None when the controller says not to move)."""
    r = Result.of(frame, scores, params, controller, t_reduced_ns)
    return r.profile, r.command


@dataclass
class Result:
    """A complete frame, reduced: its decision (and its Verdict message), its command (None: do not move)
    and, built when first asked for (a 65 KB message at 640 px with vertical search: only when someone
    subscribes to it), its profile."""

    frame: Frame
    decision: Decision
    command: Command | None
    scores: np.ndarray = field(repr=False)
    t_reduced_ns: int = 0
    _profile: Profile | None = field(default=None, repr=False)

    @classmethod
    def of(cls, frame: Frame, scores: np.ndarray, params: Params, controller: Controller,
           t_reduced_ns: int | None = None) -> "Result":
        d = decide_frame(frame, scores, params)
        now = time.time_ns() if t_reduced_ns is None else t_reduced_ns
        return cls(frame, d, _command(frame, d, controller), scores, now)

    @property
    def verdict(self) -> Verdict:
        return make_verdict(self.frame, self.decision, self.t_reduced_ns)

    @property
    def profile(self) -> Profile:
        if self._profile is None:
            self._profile = make_profile(self.frame, self.scores, self.decision, self.t_reduced_ns)
        return self._profile


@dataclass
class _Pending:
    t_first: float
    t_capture_ns: int = 0
    frame: Frame | None = None
    partials: dict[str, Partial] = field(default_factory=dict)


class Gatherer:
    """Assembles workers' Partials into complete profiles, by the plan each Frame carries.

    A frame is complete when its Frame and one Partial per plan entry (same worker, same k-range) are in;
    it is then reduced at once. A frame not complete `deadline_s` after its first message is dropped and
    counted; so is every older frame still pending once a newer one completes (a command is never older
    than one already sent). Nothing is ever published from an incomplete profile.

    A message is a claim: it moves no state unless it is plausible (LimitSettings). Its capture time must be
    within max_skew_s of this host's clock (wall_ns); its frame id at most frame_window ahead of the newest
    completed frame. Only a completed frame moves the "done up to" mark (a frame, a time) that makes older
    messages late; a frame that expires is remembered as done only when its Frame was in, and partials whose
    Frame never came (`orphaned`) are forgotten. When nothing completes for reanchor_s, the mark is
    forgotten (`reanchors`) and any plausible frame is taken again: the gatherer recovers by itself.

    counters: frames (Frames accepted), partials, complete, dropped (a Frame whose shards missed the deadline),
    superseded, orphaned (partials whose Frame never came: counted apart from dropped, a forged partial
    cannot inflate `dropped`), no_plan, unexpected (a Partial for no shard of its frame's plan, or a
    duplicate), late (for a frame already done or dropped), bad (a Partial that does not fit its frame),
    restarts (a Frame whose id went back with a newer capture time: a new capture process), reanchors,
    implausible_time, implausible_frame (rejected claims, nothing changed).

    answered: per worker, (monotonic time, frame id) of its latest partial that fitted a Frame's plan, and
    misses: frames naming it that expired without its partial, in a row (the evidence for membership,
    report())."""

    MAX_PENDING = 256
    MAX_PARTIALS = 64  # partials kept for one frame whose Frame is not in yet
    MAX_FINISHED = 1024

    def __init__(self, params: Params, control: ControlSettings | None = None, deadline_s: float = 0.05,
                 limits: LimitSettings | None = None, wall_ns=time.time_ns):
        self.params = params
        self.controller = Controller(control)
        self.deadline_s = deadline_s
        self.limits = limits or LimitSettings()
        self.wall_ns = wall_ns
        self.pending: dict[int, _Pending] = {}
        self.done_upto = -1  # every frame id <= this is finished: moved by completed frames only
        self.done_t_ns = 0  # the newest capture time among the completed frames (never ahead of our clock)
        self.expired: set[int] = set()  # ids > done_upto whose Frame expired (their stragglers are late)
        self.t_progress: float | None = None  # monotonic time of the latest completion
        self.newest = -1  # the newest frame id whose Frame was accepted
        self.answered: dict[str, tuple[float, int]] = {}
        self.misses: dict[str, int] = {}
        self.counters = dict(frames=0, partials=0, complete=0, dropped=0, superseded=0, orphaned=0, no_plan=0,
                             unexpected=0, late=0, bad=0, restarts=0, reanchors=0, implausible_time=0,
                             implausible_frame=0)

    # -- plausibility --------------------------------------------------------------------------------------
    def implausible(self, frame_id: int, t_capture_ns: int, now: float) -> str | None:
        """Why a message of this frame and capture time is not believed (a counter's name), or None."""
        if abs(t_capture_ns - self.wall_ns()) > self.limits.max_skew_s * 1e9:
            return "implausible_time"
        if self.done_upto >= 0 and frame_id > self.done_upto + self.limits.frame_window:
            return "implausible_frame"
        return None

    def _recover(self, now: float) -> None:
        """Nothing completed for reanchor_s: forget the done mark (a stuck state recovers by itself)."""
        if self.done_upto >= 0 and (self.t_progress is None or now - self.t_progress > self.limits.reanchor_s):
            self.done_upto, self.done_t_ns, self.newest = -1, 0, -1
            self.expired.clear()
            self.counters["reanchors"] += 1

    def _entry(self, frame_id: int, t_capture_ns: int, now: float, is_frame: bool) -> _Pending | None:
        self._recover(now)
        why = self.implausible(frame_id, t_capture_ns, now)
        if why is not None:
            self.counters[why] += 1
            return None
        if frame_id <= self.done_upto or frame_id in self.expired:
            if not (is_frame and frame_id <= self.done_upto and t_capture_ns > self.done_t_ns):
                self.counters["late"] += 1
                return None
            # a Frame with an id already finished, captured later than every completed frame: a new capture
            # process started its ids again
            self.pending.clear()
            self.expired.clear()
            self.done_upto, self.done_t_ns, self.newest = frame_id - 1, 0, -1
            self.counters["restarts"] += 1
        e = self.pending.get(frame_id)
        if e is None:
            if len(self.pending) >= self.MAX_PENDING:
                oldest = min(self.pending)
                self._expired(oldest, self.pending.pop(oldest))
            e = self.pending[frame_id] = _Pending(now, t_capture_ns)
        return e

    # -- inputs --------------------------------------------------------------------------------------------
    def add_frame(self, frame: Frame, now: float | None = None) -> list[Result]:
        now = time.monotonic() if now is None else now
        if not frame.plan:
            self.counters["no_plan"] += 1
            return self.expire(now)
        e = self._entry(frame.frame, frame.t_capture_ns, now, True)
        if e is None:
            return self.expire(now)
        if e.frame is not None:
            self.counters["unexpected"] += 1
            return self.expire(now)
        self.counters["frames"] += 1
        e.frame = frame
        self.newest = max(self.newest, frame.frame)
        # partials that came first: those that do not fit this plan go, the others are evidence
        for wid, p in list(e.partials.items()):
            if frame.shard(wid) != (p.k0, p.k1):
                del e.partials[wid]
                self.counters["unexpected"] += 1
            else:
                self._answer(wid, frame.frame, now)
        return self._try(frame.frame, e, now)

    def add_partial(self, partial: Partial, now: float | None = None) -> list[Result]:
        now = time.monotonic() if now is None else now
        e = self._entry(partial.frame, partial.t_capture_ns, now, False)
        if e is None:
            return self.expire(now)
        self.counters["partials"] += 1
        if partial.worker in e.partials or (e.frame is not None and
                                            e.frame.shard(partial.worker) != (partial.k0, partial.k1)) or (
                e.frame is None and len(e.partials) >= self.MAX_PARTIALS):
            self.counters["unexpected"] += 1
            return self.expire(now)
        e.partials[partial.worker] = partial
        if e.frame is not None:
            self._answer(partial.worker, partial.frame, now)
        return self._try(partial.frame, e, now)

    def _answer(self, wid: str, fid: int, now: float) -> None:
        self.answered[wid] = (now, fid)
        self.misses[wid] = 0

    # -- assembling ----------------------------------------------------------------------------------------
    def _try(self, fid: int, e: _Pending, now: float) -> list[Result]:
        out = self.expire(now)
        f = e.frame
        if f is None or len(e.partials) != len(f.plan) or fid not in self.pending:
            return out
        rows = 2 * f.vsearch + 1
        parts = []
        for wid, k0, k1 in f.plan:
            p = e.partials[wid]
            a = p.array()
            if a.shape != (rows, k1 - k0):
                self.counters["bad"] += 1
                self._expired(fid, self.pending.pop(fid))
                return out
            parts.append(a)
        scores = parts[0] if len(parts) == 1 else np.concatenate(parts, axis=1)
        self._finish(fid, now)
        self.counters["complete"] += 1
        out.append(Result.of(f, scores, self.params, self.controller))
        return out

    def _expired(self, fid: int, e: _Pending) -> None:
        """A pending frame given up (deadline, bad shard, too many pending): dropped when its Frame was in
        (its missing workers get a miss), orphaned otherwise (forgotten: it moves nothing)."""
        if e.frame is None:
            self.counters["orphaned"] += 1
            return
        self.counters["dropped"] += 1
        for wid, _, _ in e.frame.plan:
            if wid not in e.partials:
                self.misses[wid] = self.misses.get(wid, 0) + 1
        self.expired.add(fid)
        if len(self.expired) > self.MAX_FINISHED:
            self.expired.discard(min(self.expired))

    def _finish(self, fid: int, now: float) -> None:
        """Frame fid (pending) completed: the done mark moves to it and every older pending frame is
        superseded."""
        e = self.pending.pop(fid)
        self.done_upto = max(self.done_upto, fid)
        self.done_t_ns = max(self.done_t_ns, min(e.t_capture_ns, self.wall_ns()))
        self.t_progress = now
        self.expired = {k for k in self.expired if k > self.done_upto}
        for old in [k for k in self.pending if k < fid]:
            o = self.pending.pop(old)
            self.counters["superseded" if o.frame is not None else "orphaned"] += 1

    def expire(self, now: float | None = None) -> list[Result]:
        """Drop the frames whose deadline has passed; returns [] (a uniform return for the callers)."""
        now = time.monotonic() if now is None else now
        limit = now - self.deadline_s
        for fid in [k for k, e in self.pending.items() if e.t_first <= limit]:
            self._expired(fid, self.pending.pop(fid))
        return []

    def next_deadline(self) -> float | None:
        """Monotonic time of the earliest pending deadline, None when nothing is pending."""
        if not self.pending:
            return None
        return min(e.t_first for e in self.pending.values()) + self.deadline_s

    def report(self, now: float | None = None, forget_s: float = 60.0) -> dict:
        """The membership evidence the reducer publishes (vergence/<rig>/workers): the newest frame it has a
        Frame of, and per worker heard of in the last forget_s: seconds since its latest fitting partial
        (None: never) and the frames naming it that expired without its partial, in a row."""
        now = time.monotonic() if now is None else now
        for wid in [w for w, (t, _) in self.answered.items() if now - t > forget_s]:
            del self.answered[wid]
            self.misses.pop(wid, None)
        workers = {}
        for wid in set(self.answered) | set(self.misses):
            t = self.answered.get(wid)
            workers[wid] = {"age_s": None if t is None else round(now - t[0], 4), "misses": self.misses.get(wid, 0)}
        return {"frame": self.newest, "workers": workers}


class Roster:
    """The workers the capture plans with: the live liveliness tokens (an invitation, not a guarantee),
    minus those the reducer's evidence (Gatherer.report) shows missing.

    A worker in the plan for at least miss_s that the latest report (no older than 4 x miss_s) shows with
    at least miss_frames expired frames in a row without its partial, and no partial for miss_s (or none
    ever), leaves the plan for probation_s, doubling on each exclusion in a row (up to 32 x); it is then
    tried again. One that answers is back to a clean record. Without reports (no reducer), the plan is the
    tokens, as before. counters: excluded, readmitted, reports."""

    def __init__(self, miss_s: float = 0.25, probation_s: float = 1.0, miss_frames: int = 3,
                 clock=time.monotonic):
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

    def on_report(self, report: dict) -> list[str]:
        """Apply one reducer report (Gatherer.report's dict); returns the workers it excluded."""
        now = self.clock()
        gone = []
        with self.lock:
            self.counters["reports"] += 1
            workers = report.get("workers") or {}
            for wid in list(self.joined):
                w = workers.get(wid) if isinstance(workers, dict) else None
                if not isinstance(w, dict):
                    continue
                age, misses = w.get("age_s"), w.get("misses", 0)
                answers = isinstance(age, (int, float)) and age < self.miss_s
                if answers:
                    self.strikes[wid] = 0
                    continue
                if (now - self.joined[wid] >= self.miss_s and isinstance(misses, int)
                        and misses >= self.miss_frames):
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
    """The dynamic window of the service, driven by the decisions (Verdicts) coming back to the capture.

    Only a decision made with the current window counts (frames in flight with an older one are
    ignored). Not confident: grow w by 8 px up to params.max_window. Confident `patience` times in a row:
    shrink by 8 px toward params.window, so a scene that needs the larger window does not flip every frame.
    params.max_window = 0 keeps params.window."""

    def __init__(self, params: Params, patience: int = 30):
        self.base = params.window
        self.max = max(params.max_window, params.window) if params.max_window else params.window
        self.window = self.base
        self.patience = patience
        self.streak = 0

    def update(self, window: int, confident: bool) -> int:
        if window != self.window:
            return self.window
        if not confident:
            self.streak = 0
            if self.window + 8 <= self.max:
                self.window += 8
        else:
            self.streak += 1
            if self.streak >= self.patience and self.window - 8 >= self.base:
                self.window -= 8
                self.streak = 0
        return self.window


class Health:
    """Counters of one process and the bad-message policy: count, log once per kind, skip.

    status() is what the services publish as JSON on vergence/<rig>/status/<role>/<id>."""

    def __init__(self, role: str, ident: str, log=None):
        self.role, self.ident, self.log = role, ident, log
        self.counters: dict[str, int] = {}
        self.bad: dict[str, int] = {}
        self._logged: set[str] = set()
        self._lock = threading.Lock()  # zenoh callbacks of several threads count too

    def count(self, name: str, n: int = 1) -> None:
        with self._lock:
            self.counters[name] = self.counters.get(name, 0) + n

    def reject(self, kind: str, err: Exception | str) -> None:
        """A message of `kind` that failed to decode or validate: counted, logged the first time."""
        with self._lock:
            self.bad[kind] = self.bad.get(kind, 0) + 1
            first = kind not in self._logged
            self._logged.add(kind)
        if first and self.log is not None:
            self.log.warning("bad %s message skipped (further ones are only counted): %s", kind, err)

    def status(self, **extra) -> dict:
        with self._lock:
            d = {"role": self.role, "id": self.ident, "pid": os.getpid(), "t_ns": time.time_ns(),
                 "counters": dict(self.counters), "bad": dict(self.bad)}
        d.update(extra)
        return d
