"""`vergence ros2 [--namespace NS] [--joint NAME] [--frame-id FRAME]`: the rig's Zenoh topics as ROS 2 topics.

A real rclpy node (vergence.ros2.node; rclpy from a sourced ROS 2 or the `ros2` extra's wheels) under the
namespace NS (default /vergence/<rig>), publishing:

    joint_states          sensor_msgs/msg/JointState       the slave pan (position, velocity) of every
                                                            vergence/<rig>/motor_state, stamped with its t_ns
    fixation              geometry_msgs/msg/PointStamped   the fixated point in the master's optical frame
                                                            (REP 103), only while converged, stamped with the
                                                            frame's capture (exposure) time
    fixation/covariance   geometry_msgs/msg/PoseWithCovarianceStamped   the same point with its covariance
    correlation           std_msgs/msg/Float32MultiArray   layer 4 of each profile (rows v x K offsets k), while
                                                            a ROS 2 node subscribes (checked once a second)
    /diagnostics          diagnostic_msgs/msg/DiagnosticArray   one status per process of the rig, 1 Hz

and subscribing to `look_at` (geometry_msgs/msg/PointStamped in the master's optical frame): the point is
projected to a master pixel (vergence.ros2.convert.look_at_pixel, with the view of the latest frame) and sent as a
messages.Fixate on vergence/<rig>/fixate; a point that is not finite, behind the camera, outside the view,
in another frame_id or too close to the border is refused: counted, logged (at most once a second) and shown
as a warning on /diagnostics; nothing moves. A publisher of another type on look_at (which ROS 2 never
connects to us) is found in the graph once a second, counted (look_at_wrong_type) and named the same way.
More than LOOK_AT_HZ requests a second: the extra ones are counted (look_at_flood) and dropped.

Frames as the camera names them: the fixation is published in the master image's own frame_id (the Frame's,
from the ros2 source; checked by vergence.ros2.convert.frame_id_problem, else ignored and counted:
frame_id_ignored) unless --frame-id is given, else in <rig>_master_optical_frame; a look_at in either name (or
with an empty frame_id) is taken.

[ros2] look_at (vergence.config.Ros2Settings): unset, look_at is on unless the bridge's Zenoh session
authenticates (a client config of deploy/make-certs.sh: a deployed ACL is in force); true or false wins. While
off, a look_at moves nothing: counted (look_at_off), logged at most once a second, a WARN on /diagnostics
saying what to set. [ros2] discovery: this node's ROS 2 discovery range, set in this process's environment
before rclpy starts (localhost by default; subnet; environment: as given). The start's log line says both.

Its own counters go out as every service's status (vergence/<rig>/status/ros2/<id>). SIGINT/SIGTERM: the
node, then the Zenoh session, close. Exit 2 when rclpy cannot be imported (the message says how to get it).
"""

from __future__ import annotations

import argparse
import array
import json
import logging
import os
import sys
import threading
import time

from vergence.wire import keys
from vergence.ros2 import convert as conv
from vergence.config import load
from vergence.wire.messages import Fixate, MessageError, MotorState, Profile, Decision
from vergence.wire.status import Status, decode_status, status_of
from vergence.ros2.node import RosNode, RosUnavailable

from services.runtime import session
from services.runtime.args import whole
from services.runtime.node import Node

log = logging.getLogger("vergence.ros2")
LOOK_AT_HZ = 20.0  # look_at requests passed on per second at most
STALE_S = 3.0  # a process whose latest status is older than this is STALE on /diagnostics
WARN_FOR_S = 5.0  # a refused look_at keeps the bridge's own diagnostic at WARN this long
MOTOR_STATES = {"ok": conv.OK, "starting": conv.OK, "hold": conv.WARN, "disconnected": conv.ERROR,
                "stopped": conv.ERROR}


