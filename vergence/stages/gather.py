"""Reducer side: workers' Correlations -> a complete profile (Gatherer, with the plausibility rules every message
must pass), a complete profile -> its decision (decide_frame: the very decision of vergence.match()) ->
Reduced, the Decision and Profile messages and the Command (through vergence.head.control.Controller).

The decision's names (docs/SERVICE.md, "One decision, five names"): vergence.network.decide.Decision is the network's
decision for one fovea (winner, confidence); vergence.network.match.Match is one point's Decision in one process
(with its x, y, window and scores); Reduced (here) is one distributed frame's Decision in the reducer
(with its Frame, its Command and its scores); messages.Decision is a Reduced on the wire
(vergence/<rig>/decision: the Decision's fields, Decision.v as v_shift since `v` is the schema version);
vergence.sim.loop.Step is one frame of the simulated loop (the state, and its Match's Decision, flattened)."""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass, field, replace

import msgspec
import numpy as np

from ..network import kernel, retina
from ..config import LimitSettings
from ..head.control import ControlSettings, Controller
from ..head.scenery import Verdict
from ..motors.base import MotorSettings, Safety
from ..network.decide import Decision, apply_checks, decide_scores, has_texture
from ..wire import messages
from ..wire.messages import Command, Frame, Correlation, Profile
from ..network.params import Params

__all__ = ["frame_params", "Prepared", "prepare", "decide_frame", "reduce", "make_profile", "decision_message",
           "Gatherer", "Reduced"]


def frame_params(frame: Frame, params: Params) -> Params:
    """The network settings a frame was computed with: the frame's own window, vertical search, direction
    comparison and support weights over the reducer's decision settings (made once per such set: they change
    with the dynamic window only, not per frame)."""
    return _over(params, frame.window, frame.vsearch, frame.circular, frame.support, frame.support_gamma,
                 frame.support_radius)


@functools.lru_cache(maxsize=32)
def _over(params: Params, window: int, vsearch: int, circular: bool, support: bool, gamma: float,
          radius: float) -> Params:
    return replace(params, window=window, vsearch=vsearch, circular=circular, support=support, support_gamma=gamma,
                   support_radius=radius)


@dataclass
class Prepared:
    """What a frame's decision needs of its Frame alone: the reducer makes it when the Frame arrives
    (Gatherer.add_frame), while the workers compute its correlations, not after the last of them. params:
    frame_params; fovea: its planes; weights: its support weights for the halves check (None without support
    weights or that check); master: the planes of the master's rows of the fovea for the left-right check (None
    without it)."""

    params: Params
    fovea: np.ndarray
    weights: np.ndarray | None
    master: np.ndarray | None


def prepare(frame: Frame, params: Params) -> Prepared:
    p = frame_params(frame, params)
    fovea = retina.planes(frame.fovea_strip())
    weights = None
    if p.support and p.halves_check:  # as halves_consistent would make them
        weights = kernel.support_weights(fovea, p.support_gamma, p.support_radius_at(frame.window))
    mstrip = frame.master_band_strip() if p.lr_check else None
    return Prepared(p, fovea, weights, None if mstrip is None else retina.planes(mstrip))


def decide_frame(frame: Frame, scores: np.ndarray, params: Params, prep: Prepared | None = None) -> Decision:
    """vergence.network.decide.decide_scores on a frame's complete scores: the decision of vergence.match() itself.

    The slave band's features (for the left-right check, with the master rows' planes, and the halves check) are
    computed only when the checks can change the result, i.e. when the decision without them is confident;
    apply_checks then runs the checks on that decision. prep: the frame's Prepared (made here when not given)."""
    prep = prep or prepare(frame, params)
    p, fovea = prep.params, prep.fovea
    y = scores[0] if scores.shape[0] == 1 else scores
    d = decide_scores(y, fovea, frame.x, p)
    if ((p.lr_check and prep.master is not None) or p.halves_check or p.min_correlation > 0) and d.confident:
        # The checks read the slave band's features at the winning window's columns k..k+w-1 (correlation and
        # left-right checks) and k-R..k+R+w-1 (halves check, R = halves_range) only: compute those (all rows),
        # not the whole band. tests/vergence/stages/test_gather.py holds this equal to match().
        w = frame.window
        band = frame.band_strip()
        sband = np.zeros((3, band.shape[0] - 2, band.shape[1] - 2), np.uint8)
        reach = p.halves_range if p.halves_check else 0
        c0, c1 = max(0, d.k - reach), min(sband.shape[2], d.k + reach + w)
        sband[:, :, c0:c1] = retina.planes(band[:, c0 : c1 + 2])
        d = apply_checks(d, fovea, frame.x, p, prep.master, sband, prep.weights)
    return d


