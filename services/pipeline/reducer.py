"""`vergence reducer`: gathers the shards of each frame, decides, publishes the profile and the command.

Subscribes to vergence/<rig>/frame and vergence/<rig>/correlation/*; vergence.stages.gather.Gatherer assembles
each frame by the plan the frame carries, drops (and counts) a frame whose shards miss the deadline
([reducer] deadline_ms), and reduces a complete one with vergence.network.decide.decide_scores and the controller.
Messages that are not plausible ([limits]: capture time, frame id, frame size) are counted and change
nothing. Messages arrive in zenoh RingChannels (bounded, the oldest go); one thread takes everything that
arrived, newest frame first when it is a backlog (gather_order), so an overloaded reducer serves the newest frame.
Every REPORT_S it publishes the membership evidence on vergence/<rig>/workers (JSON: per worker, seconds
since its latest correlation and the frames it missed in a row), from which the capture drops silent workers
from the plan.
Publishes messages.Profile on vergence/<rig>/profile and, when the controller moves the slave,
messages.Command on vergence/<rig>/command; never from an incomplete profile. Counters go out as JSON on
vergence/<rig>/status/reducer/<id> every second and at exit. The profile is only encoded and published while
someone subscribes to it. Each decision carries the fovea centre (x, y) it was made for and the fixated
point's depth (vergence.head.depth, with the [rig] table's baseline, gimbal and master). Every [reducer] summary_s
seconds (5) with frames, one log line says what the loop is doing (summary()).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import threading
import time

import msgspec
import zenoh

from vergence.head import depth
from vergence.wire import keys
from vergence.config import load
from vergence.stages.frames import check_frame
from vergence.stages.gather import Reduced, Gatherer
from vergence.wire.status import WorkerEvidence, WorkersReport
from vergence.wire.messages import MAX_HOLD_S, Correlation, Frame, Hold, MessageError, MotorState
from vergence.wire.messages import replace as replace_message

from services.pipeline.capture_time import FUTURE_S, motor_state_implausible
from services.runtime import session
from services.runtime.args import number
from services.runtime.node import Node
from services.runtime.warm import warm_up

log = logging.getLogger("vergence.reducer")
EXPIRE_S = 0.05  # the longest sleep between deadline checks (frames also expire as messages arrive)
POLL_S = 0.001  # the shortest alarm
REPORT_S = 0.1  # the membership evidence (vergence/<rig>/workers) goes out this often
# zenoh RingChannels: the newest messages kept while the reducer's thread works (what they drop is not counted,
# so they are larger than what the inbox keeps, whose sheds are)
FRAME_RING, CORRELATION_RING = 32, 128
STATE_RING = 256  # the motor's states between two wakes (50 a second, and one a command): each is counted
KEEP_FRAMES = 3  # the newest valid frames of one batch that are decoded and gathered
WAKE = "_wake"  # the key segment of the local sample that wakes the reducer's thread (Alarm, exit)


def configure(p: argparse.ArgumentParser) -> None:
    session.add_options(p)
    p.add_argument("--deadline-ms", type=number(0, 10_000, lo_open=True), default=None,
                   help="drop a frame whose shards are not all in by then (default: settings, 50)")


def summary(seconds: float, frames: int, lost: int, commands: int, last: Reduced, window: "Window") -> str:
    """The reducer's periodic log line: what came through in the last `seconds`, the latest decision, and over
    the window the slave's pans at capture (their range: one frame's reads like a toggle on a moving target)
    and, where the frames carry a truth (the simulator), how far those pans were off it."""
    d, f = last.decision, last.frame
    line = (f"last {seconds:.0f} s: frames {frames} decided, {lost} dropped, commands {commands}; frame {f.frame}: "
            f"offset {d.offset_px:+.2f} px, {'confident' if d.confident else 'abstains'}"
            f"{'' if d.confident or last.textured else ': no texture at the fovea (a black or flat image)'} "
            f"(margin {d.confidence:.2f}, w {f.window})")
    if window.pans:
        lo, hi = math.degrees(min(window.pans)), math.degrees(max(window.pans))
        line += f"; slave pan at capture {lo:+.3f}..{hi:+.3f} deg"
    if window.errors:
        e = window.errors
        rms = math.sqrt(sum(x * x for x in e) / len(e))
        line += f", {rms:.2f} px RMS off the simulator's truth (max {max(abs(x) for x in e):.2f} px, {len(e)} frames)"
    return line


class Window:
    """The decided frames' pans at capture and, where a frame carries the simulator's truth, the pan's error
    f tan(pan - truth) in pixels, since the last summary."""

    def __init__(self):
        self.pans: list[float] = []
        self.errors: list[float] = []

    def add(self, f: Frame) -> None:
        self.pans.append(f.pan_rad)
        if f.truth_pan_rad is not None:
            self.errors.append(f.focal_px * math.tan(f.pan_rad - f.truth_pan_rad))

    def take(self) -> "Window":
        """This window (for the summary), and a new one begun."""
        out = Window()
        out.pans, out.errors, self.pans, self.errors = self.pans, self.errors, [], []
        return out


class Inbox:
    """The reducer thread's two rings (zenoh RingChannels: zenoh's receiving threads push into them in Rust, with no
    GIL, and never wait for this process; a full ring loses its oldest). take(wait) blocks on one ring: the
    frames' while no Frame awaits its correlations (the next thing a frame sends the reducer is its Frame, which
    is then prepared while the workers compute: vergence.stages.gather.prepare), else the correlations'. At each
    wake it takes both rings whole, keeping the newest `frames` and `correlations` of them: the rest is shed,
    counted per kind, so nothing queues when the reducer cannot keep up. An empty sample on a ring's wake key (the
    Alarm's, the Node's at exit: <key>/_wake) wakes it with nothing."""

    NONE_SHED = {"frame": 0, "correlation": 0}

    def __init__(self, frame_ring, correlation_ring, frames: int = 8, correlations: int = 64):
        self.rings = {"frame": frame_ring, "correlation": correlation_ring}
        self.keep = {"frame": frames, "correlation": correlations}
        self.lock = threading.Lock()  # shed: this thread counts, the status reads
        self.shed = dict(self.NONE_SHED)

    def count_shed(self, kind: str, n: int) -> None:
        with self.lock:
            self.shed[kind] += n

    def take(self, wait: str = "correlation") -> list[tuple[str, tuple[str, bytes]]]:
        """What arrived, (kind, (key, payload)) oldest first per kind, after waiting for a sample of kind `wait`
        ("frame" or "correlation") or a wake."""
        first = self.rings[wait].recv()
        out = []
        for kind, ring in self.rings.items():
            got = [first] if kind == wait else []
            while (smp := ring.try_recv()) is not None:
                got.append(smp)
            items = [(str(m.key_expr), m.payload.to_bytes()) for m in got]
            items = [(k, b) for k, b in items if b or not k.endswith("/" + WAKE)]
            if len(items) > self.keep[kind]:
                self.count_shed(kind, len(items) - self.keep[kind])
                items = items[-self.keep[kind]:]
            out += [(kind, x) for x in items]
        return out


class Alarm:
    """Wakes the reducer's thread (an empty local sample on the wake key) at the time set, and EXPIRE_S after each
    wake: its deadlines, the membership evidence and the status are kept while no message comes."""

    def __init__(self, wake, stop: threading.Event):
        self.wake, self.stop = wake, stop
        self.cond = threading.Condition()
        self.at = time.monotonic() + EXPIRE_S

    def set(self, at: float) -> None:
        """Wake by `at` (monotonic) at the latest."""
        with self.cond:
            if at < self.at:
                self.at = at
                self.cond.notify()

    def run(self) -> None:
        with self.cond:
            while not self.stop.is_set():
                delay = self.at - time.monotonic()
                if delay > 0:
                    self.cond.wait(delay)
                    continue
                self.at = time.monotonic() + EXPIRE_S
                self.wake()


class MotorPresence:
    """What the actuator says of its motor (messages.MotorState on vergence/<rig>/motor_state): while its latest
    state, less than FRESH_S old, says the motor is absent (status "absent": it has not answered for
    [actuator.motor] absent_s), the reducer sends no command (counted under motor_absent) and its status says
    motor: absent. A state that does not decode is counted under bad.motor_state; no fresh state (an actuator
    gone, or a forged "absent" not repeated) lets the commands go again by itself."""

    FRESH_S = 1.0

    def __init__(self, health, clock=time.monotonic):
        self.health, self.clock = health, clock
        self.lock = threading.Lock()
        self.status, self.at = "", -1e9

    def on_state(self, payload: bytes) -> MotorState | None:
        """One state (None: it did not decode, counted)."""
        try:
            st = MotorState.from_bytes(payload)
        except MessageError as e:
            self.health.reject("motor_state", e)
            return None
        with self.lock:
            if st.status == "absent" and self.status != "absent":
                log.warning("the motor is absent (%s): no command is sent until it answers again", st.note or
                            "no answer")
            elif st.status != "absent" and self.status == "absent":
                log.info("the motor answers again (%s): commands resume", st.status)
            self.status, self.at = st.status, self.clock()
        return st

    def absent(self) -> bool:
        with self.lock:
            return self.status == "absent" and self.clock() - self.at < self.FRESH_S

    def fields(self) -> dict:
        return {"motor": "absent" if self.absent() else (self.status or "unknown")}


class Lease:
    """A hold on the reducer's commands (messages.Hold, vergence/<rig>/hold): none goes out until its until_ns.
    A hold further than MAX_HOLD_S ahead is not believed (counted under bad.hold, nothing held), so a client
    that stops renewing it (killed, or a forgery) leaves the loop commanding again within MAX_HOLD_S."""

    def __init__(self, health, clock=time.time_ns):
        self.health, self.clock = health, clock
        self.lock = threading.Lock()
        self.until_ns = 0

    def on_hold(self, payload: bytes) -> None:
        try:
            h = Hold.from_bytes(payload)
            if h.until_ns > self.clock() + MAX_HOLD_S * 1e9:
                raise MessageError(f"hold until {(h.until_ns - self.clock()) / 1e9:.3g} s from now: more than "
                                   f"{MAX_HOLD_S:g} s")
        except MessageError as e:
            self.health.reject("hold", e)
            return
        with self.lock:
            if not self.until_ns > self.clock() and h.until_ns > self.clock():
                log.info("commands held%s", f" for {h.source}" if h.source else "")
            self.until_ns = h.until_ns

    def held(self) -> bool:
        with self.lock:
            return self.clock() < self.until_ns


def gather_order(msgs: list) -> list:
    """Decoded messages (Frame or Correlation) in the order the gatherer should see them, each Frame before its
    correlations. Those of up to KEEP_FRAMES frames (a stall of up to two frame periods: the thread descheduled while
    they came) oldest first: each complete frame is reduced, the older for a decision's time, not dropped (newest
    first superseded them: frames lost in a quarter of the runs at 250 Hz). Of more (a backlog) newest first: the
    newest complete frame is reduced, every older message is late (cheap): overloaded, it serves that."""
    sign = -1 if len({m.frame for m in msgs}) > KEEP_FRAMES else 1
    return sorted(msgs, key=lambda m: (sign * m.frame, not isinstance(m, Frame)))


class Reducer:
    """One reducer process: the gatherer, its inbox and alarm, and its loop (run) in the Node's block.

    zenoh's receiving threads only push into rings (Rust, no Python, no GIL: they never wait for this process,
    so no queue builds up in the network; the oldest go when a ring is full); the loop's thread takes them
    (Inbox.take), decodes, gathers, decides and publishes, expires deadlines, and publishes the status and the
    membership evidence. Forwarder threads handed the rings' samples to it until 2026-12-04: one thread hop
    and 0.2 ms of CPU a frame at 250 Hz more (docs/PERFORMANCE.md)."""

    def __init__(self, settings, deadline_s: float):
        self.settings, self.rig, self.limits, self.deadline = settings, settings.rig, settings.limits, deadline_s
        self.frame_key = keys.frame(self.rig)
        self.gatherer = Gatherer(settings.network, settings.control, deadline_s, self.limits,
                                 motor=settings.actuator.motor)
        self.lock = threading.Lock()  # the gatherer: the loop thread and the status
        self.inbox: Inbox | None = None
        self.alarm: Alarm | None = None
        self.presence: MotorPresence | None = None
        self.last: list[Reduced] = []
        self.window = Window()  # the pans and tracking errors for the summary

    def fields(self) -> dict:
        with self.lock:
            return dict(gatherer=dict(self.gatherer.counters), pending=len(self.gatherer.pending),
                        shed=dict(self.inbox.shed if self.inbox else Inbox.NONE_SHED),
                        **(self.presence.fields() if self.presence else {}),
                        **self.gatherer.controller.status())

    def open(self, node: Node) -> None:
        """The subscriptions, the publishers, the inbox's rings and the alarm's thread, then the liveliness token."""
        rig = self.rig
        self.node, self.health = node, node.health
        self.presence = MotorPresence(self.health)
        self.states = node.ring(keys.motor_state(rig), STATE_RING)  # read at each wake (no callback, no GIL)
        self.pub_decision = node.publisher(keys.decision(rig), express=True)
        self.pub_profile = node.publisher(keys.profile(rig), express=True)
        self.pub_command = node.publisher(keys.command(rig), express=True)
        self.pub_workers = node.publisher(keys.workers(rig), express=True)
        self.hold = Lease(self.health)
        node.subscriber(keys.hold(rig), lambda sm: self.hold.on_hold(sm.payload.to_bytes()))
        # the frames' ring also hears <frame>/_wake (its wake); any other key under it is no Frame (decode)
        wakes = [f"{keys.frame(rig)}/{WAKE}", keys.correlation(rig, WAKE)]
        self.inbox = Inbox(node.ring(f"{keys.frame(rig)}/**", FRAME_RING, wake=wakes[0]),
                           node.ring(keys.correlations(rig), CORRELATION_RING, wake=wakes[1]))
        self.alarm = Alarm(lambda: [node.session.put(w, b"", allowed_destination=zenoh.Locality.SESSION_LOCAL)
                                    for w in wakes], node.stop)
        node.thread(self.alarm.run, name="reducer-alarm")
        node.ready()
        log.info("reducer %s on %s and %s, deadline %.0f ms", node.ident, keys.frame(rig), keys.correlations(rig),
                 self.deadline * 1e3)

    def publish(self, results) -> None:
        if results:
            self.last[:] = results[-1:]
        geo, health = self.settings.geometry, self.health
        for r in results:
            self.window.add(r.frame)
            # the decision first: it does not wait for the controller, which takes it only now (gather.Reduced)
            where = depth.decision_fields(r.frame, r.decision, r.scores, geo.baseline_m, geo.gimbal,
                                          geo.master or self.settings.capture.master, geo.pan_axis_m)
            self.pub_decision.put(replace_message(r.message, **where).to_bytes())
            command = r.command
            if command is not None and self.hold.held():
                health.count("held")  # a client moves the slave itself (`vergence latency`)
            elif command is not None and self.presence.absent():
                health.count("motor_absent")  # nothing would execute it: the actuator has lost its motor
            elif command is not None:
                self.pub_command.put(command.to_bytes())
                health.count("commands")
            if self.pub_profile.matching_status.matching:  # up to 65 KB at 640 px: only encoded when wanted
                self.pub_profile.put(replace_message(r.profile, **where).to_bytes())
            health.count("profiles")

    def decode(self, kind: str, item):
        """A Frame or Correlation from (key, bytes), or None (counted by reason)."""
        key, data = item
        if kind == "frame":
            try:
                if key != self.frame_key:
                    raise MessageError(f"frame on key {key}")
                return check_frame(data, self.limits)
            except MessageError as e:
                self.health.reject("frame", e)
                return None
        try:
            part = Correlation.from_bytes(data)
            k = keys.parse(key)
            if k is None or k.ident != part.worker:
                raise MessageError(f"correlation from worker {part.worker!r} on key {key}")
            return part
        except MessageError as e:
            self.health.reject("correlation", e)
            return None

    def handle(self, batch) -> None:
        # frames newest (last arrived) first, and only until KEEP_FRAMES valid ones: the older ones of a
        # backlog would be superseded anyway, so they are let go (shed) without the cost of decoding them
        frames = [x for k, x in batch if k == "frame"]
        msgs = []
        for i, item in enumerate(reversed(frames)):
            if len(msgs) >= KEEP_FRAMES:
                self.inbox.count_shed("frame", len(frames) - i)
                break
            m = self.decode("frame", item)
            if m is not None:
                msgs.append(m)
        msgs += [m for m in (self.decode(k, x) for k, x in batch if k == "correlation") if m is not None]
        with self.lock:
            fault = self.gatherer.controller.doubt.fault
            for m in gather_order(msgs):
                try:
                    if isinstance(m, Frame):
                        self.publish(self.gatherer.add_frame(m))
                    else:
                        self.publish(self.gatherer.add_correlation(m))
                except Exception as e:  # a message that validates but cannot be decided on: never fatal
                    self.health.reject(m.KIND, e)
            changed = self.gatherer.controller.doubt.fault != fault
        if changed:
            self.node.status()  # a fault named or cleared is said at once, not at the next second

    def workers_report(self) -> bytes:
        with self.lock:
            rep = self.gatherer.report()
            return msgspec.json.encode(WorkersReport(
                rig=self.rig, id=self.node.ident, t_ns=time.time_ns(), frame=rep["frame"],
                complete=self.gatherer.counters["complete"],
                workers={w: WorkerEvidence(e["age_s"], e["misses"]) for w, e in rep["workers"].items()}))

    def counts(self) -> tuple[int, int, int]:
        """For the summary: frames complete, frames lost (dropped or superseded), commands sent."""
        with self.lock:
            c = self.gatherer.counters
            return c["complete"], c["dropped"] + c["superseded"], self.health.counters.get("commands", 0)

    def motor_state(self, st: MotorState | None) -> None:
        """A motor's report of its pan to the controller (a late camera's lag is fitted on them): only one the capture
        would take too (within the motor's limits, near our clock and not FUTURE_S ahead of it; an implausible one is
        counted under bad.motor_state), and not from a motor that does not know its pan (disconnected, absent)."""
        if st is None or st.status in ("disconnected", "absent"):
            return
        now = time.time_ns()
        why = motor_state_implausible(st, self.settings.actuator.motor, now, self.limits.max_skew_s)
        if why is None and st.t_ns > now + FUTURE_S * 1e9:  # (it would push the true ones out of the lag's second)
            why = f"state {(st.t_ns - now) / 1e9:+.3g} s ahead of our clock"
        if why is not None:
            self.health.reject("motor_state", MessageError(why))
            return
        with self.lock:
            self.gatherer.controller.motor(st.t_ns / 1e9, st.pan_rad)

    def run(self, stop: session.Stop) -> None:
        """The loop, until stop: what arrived, the deadlines, the membership evidence, the status, the summary."""
        next_report = time.monotonic() + REPORT_S
        every = self.settings.reducer.summary_s
        next_summary, seen = time.monotonic() + every, (0, 0, 0)
        while not stop.is_set():
            with self.lock:
                awaiting = self.gatherer.awaiting()
            batch = self.inbox.take("correlation" if awaiting else "frame")
            if stop.is_set():
                break
            while (smp := self.states.try_recv()) is not None:  # (the Node's empty wake comes after the stop)
                self.motor_state(self.presence.on_state(smp.payload.to_bytes()))
            if batch:
                self.handle(batch)
            with self.lock:
                self.gatherer.expire()
                due = self.gatherer.next_deadline()
            now = time.monotonic()
            if due is not None:  # woken at the next deadline (by the alarm, unless a message comes first)
                self.alarm.set(max(now + POLL_S, due))
            if now >= next_report:
                self.pub_workers.put(self.workers_report())
                next_report = now + REPORT_S
            self.node.tick(now)
            if now >= next_summary:
                counts = self.counts()
                if counts[0] > seen[0]:
                    with self.lock:
                        log.info("%s", summary(every, *(a - b for a, b in zip(counts, seen)), self.last[0],
                                               self.window.take()))
                seen, next_summary = counts, now + every


def main(settings, conf: zenoh.Config, stop: session.Stop, deadline_ms: float | None = None) -> int:
    warm_up(settings.network, settings.control)
    deadline = (deadline_ms if deadline_ms is not None else settings.reducer.deadline_ms) / 1000.0
    reducer = Reducer(settings, deadline)
    with Node("reducer", settings.rig, conf, stop, log=log, fields=reducer.fields) as node:
        reducer.open(node)
        reducer.run(stop)
    return 0


def settings_from_args(args: argparse.Namespace):
    st = load(args.config)
    return dataclasses.replace(st, **({"rig": args.rig} if args.rig else {}))


def run(args: argparse.Namespace) -> int:
    settings = settings_from_args(args)
    stop = session.Stop()
    return main(settings, session.config_from_args(args), stop, args.deadline_ms)
