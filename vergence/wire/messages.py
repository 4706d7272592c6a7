"""Every message on the wire: a msgspec.Struct per kind, msgpack maps with a schema version `v`.

Decoding never trusts its input: a message that is not a map, lacks a field, has a field of the wrong
type, or arrays whose sizes do not agree with their shape fields raises MessageError, which services count
and skip. msgspec checks the types (one Decoder per kind, made once; its errors name the field, `at $.x`),
each kind's validate() the values. Arrays travel as binary fields (raw little-endian bytes), never as lists of
numbers. A map without `v`, or with another schema's, is refused.
"""

from __future__ import annotations

import math
import typing
from typing import ClassVar

import msgspec
import numpy as np

__all__ = ["SCHEMA", "MessageError", "Message", "Frame", "Correlation", "Decision", "Profile", "Command", "MotorState",
           "Preview", "Fixate", "Hold", "MAX_HOLD_S", "KINDS", "replace"]

SCHEMA = 1
MAX_MESSAGE = 64 * 1024 * 1024

_ENCODER = msgspec.msgpack.Encoder()
_DECODERS: dict[type, msgspec.msgpack.Decoder] = {}
_FLOATS: dict[type, tuple[str, ...]] = {}


class MessageError(ValueError):
    """A message that cannot be decoded or fails validation."""


class Message(msgspec.Struct, tag_field="v", tag=SCHEMA):
    """Base of every message: to_bytes / from_bytes with validation; `v`, the schema version, is the tag."""

    KIND: ClassVar[str] = ""

    def to_dict(self) -> dict:
        d = {name: getattr(self, name) for name in self.__struct_fields__}
        d["v"] = SCHEMA
        return d

    def to_bytes(self) -> bytes:
        return _ENCODER.encode(self)

    @classmethod
    def from_bytes(cls, data: bytes) -> "Message":
        if len(data) > MAX_MESSAGE:
            raise MessageError(f"{cls.KIND}: {len(data)} bytes, more than {MAX_MESSAGE}")
        try:
            msg = _DECODERS[cls].decode(data)
            if type(msg) is not cls:  # the sentinel kind of _NoSchema
                raise msgspec.ValidationError(f"Invalid value {-2**63} - at `$.v`")
        except msgspec.ValidationError as e:
            if str(e).endswith("at `$.v`"):
                raise MessageError(f"{cls.KIND}: schema version: {e}, this build speaks {SCHEMA}") from None
            raise MessageError(f"{cls.KIND}: {e}") from None
        except (msgspec.DecodeError, TypeError, ValueError, RecursionError, OverflowError) as e:
            raise MessageError(f"{cls.KIND}: not msgpack ({type(e).__name__}: {e})") from None
        # every NaN decodes to the one math.nan, so that messages with NaN fields (a decision's depth while not
        # converged) compare equal after a round trip, as Struct equality compares identical objects as equal
        for name in _FLOATS[cls]:
            x = getattr(msg, name)
            if x != x:
                setattr(msg, name, math.nan)
        msg.validate()
        return msg

    def validate(self) -> None:
        """Cross-field checks; raise MessageError."""


class _NoSchema(Message, tag=-2**63):
    """A decoder's second choice that no message is (its v is no schema), so that msgspec, choosing between two
    tagged kinds, requires the tag: a map without `v` is refused, as it was before msgspec."""


def replace(msg: Message, **changes) -> Message:
    """A copy of a message with some fields changed (msgspec.structs.replace; no validation)."""
    return msgspec.structs.replace(msg, **changes)


def _array(name: str, data: bytes, dtype, shape: tuple[int, ...]) -> np.ndarray:
    dt = np.dtype(dtype)
    if any(s < 0 for s in shape):
        raise MessageError(f"{name}: negative shape {shape}")
    if len(data) != dt.itemsize * math.prod(shape):
        raise MessageError(f"{name}: {len(data)} bytes do not make a {dt.name} array of shape {shape}")
    return np.frombuffer(data, dtype=dt).reshape(shape)


def _finite(name: str, *values: float) -> None:
    for x in values:
        if not math.isfinite(x):
            raise MessageError(f"{name}: not a finite number ({x})")


MAX_SKEW_NS = 500_000_000  # a frame's slave exposure more than this from the master's is not believed
MAX_AGE_NS = 1_500_000_000  # nor a read more than this after the exposure (vergence.head.timing.MAX_AGE_S, and slack)