def decision_message(frame: Frame, d: Decision, t_reduced_ns: int) -> messages.Decision:
    """The Decision message of a reduced frame: its decision, without the scores."""
    return messages.Decision(rig=frame.rig, frame=frame.frame, t_capture_ns=frame.t_capture_ns,
                             t_reduced_ns=t_reduced_ns, window=frame.window, k=d.k, k_sub=d.k_sub, v_shift=d.v,
                             k_centre=d.k_centre, direction=d.direction, magnitude=d.magnitude,
                             offset_px=d.offset_px, confidence=d.confidence, confident=d.confident,
                             texture=d.texture if math.isfinite(d.texture) else 0.0, pan_rad=frame.pan_rad,
                             t_read_ns=frame.t_read_ns, skew_ns=frame.skew_ns)


def make_profile(frame: Frame, scores: np.ndarray, d: Decision, t_reduced_ns: int) -> Profile:
    """The Profile message of a reduced frame: its Decision with the whole layer-4 vector."""
    return Profile(**msgspec.structs.asdict(decision_message(frame, d, t_reduced_ns)), width=frame.width,
                   rows=scores.shape[0], scores=np.ascontiguousarray(scores, "<f8").tobytes(),
                   workers=[str(e[0]) for e in frame.plan])


def _command(frame: Frame, d: Decision, controller: Controller, now_ns: int | None = None,
             textured: bool = True, scene: Verdict | None = None) -> Command | None:
    """The command of a decided frame (None: no move). The measurement is the slave's pan at its exposure plus
    the correction, referred to the slave's exposure time; the controller aims for when the command acts
    (now_ns, this host's clock: default the read time). A frame whose pan at exposure is not known (pan_stale)
    commands nothing. scene: the frame's background verdict (Controller.scene, asked when it arrived)."""
    if frame.pan_stale:
        return None
    now = now_ns if now_ns is not None else (frame.t_read_ns or frame.t_capture_ns)
    target = controller.target(frame.pan_rad, d.offset_px, frame.focal_px, d.confident,
                               centre_px=frame.x - frame.slave_principal[0], t_s=frame.t_slave_ns / 1e9,
                               t_now=now / 1e9,
                               slave=frame.slave_digest or None, master=frame.master_digest or None,
                               fovea=(frame.x, frame.y), doubt=frame.follows, textured=textured,
                               width_px=frame.width, background=scene)
    if target is None:
        return None
    return Command(rig=frame.rig, frame=frame.frame, t_capture_ns=frame.t_capture_ns, pan_rad=target,
                   correction_rad=target - frame.pan_rad, direction=d.direction, magnitude_px=abs(d.offset_px),
                   confidence=d.confidence, t_sent_ns=time.time_ns())


def reduce(frame: Frame, scores: np.ndarray, params: Params, controller: Controller,
           t_reduced_ns: int | None = None) -> tuple[Profile, Command | None]:
    """A complete profile -> (Profile, Command or None when the controller says not to move)."""
    r = Reduced.of(frame, scores, params, controller, t_reduced_ns)
    return r.profile, r.command


@dataclass
class Reduced:
    """A complete frame, reduced: its decision (a vergence.network.decide.Decision; its Decision message), its command
    (None: do not move) and, built when first asked for (a 65 KB message at 640 px with vertical search: only
    when someone subscribes to it), its profile. The distributed counterpart of vergence.network.match.Match.

    The command is made when first asked for too: the controller takes the decision then, once (its state moves
    with each decision it takes, in the order they are asked for). So a reducer sends the decision, which does not
    depend on the controller, before the controller's work (its checks and predictors: 170 us a frame at the p50
    at 250 Hz in `vergence up`, more at a refit) delays it; the command is aimed for the same instant
    (t_reduced_ns) either way."""

    frame: Frame
    decision: Decision
    scores: np.ndarray = field(repr=False)
    t_reduced_ns: int = 0
    _profile: Profile | None = field(default=None, repr=False)
    _controller: Controller | None = field(default=None, repr=False)
    _textured: bool = field(default=True, repr=False)
    _cmd: Command | None = field(default=None, repr=False)
    _scene: Verdict | None = field(default=None, repr=False)

    @classmethod
    def of(cls, frame: Frame, scores: np.ndarray, params: Params, controller: Controller,
           t_reduced_ns: int | None = None, prep: Prepared | None = None, scene: Verdict | None = None) -> "Reduced":
        d = decide_frame(frame, scores, params, prep)
        now = time.time_ns() if t_reduced_ns is None else t_reduced_ns
        return cls(frame, d, scores, now, _controller=controller, _textured=has_texture(d, params), _scene=scene)

    @property
    def command(self) -> Command | None:
        if self._controller is not None:
            controller, self._controller = self._controller, None
            self._cmd = _command(self.frame, self.decision, controller, self.t_reduced_ns, self._textured,
                                 self._scene)
        return self._cmd

    @property
    def textured(self) -> bool:
        """The fovea had texture (False: a black or flat image, where the loop abstains and holds)."""
        return self._textured

    @property
    def message(self) -> messages.Decision:
        return decision_message(self.frame, self.decision, self.t_reduced_ns)

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
    correlations: dict[str, Correlation] = field(default_factory=dict)
    prep: Prepared | None = None
    scene: Verdict | None = None  # its background's verdict (Controller.scene)


