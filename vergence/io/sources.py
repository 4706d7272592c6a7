"""Stereo sources for the capture: plain classes that hand out (master, slave) gray image pairs.

    files:LEFT,RIGHT     one image pair, read once, given out again and again
    video:LEFT,RIGHT     two video files read in step (rewound at the end)
    camera:0,1           two OpenCV devices (indices or paths)
    ros2:LEFT,RIGHT      two ROS 2 image topics, paired by stamp (vergence.ros2.source; the [ros2] extra)
    sim[:key=value:...]  the rig simulator (vergence.sim.Rig.from_spec); the slave is rendered at the pan
                         the capture passes in, so the loop closes through the motor state. With
                         motion=SPEC (sim:motion=sine:z=0.8,amp=0.3,hz=0.5:focal=500) a target moves in
                         depth in front of the physical rig, on the wall clock from the first read

Every source has .size (W, H), .focal_px (0: unknown, the capture picks one), .start_pan_rad, read(pan_at)
-> (master, slave) uint8 gray arrays (the caller must not modify them), close(), and .truth_pan_rad: the
converged slave pan of the last read when the source knows it (the simulator, for the point at .fovea, which
the capture sets where `vergence fixate` moves it), else None. pan_at is the slave's
pan: a number, or a function of a time (ns, time.time_ns's clock) giving the pan then (the capture's motor
history); only the simulator uses it. After each read, .exposure_ns is the pair's exposure times (master,
slave; ns, the middle of each exposure) where the source knows them, else None (the capture then takes the
read time less [camera] latency_s): the simulator knows its own; a camera's come from the driver's buffer
timestamps where OpenCV's backend gives them (V4L2: CAP_PROP_POS_MSEC is the buffer's time on the monotonic
clock; docs/SERVICE.md, "The camera's time"); a video's from its frame times, anchored at the read time of its
first frame. .follows_pan says
whether the slave image moves with the slave motor (cameras, the simulator); a still pair or two videos were
taken at one pan, .start_pan_rad (0: parallel cameras), whatever the motor does since. `master` says which
camera is the fixed one ("left" or "right"). Errors are SourceError naming the file or device and the fix.
No network code here.
"""

from __future__ import annotations

import math
import os
import time
from collections import deque

import cv2
import numpy as np

from .images import Source, SourceError, read_image
from ..spec import Key, parse
from ..head.timing import CameraTiming

__all__ = ["SourceError", "Source", "FilesSource", "VideoSource", "CameraSource", "SimSource",
           "open_source", "check_source"]


def _gray(img: np.ndarray) -> np.ndarray:
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    return np.ascontiguousarray(img)


def _pair(rest: str, kind: str) -> tuple[str, str]:
    parts = [p.strip() for p in rest.split(",")]
    if len(parts) != 2 or not all(parts):
        raise SourceError(f"source {kind}:{rest!r}: want {kind}:LEFT,RIGHT (two items separated by a comma)")
    return parts[0], parts[1]


def _check_pair(a: np.ndarray, b: np.ndarray, what: str) -> tuple[int, int]:
    if a.shape != b.shape:
        raise SourceError(f"{what}: left is {a.shape[1]} x {a.shape[0]}, right is {b.shape[1]} x {b.shape[0]}; "
                          "both cameras must give images of the same size")
    return a.shape[1], a.shape[0]


class FilesSource(Source):
    """One still pair, read once at start (no per-frame work: read() returns the same arrays), taken at pan 0."""

    follows_pan = False

    def __init__(self, left: str, right: str, master: str = "left"):
        super().__init__(master)
        try:
            imgs = [np.ascontiguousarray(read_image(path)) for path in (left, right)]
        except SourceError as e:
            raise SourceError(f"files source: {e}") from None
        self.size = _check_pair(imgs[0], imgs[1], f"files:{left},{right}")
        self.pair = self._order(imgs[0], imgs[1])

    def read(self, pan_at=0.0) -> tuple[np.ndarray, np.ndarray]:
        return self.pair


