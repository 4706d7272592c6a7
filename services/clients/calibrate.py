"""`vergence calibrate [--distance Z [--at X,Y]] ... [--write FILE] [--amplitude DEG] [--hold-s S] [--wait S]`:
measure the running head on itself (issue #36).

As `vergence latency` does, it holds the reducer's commands, steps the slave through known pans about its present
one (17 levels within +-amplitude and the motor's soft limits, each held hold-s), records the decisions and the
motor's states, then puts the slave back and releases the hold. From them (vergence.head.calibrate.fit_head):
- the direction: the image moves the way the settings say, or it says to flip [actuator.motor] direction;
- the focal length in pixels (the slope of the offsets against the pan), with its sigma;
- the camera's latency (vergence.head.latency);
- with --distance Z (metres along the master's optical axis, through the fovea, to the point it fixates: a
  target the user measured), the pan zero's error, written as [actuator.motor] offset_deg (the one the actuator
  applies now, from its motor_state, plus the correction); --distance Z --at X,Y repeated: the fovea moved to each
  point (and back when done), and points at two distances or more give the baseline too ([rig] baseline_m).
It prints each figure with its uncertainty and the TOML lines; --write FILE merges them into FILE (created if
missing; comments and every other key kept) for `vergence up --config FILE`. Exit 1 when no rig answers, 2 when
the scene or the motor does not allow the measurement (it says why and what to do).
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import threading
import time

import numpy as np

from vergence.config import ConfigError, load
from vergence.head.calibrate import (AXIS_SIGMA_M, BIAS_PX, CalibrationError, calibration_plan, fit_head,
                                     merge_settings, pan_for_depth, settings_text, solve_head)
from vergence.head.depth import depth_from_pans
from vergence.wire import keys
from vergence.wire.messages import Fixate, Frame, MessageError

from services.clients.latency import Recorder, _wait, record
from services.runtime import session
from services.runtime.args import number
from services.runtime.node import Node

log = logging.getLogger("vergence.calibrate")

LOOK_S = 0.5  # the decisions looked at before moving: is anything confident?


def configure(p: argparse.ArgumentParser) -> None:
    session.add_options(p)
    p.add_argument("--distance", type=number(0, 1000, lo_open=True), action="append", default=None, metavar="Z",
                   help="metres along the master's optical axis (through the fovea) to the point the head fixates, "
                        "measured by you: gives the pan zero ([actuator.motor] offset_deg); repeated with --at, "
                        "points at two distances or more give the baseline too ([rig] baseline_m)")
    p.add_argument("--at", type=pixel, action="append", default=None, metavar="X,Y",
                   help="the master pixel of each --distance's point, in their order (default: the fovea where it is)")
    p.add_argument("--write", default=None, metavar="FILE",
                   help="merge the settings found into this TOML file (created if missing; every other key kept)")
    p.add_argument("--amplitude", type=number(0, 5, lo_open=True), default=2.0, metavar="DEG",
                   help="the steps' reach about the present pan, degrees (default 2, at most 5)")
    p.add_argument("--hold-s", type=number(0.1, 5), default=0.3, metavar="S",
                   help="how long each step is held (default 0.3)")
    p.add_argument("--wait", type=number(0, 3600, lo_open=True), default=5.0, metavar="S",
                   help="how long to wait for the rig's decisions and motor states (default 5)")


def pixel(text: str) -> tuple[int, int]:
    try:
        x, y = (int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: want X,Y (master pixels, whole numbers)") from None
    return x, y


class FrameKeeper:
    """The latest frame's bytes, decoded once at the end (its size, focal length, principal points, master pan)."""

    def __init__(self):
        self.lock = threading.Lock()
        self.payload: bytes | None = None

    def on_frame(self, sample) -> None:
        with self.lock:
            self.payload = sample.payload.to_bytes()

    def latest(self) -> Frame | None:
        with self.lock:
            payload = self.payload
        if payload is None:
            return None
        try:
            return Frame.from_bytes(payload)
        except MessageError as e:
            raise CalibrationError(f"the rig's frames are not readable ({e})") from None


