"""The closed loop in one process: expose -> read -> vergence.match -> controller -> safety -> simulated motor.

The same steps as the distributed service, with a virtual clock and a real camera's timing
(vergence.head.timing.CameraTiming, vergence.sim.camera): frame i's master is exposed at i / rate_hz (off its
schedule by the jitter), the slave skew_s after it, each integrating the scene and the slave's motion over
the exposure; the pair is read latency_s after the later exposure, decided delay_s after the read (the
pipeline: capture, workers, reducer), and its command reaches the motor then. The motor is integrated in
between and publishes its encoder reading (whole ticks) at state_hz and after each command, as the actuator
does, and at each slave exposure; the controller gets the slave's pan at its exposure from that history
(vergence.head.timing.PanHistory), as the capture gives it. (The reading at the exposure is what the service's sim
source amounts to: it renders the slave at the pan its frame carries. A real camera's image is older than the
motor's newest report, so the capture interpolates between two reports; tests/vergence/head/test_timing.py checks
that interpolation.) Events run in time order, so a frame's command may come after the next frames'
exposures (a latency longer than a frame); runs are deterministic and as fast as the maths."""

from __future__ import annotations

import heapq
import inspect
import itertools
import math
from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np

from ..head.control import ControlSettings, Controller
from ..head.frozen import digest
from ..network.decide import has_texture
from ..network.match import match
from ..network.params import Params
from ..motors.base import MotorSettings, Safety
from ..motors.simulated import SimMotor
from ..head.timing import CameraTiming, PanHistory
from .camera import Schedule, expose, sub_times
from .faults import Faults, Lies
from .optics import Region
from .rig import Rig

__all__ = ["Step", "closed_loop", "frames_to_converge", "tracking_error", "DELAY_S", "STATE_HZ"]

DELAY_S = 0.005  # read to command, about what the distributed loop takes (vergence bench pipeline)
STATE_HZ = 50.0  # the motor's position reports ([actuator] state_hz)


@dataclass(frozen=True)
class Step:
    """One frame of the loop: the slave pan at exposure and what the network made of that view (its Match's
    Decision, flattened: k, v, offset_px, confident, confidence; not a decision of its own).

    t_s: the master's exposure time. pan_deg: the slave's pan at the slave's exposure; truth_pan_deg: the
    converged pan at t_s; error_px: f tan(slave pan at t_s - truth), how far the slave is from converged at
    the master's exposure, in pixels at the view centre (NaN when the truth is unknown). offset_px,
    confident, k, window: the network's decision on this frame; target_deg: the pan commanded from it
    (None: no move). scores: the layer-4 profile (best row when searching vertically)."""

    frame: int
    t_s: float
    pan_deg: float
    truth_pan_deg: float
    error_px: float
    offset_px: float
    confident: bool
    k: int
    v: int
    window: int
    confidence: float
    target_deg: float | None
    scores: np.ndarray
    fault: str | None = None  # the loop's doubt (vergence.head.doubt): the fault it holds on, None when none
    late_ms: float | None = None  # ... and how late it named the camera (None: not named)
    focal_ratio: float | None = None  # ... and the focal length's ratio to the settings' it measured (None: not named)
    # the slave camera's own error (its pan over its exposure, as it lies: backlash, slip, reverse), where error_px is
    # the shaft's (the encoder's pan): the same without a lie
    camera_error_px: float = math.nan

    def to_dict(self) -> dict:
        """JSON-ready (NaN, an unknown truth, becomes None)."""

        def known(v: float) -> float | None:
            return v if math.isfinite(v) else None

        return {"frame": self.frame, "t_s": self.t_s, "pan_deg": self.pan_deg,
                "truth_pan_deg": known(self.truth_pan_deg),
                "error_px": known(self.error_px), "offset_px": self.offset_px, "confident": self.confident,
                "k": self.k, "v": self.v, "window": self.window, "confidence": self.confidence,
                "target_deg": self.target_deg, "fault": self.fault, "late_ms": self.late_ms,
                "focal_ratio": self.focal_ratio, "camera_error_px": known(self.camera_error_px)}