def configure(p: argparse.ArgumentParser) -> None:
    session.add_options(p)
    p.add_argument("--namespace", default=None, metavar="NS", help="ROS 2 namespace (default /vergence/<rig>)")
    p.add_argument("--joint", default=None, metavar="NAME", help="the slave pan's joint name (default <rig>_slave_pan)")
    p.add_argument("--frame-id", default=None, metavar="FRAME",
                   help="the master camera's optical frame (default: the master image's own frame_id, from the "
                        "ros2 source, else <rig>_master_optical_frame)")
    p.add_argument("--domain", type=whole(0, 232), default=None, metavar="ID",
                   help="ROS_DOMAIN_ID (default: the environment's)")


def _conf_get(conf, key: str):
    try:
        return json.loads(conf.get_json(key))
    except Exception:  # not in this zenoh's config: not set
        return None


def session_identity(conf) -> str | None:
    """Who the bridge's Zenoh session authenticates as (the user of a deploy/make-certs.sh client config, or its
    TLS certificate), or None: not authenticated (a plain `vergence up`, no deployed ACL)."""
    user = _conf_get(conf, "transport/auth/usrpwd/user")
    if user:
        return f"user {user!r}"
    cert = _conf_get(conf, "transport/link/tls/connect_certificate")
    return f"certificate {cert}" if cert else None


def _header(msg, t_ns: int, frame_id: str) -> None:
    msg.header.stamp.sec, msg.header.stamp.nanosec = conv.stamp(t_ns)
    msg.header.frame_id = frame_id


