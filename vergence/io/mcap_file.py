"""Recordings as ROS 2 MCAP files (`vergence record FILE.mcap`, `vergence replay FILE.mcap`), without ROS.

An MCAP file with the ros2 profile: each channel's schema is the ros2msg text of its type (with its
dependencies, as rosbag2 writes them) and its messages CDR, serialised by rosbags (pure Python), so that
`ros2 bag`, Foxglove, PlotJuggler and any MCAP reader open it. Under /vergence/<rig>/, as the bridge
(services/bridges/ros2.py) publishes them:

    joint_states          sensor_msgs/msg/JointState       each motor_state (stamp: its t_ns)
    fixation              geometry_msgs/msg/PointStamped   each converged decision (stamp: its capture time)
    fixation/covariance   geometry_msgs/msg/PoseWithCovarianceStamped
    correlation           std_msgs/msg/Float32MultiArray   each profile's layer 4
    preview/master, preview/slave   sensor_msgs/msg/Image (mono8)   each preview (stamp: its capture time)
    /diagnostics          diagnostic_msgs/msg/DiagnosticArray   each status, one DiagnosticStatus

and every Zenoh sample as it travelled, for `vergence replay`: /vergence/<rig>/zenoh/<kind> (kind: frame,
decision, correlation, status ...), std_msgs/msg/UInt8MultiArray whose data is the payload and whose layout's
two dims name the Zenoh key and the event (put, delete, alive, dead). A message's log time is its arrival
(time.time_ns()), its publish time the time it carries (t_capture_ns, t_ns) where it has one.

McapWriter has vergence.io.recording.Writer's interface (write(key, t_ns, payload, event), count, bytes, close);
McapReader yields vergence.io.recording.Records from the zenoh/ channels, as vergence.io.recording.Reader does.
A payload that does not decode as its kind is still recorded raw; only its ROS 2 message is left out.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator

import numpy as np

from ..wire import keys
from ..ros2 import convert as conv
from ..wire.messages import MessageError, MotorState, Preview, Profile, Decision
from .recording import EVENTS, Record, RecordingError
from ..wire.status import decode_status

__all__ = ["McapWriter", "McapReader", "is_mcap", "RAW_TYPE"]

RAW_TYPE = "std_msgs/msg/UInt8MultiArray"


def is_mcap(path: str | os.PathLike) -> bool:
    return os.fspath(path).lower().endswith(".mcap")


def _store():
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise RecordingError("MCAP recordings need rosbags and mcap: pip install 'vergence[ros2]'") from None
    return get_typestore(Stores.ROS2_JAZZY)


class McapWriter:
    """Writes a vergence rig's samples into a ROS 2 MCAP file (see the module's docstring)."""

    def __init__(self, path: str | os.PathLike, rig: str = "", t_start_ns: int | None = None, *,
                 joint: str | None = None, frame_id: str | None = None, gimbal: str = "helmholtz"):
        try:
            from mcap.writer import CompressionType, Writer
        except ImportError:
            raise RecordingError("MCAP recordings need mcap: pip install 'vergence[ros2]'") from None
        self.store = _store()
        self.path, self.rig, self.gimbal = os.fspath(path), rig, gimbal
        name = conv.ros_name(rig or "head")
        self.ns = f"/vergence/{name}"
        self.joint = joint or f"{name}_slave_pan"
        self.frame_id = frame_id or f"{name}_master_optical_frame"
        try:
            self.fh = open(self.path, "wb")
        except OSError as e:
            raise RecordingError(f"cannot write {self.path!r}: {e.strerror}") from None
        self.mcap = Writer(self.fh, compression=CompressionType.ZSTD)
        self.mcap.start(profile="ros2", library="vergence")
        self.schemas: dict[str, int] = {}
        self.channels: dict[str, int] = {}
        self.seq: dict[int, int] = {}
        self.count = 0
        self.bytes = 0
        self.durable = (0, 0)  # (samples, bytes) flushed
        self.view: conv.View | None = None
        self.motor: tuple[int, float] | None = None
        self.T = self.store.types

    # -- channels ------------------------------------------------------------------------------------------------

    def _channel(self, topic: str, typename: str) -> int:
        cid = self.channels.get(topic)
        if cid is None:
            sid = self.schemas.get(typename)
            if sid is None:
                text = self.store.generate_msgdef(typename, ros_version=2)[0]
                sid = self.schemas[typename] = self.mcap.register_schema(typename, "ros2msg", text.encode())
            cid = self.channels[topic] = self.mcap.register_channel(topic, "cdr", sid)
        return cid

    def _put(self, topic: str, typename: str, msg, log_ns: int, pub_ns: int) -> None:
        cid = self._channel(topic, typename)
        data = bytes(self.store.serialize_cdr(msg, typename))
        seq = self.seq[cid] = self.seq.get(cid, 0) + 1
        self.mcap.add_message(cid, log_time=log_ns, data=data, publish_time=pub_ns, sequence=seq)
        self.bytes += len(data)

    def _header(self, t_ns: int, frame_id: str = ""):
        sec, nsec = conv.stamp(t_ns)
        return self.T["std_msgs/msg/Header"](stamp=self.T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec),
                                             frame_id=frame_id)

    def _layout(self, dims: list[tuple[str, int, int]]):
        D = self.T["std_msgs/msg/MultiArrayDimension"]
        return self.T["std_msgs/msg/MultiArrayLayout"](dim=[D(label=lb, size=sz, stride=st) for lb, sz, st in dims],
                                                      data_offset=0)

    # -- the interface of vergence.io.recording.Writer -----------------------------------------------------------------

    def write(self, key: str, t_ns: int, payload: bytes, event: str = "put") -> None:
        """One sample (raw, and as its ROS 2 message where there is one); RecordingError, naming the file and the
        error, when the file can no longer be written (vergence record then stops: issue #29)."""
        try:
            self._write(key, t_ns, payload, event)
        except OSError as e:
            raise RecordingError(f"cannot write recording {self.path!r}: {e.strerror or e}") from None

    def check(self) -> None:
        """RecordingError if the file was removed or replaced since it was opened (writes to it would be lost)."""
        try:
            st, mine = os.stat(self.path), os.fstat(self.fh.fileno())
            same = (st.st_dev, st.st_ino) == (mine.st_dev, mine.st_ino)
        except OSError:
            same = False
        if not same:
            raise RecordingError(f"cannot write recording {self.path!r}: it was removed or replaced while recording")

    def _write(self, key: str, t_ns: int, payload: bytes, event: str) -> None:
        if event not in EVENTS:
            raise ValueError(f"event {event!r}: not one of {EVENTS}")
        k = keys.parse(key)
        kind = k.kind if k is not None else "other"
        raw = self.T[RAW_TYPE](layout=self._layout([(key, len(payload), 1), (event, 0, 0)]),
                               data=np.frombuffer(payload, np.uint8))
        self._put(f"{self.ns}/zenoh/{kind.replace('/', '_')}", RAW_TYPE, raw, t_ns, t_ns)
        self.count += 1
        if event == "put" and k is not None:
            try:
                self._convert(k.kind, t_ns, payload)
            except (MessageError, ValueError):
                pass  # recorded raw above; no ROS 2 message for what does not decode

    def _convert(self, kind: str, t_ns: int, payload: bytes) -> None:
        if kind == keys.MOTOR_STATE:
            self._joint(MotorState.from_bytes(payload), t_ns)
        elif kind == keys.FRAME:
            self.view = conv.view_of_frame(payload, self.gimbal)
        elif kind == keys.DECISION:
            self._fixation(Decision.from_bytes(payload), t_ns)
        elif kind == keys.PROFILE:
            self._correlation(Profile.from_bytes(payload), t_ns)
        elif kind == keys.PREVIEW:
            self._preview(Preview.from_bytes(payload), t_ns)
        elif kind == keys.STATUS:
            self._status(payload, t_ns)

    def _joint(self, st: MotorState, t_ns: int) -> None:
        cur = (st.t_ns, st.pan_rad)
        vel = conv.joint_velocity(self.motor, cur)
        self.motor = cur
        msg = self.T["sensor_msgs/msg/JointState"](header=self._header(st.t_ns), name=[self.joint],
                                                   position=np.array([st.pan_rad]), velocity=np.array([vel]),
                                                   effort=np.zeros(0))
        self._put(f"{self.ns}/joint_states", "sensor_msgs/msg/JointState", msg, t_ns, st.t_ns)

    def _fixation(self, v: Decision, t_ns: int) -> None:
        if not v.converged or self.view is None:
            return
        p = conv.fixation_point(v.x, v.y, v.depth_m, self.view)
        if p is None:
            return
        T = self.T
        point = T["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2])
        self._put(f"{self.ns}/fixation", "geometry_msgs/msg/PointStamped",
                  T["geometry_msgs/msg/PointStamped"](header=self._header(v.t_capture_ns, self.frame_id), point=point),
                  t_ns, v.t_capture_ns)
        pose = T["geometry_msgs/msg/Pose"](position=point, orientation=T["geometry_msgs/msg/Quaternion"](
            x=0.0, y=0.0, z=0.0, w=1.0))
        cov = np.array(conv.fixation_covariance(p, v.depth_sigma_m, self.view))
        msg = T["geometry_msgs/msg/PoseWithCovarianceStamped"](
            header=self._header(v.t_capture_ns, self.frame_id),
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov))
        self._put(f"{self.ns}/fixation/covariance", "geometry_msgs/msg/PoseWithCovarianceStamped", msg, t_ns,
                  v.t_capture_ns)

    def _correlation(self, pr: Profile, t_ns: int) -> None:
        scores = pr.array()
        msg = self.T["std_msgs/msg/Float32MultiArray"](layout=self._layout(conv.correlation_layout(*scores.shape)),
                                                       data=scores.astype(np.float32).ravel())
        self._put(f"{self.ns}/correlation", "std_msgs/msg/Float32MultiArray", msg, t_ns, pr.t_capture_ns)

    def _preview(self, pv: Preview, t_ns: int) -> None:
        name = conv.ros_name(self.rig or "head")
        for cam, img in zip(("master", "slave"), pv.images()):
            msg = self.T["sensor_msgs/msg/Image"](header=self._header(pv.t_capture_ns, f"{name}_{cam}_optical_frame"),
                                                  height=pv.height, width=pv.width, encoding="mono8", is_bigendian=0,
                                                  step=pv.width, data=np.ascontiguousarray(img).ravel())
            self._put(f"{self.ns}/preview/{cam}", "sensor_msgs/msg/Image", msg, t_ns, pv.t_capture_ns)

    def _status(self, payload: bytes, t_ns: int) -> None:
        d = conv.diagnostic(self.rig, decode_status(payload), 0.0, math.inf, None)
        T = self.T
        status = T["diagnostic_msgs/msg/DiagnosticStatus"](
            level=d.level, name=d.name, message=d.message[:500], hardware_id=d.hardware_id,
            values=[T["diagnostic_msgs/msg/KeyValue"](key=k, value=v) for k, v in d.values])
        msg = T["diagnostic_msgs/msg/DiagnosticArray"](header=self._header(t_ns), status=[status])
        self._put("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", msg, t_ns, t_ns)

    def flush(self) -> None:
        try:
            self.fh.flush()
        except OSError as e:
            raise RecordingError(f"cannot write recording {self.path!r}: {e.strerror or e}") from None
        self.durable = (self.count, self.bytes)

    def close(self) -> None:
        if self.fh.closed:
            return
        try:
            self.mcap.finish()
        except OSError:
            pass  # a failed disk: the file keeps what was written, without its summary (mcap recover reads it)
        finally:
            try:
                self.fh.close()
            except OSError:
                pass

    def __enter__(self) -> McapWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class McapReader:
    """The Zenoh samples of an MCAP file written by McapWriter, as vergence.io.recording.Records in file order (the
    order they arrived). Read without the file's summary, so that a file cut short (a recorder killed: its last
    chunk is lost) reads up to its last whole chunk; Reader.truncated then says so."""

    def __init__(self, path: str | os.PathLike):
        try:
            from mcap.reader import NonSeekingReader
        except ImportError:
            raise RecordingError("MCAP recordings need mcap: pip install 'vergence[ros2]'") from None
        self.store = _store()
        self.path = os.fspath(path)
        try:
            self.fh = open(self.path, "rb")
        except OSError as e:
            raise RecordingError(f"cannot read {self.path!r}: {e.strerror}") from None
        if self.fh.read(8) != b"\x89MCAP0\r\n":
            self.fh.close()
            raise RecordingError(f"{self.path!r} is not an MCAP file (no MCAP magic)")
        self.fh.seek(0)
        self.reader = NonSeekingReader(self.fh)
        self.truncated = False

    def __iter__(self) -> Iterator[Record]:
        try:
            for schema, channel, message in self.reader.iter_messages():
                if schema is None or schema.name != RAW_TYPE or "/zenoh/" not in channel.topic:
                    continue
                raw = self.store.deserialize_cdr(message.data, RAW_TYPE)
                dims = raw.layout.dim
                if len(dims) != 2 or dims[1].label not in EVENTS:
                    raise RecordingError(f"{self.path!r}: a message on {channel.topic} is not a vergence sample")
                yield Record(dims[0].label, message.log_time, bytes(raw.data), dims[1].label)
        except RecordingError:
            raise
        except Exception as e:  # mcap's own errors, or struct's, at a file cut short: what was read stands
            if isinstance(e, (GeneratorExit, KeyboardInterrupt)):
                raise
            self.truncated = True

    def close(self) -> None:
        self.fh.close()

    def __enter__(self) -> McapReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
