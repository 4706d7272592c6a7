"""The slave pan as a ros2_control joint: `vergence actuator --driver ros2 --port CONTROLLER[:key=value...]`.

The conventions of ros2_control users (docs/ROS2.md):
- mode=forward (default): std_msgs/msg/Float64MultiArray on /CONTROLLER/commands, the goal of a forward
  command controller (position_controllers/JointGroupPositionController), one value per joint in the
  controller's order: joints=A,B,C names them when the controller drives more than the pan (the others are
  sent at their present positions), else the controller has our joint only;
- mode=trajectory: trajectory_msgs/msg/JointTrajectory on /CONTROLLER/joint_trajectory (a joint trajectory
  controller), one point at time_from_start = reach=S (default 0.05 s);
- the position is read from sensor_msgs/msg/JointState on states=TOPIC (default /joint_states, the joint
  state broadcaster's), the entry named joint=NAME (default slave_pan).

Every goal has passed vergence.motors.base.Safety (limits, step, stale, NaN) in the MotorLoop, as with every
driver. A joint state that is not believable (its arrays of unequal lengths, a position that is not finite, a
stamp of 0 or more than max_skew_s off this machine's clock) is counted in `errors` and changes nothing. No
joint state of our joint for watchdog_s (at least 0.5 s): read_position raises Disconnected, so the MotorLoop
says "disconnected" (with the reason), sends nothing, and reopens (waits for a joint state) with its backoff.
position_ns is the stamp of the joint state the position came from: the MotorState's t_ns.
"""

from __future__ import annotations

import atexit
import logging
import math
import threading
import time

from ..ros2 import convert as conv
from ..spec import Key, SpecError, parse
from .base import Disconnected, Driver, MotorSettings, PortError

__all__ = ["Ros2Driver", "parse_port"]

log = logging.getLogger("vergence.actuator")
OPEN_WAIT_S = 2.0  # open() waits this long for a first joint state


def parse_port(port: str) -> dict:
    """'CONTROLLER[:joint=NAME][:mode=forward|trajectory][:joints=A,B][:states=TOPIC][:reach=S]' -> options;
    PortError naming what is wrong."""
    controller, *opts = (port or "forward_position_controller").split(":")
    keys = [Key("joint", "str", default="slave_pan"),
            Key("mode", "choice", "forward", choices=("forward", "trajectory")), Key("joints", "list", default=()),
            Key("states", "str", default="/joint_states"), Key("reach", default=0.05, above=0.0, unit="s")]
    try:
        out = parse(":".join(opts), keys, "ros2 driver")
    except SpecError as e:
        raise PortError(str(e)) from None
    out["controller"] = controller.strip("/") or "forward_position_controller"
    out["joints"] = list(out["joints"]) or [out["joint"]]
    if out["joint"] not in out["joints"]:
        raise PortError(f"ros2 driver: joints={','.join(out['joints'])} does not name joint={out['joint']}")
    return out