def _ready(rec: Recorder) -> bool:
    """True when the decisions of the last LOOK_S include confident ones; else it prints why not to move."""
    _wait(lambda: len(rec.snapshot()[0]) >= 5, 2 * LOOK_S)
    time.sleep(LOOK_S)
    decisions = rec.snapshot()[0][-60:]
    if any(d.confident for d in decisions):
        return True
    tex = max((d.texture for d in decisions), default=0.0)
    print(f"vergence calibrate: none of the last {len(decisions)} decisions is confident (the fovea's texture "
          f"{tex:.1f}): point the master at a still, textured scene (a printed pattern or a photo) and the slave "
          "near it (vergence fixate moves the fovea), then calibrate again", file=sys.stderr)
    return False


def main(rig: str, conf, distances: list[float] | None, write: str | None, amplitude_deg: float, hold_s: float,
         wait: float, settings, ats: list[tuple[int, int]] | None = None) -> int:
    distances, ats = distances or [], ats or []
    if ats and len(ats) != len(distances):
        print(f"vergence calibrate: {len(ats)} --at for {len(distances)} --distance: give one --at per --distance "
              "(or none: the fovea where it is)", file=sys.stderr)
        return 2
    rec, frames = Recorder(), FrameKeeper()
    runs = []  # (fovea asked for or None, distance or None, decisions, states, t_start)
    try:
        with Node("calibrate", rig, conf, session.Stop(install=False), log=log, timeout=wait, quiet=True) as node:
            node.subscriber(keys.frame(rig), frames.on_frame)
            node.subscriber(keys.decision(rig), rec.on_decision)
            node.subscriber(keys.motor_state(rig), rec.on_state)
            home = None  # the fovea before calibrate moved it (--at), where it goes back
            try:
                for z, at in zip(distances or [None], ats or [None] * max(1, len(distances))):
                    if at is not None:
                        if home is None:
                            home = _home(rec, wait)
                        if not _fixate(node, rec, rig, at, wait):
                            return 2
                    got = record(node, rec, rig, amplitude_deg, hold_s, wait, planner=calibration_plan,
                                 name="calibrate", ready=lambda: _ready(rec), subscribe=False)
                    if isinstance(got, int):
                        return got
                    runs.append((at, z) + got)
            finally:
                if home is not None:
                    _fixate(node, rec, rig, home, 1.0)
    except ConnectionError as e:
        print(f"vergence calibrate: {e}", file=sys.stderr)
        return 1
    try:
        frame = frames.latest()
        points = []  # (fit, fovea, distance) of each run
        for at, z, decisions, states, t_start in runs:
            used = [d for d in decisions if d.confident and d.t_capture_ns >= t_start and (at is None or
                                                                                      (d.x, d.y) == at)]
            xs = sorted((d.x, d.y) for d in used if d.x >= 0)
            fovea = xs[len(xs) // 2] if xs else None
            u = fovea[0] - frame.slave_principal[0] if frame is not None and fovea is not None else 0.0
            fit = fit_head([(d.t_capture_ns + d.skew_ns, d.t_read_ns or d.t_capture_ns, d.offset_px) for d in used],
                           [(m.t_ns, m.pan_rad) for m in states if m.t_ns >= t_start - 10**9],
                           [t for t in rec.sent if t >= t_start], u_px=u,
                           focal_px=frame.focal_px if frame is not None else settings.geometry.focal_px)
            points.append((fit, fovea, z))
        values, lines = report(points, runs[-1][3], frame, settings)
    except CalibrationError as e:
        print(f"vergence calibrate: {e}", file=sys.stderr)
        return 2
    print("\n".join(lines))
    print(settings_text(values))
    if write:
        try:
            merge_settings(write, values)
            load(write)
        except (CalibrationError, ConfigError, OSError) as e:
            print(f"vergence calibrate: --write {write}: {e}", file=sys.stderr)
            return 2
        print(f"written to {write}: restart the head with `vergence up --config {write}`")
    return 0


def _home(rec: Recorder, wait: float) -> tuple[int, int] | None:
    """Where the fovea is: the newest decision's (x, y), waiting for one up to `wait` s."""
    _wait(lambda: rec.snapshot()[0], wait)
    d = rec.snapshot()[0]
    return (d[-1].x, d[-1].y) if d and d[-1].x >= 0 else None


def _fixate(node: Node, rec: Recorder, rig: str, at: tuple[int, int], wait: float) -> bool:
    """The fovea moved to `at` (messages.Fixate), and a decision made there within `wait` s; else it says why."""
    t = time.time_ns()
    node.session.put(keys.fixate(rig), Fixate(x=at[0], y=at[1], t_ns=t, source="vergence calibrate").to_bytes())
    if _wait(lambda: any((d.x, d.y) == at and d.t_capture_ns > t for d in rec.snapshot()[0][-30:]), wait):
        return True
    print(f"vergence calibrate: no decision at {at[0]},{at[1]} within {wait:g} s of asking the fovea there (outside "
          "the image, too near its border, or no capture listening on the fixate key)", file=sys.stderr)
    return False


def _focal_line(f: float, fit, told: float | None) -> str:
    return (f"focal length: {f:.1f} +- {fit.focal_sigma_px:.1f} px"
            + (f" (the frames say {told:g}: {100 * (f / told - 1):+.1f} %)" if told else ""))


def _geometry(frame, settings) -> dict:
    return dict(master_pan_rad=frame.master_pan_rad, tilt_rad=frame.tilt_rad, gimbal=settings.geometry.gimbal,
                master=settings.geometry.master or settings.capture.master)


def _points(points, frame, f: float, b: float, d: float, geo: dict):
    """([(distance, p0, sigma, geometry)] of the points with a distance, [slope_focal's (focal, sigma, distance,
    master_u, slave_u)] of every point: one without a distance at the one its pan tells with these settings)."""
    (cx, cy), (sx, sy) = frame.principal, frame.slave_principal
    obs, slopes = [], []
    for p_fit, fovea, z in points:
        x, y = fovea if fovea is not None else (frame.width // 2, frame.height // 2)
        kw = dict(master_px=(x - cx, y - cy), slave_px=(x - sx, y - sy), **geo)
        if z is not None:
            obs.append((z, p_fit.pan0_rad, max(p_fit.pan0_sigma_rad, math.atan(BIAS_PX / f)), kw))
        else:
            z = depth_from_pans(kw.pop("master_pan_rad"), p_fit.pan0_rad, b, f, axis_m=d, **kw)
        if math.isfinite(z) and z > 0:
            slopes.append((p_fit.focal_px, p_fit.focal_sigma_px, z, x - cx, x - sx))
    return obs, slopes


def report(points, states, frame, settings):
    """({table: {key: value}} to write, lines to print) of the runs' fits (points: [(HeadFit, fovea, distance or
    None)]); CalibrationError where the distances cannot be used. frame: the rig's latest messages.Frame."""
    fit = points[0][0]
    told = frame.focal_px if frame is not None else settings.geometry.focal_px
    f = float(np.mean([p[0].focal_px for p in points]))
    b0, d0 = settings.geometry.baseline_m, settings.geometry.pan_axis_m
    geo = _geometry(frame, settings) if frame is not None else {}
    obs, slopes = _points(points, frame, f, b0, d0, geo) if frame is not None else ([], [])
    master = geo.get("master", "left")
    if not obs and slopes:  # a pan axis the settings tell: its parallax out of the slopes
        f = solve_head([], slopes, f, b0, d0, master=master).focal_px
    lines = [f"direction: the image follows the motor ({fit.n} decisions, r2 {fit.r2:.5f}, residual "
             f"{fit.rms_px:.3f} px)", _focal_line(f, fit, told),
             f"camera latency: {fit.latency.latency_s * 1e3:.1f} +- {fit.latency.sigma_s * 1e3:.1f} ms "
             f"(the frames' stamps {fit.latency.delta_s * 1e3:+.1f} ms off)"]
    values: dict[str, dict[str, float]] = {"rig": {"focal_px": round(f, 2)}}
    if abs(fit.latency.delta_s) * 1e3 >= max(2.0, 2 * fit.latency.sigma_s * 1e3):
        values["camera"] = {"latency_s": round(max(0.0, float(fit.latency.latency_s)), 4)}
    if not any(p[2] is not None for p in points):
        lines.append("pan zero: not measured (give --distance Z, metres to the fixated point along the master's "
                     "optical axis)")
        return values, lines
    if frame is None:
        raise CalibrationError("no frame seen on the rig: the image size and the master's pan are unknown "
                               "(is the capture running?)")
    distances = len({round(z, 3) for z, *_ in obs})
    distinct = distances >= 2
    axis = solve_head(obs, slopes, f, b0, d0, fit_baseline=True, fit_axis=True, master=master) \
        if distances >= 3 else None
    told_axis = axis is not None and axis.axis_sigma_m <= AXIS_SIGMA_M  # the points tell the pan axis too
    got = axis if told_axis else solve_head(obs, slopes, f, b0, d0, fit_baseline=distinct, master=master)
    zero, b, d, f = got.zero_rad, got.baseline_m, got.axis_m, got.focal_px
    lines[1], values["rig"]["focal_px"] = _focal_line(f, fit, told), round(f, 2)
    now = next((m.offset_deg for m in reversed(states)), 0.0)
    offset = now + math.degrees(zero)
    for z, p0, sig, kw in obs:
        want = pan_for_depth(z, b, f, axis_m=d, **kw)
        lines.append(f"at {z:g} m: the slave sees the point at {math.degrees(p0):+.4f} deg as the motor reports it, "
                     f"where it should at {math.degrees(want):+.4f} deg (+- {math.degrees(sig):.4f})")
    sig0 = math.sqrt(sum(o[2] ** 2 for o in obs)) / len(obs)
    lines.append(f"pan zero: off by {math.degrees(zero):+.4f} +- {math.degrees(sig0):.4f} deg (offset_deg {now:+.4f} "
                 f"now -> {offset:+.4f})")
    values["actuator.motor"] = {"offset_deg": round(float(offset), 5)}
    if distinct:
        lines.append(f"baseline: {b:.4f} +- {got.baseline_sigma_m:.4f} m (the settings say {b0:g})")
        values["rig"]["baseline_m"] = round(float(b), 5)
    elif len(obs) == 1:
        lines.append(f"baseline: the settings' {b0:g} m (points at two distances or more measure it)")
    if told_axis:
        lines.append(f"pan axis: {d * 1e3:+.1f} +- {got.axis_sigma_m * 1e3:.1f} mm behind the slave's optical centre "
                     f"(the settings say {d0 * 1e3:g} mm)")
        values["rig"]["pan_axis_m"] = round(float(d), 4)
    else:
        these = "" if axis is None else f" (these give {axis.axis_m * 1e3:+.0f} +- {axis.axis_sigma_m * 1e3:.0f} mm)"
        lines.append(f"pan axis: the settings' {d * 1e3:g} mm behind the optical centre{these}; points at three "
                     "distances or more, one near (0.3-0.5 m), measure it")
    return values, lines


def run(args: argparse.Namespace) -> int:
    settings = load(args.config)
    rig = args.rig or settings.rig
    return main(rig, session.config_from_args(args), args.distance, args.write, args.amplitude, args.hold_s,
                args.wait, settings, args.at)
