"""The closed loop in one process: render -> vergence.match -> controller -> safety -> simulated motor.

The same steps as the distributed service (capture renders the slave at the motor's present pan, the
network decides, the controller turns the decision into an absolute pan target, the actuator's safety layer
bounds it, the motor moves), with a virtual clock: frame i is captured at i / rate_hz seconds, its command
reaches the motor delay_s later (the capture-to-command latency of the distributed loop), and the motor is
integrated in between, so runs are deterministic and as fast as the maths. The camera sees the motor's
exact shaft angle; the controller is told the pan the encoder reports (whole ticks), as the capture is."""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np

from ..control import ControlSettings, Controller
from ..match import match
from ..params import Params
from ..motors.base import MotorSettings, Safety
from ..motors.simulated import SimMotor
from .rig import Rig

__all__ = ["Step", "closed_loop", "frames_to_converge", "tracking_error", "DELAY_S"]

DELAY_S = 0.005  # capture to command, about what the distributed loop takes (vergence bench pipeline)


@dataclass(frozen=True)
class Step:
    """One frame of the loop: the slave pan at capture and what the network made of that view (its Match's
    Decision, flattened: k, v, offset_px, confident, confidence; not a decision of its own).

    pan_deg / truth_pan_deg: the slave's pan and the converged pan; error_px: f tan(pan - truth), how far
    the slave is from converged, in pixels at the view centre (NaN when the truth is unknown). offset_px,
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

    def to_dict(self) -> dict:
        """JSON-ready (NaN, an unknown truth, becomes None)."""

        def known(v: float) -> float | None:
            return v if math.isfinite(v) else None

        return {"frame": self.frame, "t_s": self.t_s, "pan_deg": self.pan_deg,
                "truth_pan_deg": known(self.truth_pan_deg),
                "error_px": known(self.error_px), "offset_px": self.offset_px, "confident": self.confident,
                "k": self.k, "v": self.v, "window": self.window, "confidence": self.confidence,
                "target_deg": self.target_deg}


def closed_loop(rig: Rig, frames: int, params: Params | None = None, control: ControlSettings | None = None,
                motor: MotorSettings | None = None, rate_hz: float = 30.0, delay_s: float = DELAY_S,
                fixations: dict[int, tuple[int, int]] | None = None) -> Iterator[Step]:
    """Yield frames + 1 Steps: the starting state (frame 0), then the state at each following capture.

    rig: a Rig (a still scene) or a MovingRig (render(pan, t), truth_pan(t)). motor: the simulated motor's
    settings (its start pan is the rig's; default: MotorSettings(), a Dynamixel X-series), whose pan and step
    limits bound the controller's set-points too; control: the controller's (mode, gain, dead band).
    delay_s: from capture to the command.
    fixations: {frame: (x, y)}, the fovea at (x, y) of the master view from that frame on (default: the view
    centre); a Step's truth and error stay the centre's (vergence.sim.fixation.truth_at gives the fovea's)."""
    if not (0 <= delay_s < 1 / rate_hz):
        raise ValueError(f"delay {delay_s} s must be >= 0 and shorter than a frame (1 / {rate_hz:g} Hz)")
    params = params or Params()
    ms = replace(motor or MotorSettings(), start_deg=math.degrees(rig.start_pan_rad))
    clock = [0.0]
    drive = SimMotor(ms, clock=lambda: clock[0])
    safety = Safety(ms, drive.open())
    controller = Controller(control, safety)  # asks the motor's limits of the Safety (as the reducer does)
    at = None
    for i in range(frames + 1):
        t = i / rate_hz
        clock[0] = t
        at = (fixations or {}).get(i, at)
        pan = drive.shaft
        reading = drive.read_position()
        master, slave = rig.render(pan, t)
        m = match(master, slave, at, params)
        d = m.decision
        target = controller.target(reading, d.offset_px, rig.focal_px, d.confident, t_s=t,
                                   centre_px=0.0 if at is None else at[0] - master.shape[1] // 2)
        clock[0] = t + delay_s
        if target is not None:
            target = safety.command(target).goal
            if target is not None:
                drive.write_goal(target)
        yield Step(frame=i, t_s=t, pan_deg=math.degrees(pan), truth_pan_deg=math.degrees(rig.truth_pan(t)),
                   error_px=rig.error_px(pan, t), offset_px=d.offset_px, confident=d.confident, k=d.k, v=d.v,
                   window=m.window, confidence=d.confidence,
                   target_deg=None if target is None else math.degrees(target),
                   scores=np.atleast_2d(m.scores)[d.v + params.vsearch])


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