class VideoSource(Source):
    """Two video files read frame by frame in step; both are rewound when either ends. Taken at pan 0."""

    follows_pan = False

    def __init__(self, left: str, right: str, master: str = "left"):
        super().__init__(master)
        self.paths = (left, right)
        self.caps = []
        for path in self.paths:
            if not os.path.isfile(path):
                self.close()
                raise SourceError(f"video source: cannot read {path!r}: no such file")
            cap = cv2.VideoCapture(path)
            if not cap.isOpened():
                self.close()
                raise SourceError(f"video source: OpenCV cannot open {path!r} (not a video, or no codec for it)")
            self.caps.append(cap)
        self.anchor: tuple[int, float] | None = None  # (read time ns, the video's time ms) of the first frame
        a, b = self._grab()
        self.size = _check_pair(a, b, f"video:{left},{right}")
        self.first = self._order(a, b), self.msec

    def _grab(self) -> tuple[np.ndarray, np.ndarray]:
        out, msec = [], []
        for cap, path in zip(self.caps, self.paths):
            ok, img = cap.read()
            if not ok:
                cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
                self.anchor = None  # rewound: the video's time starts again
                ok, img = cap.read()
                if not ok:
                    raise SourceError(f"video source: no frame can be read from {path!r}")
            out.append(_gray(img))
            msec.append(cap.get(cv2.CAP_PROP_POS_MSEC))
        self.msec = msec
        return out[0], out[1]

    def _stamps(self, msec: list[float]) -> tuple[int, int] | None:
        """The frames' times in the video, on our clock: anchored at the read of the first frame (and again
        after a rewind, or where the reads have drifted from the video's pace by more than a second)."""
        now = time.time_ns()
        if not all(math.isfinite(m) and m >= 0 for m in msec):
            return None
        if self.anchor is None or abs(self.anchor[0] + (msec[0] - self.anchor[1]) * 1e6 - now) > 1e9:
            self.anchor = (now, msec[0])
        t0, m0 = self.anchor
        stamps = [t0 + round((m - m0) * 1e6) for m in msec]
        return (stamps[1], stamps[0]) if self.swap else (stamps[0], stamps[1])

    def read(self, pan_at=0.0) -> tuple[np.ndarray, np.ndarray]:
        if self.first is not None:
            (pair, msec), self.first = self.first, None
        else:
            pair, msec = self._order(*self._grab()), self.msec
        self.exposure_ns = self._stamps(msec)
        return pair

    def close(self) -> None:
        for cap in self.caps:
            cap.release()
        self.caps = []


class CameraSource(Source):
    """Two OpenCV capture devices (an index like 0, or a device path like /dev/video2)."""

    def __init__(self, left: str, right: str, master: str = "left", size: tuple[int, int] | None = None):
        super().__init__(master)
        self.caps = []
        self.names = (left, right)
        for name in self.names:
            dev = int(name) if name.isdigit() else name
            level = cv2.utils.logging.getLogLevel()
            cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)  # our error below says more
            try:
                cap = cv2.VideoCapture(dev)
            finally:
                cv2.utils.logging.setLogLevel(level)
            if not cap.isOpened():
                self.close()
                raise SourceError(
                    f"camera source: cannot open camera {name!r}. Check that it is plugged in and not used by "
                    "another program, list devices with `ls /dev/video*` (or `v4l2-ctl --list-devices`), "
                    "check that this user may read them (group 'video'), and pass their indices or paths as "
                    "camera:LEFT,RIGHT (for example camera:0,2)")
            if size is not None:
                cap.set(cv2.CAP_PROP_FRAME_WIDTH, size[0])
                cap.set(cv2.CAP_PROP_FRAME_HEIGHT, size[1])
            cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # as little driver buffering as the backend allows
            self.caps.append(cap)
        a, b = self._grab()
        self.size = _check_pair(a, b, f"camera:{left},{right}")

    def _grab(self) -> tuple[np.ndarray, np.ndarray]:
        for cap in self.caps:  # grab both first, then decode: the two exposures are as close as possible
            cap.grab()
        out, stamps = [], []
        for cap, name in zip(self.caps, self.names):
            ok, img = cap.retrieve()
            if not ok or img is None:
                raise SourceError(f"camera source: camera {name!r} gave no image (unplugged, or busy?)")
            out.append(_gray(img))
            stamps.append(cap.get(cv2.CAP_PROP_POS_MSEC))
        self.exposure_ns = self._stamps(stamps)
        return out[0], out[1]

    def _stamps(self, msec: list[float]) -> tuple[int, int] | None:
        """V4L2's buffer times (ms on the monotonic clock) on time.time_ns's clock; None where the backend
        gives none (0, or not a number). Whether they are believable is the capture's to judge."""
        if not all(math.isfinite(m) and m > 0 for m in msec):
            return None
        offset = time.time_ns() - time.monotonic_ns()
        ns = [offset + round(m * 1e6) for m in msec]
        return (ns[1], ns[0]) if self.swap else (ns[0], ns[1])

    def read(self, pan_at=0.0) -> tuple[np.ndarray, np.ndarray]:
        return self._order(*self._grab())

    def close(self) -> None:
        for cap in self.caps:
            cap.release()
        self.caps = []