def closed_loop(rig: Rig, frames: int, params: Params | None = None, control: ControlSettings | None = None,
                motor: MotorSettings | None = None, rate_hz: float = 30.0, delay_s: float = DELAY_S,
                fixations: dict[int, tuple[int, int]] | None = None, timing: CameraTiming | None = None,
                state_hz: float = STATE_HZ, seed: int = 0, faults: Faults | None = None,
                focal_px: float | None = None) -> Iterator[Step]:
    """Yield frames + 1 Steps: the starting state (frame 0), then the state at each following exposure.

    rig: a Rig (a still scene) or a MovingRig (master_view(t), slave_view(pan, t), truth_pan(t)). motor: the
    simulated motor's settings (its start pan is the rig's; default: MotorSettings(), a Dynamixel X-series),
    whose pan and step limits bound the controller's set-points too; control: the controller's (mode, gain,
    dead band). timing: the cameras' (default: none of it, an image read the instant it is exposed).
    delay_s: from the read to the command. state_hz: the motor's position reports. seed: the jitter's.
    fixations: {frame: (x, y)}, the fovea at (x, y) of the master view from that frame on (default: the view
    centre); a Step's truth and error stay the centre's (vergence.sim.fixation.truth_at gives the fovea's).
    faults: the simulator's lies (vergence.sim.faults); focal_px: the focal length the controller is told (default
    the rig's: a rig rendered at focal_true is told another)."""
    _check(delay_s, state_hz)
    params = params or Params()
    timing = timing or CameraTiming()
    schedule = Schedule(rate_hz, timing, seed)
    ms = replace(motor or MotorSettings(), start_deg=math.degrees(rig.start_pan_rad))
    clock = [0.0]
    drive = SimMotor(ms, clock=lambda: clock[0])
    # the motor turns direction x (pan - offset) (a MotorLoop's job in the actuator, done here)
    safety = Safety(ms, ms.from_motor(drive.open()))
    controller = Controller(control, safety)  # asks the motor's limits of the Safety (as the reducer does)
    history = PanHistory(max_gap_s=max(0.1, 3.0 / state_hz))
    lies = Lies(faults or Faults(), seed)

    def report(t: float) -> None:  # the encoder's reading into the history, and the motor's report to the controller
        if history.add(t, pan := lies.encoder(ms.from_motor(drive.read_position()))):
            controller.motor(t, pan)

    report(0.0)
    events: list = []  # (time, order, kind, frame, payload)
    order = itertools.count()

    def push(t: float, kind: str, frame: int = -1, payload=None) -> None:
        heapq.heappush(events, (t, next(order), kind, frame, payload))

    times = [schedule.frame(i) for i in range(frames + 1)]
    shafts: dict[int, dict] = {}  # frame -> what its exposures saw of the shaft
    for i, (tm, ts, tr) in enumerate(times):
        shafts[i] = {"slave": [], "master_t": sub_times(tm, timing.exposure_s)}
        for t in sub_times(ts, timing.exposure_s):
            push(t, "slave", i, t)
        push(tm, "at_master", i)
        push(ts, "at_slave", i)
        push(tr, "read", i)
    for k in range(1, int(times[-1][2] * state_hz) + 2):
        push(k / state_hz, "state")
    if lies.f.stall is not None:
        push(lies.f.stall[0], "stall")
    focal = rig.focal_px if focal_px is None else focal_px
    at = None
    while events:
        t, _, kind, i, payload = heapq.heappop(events)
        clock[0] = max(clock[0], t)
        if kind == "slave":
            shafts[i]["slave"].append((lies.camera(drive.shaft, payload), payload))
        elif kind == "stall":
            drive.write_goal(drive.shaft)  # it stops where it is
        elif kind in ("at_master", "at_slave"):
            shafts[i][kind] = ms.from_motor(drive.shaft)  # (the pan the encoder would read)
            if kind == "at_slave":  # the encoder's reading at the slave's exposure (see the docstring)
                report(clock[0])
        elif kind == "state":
            report(clock[0])
        elif kind == "read":
            at = (fixations or {}).get(i, at)
            push(t + delay_s, "command", i, _decide(rig, i, shafts.pop(i), times[i], at, params, controller,
                                                    history, t + delay_s, lies, focal))
        elif kind == "command":
            step, target = payload
            if target is not None:
                target = safety.command(target).goal
                if target is not None and not lies.stalled(t):
                    drive.write_goal(ms.to_motor(target))
                    report(clock[0])
            yield replace(step, target_deg=None if target is None else math.degrees(target))


def _check(delay_s: float, state_hz: float) -> None:
    if not (delay_s >= 0 and math.isfinite(delay_s)):
        raise ValueError(f"delay {delay_s} s must be a finite number >= 0")
    if not (state_hz > 0 and math.isfinite(state_hz)):
        raise ValueError(f"state rate {state_hz} Hz must be a positive number")


def _cx(rig) -> float:
    """The slave's principal point's column (the moving target's cameras may have one off the view centre)."""
    head = getattr(rig, "head", None)
    return head.principal[0] if head is not None else rig.size[0] // 2