class Bridge:
    """The ROS 2 side: publishers, the look_at subscription, the latest view and statuses. The on_* methods
    take Zenoh payloads (from zenoh's threads); on_look_at runs in the rclpy thread."""

    def __init__(self, ros: RosNode, rig: str, joint: str, frame_id: str, settings, health, put_fixate,
                 profiles=None, explicit_frame: bool = False, look_at: bool = True):
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PointStamped, PoseWithCovarianceStamped
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float32MultiArray

        self.ros, self.rig, self.joint, self.frame_id = ros, rig, joint, frame_id
        self.explicit_frame = explicit_frame  # --frame-id given: it names the optical frame, whatever the camera's
        self.look_at = look_at  # [ros2] look_at (look_at_mode): off, a look_at moves nothing
        self.settings, self.health, self.put_fixate = settings, health, put_fixate
        self.profiles = profiles  # profiles(True | False): follow vergence/<rig>/profile or not
        self.following = False
        n, q = ros.node, ros.reliable_qos
        self.pub_joint = n.create_publisher(JointState, "joint_states", q)
        self.pub_fix = n.create_publisher(PointStamped, "fixation", q)
        self.pub_cov = n.create_publisher(PoseWithCovarianceStamped, "fixation/covariance", q)
        self.pub_corr = n.create_publisher(Float32MultiArray, "correlation", q)
        self.pub_diag = n.create_publisher(DiagnosticArray, "/diagnostics", q)
        self.sub_look = n.create_subscription(PointStamped, "look_at", self.on_look_at, q)
        self.lock = threading.Lock()
        self.view: conv.View | None = None
        self.motor: tuple[int, float] | None = None
        self.motor_state: MotorState | None = None
        self.statuses: dict[str, tuple[float, Status, int | None]] = {}  # key: (arrival, status, bad before)
        self.refusal: tuple[float, str] | None = None
        self.look_times: list[float] = []
        self.wrong_types: set[tuple[str, str, str]] = set()
        self._last_log = -1e9
        self._said_frame_id: set[str] = set()
        self.timer = n.create_timer(1.0, self.publish_diagnostics)

    # -- Zenoh -> ROS 2 ---------------------------------------------------------------------------------------

    def on_motor(self, payload: bytes) -> None:
        from sensor_msgs.msg import JointState

        try:
            st = MotorState.from_bytes(payload)
            cur = (st.t_ns, st.pan_rad)
            msg = JointState()
            _header(msg, st.t_ns, "")
        except (MessageError, ValueError) as e:
            self.health.reject("motor_state", e)
            return
        with self.lock:
            vel = conv.joint_velocity(self.motor, cur)
            self.motor, self.motor_state = cur, st
        msg.name = [self.joint]
        msg.position = array.array("d", [st.pan_rad])
        msg.velocity = array.array("d", [vel])
        self.pub_joint.publish(msg)
        self.health.count("joint_states")

    def on_frame(self, payload: bytes) -> None:
        try:
            view = conv.view_of_frame(payload, self.settings.geometry.gimbal)
        except ValueError as e:
            self.health.reject("frame", e)
            return
        if view.bad_frame_id:
            self.health.count("frame_id_ignored")
            if view.bad_frame_id not in self._said_frame_id and len(self._said_frame_id) < 10:
                self._said_frame_id.add(view.bad_frame_id)
                log.warning("the frame's %s: not taken as the optical frame's name (further ones are only "
                            "counted); using %s", view.bad_frame_id, self.frame_id)
        with self.lock:
            self.view = view
        self.health.count("frames")

    def optical_frame(self, view: conv.View | None) -> str:
        """The name of the master's optical frame: --frame-id when given, else the master image's own frame_id
        (the latest frame's, when it had one), else <rig>_master_optical_frame."""
        if self.explicit_frame or view is None or not view.frame_id:
            return self.frame_id
        return view.frame_id

    def on_decision(self, payload: bytes) -> None:
        from geometry_msgs.msg import PointStamped, PoseWithCovarianceStamped

        try:
            v = Decision.from_bytes(payload)
        except MessageError as e:
            self.health.reject("decision", e)
            return
        with self.lock:
            view = self.view
        if not v.converged or view is None:
            return
        p = conv.fixation_point(v.x, v.y, v.depth_m, view)
        if p is None:
            return
        try:
            msg, cov = PointStamped(), PoseWithCovarianceStamped()
            frame_id = self.optical_frame(view)
            _header(msg, v.t_capture_ns, frame_id)
            _header(cov, v.t_capture_ns, frame_id)
        except ValueError as e:
            self.health.reject("decision", e)
            return
        msg.point.x, msg.point.y, msg.point.z = p
        pos = cov.pose.pose.position
        pos.x, pos.y, pos.z = p
        cov.pose.covariance = array.array("d", conv.fixation_covariance(p, v.depth_sigma_m, view))
        self.pub_fix.publish(msg)
        self.pub_cov.publish(cov)
        self.health.count("fixations")

    def on_profile(self, payload: bytes) -> None:
        from std_msgs.msg import Float32MultiArray, MultiArrayDimension

        try:
            pr = Profile.from_bytes(payload)
            scores = pr.array()
        except MessageError as e:
            self.health.reject("profile", e)
            return
        msg = Float32MultiArray()
        msg.layout.dim = [MultiArrayDimension(label=lb, size=sz, stride=st)
                          for lb, sz, st in conv.correlation_layout(*scores.shape)]
        data = array.array("f")
        data.frombytes(scores.astype("<f4").tobytes())
        msg.data = data
        self.pub_corr.publish(msg)
        self.health.count("correlations")

    def on_status(self, key: str, payload: bytes) -> None:
        try:
            st = decode_status(payload)
        except MessageError as e:
            self.health.reject("status", e)
            return
        with self.lock:
            prev = self.statuses.get(key)
            self.statuses[key] = (time.monotonic(), st, prev[1].bad_total if prev is not None else None)

    # -- /diagnostics --------------------------------------------------------------------------------------------

    def diagnostics(self, own: Status) -> list[conv.Diagnostic]:
        now = time.monotonic()
        with self.lock:
            items = sorted(self.statuses.items())
            motor, refusal = self.motor_state, self.refusal
        out = [conv.diagnostic(self.rig, st, now - t, STALE_S, before) for _, (t, st, before) in items]
        if motor is not None:
            age = (time.time_ns() - motor.t_ns) / 1e9
            level = conv.STALE if age > STALE_S else MOTOR_STATES.get(motor.status, conv.WARN)
            vals = [(k, str(getattr(motor, k))) for k in ("pan_rad", "goal_rad", "status", "driver", "commands",
                                                         "clamped", "ignored", "errors", "malformed")]
            out.append(conv.Diagnostic(level, f"vergence/{self.rig}/motor", motor.note or motor.status, self.rig, vals))
        mine = conv.diagnostic(self.rig, own, 0.0, STALE_S, None)
        if refusal is not None and now - refusal[0] < WARN_FOR_S:
            mine.level, mine.message = conv.WARN, refusal[1]
        out.append(mine)
        return out

    def check_look_at_types(self) -> None:
        """A publisher of another type on look_at never reaches us (ROS 2 matches by type): find it in the
        graph, count it once and say so (log, /diagnostics)."""
        for info in self.ros.node.get_publishers_info_by_topic(self.sub_look.topic_name):
            who = (info.node_namespace, info.node_name, info.topic_type)
            if info.topic_type != "geometry_msgs/msg/PointStamped" and who not in self.wrong_types:
                self.wrong_types.add(who)
                self.health.count("look_at_wrong_type")
                self.refuse(f"node {info.node_namespace.rstrip('/')}/{info.node_name} publishes {info.topic_type} "
                            f"on {self.sub_look.topic_name}: want geometry_msgs/msg/PointStamped")

    def follow_correlation(self) -> None:
        """Subscribe to the profiles only while someone subscribes to `correlation`: the reducer encodes and
        sends its 65 KB profiles only while it has a subscriber."""
        want = self.pub_corr.get_subscription_count() > 0
        if self.profiles is not None and want != self.following:
            self.profiles(want)
            self.following = want
            log.info("correlation: %s", "a ROS 2 subscriber: following the profiles" if want else
                     "no ROS 2 subscriber: not following the profiles")

    def publish_diagnostics(self) -> None:
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

        self.check_look_at_types()
        self.follow_correlation()

        arr = DiagnosticArray()
        arr.header.stamp = self.ros.node.get_clock().now().to_msg()
        for d in self.diagnostics(status_of(self.health.status())):
            arr.status.append(DiagnosticStatus(level=bytes([d.level]), name=d.name, message=d.message[:500],
                                               hardware_id=d.hardware_id,
                                               values=[KeyValue(key=k, value=v) for k, v in d.values]))
        self.pub_diag.publish(arr)
        self.health.count("diagnostics")

    # -- ROS 2 -> Zenoh --------------------------------------------------------------------------------------------

    def refuse(self, why: str, counter: str = "look_at_refused", say: str = "look_at refused") -> None:
        self.health.count(counter)
        with self.lock:
            self.refusal = (time.monotonic(), f"{say}: {why}")
        now = time.monotonic()
        if now - self._last_log >= 1.0:
            self._last_log = now
            log.warning("%s, the fovea stays: %s", say, why)

    def on_look_at(self, msg) -> None:
        self.health.count("look_at")
        if not self.look_at:
            return self.refuse("set [ros2] look_at = true in the settings (under a deployed ACL, with the ros2 "
                               "role's client config) to let look_at move the fovea", "look_at_off", "look_at is off")
        now = time.monotonic()
        self.look_times = [t for t in self.look_times if now - t < 1.0]
        if len(self.look_times) >= LOOK_AT_HZ:
            self.health.count("look_at_flood")
            return
        self.look_times.append(now)
        with self.lock:
            view = self.view
        names = [self.frame_id] + ([view.frame_id] if view is not None and view.frame_id not in ("", self.frame_id)
                                   else [])
        if msg.header.frame_id not in ("", *names):
            return self.refuse(f"frame_id {msg.header.frame_id[:80]!r}: want {' or '.join(map(repr, names))} (the "
                               "master's optical frame; this node does no tf lookup)")
        if view is None:
            return self.refuse("no frame seen yet: the master's view is unknown (is the capture running?)")
        net = self.settings.network
        try:
            x, y = conv.look_at_pixel((msg.point.x, msg.point.y, msg.point.z), view, net.window, net.vsearch)
        except conv.Refused as e:
            return self.refuse(str(e))
        self.put_fixate(Fixate(x=float(x), y=float(y), t_ns=time.time_ns(), source="ros2 look_at").to_bytes())
        self.health.count("look_at_sent")
        log.info("look_at (%.3f, %.3f, %.3f) m -> fovea (%d, %d)", msg.point.x, msg.point.y, msg.point.z, x, y)