class SimSource(Source):
    """The rig simulator: the master view is fixed, the slave is rendered at the pan at its exposure.

    Its cameras are as the spec's timing keys say (vergence.head.timing.CameraTiming): latency=S (the image is S
    old when read), skew=S (the slave exposed S after the master), exposure=S (each view integrates the scene
    and the slave's motion over S: motion blur), jitter=S (exposure times off their schedule); stamps=no
    gives no exposure times (as a camera whose backend has none: the capture then takes [camera]
    latency_s), for measuring the latency from outside (`vergence latency`). The camera-side faults of
    vergence.sim.faults (freeze=T0-T1, freeze_master=, black=, reverse, slip=, backlash=, focal_true=, zero=) make it
    lie as a real head's cameras do; the motor-side ones (stall=, encoder_noise=) are the sim actuator's, which
    `vergence up` gives them (`motor_faults`): the frames' pans are then the encoder's readings (encoder()), each
    with its noise, while the slave is rendered where the shaft is."""

    TIMING = {"latency": "latency_s", "skew": "skew_s", "exposure": "exposure_s", "jitter": "jitter_s"}
    renders = True

    def __init__(self, spec: str = "", master: str = "left"):
        super().__init__(master)
        if self.swap:
            raise SourceError("sim source: the simulator's master is its left camera (it pans the right one): "
                              "leave master out of [rig] and [capture], or set it to 'left', for a sim source "
                              "('right' is for a real head whose right camera is the fixed one)")
        from ..sim import Rig  # the simulator is only loaded when used

        from ..sim.faults import Faults, Lies

        try:
            items, timing, self.stamps = self._timing(spec)
            self.timing = self.camera_timing(timing)
            faults = Faults.take(items)
            if faults.late:
                raise ValueError("sim source: late is `vergence sim`'s; here latency=S:stamps=no with [camera] "
                                 "latency_s unset gives images S older than the capture is told")
            self.rig = Rig.from_items(items)
            told = float(self.rig.focal_px)  # the focal length the settings say; focal_true renders at another
            if faults.focal_true is not None:
                self.rig = Rig.from_items(dict(items, focal=faults.focal_true))
        except (ValueError, OSError) as e:
            raise SourceError(str(e)) from None
        self.size = tuple(self.rig.size)
        self.focal_px = told
        head = getattr(self.rig, "head", None)  # the moving target's cameras: their principal point (cx=, cy=)
        if head is not None and (head.cx is not None or head.cy is not None):
            self.principal = (head.principal, head.principal)
        if head is not None and head.lens is not None:
            self.lenses = (head.lens, head.lens)
        self.start_pan_rad = float(self.rig.start_pan_rad)
        # the master's aim and the gimbal, for the depth of the fixated point (services/pipeline/capture.py)
        self.master_pan_rad, self.tilt_rad = float(self.rig.master_pan_rad), float(self.rig.tilt_rad)
        self.gimbal = self.rig.gimbal
        self.t0: int | None = None  # the scene's time 0 (ns): the first exposure
        self.rng = np.random.default_rng(0)
        self.lies = Lies(faults)
        self.motor_faults = faults.motor()  # the sim actuator's lies, which this source passes on (`vergence up`)
        # [actuator.motor] direction and offset_deg: the shaft's angle for a pan the motor reports (to_motor)
        self.shaft = float
        self._still_truth: tuple = (None, math.nan)  # (fovea, its truth) of the still scene
        self._last: tuple = ([0.0], [(self.start_pan_rad, 0.0)])  # the latest read's instants and pans
        self.render_ns: deque[int] = deque(maxlen=15)  # the last renders' durations (their median: the lead)

    @classmethod
    def camera_timing(cls, timing: dict) -> CameraTiming:
        """CameraTiming from the spec's timing keys; ValueError naming the key as the spec has it (latency)."""
        try:
            return CameraTiming(**timing)
        except ValueError as e:
            name, _, why = str(e).partition(":")
            key = {v: k for k, v in cls.TIMING.items()}.get(name, name)
            raise ValueError(f"sim source: {key}:{why}") from None

    @classmethod
    def _timing(cls, spec: str) -> tuple[dict, dict, bool]:
        """The spec's rig items, the CameraTiming's arguments, and whether to stamp (one parse, vergence.spec)."""
        from ..sim import Rig
        from ..sim.faults import FAULT_KEYS

        keys = [Key(k, unit="s") for k in cls.TIMING] + [Key("stamps", "choice", "yes", choices=("yes", "no"))]
        items = parse(spec, keys + Rig.spec_keys() + FAULT_KEYS, "sim source")
        timing = {field: items[k] for k, field in cls.TIMING.items() if items[k] is not None}
        for k in cls.TIMING:
            del items[k]
        return items, timing, items.pop("stamps") == "yes"

    def read(self, pan_at=0.0) -> tuple[np.ndarray, np.ndarray]:
        from ..sim.camera import expose, sub_times

        pan_of = pan_at if callable(pan_at) else (lambda t_ns: pan_at)
        tm = self.timing
        ready = getattr(pan_at, "ready", None)  # the capture's: until the motor has counted the commands seen
        if ready is not None:
            ready()
        start = time.time_ns()
        # render ahead: the pair is exposed when its render will be done (a camera's read-out is the camera's, not
        # the host's), where the pan is known that far ahead (ahead_ns: the capture's, with the sim motor's replica)
        lead = min(sorted(self.render_ns)[len(self.render_ns) // 2] if self.render_ns else 0,
                   getattr(pan_at, "ahead_ns", lambda: 0)())
        later = start + lead - round(tm.age_s * 1e9)
        if tm.jitter_s > 0:
            later += round(float(np.clip(self.rng.normal(0.0, tm.jitter_s), -0.02, 0.02)) * 1e9)
        skew = round(tm.skew_s * 1e9)
        t_master, t_slave = (later - skew, later) if skew > 0 else (later, later + skew)
        if self.t0 is None:
            self.t0 = t_master
        settle = getattr(pan_at, "settle", None)  # the capture's: until the motor has told its pan then
        if settle is not None:
            settle(t_slave + round(tm.exposure_s * 5e8))
        t_render = time.time_ns()
        lies, at = self.lies, (t_master - self.t0) / 1e9
        scene = lies.inputs("master", at, sub_times(at, tm.exposure_s))
        slave = lies.inputs("slave", at, [(lies.camera(self.shaft(pan_of(self.t0 + round(t * 1e9))), t), t)
                                          for t in sub_times((t_slave - self.t0) / 1e9, tm.exposure_s)])
        truth = self._truth((t_master - self.t0) / 1e9)
        self.truth_pan_rad = truth if math.isfinite(truth) else None
        self.exposure_ns = (t_master, t_slave) if self.stamps else None
        self._last = (scene, slave)
        if self.rows is None:
            pair = lies.images(at, None, *expose(self.rig, scene, slave))
        else:
            from ..sim.optics import Region

            w, h = self.size
            y0, y1 = max(0, self.rows[0]), min(h, self.rows[1])
            band = expose(self.rig, scene, slave, Region.band(w, y0, y1))
            out = np.zeros((2, h, w), np.uint8)
            out[0, y0:y1], out[1, y0:y1] = band
            pair = lies.images(at, (y0, y1), out[0], out[1])
        done = time.time_ns()
        self.render_ns.append(done - t_render)
        if done < start + lead:  # read out no earlier than the exposure the lead claimed
            time.sleep((start + lead - done) / 1e9)
        return pair

    def encoder(self, pan: float) -> float:
        """The encoder's reading of a shaft at `pan` (encoder_noise=), for a frame's pan where the capture knows the
        shaft itself (its replica of the sim motor)."""
        return self.lies.encoder(pan)

    def preview(self, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """The latest pair read, rendered whole at width x height without noise (a preview at the cost of a
        band, where a read of `rows` left the rest of the views black)."""
        from ..sim.camera import expose
        from ..sim.optics import Region

        scene, slave = self._last
        return expose(self.rig, scene, slave, Region.scaled(self.size, (width, height)))

    def _truth(self, t: float) -> float:
        """The converged pan at the master's exposure (t s after the first) for the fovea where it is now."""
        from ..sim.fixation import truth_pan_at

        w, h = self.size
        at = self.fovea
        if hasattr(self.rig, "motion"):  # the moving target: its truth changes with t (closed form)
            x, y = at if at is not None else (w // 2, h // 2)
            return truth_pan_at(self.rig, x, y, t)
        if at is None or tuple(at) == (w // 2, h // 2):
            return self.rig.truth_pan(t)
        if self._still_truth[0] != at:  # the still scene: once per fovea (a search, some 2 ms)
            self._still_truth = (at, truth_pan_at(self.rig, at[0], at[1]))
        return self._still_truth[1]


def check_source(spec: str) -> None:
    """SourceError when open_source(spec) would refuse its text, found without opening a camera, a video or a
    ROS 2 topic (`vergence up` checks its --source before it starts anything): the kind, the LEFT,RIGHT pair,
    that the files are there, a ros2 spec's options; a sim spec is built (its scene, well under a second)."""
    kind, _, rest = (spec or "").partition(":")
    kind = kind.strip()
    if kind in ("files", "video", "camera"):
        pair = _pair(rest, kind)
        for path in pair if kind != "camera" else ():
            if not os.path.exists(path):
                raise SourceError(f"source {kind}: {path}: no such file")
    elif kind == "ros2":
        from ..ros2.source import parse_spec

        parse_spec(rest)
    elif kind == "sim":
        SimSource(rest).close()
    else:
        open_source(spec)  # the error naming every kind


def motor_faults(spec: str) -> str:
    """A sim source's motor-side lies (stall=, encoder_noise=) as the sim actuator's --faults spec; '' for none (or a
    source other than the simulator). `vergence up` passes them on; SourceError as check_source's."""
    kind, _, rest = (spec or "").partition(":")
    return SimSource(rest).motor_faults.spec() if kind.strip() == "sim" else ""


def open_source(spec: str, master: str = "left") -> Source:
    """A source from its text: files:L,R | video:L,R | camera:0,1 | sim[:key=value:...]."""
    kind, _, rest = (spec or "").partition(":")
    kind = kind.strip()
    if kind == "files":
        return FilesSource(*_pair(rest, kind), master=master)
    if kind == "video":
        return VideoSource(*_pair(rest, kind), master=master)
    if kind == "camera":
        return CameraSource(*_pair(rest, kind), master=master)
    if kind == "sim":
        return SimSource(rest, master=master)
    if kind == "ros2":  # two ROS 2 image topics (vergence/ros2/source.py; rclpy is imported only here)
        from ..ros2.source import Ros2Source

        return Ros2Source(rest, master=master)
    raise SourceError(f"unknown source {spec!r}: want files:LEFT,RIGHT, video:LEFT,RIGHT, camera:0,1, "
                      "sim[:key=value:...] or ros2:LEFT_TOPIC,RIGHT_TOPIC")