class Ros2Driver(Driver):
    name = "ros2"

    def __init__(self, settings: MotorSettings, port: str = ""):
        super().__init__(settings)
        self.opts = parse_port(port)
        self.ros = None
        self.pub = None
        self.cond = threading.Condition()
        self.positions: dict[str, tuple[float, int, float]] = {}  # joint: (position, stamp ns, arrival monotonic)
        self.position_ns: int | None = None
        self._logged: set[str] = set()
        self.stale_s = max(settings.watchdog_s, 0.5)

    def describe(self) -> str:
        o = self.opts
        topic = "commands" if o["mode"] == "forward" else "joint_trajectory"
        return f"ros2 /{o['controller']}/{topic} (joint {o['joint']}, states {o['states']})"

    # -- joint states (the rclpy thread) ---------------------------------------------------------------------------

    def _bad(self, kind: str, why: str) -> None:
        self.errors += 1
        if kind not in self._logged:
            self._logged.add(kind)
            log.warning("ros2 driver: joint state refused (%s; further ones are only counted): %s", kind, why)

    def _on_state(self, msg) -> None:
        names, pos = list(msg.name), list(msg.position)
        if len(names) != len(pos):
            return self._bad("lengths", f"{len(names)} names, {len(pos)} positions")
        st = msg.header.stamp
        why = conv.stamp_problem(st.sec, st.nanosec, time.time_ns(), self.settings.max_skew_s or math.inf)
        if why is not None:
            return self._bad("stamp", why)
        t_ns, now = conv.from_stamp(st.sec, st.nanosec), time.monotonic()
        with self.cond:
            for n, p in zip(names, pos):
                if n not in self.opts["joints"]:
                    continue
                if not math.isfinite(p):
                    self._bad("position", f"joint {n}: position {p}")
                    continue
                old = self.positions.get(n)
                if old is not None and t_ns < old[1]:
                    self._bad("order", f"joint {n}: a stamp older than the previous one")
                    continue
                self.positions[n] = (float(p), t_ns, now)
            self.cond.notify_all()

    # -- Driver ---------------------------------------------------------------------------------------------------

    def open(self) -> float:
        from ..ros2.node import RosNode, RosUnavailable

        if self.ros is None:
            try:
                self.ros = RosNode("vergence_actuator")
            except RosUnavailable as e:
                raise PortError(f"ros2 driver: {e}") from None
            atexit.register(self.shutdown)
            from sensor_msgs.msg import JointState
            from std_msgs.msg import Float64MultiArray
            from trajectory_msgs.msg import JointTrajectory

            o, n = self.opts, self.ros.node
            if o["mode"] == "forward":
                self.pub = n.create_publisher(Float64MultiArray, f"/{o['controller']}/commands", self.ros.reliable_qos)
            else:
                self.pub = n.create_publisher(JointTrajectory, f"/{o['controller']}/joint_trajectory",
                                              self.ros.reliable_qos)
            n.create_subscription(JointState, o["states"], self._on_state, self.ros.sensor_qos)
        with self.cond:
            fresh = lambda: all(j in self.positions and time.monotonic() - self.positions[j][2] < self.stale_s  # noqa: E731
                                for j in self.opts["joints"])
            if not self.cond.wait_for(fresh, OPEN_WAIT_S):
                raise Disconnected(f"no joint state of {', '.join(self.opts['joints'])} on {self.opts['states']} "
                                   f"within {OPEN_WAIT_S:g} s (is the controller manager running, on this "
                                   "ROS_DOMAIN_ID?)")
        return self.read_position()

    def close(self, torque_off: bool = True) -> None:
        """Forget the joint's position (a reopen waits for a new joint state). The node itself stays, so that a
        reconnection needs no new DDS discovery; it closes at exit (shutdown, registered with atexit)."""
        with self.cond:
            self.positions.clear()
        self.position_ns = None

    def shutdown(self) -> None:
        ros, self.ros, self.pub = self.ros, None, None
        if ros is not None:
            ros.close()

    def read_position(self) -> float:
        with self.cond:
            got = self.positions.get(self.opts["joint"])
        if got is None or time.monotonic() - got[2] > self.stale_s:
            age = "never" if got is None else f"not for {time.monotonic() - got[2]:.1f} s"
            raise Disconnected(f"joint {self.opts['joint']}: no joint state on {self.opts['states']} ({age})")
        self.position_ns = got[1]
        return got[0]

    def write_goal(self, pan_rad: float) -> None:
        if self.pub is None:
            raise Disconnected("ros2 driver: not open")
        o = self.opts
        with self.cond:
            goals = [pan_rad if j == o["joint"] else self.positions[j][0] for j in o["joints"]]
        if o["mode"] == "forward":
            from std_msgs.msg import Float64MultiArray

            self.pub.publish(Float64MultiArray(data=goals))
            return
        from builtin_interfaces.msg import Duration
        from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

        sec, nsec = divmod(int(o["reach"] * 1e9), 10**9)
        self.pub.publish(JointTrajectory(joint_names=o["joints"], points=[JointTrajectoryPoint(
            positions=goals, time_from_start=Duration(sec=sec, nanosec=nsec))]))