class ProfileSwitch:
    """The bridge's profiles(on) (from the rclpy thread, once a second at most): the subscriber to the profiles
    declared while ROS 2 subscribes to them, undeclared when it no longer does (and at exit)."""

    def __init__(self, node: Node):
        self.node, self.bridge = node, None
        self.subs: list = []

    def __call__(self, on: bool) -> None:
        if on:
            self.subs.append(self.node.session.declare_subscriber(
                keys.profile(self.node.rig), lambda s: self.bridge.on_profile(s.payload.to_bytes())))
        else:
            while self.subs:
                self.subs.pop().undeclare()


def main(settings, conf, stop: session.Stop, namespace: str, joint: str, frame_id: str,
         domain: int | None = None, explicit_frame: bool = False) -> int:
    rig = settings.rig
    look_at, why = conv.look_at_mode(settings.ros2.look_at, session_identity(conf))
    changes, reach = conv.discovery_env(settings.ros2.discovery, os.environ)
    for name, value in changes.items():  # this process's only (`up` starts the bridge as a process of its own)
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value
    try:
        ros = RosNode("vergence_bridge", namespace=namespace, domain_id=domain)
    except RosUnavailable as e:
        print(f"vergence ros2: {e}", file=sys.stderr)
        return 2
    log.info("ros2 bridge: look_at %s (%s), discovery %s", "on" if look_at else "off", why, reach)
    user = _conf_get(conf, "transport/auth/usrpwd/user") if look_at else None
    if user and user not in ("ros2", "fixate"):
        log.warning("look_at is on, but the Zenoh session authenticates as %r: the deployed ACL lets only the ros2 "
                    "(and fixate) role put a fixate, so no look_at will move the fovea; run the bridge with "
                    "secrets/clients/ros2-tls.json5 (deploy/README.md)", user)
    fields = {"look_at": "on" if look_at else "off", "discovery": settings.ros2.discovery}
    try:
        with Node("ros2", rig, conf, stop, log=log, fields=lambda: fields) as node:
            pub_fixate = node.publisher(keys.fixate(rig))
            profiles = ProfileSwitch(node)
            b = Bridge(ros, rig, joint, frame_id, settings, node.health, pub_fixate.put, profiles,
                       explicit_frame=explicit_frame, look_at=look_at)
            profiles.bridge = b
            node.subscriber(keys.motor_state(rig), lambda s: b.on_motor(s.payload.to_bytes()))
            node.subscriber(keys.frame(rig), lambda s: b.on_frame(s.payload.to_bytes()))
            node.subscriber(keys.decision(rig), lambda s: b.on_decision(s.payload.to_bytes()))
            own = keys.status(rig, "ros2", node.ident)  # its own counters go on /diagnostics directly
            node.subscriber(keys.statuses(rig), lambda s: str(s.key_expr) != own and b.on_status(
                str(s.key_expr), s.payload.to_bytes()))
            node.ready()
            log.info("ros2 %s: vergence/%s/** <-> ROS 2 %s (joint %s, frame %s)", node.ident, rig, namespace, joint,
                     frame_id if explicit_frame else f"the master image's frame_id, else {frame_id}")
            try:
                node.run_status()
            finally:
                ros.close()  # no rclpy callback (the timer's declarations) runs while the subscribers go
                profiles(False)
    finally:
        ros.close()
    return 0


def run(args: argparse.Namespace) -> int:
    settings = load(args.config)
    if args.rig:
        import dataclasses

        settings = dataclasses.replace(settings, rig=args.rig)
    rig = settings.rig
    namespace = args.namespace or f"/vergence/{conv.ros_name(rig)}"
    if not namespace.startswith("/"):
        namespace = "/" + namespace
    name = conv.ros_name(rig)
    stop = session.Stop()
    return main(settings, session.config_from_args(args), stop, namespace, args.joint or f"{name}_slave_pan",
                args.frame_id or f"{name}_master_optical_frame", args.domain, explicit_frame=bool(args.frame_id))
