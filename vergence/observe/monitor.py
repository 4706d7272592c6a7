"""What `vergence monitor` knows about a running rig, and how it draws it: a pure model, no network.

Monitor is fed with (key, bytes, arrival time) exactly as they come off vergence/<rig>/** and with the
liveliness events of vergence/<rig>/alive/**; it decodes them with vergence.wire.messages, counts and skips the
malformed ones, and keeps what a user watches: rates, capture-to-command latency percentiles over the last
seconds, dropped frames, live workers and their shards, pan and target, the latest profile and the recent
pan history. snapshot() returns a plain Snapshot; screen.render_text() draws the terminal screen (ANSI optional)
from it, and plots.monitor_figure() the paper's figure 5 (layer 4 against k, winner and centre marked) with the
pan history (both in vergence.observe), so both are tested without Zenoh.

Clocks: latencies are differences of time.time_ns() stamps taken on the capture and the reducer
(t_capture_ns, Command.t_sent_ns / Profile.t_reduced_ns): across machines they need synchronised clocks.
Rates, drops and histories use the monitor's own arrival times.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from ..wire import keys
from ..wire import messages as m
from ..wire.status import Status, decode_status

__all__ = ["Monitor", "Snapshot", "Rate", "decode", "MESSAGES", "WATCHED"]

# key kind -> the message class its payload decodes to (a message's kind is its key's kind: docs/NAMES.md)
MESSAGES: dict[str, type[m.Message]] = m.KINDS
# the key kinds the model keeps (the others are ignored)
WATCHED = (keys.FRAME, keys.PROFILE, keys.COMMAND, keys.MOTOR_STATE, keys.PREVIEW, keys.CORRELATION, keys.STATUS)


def decode(kind: str, payload: bytes) -> m.Message | Status:
    """The payload of a key of this kind (vergence.wire.keys), decoded: a message (vergence.wire.messages), or for a
    status a vergence.wire.status.Status. The one decoding of the wire for `vergence monitor` and `vergence view`;
    m.MessageError when it is malformed, KeyError for a kind that carries no payload."""
    if kind != keys.STATUS:
        return MESSAGES[kind].from_bytes(payload)
    return decode_status(payload)


class Rate:
    """Events per second over a sliding window of arrival times."""

    def __init__(self, window_s: float):
        self.window_ns = int(window_s * 1e9)
        self.times: deque[int] = deque()
        self.first_ns: int | None = None
        self.count = 0

    def add(self, t_ns: int) -> None:
        if self.first_ns is None:
            self.first_ns = t_ns
        self.times.append(t_ns)
        self.count += 1

    def _trim(self, now_ns: int) -> None:
        while self.times and self.times[0] <= now_ns - self.window_ns:
            self.times.popleft()

    def per_second(self, now_ns: int) -> float:
        self._trim(now_ns)
        if self.first_ns is None or not self.times:
            return 0.0
        span = min(self.window_ns, now_ns - self.first_ns)
        if span < self.window_ns:
            # still filling the window: the rate between the first and the last arrival
            n = len(self.times)
            span = self.times[-1] - self.times[0]
            return (n - 1) / (span / 1e9) if n >= 2 and span > 0 else 0.0
        return len(self.times) / (self.window_ns / 1e9)


@dataclass
class Snapshot:
    """Everything a screen or a picture shows, at one instant (plain data, safe to keep)."""

    rig: str | None
    now_ns: int
    window_s: float
    frames_per_s: float = 0.0
    profiles_per_s: float = 0.0
    commands_per_s: float = 0.0
    frames: int = 0
    profiles: int = 0
    commands: int = 0
    latency_p50_ms: float = math.nan      # capture -> command
    latency_p99_ms: float = math.nan
    latency_n: int = 0
    reduce_p50_ms: float = math.nan       # capture -> profile (reducer done)
    reduce_p99_ms: float = math.nan
    dropped: int = 0
    # how drops were counted: "reducer" (its status counters: deadline + superseded, since it started),
    # "frames" seen on the wire and never answered by a profile, or "gaps" in the profiles' frame ids
    dropped_from: str = "frames"
    dropped_of: int = 0                   # out of how many frames (same origin as dropped)
    status: dict[str, Status] = field(default_factory=dict)    # "role/id" -> its latest status
    workers: dict[str, tuple[int, int] | None] = field(default_factory=dict)
    alive: dict[str, list[str]] = field(default_factory=dict)   # role -> ids
    plan_frame: int = -1
    pan_rad: float = math.nan             # actuator's measured position
    goal_rad: float = math.nan            # actuator's goal
    target_rad: float = math.nan          # last command's target
    # a simulated source's ground truth, from the latest frame that carries it: the converged pan at its
    # capture, and the frame's pan's error f tan(pan - truth) in pixels (NaN: no truth)
    truth_rad: float = math.nan
    truth_error_px: float = math.nan
    # the tracking over the last window_s: the frames' pans' errors against their truth (RMS, max |e|, count)
    tracking_rms_px: float = math.nan
    tracking_max_px: float = math.nan
    tracking_n: int = 0
    min_rad: float = math.nan
    max_rad: float = math.nan
    motor_status: str = ""
    motor_note: str = ""  # the motor state's note (why it is disconnected or absent)
    at_limit: bool = False
    profile: m.Profile | None = None
    command: m.Command | None = None
    pan_history: list[tuple[float, float]] = field(default_factory=list)     # (seconds before now, pan)
    target_history: list[tuple[float, float]] = field(default_factory=list)  # (seconds before now, target)
    truth_history: list[tuple[float, float]] = field(default_factory=list)   # (seconds before now, truth)
    malformed: dict[str, int] = field(default_factory=dict)
    last_error: dict[str, str] = field(default_factory=dict)
    ignored: int = 0
    fovea: tuple[int, int] | None = None  # the fovea centre (master px) of the latest frame seen


class Monitor:
    """The model of a live rig, fed from any thread (a lock guards it).

    rig: accept only vergence/<rig>/... (None: any). window_s: rates and latency percentiles cover the
    last window_s seconds. history_s: length of the pan history. drop_grace_s: a frame seen on the wire
    with no profile after this long counts as dropped. When no frames are seen (a monitor that does not
    subscribe to them), drops are the gaps in the profiles' frame ids instead."""

    def __init__(self, rig: str | None = None, window_s: float = 5.0, history_s: float = 30.0,
                 drop_grace_s: float = 1.0, clock=time.time_ns):
        self.rig = rig
        self.window_s = window_s
        self.history_s = history_s
        self.drop_grace_ns = int(drop_grace_s * 1e9)
        self.clock = clock
        self._lock = threading.Lock()
        self._rates = {k: Rate(window_s) for k in ("frame", "profile", "command")}
        self._lat: deque[tuple[int, int]] = deque()       # (arrival, capture->command ns)
        self._red: deque[tuple[int, int]] = deque()       # (arrival, capture->profile ns)
        self._pending: dict[int, int] = {}                # frame id -> arrival, awaiting its profile
        self._answered: deque[int] = deque(maxlen=4096)   # profile ids seen before their frame arrived
        self._dropped = 0
        self._gaps = 0
        self._last_profile_id: int | None = None
        self._alive: dict[str, set[str]] = {}
        self._plan: dict[str, tuple[int, int]] = {}
        self._plan_frame = -1
        self._fovea: tuple[int, int] | None = None
        self._truth: tuple[float, float] | None = None  # (truth, error px) of the latest frame with a truth
        self._truth_hist: deque[tuple[int, float, float]] = deque()  # (arrival, truth, error px)
        self._correlations: dict[str, tuple[int, int]] = {}
        self._motor: m.MotorState | None = None
        self._status: dict[str, Status] = {}
        self._profile: m.Profile | None = None
        self._command: m.Command | None = None
        self._pan_hist: deque[tuple[int, float]] = deque()
        self._target_hist: deque[tuple[int, float]] = deque()
        self.malformed: dict[str, int] = {}
        self.last_error: dict[str, str] = {}
        self.ignored = 0
        self.listeners: list = []   # callables(kind, message), called under no lock after a good message

    # ---- input -------------------------------------------------------------------------------------
    def feed(self, key: str, payload: bytes, t_ns: int | None = None) -> m.Message | Status | None:
        """One sample from the wire. Returns the decoded message (a Status for a status), or None when the
        key is not watched (ignored) or the payload is malformed (counted per kind in self.malformed,
        never raised)."""
        t_ns = self.clock() if t_ns is None else t_ns
        k = keys.parse(key)
        if k is None or (self.rig is not None and k.rig != self.rig) or k.kind not in WATCHED:
            with self._lock:
                self.ignored += 1
            return None
        kind = k.kind
        try:
            msg = decode(kind, payload)
        except m.MessageError as e:
            with self._lock:
                self.malformed[kind] = self.malformed.get(kind, 0) + 1
                self.last_error[kind] = f"status/{k.name}: {e}" if kind == keys.STATUS else str(e)
            return None
        if kind == keys.STATUS:
            self._on_status(k.name, msg, t_ns)
        else:
            self.add(msg, t_ns)
        return msg

    def add(self, msg: m.Message, t_ns: int | None = None) -> None:
        """One decoded message (any of the messages.* classes), received at t_ns."""
        t_ns = self.clock() if t_ns is None else t_ns
        with self._lock:
            if isinstance(msg, m.Frame):
                self._on_frame(msg, t_ns)
            elif isinstance(msg, m.Profile):
                self._on_profile(msg, t_ns)
            elif isinstance(msg, m.Command):
                self._on_command(msg, t_ns)
            elif isinstance(msg, m.MotorState):
                self._motor = msg
                self._pan_hist.append((t_ns, msg.pan_rad))
            elif isinstance(msg, m.Correlation):
                self._correlations[msg.worker] = (msg.k0, msg.k1)
            self._trim(t_ns)
        for fn in self.listeners:
            fn(msg.KIND, msg)

    def _on_status(self, name: str, d: Status, t_ns: int) -> None:
        """vergence/<rig>/status/<role>/<id>: a process's status; the latest one per process is kept (the
        reducer's give the dropped frames), an exiting one removes the process."""
        with self._lock:
            if d.exiting:
                self._status.pop(name, None)
            else:
                self._status[name] = d
            self._trim(t_ns)

    def liveliness(self, key: str, present: bool) -> None:
        """A liveliness token vergence/<rig>/alive/<role>/<id> appeared (present) or went away."""
        k = keys.parse(key)
        if k is None or k.kind != keys.ALIVE or (self.rig is not None and k.rig != self.rig):
            return
        role, ident = k.role, k.ident
        with self._lock:
            ids = self._alive.setdefault(role, set())
            if present:
                ids.add(ident)
            else:
                ids.discard(ident)
                self._correlations.pop(ident, None)

    def _on_frame(self, f: m.Frame, t: int) -> None:
        self._rates["frame"].add(t)
        self._fovea = (f.x, f.y)
        if f.frame in self._answered:
            self._answered.remove(f.frame)
        elif len(self._pending) < 100_000:
            self._pending[f.frame] = t
        if f.plan:
            self._plan = {str(w): (int(a), int(b)) for w, a, b in f.plan}
            self._plan_frame = f.frame
        if f.truth_pan_rad is not None:
            self._truth = (f.truth_pan_rad, f.focal_px * math.tan(f.pan_rad - f.truth_pan_rad))
            self._truth_hist.append((t, *self._truth))

    def _on_profile(self, p: m.Profile, t: int) -> None:
        self._rates["profile"].add(t)
        self._profile = p
        if self._pending.pop(p.frame, None) is None:
            self._answered.append(p.frame)
        last = self._last_profile_id
        if last is not None and p.frame > last + 1:
            self._gaps += p.frame - last - 1
        self._last_profile_id = p.frame
        if p.t_reduced_ns > 0 and p.t_capture_ns > 0:
            self._red.append((t, p.t_reduced_ns - p.t_capture_ns))

    def _on_command(self, c: m.Command, t: int) -> None:
        self._rates["command"].add(t)
        self._command = c
        if c.t_capture_ns > 0:
            sent = c.t_sent_ns if c.t_sent_ns > 0 else t
            self._lat.append((t, sent - c.t_capture_ns))
        self._target_hist.append((t, c.pan_rad))

    def _trim(self, now: int) -> None:
        w = int(self.window_s * 1e9)
        h = int(self.history_s * 1e9)
        for dq, span in ((self._lat, w), (self._red, w), (self._pan_hist, h), (self._target_hist, h),
                         (self._truth_hist, h)):
            while dq and dq[0][0] <= now - span:
                dq.popleft()
        if self._pending:
            late = [fid for fid, ta in self._pending.items() if ta <= now - self.drop_grace_ns]
            for fid in late:
                del self._pending[fid]
            self._dropped += len(late)

    # ---- output ------------------------------------------------------------------------------------
    def snapshot(self, now_ns: int | None = None) -> Snapshot:
        now = self.clock() if now_ns is None else now_ns
        with self._lock:
            self._trim(now)
            s = Snapshot(rig=self.rig, now_ns=now, window_s=self.window_s)
            s.frames_per_s = self._rates["frame"].per_second(now)
            s.profiles_per_s = self._rates["profile"].per_second(now)
            s.commands_per_s = self._rates["command"].per_second(now)
            s.frames, s.profiles, s.commands = (self._rates[k].count for k in ("frame", "profile", "command"))
            if self._lat:
                lat = np.array([x for _, x in self._lat], dtype=np.float64) / 1e6
                s.latency_p50_ms, s.latency_p99_ms = (float(v) for v in np.percentile(lat, [50, 99]))
                s.latency_n = len(lat)
            if self._red:
                red = np.array([x for _, x in self._red], dtype=np.float64) / 1e6
                s.reduce_p50_ms, s.reduce_p99_ms = (float(v) for v in np.percentile(red, [50, 99]))
            gatherers = [g for n, d in self._status.items() if n.startswith("reducer/") and (g := d.gatherer())]
            if gatherers:
                def total(name: str) -> int:  # (Status.gatherer keeps the plausible counters only)
                    return sum(g.get(name, 0) for g in gatherers)
                s.dropped, s.dropped_from = total("dropped") + total("superseded"), "reducer"
                s.dropped_of = total("frames")
            elif s.frames:
                s.dropped, s.dropped_from, s.dropped_of = self._dropped, "frames", s.frames
            else:
                s.dropped, s.dropped_from, s.dropped_of = self._gaps, "gaps", s.profiles + self._gaps
            s.status = dict(sorted(self._status.items()))
            s.alive = {r: sorted(ids) for r, ids in sorted(self._alive.items()) if ids}
            live = set(self._alive.get("worker", set()))
            shards = dict(self._correlations)
            shards.update(self._plan)
            s.workers = {w: shards.get(w) for w in sorted(live | set(self._plan))
                         if w in live or not self._alive.get("worker")}
            s.plan_frame = self._plan_frame
            s.fovea = self._fovea
            if self._motor is not None:
                mo = self._motor
                s.pan_rad, s.goal_rad, s.min_rad, s.max_rad = mo.pan_rad, mo.goal_rad, mo.min_rad, mo.max_rad
                s.motor_status, s.at_limit, s.motor_note = mo.status, mo.at_limit, mo.note
            if self._command is not None:
                s.target_rad = self._command.pan_rad
            if self._truth is not None:
                s.truth_rad, s.truth_error_px = self._truth
            err = np.array([e for t, _, e in self._truth_hist if t > now - self.window_s * 1e9], np.float64)
            if len(err):
                s.tracking_rms_px, s.tracking_max_px = float(np.sqrt(np.mean(err ** 2))), float(np.abs(err).max())
                s.tracking_n = len(err)
            s.truth_history = [((now - t) / 1e9, v) for t, v, _ in self._truth_hist]
            s.profile, s.command = self._profile, self._command
            s.pan_history = [((now - t) / 1e9, v) for t, v in self._pan_hist]
            s.target_history = [((now - t) / 1e9, v) for t, v in self._target_hist]
            s.malformed = dict(self.malformed)
            s.last_error = dict(self.last_error)
            s.ignored = self.ignored
            return s