class Gatherer:
    """Assembles workers' Correlations into complete profiles, by the plan each Frame carries.

    A frame is complete when its Frame and one Correlation per plan entry (same worker, same k-range) are in;
    it is then reduced at once. A frame not complete `deadline_s` after its first message is dropped and
    counted; so is every older frame still pending once a newer one completes (a command is never older
    than one already sent). Nothing is ever published from an incomplete profile.

    A message is a claim: it moves no state unless it is plausible (LimitSettings). Its capture time must be
    within max_skew_s of this host's clock (wall_ns); its frame id at most frame_window ahead of the newest
    completed frame. Only a completed frame moves the "done up to" mark (a frame, a time) that makes older
    messages late; a frame that expires is remembered as done only when its Frame was in, and correlations whose
    Frame never came (`orphaned`) are forgotten. When nothing completes for reanchor_s, the mark is
    forgotten (`reanchors`) and any plausible frame is taken again: the gatherer recovers by itself.

    counters: frames (Frames accepted), correlations, complete, dropped (a Frame whose shards missed the deadline),
    superseded, orphaned (correlations whose Frame never came: counted apart from dropped, a forged correlation
    cannot inflate `dropped`), no_plan, unexpected (a Correlation for no shard of its frame's plan, or a
    duplicate), late (for a frame already done or dropped), bad (a Correlation that does not fit its frame),
    restarts (a Frame whose id went back with a newer capture time: a new capture process), reanchors,
    implausible_time, implausible_frame (rejected claims, nothing changed).

    answered: per worker, (monotonic time, frame id) of its latest correlation that fitted a Frame's plan, and
    misses: frames naming it that expired without its correlation, in a row (the evidence for membership,
    report())."""

    MAX_PENDING = 256
    MAX_CORRELATIONS = 64  # correlations kept for one frame whose Frame is not in yet
    MAX_FINISHED = 1024

    def __init__(self, params: Params, control: ControlSettings | None = None, deadline_s: float = 0.05,
                 limits: LimitSettings | None = None, wall_ns=time.time_ns,
                 motor: MotorSettings | Safety | None = None):
        self.params = params
        self.controller = Controller(control, motor)  # motor: [actuator.motor], whose limits bound each command
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
        self.counters = dict(frames=0, correlations=0, complete=0, dropped=0, superseded=0, orphaned=0, no_plan=0,
                             unexpected=0, late=0, bad=0, restarts=0, reanchors=0, implausible_time=0,
                             implausible_frame=0)

    # -- plausibility --------------------------------------------------------------------------------------
    def implausible(self, frame_id: int, t_capture_ns: int) -> str | None:
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
        why = self.implausible(frame_id, t_capture_ns)
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
    def add_frame(self, frame: Frame, now: float | None = None) -> list[Reduced]:
        now = time.monotonic() if now is None else now
        if not frame.plan:
            self.counters["no_plan"] += 1
            return self._nothing(now)
        e = self._entry(frame.frame, frame.t_capture_ns, now, True)
        if e is None:
            return self._nothing(now)
        if e.frame is not None:
            self.counters["unexpected"] += 1
            return self._nothing(now)
        prep = prepare(frame, self.params)  # before the frame counts: one that cannot be prepared is not taken
        self.counters["frames"] += 1
        e.frame, e.prep = frame, prep
        if frame.follows and not (frame.pan_stale or frame.pan_guessed):  # (while the workers compute)
            e.scene = self.controller.scene(frame.t_slave_ns / 1e9, frame.pan_rad, frame.band_strip(), frame.focal_px,
                                            frame.x + 1, (frame.x, frame.y), frame.slave_principal[0] + 1)
        self.newest = max(self.newest, frame.frame)
        # correlations that came first: those that do not fit this plan go, the others are evidence
        for wid, p in list(e.correlations.items()):
            if frame.shard(wid) != (p.k0, p.k1):
                del e.correlations[wid]
                self.counters["unexpected"] += 1
            else:
                self._answer(wid, frame.frame, now)
        return self._try(frame.frame, e, now)

    def add_correlation(self, correlation: Correlation, now: float | None = None) -> list[Reduced]:
        now = time.monotonic() if now is None else now
        e = self._entry(correlation.frame, correlation.t_capture_ns, now, False)
        if e is None:
            return self._nothing(now)
        self.counters["correlations"] += 1
        if correlation.worker in e.correlations or (e.frame is not None and
                                            e.frame.shard(correlation.worker) != (correlation.k0, correlation.k1)) or (
                e.frame is None and len(e.correlations) >= self.MAX_CORRELATIONS):
            self.counters["unexpected"] += 1
            return self._nothing(now)
        e.correlations[correlation.worker] = correlation
        if e.frame is not None:
            self._answer(correlation.worker, correlation.frame, now)
        return self._try(correlation.frame, e, now)

    def _answer(self, wid: str, fid: int, now: float) -> None:
        self.answered[wid] = (now, fid)
        self.misses[wid] = 0

    # -- assembling ----------------------------------------------------------------------------------------
    def _try(self, fid: int, e: _Pending, now: float) -> list[Reduced]:
        out = self._nothing(now)
        f = e.frame
        if f is None or len(e.correlations) != len(f.plan) or fid not in self.pending:
            return out
        rows = 2 * f.vsearch + 1
        parts = []
        for wid, k0, k1 in f.plan:
            p = e.correlations[wid]
            a = p.array()
            if a.shape != (rows, k1 - k0):
                self.counters["bad"] += 1
                self._expired(fid, self.pending.pop(fid))
                return out
            parts.append(a)
        scores = parts[0] if len(parts) == 1 else np.concatenate(parts, axis=1)
        self._finish(fid, now)
        self.counters["complete"] += 1
        out.append(Reduced.of(f, scores, self.params, self.controller, prep=e.prep, scene=e.scene))
        return out

    def _expired(self, fid: int, e: _Pending) -> None:
        """A pending frame given up (deadline, bad shard, too many pending): dropped when its Frame was in
        (its missing workers get a miss), orphaned otherwise (forgotten: it moves nothing)."""
        if e.frame is None:
            self.counters["orphaned"] += 1
            return
        self.counters["dropped"] += 1
        for wid, _, _ in e.frame.plan:
            if wid not in e.correlations:
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

    def expire(self, now: float | None = None) -> None:
        """Drop the frames whose deadline has passed."""
        now = time.monotonic() if now is None else now
        limit = now - self.deadline_s
        for fid in [k for k, e in self.pending.items() if e.t_first <= limit]:
            self._expired(fid, self.pending.pop(fid))

    def _nothing(self, now: float) -> list[Reduced]:
        """What an input that completes no frame returns, after the deadlines."""
        self.expire(now)
        return []

    def awaiting(self) -> bool:
        """Whether a pending frame has its Frame in and awaits correlations (the reducer then waits for those)."""
        return any(e.frame is not None and len(e.correlations) < len(e.frame.plan) for e in self.pending.values())

    def next_deadline(self) -> float | None:
        """Monotonic time of the earliest pending deadline, None when nothing is pending."""
        if not self.pending:
            return None
        return min(e.t_first for e in self.pending.values()) + self.deadline_s

    def report(self, now: float | None = None, forget_s: float = 60.0) -> dict:
        """The membership evidence the reducer publishes (vergence/<rig>/workers): the newest frame it has a
        Frame of, and per worker heard of in the last forget_s: seconds since its latest fitting correlation
        (None: never) and the frames naming it that expired without its correlation, in a row."""
        now = time.monotonic() if now is None else now
        for wid in [w for w, (t, _) in self.answered.items() if now - t > forget_s]:
            del self.answered[wid]
            self.misses.pop(wid, None)
        workers = {}
        for wid in set(self.answered) | set(self.misses):
            t = self.answered.get(wid)
            workers[wid] = {"age_s": None if t is None else round(now - t[0], 4), "misses": self.misses.get(wid, 0)}
        return {"frame": self.newest, "workers": workers}
