"""ROS 2 conversions, with no ROS import: what the bridge (services/bridges/ros2.py), the ros2 source
(vergence/ros2/source.py), the ros2 motor driver and the MCAP recorder put into or take out of ROS 2 messages,
as plain numbers and arrays, so that every rule here is unit-tested without rclpy.

Conventions (docs/ROS2.md): the master camera's optical frame is REP 103's (z forward, x right, y down), its
principal point the frame's (a camera_info's or the settings'; the image centre (W // 2, H // 2) where none is
known: vergence.head.depth); a stamp is (sec, nanosec) since the Unix epoch on
the same clock as time.time_ns(), and an image's stamp is its exposure time.

- fixation_point: a converged decision (fovea pixel and depth along the head's forward axis) -> the fixated 3-D
  point in the master's optical frame; fixation_covariance its 3 x 3 covariance (the depth sigma along the
  viewing ray, the pixel's quantisation across it), as the position block of a PoseWithCovariance.
- view_of_frame: a Frame's bytes -> the master's View (size, focal length, pan and tilt, and the image's own frame
  id when it passes frame_id_problem: the camera's name for its optical frame is a claim, checked).
- look_at_mode, discovery_env: the bridge's [ros2] look_at and discovery as it applies them.
- look_at_pixel: a 3-D point in the master's optical frame -> the master pixel a Fixate asks for, or Refused
  with the reason (not finite, behind the camera, outside the view, where the fovea does not fit).
- diagnostic: one process's status (the JSON of services.runtime.health) -> one DiagnosticStatus's fields.
- image_gray, compressed_gray: sensor_msgs Image / CompressedImage fields -> a uint8 gray array, or ImageError.
- Pairer: approximate-time pairing of two image streams by stamp (message_filters' ApproximateTime, simplified:
  the closest partner within `slop`), with the images it could not pair counted.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field

import cv2
import msgspec
import numpy as np

from ..wire.status import Status

__all__ = ["NS_PER_S", "OK", "ros_name", "WARN", "ERROR", "STALE", "stamp", "from_stamp", "stamp_problem", "View",
           "FrameView", "view_of_frame", "MAX_FRAME_ID", "frame_id_problem", "fixation_point", "fixation_covariance",
           "Refused", "look_at_pixel",
           "pan_at", "joint_velocity", "look_at_mode", "DISCOVERY_ENV", "discovery_env",
           "correlation_layout", "Diagnostic", "diagnostic", "ImageError", "ENCODINGS",
           "image_gray", "compressed_gray", "Pairer"]

NS_PER_S = 1_000_000_000
OK, WARN, ERROR, STALE = 0, 1, 2, 3  # diagnostic_msgs/msg/DiagnosticStatus levels (a byte)
INT32_MAX = 2**31 - 1
PIXEL_SIGMA = 1.0 / math.sqrt(12.0)  # a fovea centre rounded to the pixel: its uniform quantisation's sigma
MAX_FRAME_ID = 128  # the longest frame id taken from a camera (tf2 names are short)
_FRAME_ID = re.compile(r"[!-~]+")  # printable ASCII without spaces
UNKNOWN_VARIANCE = -1.0  # the orientation rows of a point's PoseWithCovariance: not estimated (as sensor_msgs/Imu)


# -- time ------------------------------------------------------------------------------------------------------

def ros_name(text: str) -> str:
    """text as one token of a ROS 2 name (letters, digits and underscores, not starting with a digit)."""
    out = "".join(c if c.isascii() and (c.isalnum() or c == "_") else "_" for c in text) or "_"
    return "_" + out if out[0].isdigit() else out


def stamp(t_ns: int) -> tuple[int, int]:
    """builtin_interfaces/msg/Time (sec, nanosec) of t_ns since the epoch; ValueError outside its range."""
    t_ns = int(t_ns)
    sec, nsec = divmod(t_ns, NS_PER_S)
    if not 0 <= sec <= INT32_MAX:
        raise ValueError(f"time {t_ns} ns is outside builtin_interfaces/Time (0 .. 2^31 - 1 s)")
    return sec, nsec


def from_stamp(sec: int, nanosec: int) -> int:
    """ns since the epoch of a (sec, nanosec) stamp."""
    return int(sec) * NS_PER_S + int(nanosec)


def stamp_problem(sec: int, nanosec: int, now_ns: int, max_skew_s: float) -> str | None:
    """Why a stamp is not believed as a time on our clock: zero (a driver that does not stamp), nanosec out of
    range, or further than max_skew_s from now. None: plausible."""
    if sec == 0 and nanosec == 0:
        return "stamp 0 (the publisher does not stamp its messages)"
    if not 0 <= nanosec < NS_PER_S:
        return f"stamp nanosec {nanosec} out of range"
    off = (from_stamp(sec, nanosec) - now_ns) / NS_PER_S
    if abs(off) > max_skew_s:
        return f"stamp {off:+.3g} s off our clock (more than {max_skew_s:g} s)"
    return None


# -- the bridge's settings -----------------------------------------------------------------------------------

def look_at_mode(setting: bool | None, identity: str | None) -> tuple[bool, str]:
    """Whether look_at moves the fovea, and why (for the start's log line): [ros2] look_at when set, else on
    without a deployed ACL (an unauthenticated session) and off under one."""
    if setting is not None:
        return setting, f"[ros2] look_at = {str(setting).lower()}"
    if identity is None:
        return True, "no deployed ACL (the Zenoh session is not authenticated)"
    return False, (f"a deployed ACL (the Zenoh session authenticates as {identity}); [ros2] look_at = true, with "
                   "the ros2 role's client config, turns it on")


DISCOVERY_ENV = {"localhost": "LOCALHOST", "subnet": "SUBNET"}


def discovery_env(discovery: str, environ) -> tuple[dict[str, str | None], str]:
    """The environment changes ({name: value, or None to remove}) that give the bridge's rclpy context the range
    [ros2] discovery asks for (rcl reads them when the context starts), and the range as the log says it.
    localhost drops ROS_STATIC_PEERS too (they would widen it); environment changes nothing."""
    if discovery == "environment":
        rng = environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") or "SYSTEM_DEFAULT"
        if environ.get("ROS_LOCALHOST_ONLY") == "1" and not environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE"):
            rng = "LOCALHOST (ROS_LOCALHOST_ONLY=1)"
        peers = environ.get("ROS_STATIC_PEERS")
        return {}, f"the environment's: {rng}" + (f", static peers {peers}" if peers else "")
    changes: dict[str, str | None] = {"ROS_AUTOMATIC_DISCOVERY_RANGE": DISCOVERY_ENV[discovery],
                                      "ROS_LOCALHOST_ONLY": None}
    if discovery == "localhost":
        changes["ROS_STATIC_PEERS"] = None
        return changes, "localhost (this host only)"
    peers = environ.get("ROS_STATIC_PEERS")
    return changes, "subnet" + (f", static peers {peers}" if peers else "")


# -- the master's view ------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class View:
    """The master camera as the frames describe it: image size, focal length (px), its pan and the common tilt
    (0, 0 for a fixed master) and the gimbal (vergence.head.depth). The principal point (cx, cy): the frame's (a
    camera_info's or the settings'), the image centre (W // 2, H // 2) where it is not known (-1)."""

    width: int
    height: int
    focal_px: float
    master_pan_rad: float = 0.0
    tilt_rad: float = 0.0
    gimbal: str = "helmholtz"
    frame_id: str = ""  # the master image's own frame id, checked (frame_id_problem); "": not known
    bad_frame_id: str = ""  # why the frame id the Frame claimed was not taken ("": it was, or there was none)
    cx: float = -1.0
    cy: float = -1.0

    @property
    def centre(self) -> tuple[float, float]:
        """The principal point."""
        return (self.cx if self.cx >= 0 else self.width // 2, self.cy if self.cy >= 0 else self.height // 2)


class FrameView(msgspec.Struct, tag_field="v", tag=1):
    """The few fields of a messages.Frame the bridge needs (msgspec skips the rest, strips included)."""

    width: int
    height: int
    focal_px: float
    master_pan_rad: float = 0.0
    tilt_rad: float = 0.0
    frame_id: str = ""
    cx: float = -1.0
    cy: float = -1.0


_FRAME_VIEW = msgspec.msgpack.Decoder(FrameView)


def view_of_frame(payload: bytes, gimbal: str = "helmholtz") -> View:
    """The View of a Frame's bytes; ValueError when they are not a frame with a plausible geometry."""
    try:
        f = _FRAME_VIEW.decode(payload)
    except (msgspec.DecodeError, msgspec.ValidationError) as e:
        raise ValueError(f"frame: {e}") from None
    if not (0 < f.width <= 65535 and 0 < f.height <= 65535):
        raise ValueError(f"frame: size {f.width} x {f.height}")
    if not (math.isfinite(f.focal_px) and f.focal_px > 0):
        raise ValueError(f"frame: focal_px {f.focal_px}")
    if not (math.isfinite(f.master_pan_rad) and math.isfinite(f.tilt_rad)):
        raise ValueError("frame: master pan or tilt not finite")
    why = frame_id_problem(f.frame_id) if f.frame_id else None
    for v, most in ((f.cx, f.width), (f.cy, f.height)):
        if not (v == -1.0 or 0 <= v <= most):
            raise ValueError(f"frame: principal point ({f.cx}, {f.cy}) outside the image")
    return View(f.width, f.height, float(f.focal_px), float(f.master_pan_rad), float(f.tilt_rad), gimbal,
                "" if why else f.frame_id, why or "", float(f.cx), float(f.cy))


def frame_id_problem(frame_id: str) -> str | None:
    """Why a frame id that a camera (or a Frame) claims is not taken as the name of the master's optical frame:
    empty, longer than MAX_FRAME_ID characters, or other than printable ASCII without spaces (what tf2's frame
    names are). None: taken."""
    if not frame_id:
        return "empty"
    if len(frame_id) > MAX_FRAME_ID:
        return f"frame_id of {len(frame_id)} characters (at most {MAX_FRAME_ID})"
    if not _FRAME_ID.fullmatch(frame_id):
        return f"frame_id {frame_id[:40]!r}: not printable ASCII without spaces"
    return None


def _forward(view: View, u: float, v: float) -> float:
    """The head-forward component of the master's ray (u, v, f) (pixels off the principal point), by the rig
    model of vergence.head.depth: the depth Z of a point on that ray is this times its scale."""
    f, p, t = view.focal_px, view.master_pan_rad, view.tilt_rad
    cp, sp, ct, st = math.cos(p), math.sin(p), math.cos(t), math.sin(t)
    if view.gimbal == "fick":
        return -u * sp + (v * st + f * ct) * cp
    return (-u * sp + f * cp) * ct + v * st


def fixation_point(x: float, y: float, depth_m: float, view: View) -> tuple[float, float, float] | None:
    """The point fixated at master pixel (x, y) whose depth along the head's forward axis is depth_m, in the
    master's optical frame (m); None without a finite positive depth or when the ray does not go forward."""
    if not (math.isfinite(depth_m) and depth_m > 0 and math.isfinite(x) and math.isfinite(y)):
        return None
    cx, cy = view.centre
    u, v = x - cx, y - cy
    fwd = _forward(view, u, v)
    if not fwd > 0:
        return None
    s = depth_m / fwd
    return u * s, v * s, view.focal_px * s


def fixation_covariance(point: tuple[float, float, float], depth_sigma_m: float, view: View) -> list[float]:
    """The 6 x 6 row-major covariance of a geometry_msgs/PoseWithCovariance whose position is `point`: the
    position block sigma_r^2 d d^T + sigma_l^2 (I - d d^T), d the unit viewing ray, sigma_r the depth's sigma
    along it and sigma_l the pixel's quantisation across it; the orientation rows UNKNOWN_VARIANCE (a point has
    none). A sigma that is not finite gives UNKNOWN_VARIANCE on the position's diagonal too."""
    p = np.asarray(point, dtype=np.float64)
    r = float(np.linalg.norm(p))
    cov = np.zeros((6, 6))
    cov[3, 3] = cov[4, 4] = cov[5, 5] = UNKNOWN_VARIANCE
    if not (math.isfinite(depth_sigma_m) and depth_sigma_m >= 0 and r > 0):
        cov[0, 0] = cov[1, 1] = cov[2, 2] = UNKNOWN_VARIANCE
        return cov.ravel().tolist()
    d = p / r
    sigma_r = depth_sigma_m * r / p[2]  # the depth's sigma is along z; along the ray it is longer by r / z
    sigma_l = PIXEL_SIGMA * p[2] / view.focal_px
    dd = np.outer(d, d)
    cov[:3, :3] = sigma_r**2 * dd + sigma_l**2 * (np.eye(3) - dd)
    return cov.ravel().tolist()


class Refused(ValueError):
    """A look-at point that moves nothing; the message says why."""


def look_at_pixel(point: tuple[float, float, float], view: View, window: int, vsearch: int) -> tuple[int, int]:
    """The master pixel (rounded) where `point` (x, y, z in the master's optical frame, m) is seen; Refused
    when it is not finite, not in front of the camera, outside the view, or where the fovea (window, vsearch)
    would not fit."""
    from ..network.retina import BorderError, check_point

    x, y, z = (float(c) for c in point)
    if not all(math.isfinite(c) for c in (x, y, z)):
        raise Refused(f"point ({x:g}, {y:g}, {z:g}) is not finite")
    if not z > 1e-6:
        raise Refused(f"point ({x:g}, {y:g}, {z:g}) is not in front of the camera (z must be > 0)")
    cx, cy = view.centre
    u, v = view.focal_px * x / z + cx, view.focal_px * y / z + cy
    if not (0 <= u < view.width and 0 <= v < view.height):
        raise Refused(f"point ({x:g}, {y:g}, {z:g}) is outside the view: pixel ({u:.0f}, {v:.0f}) of a "
                      f"{view.width} x {view.height} image")
    px, py = int(round(u)), int(round(v))
    try:
        check_point((view.height, view.width), px, py, window, vsearch)
    except BorderError as e:
        raise Refused(f"point ({x:g}, {y:g}, {z:g}) at pixel ({px}, {py}): {e}") from None
    return px, py


def pan_at(states: list[tuple[int, float]], t_ns: int, default: float) -> float:
    """The pan at t_ns from motor states (t_ns, pan_rad) in arrival order: interpolated between the two that
    bracket it, the latest one before it when none is later yet, the earliest one when t_ns precedes them all,
    `default` without any."""
    if not states:
        return default
    before = max((s for s in states if s[0] <= t_ns), default=None, key=lambda s: s[0])
    after = min((s for s in states if s[0] > t_ns), default=None, key=lambda s: s[0])
    if before is None:
        return after[1]
    if after is None or after[0] == before[0]:
        return before[1]
    return before[1] + (after[1] - before[1]) * (t_ns - before[0]) / (after[0] - before[0])


# -- joint, correlation -----------------------------------------------------------------------------------------

def joint_velocity(prev: tuple[int, float] | None, cur: tuple[int, float]) -> float:
    """The pan's velocity (rad/s) between two motor states (t_ns, pan_rad); NaN without a previous one or when
    the times do not increase (JointState's convention for an unknown value)."""
    if prev is None or not cur[0] > prev[0]:
        return math.nan
    return (cur[1] - prev[1]) * NS_PER_S / (cur[0] - prev[0])


def correlation_layout(rows: int, k_count: int) -> list[tuple[str, int, int]]:
    """std_msgs/MultiArrayLayout dims (label, size, stride) of the rows x K layer-4 profile, row-major."""
    return [("v", rows, rows * k_count), ("k", k_count, k_count)]


# -- diagnostics ------------------------------------------------------------------------------------------------

@dataclass
class Diagnostic:
    """The fields of one diagnostic_msgs/msg/DiagnosticStatus."""

    level: int
    name: str
    message: str
    hardware_id: str
    values: list[tuple[str, str]] = field(default_factory=list)


def _flat(prefix: str, value, out: list[tuple[str, str]]) -> None:
    if isinstance(value, dict):
        for k, v in value.items():
            _flat(f"{prefix}.{k}" if prefix else str(k), v, out)
    elif isinstance(value, float):
        out.append((prefix, f"{value:.6g}"))
    elif isinstance(value, str):
        out.append((prefix, value))
    else:
        out.append((prefix, json.dumps(value)))


def diagnostic(rig: str, status: Status, age_s: float, stale_s: float, bad_before: int | None) -> Diagnostic:
    """One process's DiagnosticStatus from its latest status (vergence.wire.status.Status), received age_s ago: STALE
    when older than stale_s, ERROR when it said it exits or names a fault (vergence.head.doubt), WARN when its `bad`
    total grew since the previous status (bad_before; None: the first one) or it searches (vergence.head.search),
    else OK. Its counters and fields as key-values."""
    values: list[tuple[str, str]] = []
    for k, v in status.to_dict().items():
        if k not in ("role", "id"):
            _flat("" if k == "counters" else k, v, values)
    name = f"vergence/{rig}/{status.role}/{status.id}"
    if age_s > stale_s:
        return Diagnostic(STALE, name, f"no status for {age_s:.1f} s", rig, values)
    if status.exiting:
        return Diagnostic(ERROR, name, "exited", rig, values)
    if (fault := status.fault()) is not None:
        return Diagnostic(ERROR, name, f"fault {fault[0]}: {fault[1]}"[:400], rig, values)
    if bad_before is not None and status.bad_total > bad_before:
        kinds = ", ".join(f"{k} {v}" for k, v in sorted(status.bad.items()))
        return Diagnostic(WARN, name, f"bad messages: {kinds}", rig, values)
    if (note := status.search_note() or status.texture_note()) is not None:  # lost, searching; or black frames
        return Diagnostic(WARN, name, note, rig, values)
    return Diagnostic(OK, name, "ok", rig, values)


# -- images -----------------------------------------------------------------------------------------------------

class ImageError(ValueError):
    """An image message that cannot be used; the message says why."""


# encoding: (channels, bytes per channel, cv2 conversion to gray or None)
ENCODINGS = {"mono8": (1, 1, None), "8uc1": (1, 1, None), "mono16": (1, 2, None), "bgr8": (3, 1, cv2.COLOR_BGR2GRAY),
             "rgb8": (3, 1, cv2.COLOR_RGB2GRAY), "bgra8": (4, 1, cv2.COLOR_BGRA2GRAY),
             "rgba8": (4, 1, cv2.COLOR_RGBA2GRAY)}


def image_gray(encoding: str, width: int, height: int, step: int, data, is_bigendian: int = 0) -> np.ndarray:
    """A sensor_msgs/Image's fields -> a (height, width) uint8 gray array (mono16 keeps its high byte)."""
    enc = ENCODINGS.get(str(encoding).lower())
    if enc is None:
        raise ImageError(f"encoding {encoding!r} is not one vergence reads (want one of {', '.join(ENCODINGS)})")
    ch, bpc, conv = enc
    row = width * ch * bpc
    if width <= 0 or height <= 0:
        raise ImageError(f"image of {width} x {height} pixels")
    if step < row:
        raise ImageError(f"step {step} is less than width x bytes per pixel ({row})")
    buf = np.frombuffer(memoryview(data), dtype=np.uint8)
    if buf.size < step * (height - 1) + row:
        raise ImageError(f"{buf.size} bytes of data for {height} rows of step {step}")
    rows = np.lib.stride_tricks.as_strided(buf, shape=(height, row), strides=(step, 1))
    if bpc == 2:
        px = rows.view(">u2" if is_bigendian else "<u2").reshape(height, width)
        return np.ascontiguousarray((px >> 8).astype(np.uint8))
    img = rows.reshape(height, width, ch) if ch > 1 else rows
    return cv2.cvtColor(np.ascontiguousarray(img), conv) if conv is not None else np.ascontiguousarray(img)


def compressed_gray(fmt: str, data) -> np.ndarray:
    """A sensor_msgs/CompressedImage (format: jpeg, png, or image_transport's "bgr8; jpeg compressed bgr8")
    -> a uint8 gray array."""
    kind = str(fmt).lower()
    if "compresseddepth" in kind:
        raise ImageError(f"format {fmt!r}: a compressed depth image, not a camera image")
    if not any(k in kind for k in ("jpeg", "jpg", "png")):
        raise ImageError(f"format {fmt!r}: want jpeg or png")
    buf = np.frombuffer(memoryview(data), dtype=np.uint8)
    img = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE) if buf.size else None
    if img is None:
        raise ImageError(f"{buf.size} bytes that OpenCV cannot decode as {fmt!r}")
    return img


# -- pairing ----------------------------------------------------------------------------------------------------

class Pairer:
    """Approximate-time pairing of a left and a right stream: add(side, t_ns, item) -> (t_left, left, t_right,
    right) when the newcomer's closest partner on the other side is within slop_ns, else None. A pair drops
    every older item on both sides; items that leave unpaired (older than a pair, or pushed out of the
    `depth` newest) are counted in `unmatched`."""

    def __init__(self, slop_ns: int, depth: int = 8):
        self.slop_ns, self.depth = int(slop_ns), depth
        self.queues: tuple[list, list] = ([], [])
        self.unmatched = 0
        self.pairs = 0

    def add(self, side: int, t_ns: int, item):
        mine, other = self.queues[side], self.queues[1 - side]
        best = min(range(len(other)), key=lambda i: abs(other[i][0] - t_ns), default=None)
        if best is not None and abs(other[best][0] - t_ns) <= self.slop_ns:
            t_o, o = other[best]
            self.unmatched += best + len([m for m in mine if m[0] <= t_ns])
            del other[: best + 1]
            mine[:] = [m for m in mine if m[0] > t_ns]
            self.pairs += 1
            return (t_ns, item, t_o, o) if side == 0 else (t_o, o, t_ns, item)
        mine.append((t_ns, item))
        mine.sort(key=lambda m: m[0])
        if len(mine) > self.depth:
            self.unmatched += len(mine) - self.depth
            del mine[: len(mine) - self.depth]
        return None