def _decide(rig, frame: int, seen: dict, times: tuple[float, float, float], at, params: Params, controller: Controller,
            history: PanHistory, t_now: float, lies: Lies, focal: float) -> tuple[Step, float | None]:
    """One frame read: its images (as the cameras lie), the network's decision, the controller's target (None: no
    move)."""
    t_master, t_slave, _ = times
    shown = dict(seen, slave=lies.inputs("slave", t_master, seen["slave"]),
                 master_t=lies.inputs("master", t_master, seen["master_t"]))
    master, slave = lies.images(t_master, at, *_band(rig, shown, at, params))
    m = match(master, slave, at, params)
    d = m.decision
    y, reach = master.shape[0] // 2 if at is None else at[1], params.band_reach(m.window)
    band = slice(max(0, y - reach), y + reach + 1)  # the rows the match read (the background's)
    base = params.band_reach()  # the digests': the base window's (a grown one resets no run)
    x = master.shape[1] // 2 if at is None else at[0]
    t_told = min(t_slave + (lies.f.late or 0.0), times[2])  # the exposure the loop is told (`late`: a later one)
    pan = history.at(t_told)  # the slave's pan at its exposure, as the encoder reports it
    target = None
    if pan is not None:
        # the background's verdict, not on a pan told past the motor's newest report (a guess: Frame.pan_guessed)
        scene = controller.scene(t_told, pan, slave[band], focal, x, at, _cx(rig)) if t_told <= history.t[-1] else None
        target = controller.target(pan, d.offset_px, focal, d.confident, t_s=t_told, t_now=t_now,
                                   centre_px=x - _cx(rig), slave=digest(slave, y, base) or None,
                                   master=digest(master, y, base) or None, fovea=at, textured=has_texture(d, params),
                                   width_px=master.shape[1], background=scene)
    step = Step(frame=frame, t_s=t_master, pan_deg=math.degrees(seen["at_slave"]),
                truth_pan_deg=math.degrees(rig.truth_pan(t_master)), error_px=rig.error_px(seen["at_master"], t_master),
                camera_error_px=rig.error_px(float(np.mean([c for c, _ in seen["slave"]])), t_slave),
                offset_px=d.offset_px, confident=d.confident, k=d.k, v=d.v, window=m.window,
                confidence=d.confidence, target_deg=None, scores=np.atleast_2d(m.scores)[d.v + params.vsearch],
                fault=None if controller.doubt.fault is None else str(controller.doubt.fault),
                late_ms=None if controller.doubt.lag.late_s is None else round(controller.doubt.lag.late_s * 1e3, 2),
                focal_ratio=controller.doubt.focal.ratio)
    return step, target


def _band(rig, seen: dict, at, params: Params) -> tuple[np.ndarray, np.ndarray]:
    """The frame's views with only the rows the match reads rendered (the largest window's half, the vertical
    search and Sobel's margin about the fovea's row; the same rows, noise included, as in the whole view), the
    rest black: as the capture's sim source renders. A rig of the caller's own whose views take no region is
    rendered whole."""
    if "region" not in inspect.signature(rig.master_view).parameters:
        return expose(rig, seen["master_t"], seen["slave"])
    w, h = rig.size
    y = h // 2 if at is None else at[1]
    margin = params.band_reach(max(params.windows()))
    y0, y1 = max(0, y - margin), min(h, y + margin + 1)
    band = expose(rig, seen["master_t"], seen["slave"], Region.band(w, y0, y1))
    out = np.zeros((2, h, w), np.uint8)
    out[0, y0:y1], out[1, y0:y1] = band
    return out[0], out[1]


def frames_to_converge(steps: list[Step], tol_px: float = 1.0) -> int | None:
    """The first frame from which |error_px| <= tol_px holds to the end of the run, or None."""
    first = None
    for s in steps:
        if abs(s.error_px) <= tol_px:
            if first is None:
                first = s.frame
        else:
            first = None
    return first


def tracking_error(steps: list[Step], first: int = 0, last: int | None = None) -> dict:
    """RMS and maximum |error| (px and degrees) over frames first..last (inclusive)."""
    sel = [s for s in steps if s.frame >= first and (last is None or s.frame <= last)]
    px = np.array([s.error_px for s in sel], float)
    deg = np.array([s.pan_deg - s.truth_pan_deg for s in sel], float)
    if not px.size:
        return dict(frames=0, rms_px=math.nan, max_px=math.nan, rms_deg=math.nan, max_deg=math.nan)
    return dict(frames=int(px.size), rms_px=float(np.sqrt(np.mean(px ** 2))), max_px=float(np.abs(px).max()),
                rms_deg=float(np.sqrt(np.mean(deg ** 2))), max_deg=float(np.abs(deg).max()))
