"""`vergence capture --source SPEC [--rate HZ] [--frames N]`: reads stereo frames and publishes them.

Publishes on vergence/<rig>/frame a messages.Frame per image pair: only what layer 1 needs (the master fovea and
the slave band with their Sobel margins, the master band for the left-right check), the exposure times of both
images and the read time (ExposureClock: the source's stamps where believable, else the read time less [camera]
latency_s), the slave's pan at its exposure (PanLookup: the messages.MotorState history of vergence/<rig>/motor_state
interpolated there; the source's start pan before any; always the start pan, 0, for a source whose images do not
move with the motor: a still pair, videos; pan_stale where the history cannot tell), and the shard plan made from
the workers' liveliness tokens vergence/<rig>/alive/worker/* at that moment, minus the workers the reducer's
evidence (vergence/<rig>/workers) shows silent (vergence.stages.frames.Roster: a token is an invitation, not a
guarantee).
A motor_state whose pan is outside the motor's limits or whose time is off our clock by more than [limits]
max_skew_s is counted and ignored. With no worker alive, frames are counted (no_workers) and not published. A
downscaled messages.Preview goes on vergence/<rig>/preview at [capture] preview_hz. With [network] max_window > 0 the
window grows by 8 px while the decisions (vergence/<rig>/decision) are not confident (the dynamic window), and
with clip_fallback, where the master was clipped, the same windows follow with it unclipped (WindowControl).
A messages.Fixate on vergence/<rig>/fixate moves the fovea to its (x, y) from the next frame on; a request
that is not a valid Fixate, or where the fovea would not fit the image, is rejected (counted under bad.fixate
and in the fixate_rejected counter, its reason logged and, for a well-formed request, named with its t_ns in the
status's fixate_rejection) and nothing moves.
Counters go out as JSON on vergence/<rig>/status/capture/<id> every second and at exit, with the rate
published and the rate the reducer completed (published_hz, decided_hz; a warning when the pipeline
holds less than half), and what each camera clips of the fovea's rows where the other sees texture (clipped:
retina.clipped_share of the latest pair; a warning, once per camera, over retina.CLIP_WARN).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import logging
import math
import sys
import threading
import time

import cv2
import zenoh

from vergence.wire import keys
from vergence.network import retina
from vergence.config import load
from vergence.stages.frames import Roster, WindowControl, make_frame, plan_shards
from vergence.wire.messages import Command, MessageError, MotorState, Preview, Decision
from vergence.motors.simulated import Replica, SimMotor
from vergence.io.lens import band_rows, principal_points, undistorters
from vergence.io.sources import SourceError, open_source
from vergence.wire.status import decode_report
from vergence.head.timing import PanHistory

from services.runtime import session
from services.runtime.args import number, pixel, whole
from services.runtime.node import STATUS_S, Node
from services.pipeline.fovea import Fovea
from services.pipeline.capture_time import ExposureClock, PanLookup, Pacer, motor_state_implausible, remember

log = logging.getLogger("vergence.capture")


def configure(p: argparse.ArgumentParser) -> None:
    session.add_options(p)
    p.add_argument("--source", default=None, metavar="SPEC",
                   help="files:LEFT,RIGHT | video:LEFT,RIGHT | camera:0,1 | sim[:key=value:...] | ros2:LEFT,RIGHT "
                        "(default: settings, else the demo: a target moving in depth; sim: a still scene)")
    p.add_argument("--rate", type=number(0, 1000, note="0: as fast as possible"), default=None, metavar="HZ",
                   help="frames per second, 0 = as fast as possible (default: settings, 30)")
    p.add_argument("--frames", type=whole(0, None), default=0, metavar="N",
                   help="exit after publishing N frames (0: never)")
    p.add_argument("--at", type=pixel, default=None, metavar="X,Y", help="fovea centre (default: image centre)")
    p.add_argument("--focal", type=number(0, 100_000), default=None,
                   help="focal length in pixels (default: the source's)")


class Rates:
    """The rate the pipeline holds, for each status: frames published here against frames the reducer
    completed (the `complete` of its latest report); one warning when it holds less than half."""

    def __init__(self, period: float = STATUS_S):
        self.period = period
        self.published = 0
        self.decided = 0
        self._then = (0, 0)  # both at the previous status
        self._warned = False

    def fields(self) -> dict:
        sent, done = self.published - self._then[0], self.decided - self._then[1]
        self._then = (self.published, self.decided)
        # (the reducer's count lags by up to its report period: never more than was published; a negative
        # difference is a new reducer)
        held = min(done, sent) / self.period if done >= 0 else None
        if held is not None and sent >= 20 and done < 0.5 * sent and not self._warned:
            self._warned = True
            log.warning("the pipeline completes %.0f of the %.0f frames/s published: lower the rate (--rate) or "
                        "add workers", held, sent / self.period)
        return dict(published_hz=sent / self.period, decided_hz=held)


class Capture:
    """One capture process: the source, what moves the frames (the fovea, the windows, the workers' roster, the
    motor's history), the callbacks that feed them, and the loop that reads, plans and publishes (run)."""

    def __init__(self, settings, source, focal: float, at: tuple[int, int], conf: zenoh.Config, stop: session.Stop,
                 principal: tuple = ((-1.0, -1.0), (-1.0, -1.0)), lenses: tuple = (None, None)):
        self.settings, self.source, self.focal, self.stop = settings, source, focal, stop
        self.principal = principal  # (master's, slave's) (cx, cy) for the frames; -1: the image centre
        self.lenses = lenses  # (master's, slave's) Undistorter (None: a pinhole camera)
        self.rig, self.cs, self.params, self.limits = settings.rig, settings.capture, settings.network, settings.limits
        self.wd, self.ht = source.size
        # the master's pan and the common tilt (the simulated rig aims its master; a real master is fixed: 0, 0)
        self.master_pan, self.tilt = getattr(source, "master_pan_rad", 0.0), getattr(source, "tilt_rad", 0.0)
        self.windows = WindowControl(self.params)
        lim = self.limits
        self.members = Roster(lim.miss_s, lim.probation_s, lim.miss_frames)
        hz = settings.actuator.state_hz
        self.history = PanHistory(max_gap_s=max(0.1, 3.0 / hz if hz > 0 else 0.1))
        self.history_lock = threading.Condition()  # notified on each motor state (PanLookup.ready waits on it)
        # the sim motor's replica, for a source that renders the slave (its states tell whether it is the sim)
        self.renders = getattr(source, "renders", False)  # (the ros2 source is not a vergence.io.sources.Source)
        lies = getattr(source, "motor_faults", None)  # (the sim source's stall= and encoder_noise=)
        noise, stall = (lies.encoder_noise or 0.0, lies.stall) if lies is not None else (0.0, None)
        self.replica = Replica(settings.actuator.motor, noise, stall) if self.renders else None
        if lies:
            log.info("the sim source's %s lie about the motor: the sim actuator takes them (`vergence actuator "
                     "--faults %s`; `vergence up` passes them on)", lies.spec(), lies.spec())
        if self.renders:  # the sim camera sits on the shaft, which turns direction x (the pan reported - offset)
            source.shaft = settings.actuator.motor.to_motor
        rate = self.cs.rate_hz
        self.clock = ExposureClock(settings.camera.timing(), 1.0 / rate if rate > 0 else 0.0)
        self.rates = Rates()
        self.plan: list = []
        self.plan_key = None
        self.fid = 0
        self.unclipped: dict[int, None] = {}  # the recent frames published with the master unclipped (clip_fallback)
        self.pair: list = []  # the latest (master, slave, fovea row, window), for the clipped shares of the status
        self.warned: set[str] = set()
        self.node = Node("capture", self.rig, conf, stop, log=log, fields=self.fields, final_fields=lambda: dict(
            window=self.windows.window, workers=len(self.plan)))
        self.health = self.node.health
        self.fovea = Fovea(*at, (self.ht, self.wd), self.params, self.health)
        self.period = 1.0 / rate if rate > 0 else 0.0
        self.preview_period = 1.0 / self.cs.preview_hz if self.cs.preview_hz > 0 else 0.0
        self.pw = min(self.cs.preview_width, self.wd) if self.cs.preview_width > 0 else self.wd
        self.ph = max(1, round(self.ht * self.pw / self.wd))

    # -- the status ---------------------------------------------------------------------------------------------

    def clipped(self) -> dict:
        """retina.clipped_share at the fovea's rows; one warning per camera over CLIP_WARN."""
        if not self.pair:
            return {}
        try:
            master, slave, y, w = self.pair  # a renderer's pair has only the rows of its fovea and window
            out = retina.clipped_share(master, slave, y, w, self.params.vsearch)
        except ValueError as e:  # a figure of the status never stops the capture
            if "error" not in self.warned:
                self.warned.add("error")
                log.warning("no clipped shares in the status: %s", e)
            return {}
        for cam, share in out.items():
            if share >= retina.CLIP_WARN and cam not in self.warned:
                self.warned.add(cam)
                log.warning("the %s camera shows %.0f %% of the fovea's rows black or saturated where the other "
                            "camera sees texture: that texture is lost to the match; set both cameras' exposure "
                            "and gain alike (README, Two real cameras)", cam, 100 * share)
        return {cam: round(share, 3) for cam, share in out.items()}

    def fields(self) -> dict:
        source = self.source
        return dict(window=self.windows.window, workers=len(self.plan), excluded=self.members.excluded(),
                    **self.rates.fields(), roster=dict(self.members.counters), clipped=self.clipped(),
                    **self.fovea.fields(), **self.clock.fields(),
                    **({"source": source.status()} if hasattr(source, "status") else {}),
                    **({"replica": dict(trusted=self.replica.trusted, mismatches=self.replica.mismatches,
                                    unheard=self.replica.unheard)}
                       if self.replica is not None else {}))

    # -- the callbacks (zenoh's threads) ------------------------------------------------------------------------

    def on_motor(self, sample) -> None:
        try:
            st = MotorState.from_bytes(sample.payload.to_bytes())
            why = motor_state_implausible(st, self.settings.actuator.motor, time.time_ns(), self.limits.max_skew_s)
            if why is not None:
                raise MessageError(why)
            with self.history_lock:
                if not remember(self.history, st, time.time_ns()):
                    self.health.count("motor_states_away")  # disconnected or absent: its pan is not known
                    return
                if self.replica is not None:
                    self.follow(st)
            self.health.count("motor_states")
        except MessageError as e:
            self.health.reject("motor_state", e)

    def follow(self, st: MotorState) -> None:
        """A plausible motor state into the replica (under the history's lock): only the sim motor's."""
        rep = self.replica
        if st.driver != SimMotor.name:  # another motor's states say nothing of the sim's (nor distrust it)
            return
        before = rep.mismatches
        rep.observe(st.t_ns, st.pan_rad, st.goal_rad, torque=st.status != "stopped")
        rep.counted(st.commands, time.monotonic_ns())
        self.history_lock.notify_all()
        if rep.mismatches > before:
            self.health.count("replica_mismatch")
            if rep.mismatches == 1:
                log.warning("the sim motor's reading is more than a tick off the capture's replica of it "
                            "(different [actuator.motor] settings for capture and actuator?): the frames wait "
                            "for the motor's reports until it rests on its goal")

    def on_command(self, sample) -> None:
        """A command on the rig's key (the reducer's, or a client's): its goal is not in the replica until the
        motor's state counts it (PanLookup.ready). Only a command that decodes, for this rig, counts, and only
        while the replica is trusted (another driver's motor never counts here: nothing would answer it)."""
        try:
            cmd = Command.from_bytes(sample.payload.to_bytes())
            if cmd.rig != self.rig:
                raise MessageError(f"command for rig {cmd.rig!r}")
        except MessageError as e:
            self.health.reject("command", e)
            return
        with self.history_lock:
            m, now = self.settings.actuator.motor, time.time_ns()
            if -(m.max_age_s or math.inf) <= (cmd.t_capture_ns - now) / 1e9 <= (m.max_skew_s or math.inf):
                # a stall's time 0: the first plausible command's exposure, as the actuator's Safety takes it
                self.replica.first_exposure(min(cmd.t_capture_ns, now))
            if self.replica.trusted:
                self.replica.commanded(time.monotonic_ns())

    def on_token(self, sample) -> None:
        wid = keys.parse(str(sample.key_expr)).ident
        self.members.token(wid, sample.kind == zenoh.SampleKind.PUT)
        log.info("workers: %s", sorted(self.members.tokens))

    def on_report(self, sample) -> None:
        try:
            rep = decode_report(sample.payload.to_bytes())
        except MessageError as e:
            self.health.reject("workers", e)
            return
        for wid in self.members.on_report(rep):
            log.warning("worker %s left the plan: its shards stopped arriving at the reducer", wid)
        if rep.complete is not None:
            self.rates.decided = rep.complete

    def on_decision(self, sample) -> None:
        try:
            v = Decision.from_bytes(sample.payload.to_bytes())
        except MessageError as e:
            self.health.reject("decision", e)
            return
        self.windows.update(v.window, v.confident, v.frame not in self.unclipped)

    # -- the loop -----------------------------------------------------------------------------------------------

    def open(self) -> None:
        """In the Node's block: the publishers and subscriptions, the warm-up, then the liveliness token."""
        node, rig = self.node, self.rig
        self.pub_frame = node.publisher(keys.frame(rig), express=True)
        self.pub_preview = node.publisher(keys.preview(rig))
        node.subscriber(keys.motor_state(rig), self.on_motor)
        if self.replica is not None:
            node.subscriber(keys.command(rig), self.on_command)
        node.subscriber(keys.workers(rig), self.on_report)
        node.liveliness_subscriber(keys.alives(rig, "worker"), self.on_token, history=True)
        if len(self.windows.states) > 1:  # a dynamic window (max_window, clip_fallback): the decisions drive it
            node.subscriber(keys.decision(rig), self.on_decision)
        node.subscriber(keys.fixate(rig), lambda sm: self.fovea.on_fixate(sm.payload.to_bytes()))
        retina.warm_up()
        node.ready()
        pp = " ".join("(" + ", ".join("centre" if v < 0 else f"{v:g}" for v in p) + ")" for p in self.principal)
        lens = " ".join("pinhole" if u is None else u.lens.model for u in self.lenses)
        log.info("capture %s: %s (%d x %d, f=%.1f px, principal points %s, lenses %s) at %s Hz on %s", node.ident,
                 self.cs.source, self.wd, self.ht, self.focal, pp, lens,
                 self.cs.rate_hz or "max", keys.frame(rig))
        if not self.source.follows_pan:
            log.info("the source's images do not move with the slave motor: every frame carries the pan they were "
                     "taken at, %.1f deg, so the commands hold the motor at one pan instead of winding it to a limit "
                     "(the loop closes with camera and sim sources)",
                     math.degrees(self.source.start_pan_rad))

    def run(self, frames: int = 0) -> int:
        """Read, plan and publish until the stop or `frames` published (0: never); 2 when the source fails."""
        stop = self.stop
        pacer = Pacer(self.period) if self.period else None
        self.next_preview = time.monotonic()
        while not stop.is_set() and (frames <= 0 or self.rates.published < frames):
            if pacer is not None:
                missed = pacer.wait(stop)  # a read a period late is made up at once
                if stop.is_set():
                    break
                if missed:
                    self.health.count("periods_missed", missed)
            pan_at = PanLookup(self.history, self.history_lock, self.source, self.replica)
            at = self.source.fovea = self.fovea.at()  # this pair's fovea (a simulator's truth is for it)
            window = self.windows.state  # this pair's window (a decision may change it meanwhile)
            # the rows its frame reads (a renderer renders only these): the window's half, the vertical search and
            # Sobel's margin around the fovea's
            band = band_rows(at[1], window[0], self.params.vsearch, self.ht)
            self.source.rows = self._source_rows(band)
            try:
                master, slave = self.source.read(pan_at)
            except SourceError as e:
                if getattr(e, "transient", False):  # a live stream with no new image yet (ros2): try again
                    self.node.tick()
                    continue
                print(f"vergence capture: {e}", file=sys.stderr)
                return 2
            if self.lenses != (None, None):
                master, slave = (self._undistort(img, und, band) for img, und in zip((master, slave), self.lenses))
            self.step(master, slave, pan_at, at, window)
        return 0

    def _source_rows(self, band: tuple[int, int]) -> tuple[int, int]:
        """The rows to read of the next pair: the frame's band, and with a lens to undistort the rows it reads."""
        spans = [band] + [und.source_rows(*band) for und in self.lenses if und is not None]
        return min(a for a, _ in spans), max(b for _, b in spans)

    @staticmethod
    def _undistort(img, und, band: tuple[int, int]):
        """The image with the lens removed from the band's rows (the others as read: the digest of a frozen camera's
        repeated image stays the same)."""
        if und is None:
            return img
        out = img.copy()
        out[band[0]:band[1]] = und.rows(img, *band)
        return out

    def step(self, master, slave, pan_at: PanLookup, at: tuple[int, int], window: tuple[int, bool]) -> None:
        """One pair read: stamped, planned, published (when some worker is alive), previewed; the status."""
        t_read = time.time_ns()
        t_ns, t_slave = self.clock.stamp(t_read, self.source.exposure_ns)
        p_now, stale, guessed = pan_at.frame(t_slave)
        if stale:
            self.health.count("pan_unknown")
        if pan_at.waited:
            self.health.count("command_waits")
        w, clip = window
        self.pair[:] = master, slave, at[1], w
        changes, ids = self.members.snapshot()
        if (changes, w) != self.plan_key:
            self.plan_key = (changes, w)
            self.plan = plan_shards(ids, self.wd - w + 1)
        self.fid += 1
        self.health.count("frames")
        if self.plan and not self.pub_frame.matching_status.matching:
            # workers are alive but the router has not yet told this session about their
            # subscriptions (just after start): a frame now would go nowhere
            self.health.count("unrouted")
        elif self.plan:
            if not self.publish(master, slave, w, clip, t_ns, t_slave, t_read, p_now, (stale, guessed), at):
                return  # a grown window that no longer fits: back to the base one, and the next pair
        else:
            self.health.count("no_workers")
        now = time.monotonic()
        if self.preview_period and now >= self.next_preview:
            self.next_preview = now + self.preview_period
            self.preview(master, slave, t_ns, p_now)
        self.node.tick(now)

    def publish(self, master, slave, w: int, clip: bool, t_ns: int, t_slave: int, t_read: int, p_now: float,
                known: tuple[bool, bool], at: tuple[int, int]) -> bool:
        """The frame of this pair (known: its pan_stale, pan_guessed), published; False when the window no longer
        fits (reset to the base one)."""
        windows, fid = self.windows, self.fid
        clipped: list[bool] = []
        try:
            frame = make_frame(master, slave, rig=self.rig, frame=fid, pan_rad=p_now, focal_px=self.focal,
                               params=self.params, plan=self.plan, at=at, window=w,
                               t_capture_ns=t_ns, clip=clip, clipped=clipped)
            frame.master_pan_rad, frame.tilt_rad = self.master_pan, self.tilt
            frame.skew_ns, frame.t_read_ns, (frame.pan_stale, frame.pan_guessed) = t_slave - t_ns, t_read, known
            frame.follows = self.source.follows_pan
            (frame.cx, frame.cy), (frame.slave_cx, frame.slave_cy) = self.principal
        except retina.BorderError:
            windows.reset()
            return False
        if len(windows.states) > len(windows.sizes):  # clip_fallback: the decision's state is ours
            if clip:
                if not windows.was_clipped:  # once set, it stays until a confident decision: no re-check
                    windows.clipped(clipped[0])  # retina.master_clipped, as make_frame found it
            else:
                self.unclipped[fid] = None
                while len(self.unclipped) > 1024:
                    del self.unclipped[next(iter(self.unclipped))]
        frame.truth_pan_rad = self.source.truth_pan_rad  # the simulator's ground truth at the fovea, else None
        frame.frame_id = getattr(self.source, "frame_id", "")  # the master image's own frame id (ros2), else ""
        self.pub_frame.put(frame.to_bytes())
        self.rates.published += 1
        self.health.count("published")
        return True

    def preview(self, master, slave, t_ns: int, p_now: float) -> None:
        pw, ph = self.pw, self.ph
        if self.renders:  # it rendered the band only: the whole views at the preview's size
            m, sl = self.source.preview(pw, ph)
        else:
            m = cv2.resize(master, (pw, ph), interpolation=cv2.INTER_AREA)
            sl = cv2.resize(slave, (pw, ph), interpolation=cv2.INTER_AREA)
        self.pub_preview.put(Preview(rig=self.rig, frame=self.fid, t_capture_ns=t_ns, width=pw, height=ph,
                                     scale=pw / self.wd, master=m.tobytes(), slave=sl.tobytes(), pan_rad=p_now,
                                     truth_pan_rad=self.source.truth_pan_rad).to_bytes())


def main(settings, conf: zenoh.Config, stop: session.Stop, *, frames: int = 0,
         at: tuple[int, int] | None = None) -> int:
    cs, params, geo = settings.capture, settings.network, settings.geometry
    try:
        source = open_source(cs.source, geo.master or cs.master)
    except SourceError as e:
        print(f"vergence capture: {e}", file=sys.stderr)
        return 2
    wd, ht = source.size
    focal = geo.focal_px or cs.focal_px or source.focal_px or 0.8 * wd
    if getattr(source, "gimbal", geo.gimbal) != geo.gimbal:
        log.warning("the source's gimbal is %s, [rig] gimbal %s: the reducer's depth assumes the latter",
                    source.gimbal, geo.gimbal)
    x, y = at if at is not None else (wd // 2, ht // 2)
    try:
        retina.check_point((ht, wd), x, y, params.window, params.vsearch)
        principal = principal_points(settings.camera, getattr(source, "principal", None), (wd, ht))
        lenses = undistorters(settings.camera, getattr(source, "lenses", None), focal, principal, (wd, ht))
    except (retina.BorderError, ValueError) as e:
        print(f"vergence capture: {e}", file=sys.stderr)
        source.close()
        return 2
    capture = Capture(settings, source, focal, (x, y), conf, stop, principal, lenses)
    source.on_reject = capture.node.health.flag  # a source's own bad images (ros2) shown as promptly as ours
    with contextlib.closing(source), capture.node:
        capture.open()
        return capture.run(frames)


def settings_from_args(args: argparse.Namespace):
    st = load(args.config)
    cs = st.capture
    changes = {k: v for k, v in (("source", args.source), ("rate_hz", args.rate), ("focal_px", args.focal))
               if v is not None}
    cs = dataclasses.replace(cs, **changes)
    return dataclasses.replace(st, capture=cs, **({"rig": args.rig} if args.rig else {}))


def run(args: argparse.Namespace) -> int:
    settings = settings_from_args(args)
    stop = session.Stop()
    return main(settings, session.config_from_args(args), stop, frames=args.frames, at=args.at)