class Frame(Message):
    """vergence/<rig>/frame: what layer 1 needs of one stereo frame, and the shard plan for it.

    fovea: the (w+2) x (w+2) gray master strip around (x, y) with its Sobel margin; band: the
    (w+2R+2) x (W+2) gray slave strip. plan: [[worker id, k0, k1], ...] covering 0..K-1, K = W - w + 1.
    pan_rad: the slave pan at capture time; focal_px the focal length used to turn pixels into angles."""

    KIND: ClassVar[str] = "frame"
    rig: str
    frame: int
    t_capture_ns: int
    pan_rad: float
    width: int
    height: int
    x: int
    y: int
    window: int
    vsearch: int
    focal_px: float
    fovea: bytes
    band: bytes
    plan: list[list[str | int]] = []
    circular: bool = True
    support: bool = False
    # the master's rows of the fovea at full width, for the reducer's left-right check (empty when the
    # check is off); the support weights' two scales (vergence.network.params.Params.support_gamma / support_radius)
    master_band: bytes = b""
    support_gamma: float = 8.0
    support_radius: float = 7.0
    # the master's pan and the common tilt at capture (a fixed master: 0, 0), for the depth of the fixated point
    master_pan_rad: float = 0.0
    tilt_rad: float = 0.0
    # a simulated source's ground truth: the converged slave pan at capture (None from real cameras)
    truth_pan_rad: float | None = None
    # the camera's time (vergence.head.timing): t_capture_ns is the master's exposure; the slave's is skew_ns after it
    # (pan_rad is the slave's pan then); t_read_ns when the capture read the pair (0: an older capture, which
    # stamped its read time); pan_stale: the slave's pan at its exposure is not known (older than the motor's
    # history, or across a gap in it): the frame is decided, and commands nothing; pan_guessed: the pan was told past
    # the motor's newest state (extrapolated): no background verdict is read on it (vergence.head.scenery)
    skew_ns: int = 0
    t_read_ns: int = 0
    pan_stale: bool = False
    pan_guessed: bool = False
    # the CRC-32 of each whole image as read (0: not known): a frozen camera repeats its bytes (vergence.head.doubt)
    master_digest: int = 0
    slave_digest: int = 0
    # the slave's image moves with the slave motor (a camera, the simulator; not a still pair or a video, taken at
    # one pan): only then is each decision checked against the motor's motion
    follows: bool = True
    # the master image's own frame id as its camera named it (a ROS 2 header.frame_id; "": not known): the ROS 2
    # bridge publishes the fixation in it and accepts look_at in it (a claim: it checks it, vergence.ros2.convert)
    frame_id: str = ""
    # each camera's principal point in its image (px; -1: not known, the image centre (width // 2, height // 2), as
    # an older capture had it): pixels_to_angle, the depth, look_at and the fixation measure from it (issue #36)
    cx: float = -1.0
    cy: float = -1.0
    slave_cx: float = -1.0
    slave_cy: float = -1.0

    @property
    def principal(self) -> tuple[float, float]:
        """The master's principal point (the image centre where the frame does not say)."""
        return (self.cx if self.cx >= 0 else self.width // 2, self.cy if self.cy >= 0 else self.height // 2)

    @property
    def slave_principal(self) -> tuple[float, float]:
        """The slave's principal point (the image centre where the frame does not say)."""
        return (self.slave_cx if self.slave_cx >= 0 else self.width // 2,
                self.slave_cy if self.slave_cy >= 0 else self.height // 2)

    @property
    def t_slave_ns(self) -> int:
        """The slave's exposure time."""
        return self.t_capture_ns + self.skew_ns

    @property
    def k_count(self) -> int:
        return self.width - self.window + 1

    def fovea_strip(self) -> np.ndarray:
        return _array("frame.fovea", self.fovea, np.uint8, (self.window + 2, self.window + 2))

    def band_strip(self) -> np.ndarray:
        return _array("frame.band", self.band, np.uint8, (self.window + 2 * self.vsearch + 2, self.width + 2))

    def master_band_strip(self) -> np.ndarray | None:
        """The master's rows of the fovea, full width ((w+2) x (W+2) with the Sobel margin), or None when the
        frame does not carry them."""
        if not self.master_band:
            return None
        return _array("frame.master_band", self.master_band, np.uint8, (self.window + 2, self.width + 2))

    def validate(self) -> None:
        if self.window < 1 or self.window % 2 == 0 or self.window > self.width:
            raise MessageError(f"frame.window {self.window} must be odd and at most width {self.width}")
        if self.vsearch < 0 or self.window + 2 * self.vsearch > self.height:
            raise MessageError(f"frame.vsearch {self.vsearch} does not fit height {self.height}")
        _finite("frame.pan_rad", self.pan_rad)
        _finite("frame.focal_px", self.focal_px)
        _finite("frame.master_pan_rad", self.master_pan_rad, self.tilt_rad)
        if self.focal_px <= 0:
            raise MessageError("frame.focal_px must be positive")
        for name, v, most in (("cx", self.cx, self.width), ("cy", self.cy, self.height),
                              ("slave_cx", self.slave_cx, self.width), ("slave_cy", self.slave_cy, self.height)):
            if not (v == -1.0 or 0 <= v <= most):
                raise MessageError(f"frame.{name} {v}: a principal point in the image (0..{most}), or -1")
        self.fovea_strip()
        self.band_strip()
        self.master_band_strip()
        _finite("frame.support_gamma", self.support_gamma, self.support_radius)
        if self.truth_pan_rad is not None:
            _finite("frame.truth_pan_rad", self.truth_pan_rad)
        if abs(self.skew_ns) > MAX_SKEW_NS:
            raise MessageError(f"frame.skew_ns {self.skew_ns}: the cameras more than 0.5 s apart")
        later, earlier = self.t_capture_ns + max(0, self.skew_ns), self.t_capture_ns + min(0, self.skew_ns)
        if self.t_read_ns and not (self.t_read_ns >= later - 2_000_000 and self.t_read_ns - earlier <= MAX_AGE_NS):
            raise MessageError(f"frame.t_read_ns: read {(self.t_read_ns - self.t_capture_ns) / 1e9:.3g} s after its "
                               "exposure (an image is read after it, within a second)")
        if self.support_gamma <= 0 or self.support_radius <= 0:
            raise MessageError("frame.support_gamma and frame.support_radius must be positive")
        covered = 0
        for entry in self.plan:
            if len(entry) != 3 or not isinstance(entry[0], str) or not all(
                    isinstance(v, int) and not isinstance(v, bool) for v in entry[1:]):
                raise MessageError(f"frame.plan entry {entry!r} is not [worker, k0, k1]")
            if entry[1] != covered or entry[2] <= entry[1]:
                raise MessageError(f"frame.plan is not a partition of 0..{self.k_count - 1}: {self.plan!r}")
            covered = entry[2]
        if self.plan and covered != self.k_count:
            raise MessageError(f"frame.plan covers 0..{covered - 1}, not 0..{self.k_count - 1}")

    def shard(self, worker: str) -> tuple[int, int] | None:
        """This worker's k-range in the frame's plan, or None."""
        for wid, k0, k1 in self.plan:
            if wid == worker:
                return int(k0), int(k1)
        return None


class Correlation(Message):
    """vergence/<rig>/correlation/<worker>: one worker's layer-4 scores y(v, k) for k0..k1-1, float64."""

    KIND: ClassVar[str] = "correlation"
    rig: str
    frame: int
    t_capture_ns: int
    worker: str
    k0: int
    k1: int
    rows: int
    scores: bytes
    t_done_ns: int = 0

    def array(self) -> np.ndarray:
        return _array("correlation.scores", self.scores, "<f8", (self.rows, self.k1 - self.k0))

    def validate(self) -> None:
        if self.k1 <= self.k0 or self.k0 < 0 or self.rows < 1:
            raise MessageError(f"correlation: bad range k0={self.k0} k1={self.k1} rows={self.rows}")
        self.array()


class _Where(Message, kw_only=True):
    """A decision's keyword-only fields with their defaults (what an older reducer did not send)."""

    t_read_ns: int = 0  # when the capture read the frame (t_capture_ns is its master's exposure)
    skew_ns: int = 0  # the slave's exposure after the master's
    x: int = -1
    y: int = -1
    converged: bool = False
    depth_m: float = math.nan
    depth_sigma_m: float = math.nan


class Decision(_Where):
    """vergence/<rig>/decision: the reducer's decision on every frame, a Profile without its scores (under 300
    bytes, where a profile is 65 KB at 640 px with vertical search), for whoever needs only the decision (the
    capture's dynamic window, a user's own logic). window: the fovea side it was decided with. It is a
    vergence.stages.gather.Reduced on the wire (a vergence.network.decide.Decision's fields, its v as v_shift: `v` is
    the schema version; docs/SERVICE.md, "One decision, five names").

    x, y: the fovea centre in master pixels the decision was made for (-1: unknown, an older reducer), so a
    client sees when its vergence/<rig>/fixate request took effect. converged: confident and within 1 px
    (vergence.head.depth.CONVERGED_PX) of the fovea. depth_m, depth_sigma_m: the fixated point's distance along the
    head's forward axis and its one sigma (vergence.head.depth), NaN unless converged (or without rig geometry)."""

    KIND: ClassVar[str] = "decision"
    rig: str
    frame: int
    t_capture_ns: int
    t_reduced_ns: int
    window: int
    k: int
    k_sub: float
    v_shift: int
    k_centre: int
    direction: int
    magnitude: int
    offset_px: float
    confidence: float
    confident: bool
    texture: float
    pan_rad: float

    def validate(self) -> None:
        if self.window < 1:
            raise MessageError(f"{self.KIND}: bad window {self.window}")
        for name in ("offset_px", "k_sub", "confidence", "pan_rad"):
            _finite(f"{self.KIND}.{name}", getattr(self, name))


class Profile(Decision):
    """vergence/<rig>/profile: the decision (Decision's fields) with the full layer-4 scores of the frame
    (rows x K float64), its width and the plan's workers."""

    KIND: ClassVar[str] = "profile"
    width: int
    rows: int
    scores: bytes
    workers: list[str] = []

    def array(self) -> np.ndarray:
        return _array("profile.scores", self.scores, "<f8", (self.rows, self.width - self.window + 1))

    def validate(self) -> None:
        if self.window < 1 or self.window > self.width or self.rows < 1:
            raise MessageError(f"profile: bad shape width={self.width} window={self.window} rows={self.rows}")
        super().validate()
        self.array()


class Command(Message):
    """vergence/<rig>/command: pan_rad, the absolute target pan of the slave (pan at capture + correction)."""

    KIND: ClassVar[str] = "command"
    rig: str
    frame: int
    t_capture_ns: int
    pan_rad: float
    correction_rad: float
    direction: int
    magnitude_px: float
    confidence: float
    t_sent_ns: int = 0


class MotorState(Message):
    """vergence/<rig>/motor_state: where the slave pan is, where it is going, and what safety did."""

    KIND: ClassVar[str] = "motor_state"
    rig: str
    t_ns: int
    pan_rad: float
    goal_rad: float
    min_rad: float
    max_rad: float
    status: str
    driver: str = "sim"
    frame: int = -1
    t_capture_ns: int = 0
    at_limit: bool = False
    clamped: int = 0
    ignored: int = 0
    errors: int = 0
    note: str = ""
    malformed: int = 0  # command messages that failed to decode, skipped
    commands: int = 0  # command messages received (valid or not)
    offset_deg: float = 0.0  # [actuator.motor] offset_deg, applied to every pan here (vergence calibrate reads it)

    def validate(self) -> None:
        _finite("motor_state.pan_rad", self.pan_rad, self.goal_rad, self.min_rad, self.max_rad, self.offset_deg)


class Preview(Message):
    """vergence/<rig>/preview: downscaled gray master and slave images (width x height each), low rate."""

    KIND: ClassVar[str] = "preview"
    rig: str
    frame: int
    t_capture_ns: int
    width: int
    height: int
    scale: float
    master: bytes
    slave: bytes
    pan_rad: float = 0.0
    truth_pan_rad: float | None = None  # a simulated source's converged slave pan at capture

    def images(self) -> tuple[np.ndarray, np.ndarray]:
        shape = (self.height, self.width)
        return _array("preview.master", self.master, np.uint8, shape), _array("preview.slave", self.slave,
                                                                               np.uint8, shape)

    def validate(self) -> None:
        self.images()
        if self.truth_pan_rad is not None:
            _finite("preview.truth_pan_rad", self.truth_pan_rad)


class Fixate(Message):
    """vergence/<rig>/fixate: move the fovea of the running capture to master pixel (x, y) from the next frame
    on (`vergence fixate X,Y`). x, y are rounded to the nearest pixel; a point where the fovea does not fit
    the image is rejected by the capture (counted and logged, nothing moves). source: who asks (free text)."""

    KIND: ClassVar[str] = "fixate"
    x: float
    y: float
    t_ns: int
    source: str = ""

    def validate(self) -> None:
        _finite("fixate.x", self.x, self.y)
        if len(self.source) > 200:
            raise MessageError("fixate.source: longer than 200 characters")


class Hold(Message):
    """vergence/<rig>/hold: the reducer sends no command until until_ns (this host's clock, ns), while a client
    moves the slave itself (`vergence latency`). A lease: it ends by itself, and one further than MAX_HOLD_S
    ahead is not believed (counted, nothing held); until_ns in the past releases it. source: who asks."""

    KIND: ClassVar[str] = "hold"
    until_ns: int
    t_ns: int
    source: str = ""

    def validate(self) -> None:
        if len(self.source) > 200:
            raise MessageError("hold.source: longer than 200 characters")


MAX_HOLD_S = 5.0  # the longest hold one message may claim


KINDS: dict[str, type[Message]] = {c.KIND: c for c in (Frame, Correlation, Decision, Profile, Command, MotorState,
                                                         Preview, Fixate, Hold)}

for _cls in KINDS.values():
    _DECODERS[_cls] = msgspec.msgpack.Decoder(typing.Union[_cls, _NoSchema])
    _FLOATS[_cls] = tuple(name for name, tp in typing.get_type_hints(_cls).items()
                          if name in _cls.__struct_fields__ and tp in (float, float | None))
