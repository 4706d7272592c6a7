"""The tests' own ROS 2 side: a real rclpy node of the test process (not vergence's), on a ROS domain of its own,
discovering only on this machine, that publishes to and reads from the node under test.

    rclpy = rosnode.require()               # skips the test, saying why, where rclpy cannot be imported
    with rosnode.TestNode(domain) as t:     # an rclpy node in its own context, spun in a thread
        got = t.collect(JointState, "/vergence/head/joint_states")
        t.wait(got, 3, timeout=10)          # the first 3 messages (arrival time.time_ns(), message)

ros_env(monkeypatch) gives the test a random ROS_DOMAIN_ID and ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, in
its own environment and so in every process it starts (tests/procs.py copies os.environ): tests never see
each other's nodes, nor anything on the network, and send nothing off this machine.
"""

from __future__ import annotations

import collections
import os
import random
import threading
import time

import pytest

import split

__all__ = ["require", "ros_env", "TestNode"]


def require():
    """rclpy, or skip: the ROS 2 tests need it (the test extra installs the PyPI wheels of Jazzy)."""
    try:
        import rclpy
        import sensor_msgs.msg  # noqa: F401
    except ImportError as e:
        pytest.skip(f"rclpy cannot be imported ({e}): pip install -e '.[test]' installs ROS 2 Jazzy's wheels")
    return rclpy


def ros_env(monkeypatch) -> int:
    """A ROS domain of this test's own (and localhost-only discovery) for the test and its processes: 51-100 in
    the scenarios' pytest of a whole run, 1-50 in the others (tests/split.py: the two run at once)."""
    domain = random.randint(51, 100) if os.environ.get(split.CHILD) == split.SCENARIOS else random.randint(1, 50)
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.delenv("ROS_LOCALHOST_ONLY", raising=False)
    return domain


class TestNode:
    """An rclpy node of the test's own (context, executor thread); collect() and publisher() on it."""

    __test__ = False  # not a test class for pytest

    def __init__(self, domain: int, name: str = "vergence_test"):
        rclpy = require()
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node(f"{name}_{random.randint(0, 10**6)}", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.cond = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self):
        while not self._stop.is_set() and self.context.ok():
            self.executor.spin_once(timeout_sec=0.05)

    def collect(self, msg_type, topic: str, qos=10) -> list:
        """A list that fills with (arrival time.time_ns(), message) for every message on topic."""
        got: list = []

        def on(msg):
            with self.cond:
                got.append((time.time_ns(), msg))
                self.cond.notify_all()

        self.node.create_subscription(msg_type, topic, on, qos)
        return got

    def wait(self, got: list, n: int, timeout: float, what: str = "messages", logs=None) -> list:
        """The first n items of a collect() list, waiting up to timeout s (TimeoutError with logs())."""
        with self.cond:
            if self.cond.wait_for(lambda: len(got) >= n, timeout):
                return got[:n]
        raise TimeoutError(f"{len(got)} of {n} {what} within {timeout} s" + (f"\n{logs()}" if logs else ""))

    def wait_until(self, cond, timeout: float, what: str, logs=None):
        """cond() (called under the lock, re-checked as messages arrive, and every 0.1 s) until true."""
        end = time.monotonic() + timeout
        with self.cond:
            while True:
                v = cond()
                if v:
                    return v
                left = end - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"timed out after {timeout} s waiting for {what}" + (f"\n{logs()}" if logs
                                                                                            else ""))
                self.cond.wait(min(left, 0.1))

    def publisher(self, msg_type, topic: str, qos=10, matched: int = 1, timeout: float = 15.0, logs=None):
        """A publisher, returned once `matched` subscriptions (the node under test's) have matched it."""
        pub = self.node.create_publisher(msg_type, topic, qos)
        end = time.monotonic() + timeout
        while pub.get_subscription_count() < matched:
            if time.monotonic() > end:
                raise TimeoutError(f"no subscriber on {topic} within {timeout} s" + (f"\n{logs()}" if logs else ""))
            time.sleep(0.02)
        return pub

    def close(self):
        self._stop.set()
        self._thread.join(2.0)
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self.context.try_shutdown()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class StereoCamera:
    """A stereo camera driver played by the test: at `hz`, the pair render(pan) (numpy uint8 gray, master left)
    as sensor_msgs/Image mono8 on LEFT and RIGHT, both stamped with their exposure time, and a
    sensor_msgs/CameraInfo with fx = fy = focal beside each (<namespace>/camera_info; principal: its (cx, cy), default
    the image centre; d: its plumb_bob distortion, default none). The images come out
    `latency_s` after their exposure (a real camera's exposure, readout and driver); pan_at(t_ns) says where the
    slave was at the exposure (the test knows it from the rig's joint_states, or from the joint it plays), None
    while it does not know: then no picture is taken (a camera on the shaft always sees its pan; one that
    rendered pan 0 while the motor turned would send the loop to a limit)."""

    LEFT, RIGHT = "/stereo/left/image_raw", "/stereo/right/image_raw"

    def __init__(self, t: TestNode, render, pan_at, focal: float, hz: float = 30.0, latency_s: float = 0.03,
                 principal: tuple[float, float] | None = None, d: list[float] | None = None):
        from sensor_msgs.msg import CameraInfo, Image

        self.t, self.render, self.pan_at, self.focal, self.period = t, render, pan_at, focal, 1.0 / hz
        self.principal, self.d = principal, d
        self.latency_ns = int(latency_s * 1e9)
        self.pubs = [t.node.create_publisher(Image, topic, 10) for topic in (self.LEFT, self.RIGHT)]
        self.infos = [t.node.create_publisher(CameraInfo, topic.rpartition("/")[0] + "/camera_info", 10)
                      for topic in (self.LEFT, self.RIGHT)]
        self.sent: list[tuple[int, float]] = []  # (stamp ns, pan rendered at)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def message(self, img, t_ns: int, frame: str):
        from sensor_msgs.msg import Image

        m = Image()
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(t_ns, 10**9)
        m.header.frame_id = frame
        m.height, m.width = img.shape
        m.encoding, m.step = "mono8", img.shape[1]
        m.data = img.tobytes()
        return m

    def _info(self, shape, t_ns: int):
        from sensor_msgs.msg import CameraInfo

        m = CameraInfo()
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(t_ns, 10**9)
        m.height, m.width = shape
        cx, cy = self.principal or (shape[1] // 2, shape[0] // 2)
        m.k = [self.focal, 0.0, float(cx), 0.0, self.focal, float(cy), 0.0, 0.0, 1.0]
        if self.d:
            m.distortion_model, m.d = "plumb_bob", [float(v) for v in self.d]
        return m

    def _loop(self):
        next_t = time.monotonic()
        while not self._stop.wait(max(0.0, next_t - time.monotonic())):
            next_t += self.period
            t_ns = time.time_ns() - self.latency_ns  # the exposure
            pan = self.pan_at(t_ns)
            if pan is None:  # the pan at that time is not known (yet): no picture
                continue
            imgs = self.render(pan)
            for pub, info, img, name in zip(self.pubs, self.infos, imgs, ("left", "right")):
                pub.publish(self.message(img, t_ns, f"{name}_optical_frame"))
                info.publish(self._info(img.shape, t_ns))
            self.sent.append((t_ns, pan))

    def close(self):
        self._stop.set()
        self._thread.join(2.0)


class ForwardController:
    """A ros2_control forward command controller played by the test: std_msgs/Float64MultiArray goals on
    /<name>/commands (one value: the joint's), a joint that heads for its goal at `speed` rad/s, and
    sensor_msgs/JointState on /joint_states at `hz`, stamped now. Every command it took is in `commands`
    (arrival time.time_ns(), value); `publishing` cleared: no more joint states (a controller manager gone). noise:
    each joint state's position off the joint's by that much (rad, Gaussian: a noisy encoder; the joint is where it
    is, and the camera there)."""

    def __init__(self, t: TestNode, name: str = "forward_position_controller", joint: str = "slave_pan",
                 speed: float = 3.0, hz: float = 100.0, noise: float = 0.0):
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64MultiArray

        self.t, self.joint, self.speed, self.period = t, joint, speed, 1.0 / hz
        self.noise, self.rng = noise, random.Random(7)
        self.lock = threading.Lock()
        self.pan = self.goal = 0.0
        self.commands: list[tuple[int, float]] = []
        self.bad_commands = 0
        self.stamps: set[int] = set()  # of every joint state published
        self.history: collections.deque = collections.deque([(time.time_ns(), 0.0)], maxlen=1000)  # (t_ns, pan)
        self.publishing = threading.Event()
        self.publishing.set()
        self.pub = t.node.create_publisher(JointState, "/joint_states", 10)
        t.node.create_subscription(Float64MultiArray, f"/{name}/commands", self._on_command, 10)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _on_command(self, msg) -> None:
        if len(msg.data) != 1:
            self.bad_commands += 1
            return
        with self.lock:
            self.goal = float(msg.data[0])
            self.commands.append((time.time_ns(), self.goal))

    def position(self) -> float:
        with self.lock:
            return self.pan

    def pan_at(self, t_ns: int) -> float:
        """Where the joint was at t_ns (its motion is piecewise linear between its steps)."""
        from vergence.ros2.convert import pan_at

        with self.lock:
            return pan_at(list(self.history), t_ns, self.pan)

    def state(self, t_ns: int, names=None, positions=None):
        from sensor_msgs.msg import JointState

        m = JointState()
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(t_ns, 10**9)
        m.name = names if names is not None else [self.joint]
        m.position = positions if positions is not None else [self.position() + (self.rng.gauss(0.0, self.noise)
                                                                                  if self.noise else 0.0)]
        return m

    def _loop(self):
        last = time.monotonic()
        while not self._stop.wait(self.period):
            now = time.monotonic()
            with self.lock:
                step = self.speed * (now - last)
                self.pan += max(-step, min(step, self.goal - self.pan))
                self.history.append((time.time_ns(), self.pan))
            last = now
            if self.publishing.is_set():
                t_ns = time.time_ns()
                self.stamps.add(t_ns)
                self.pub.publish(self.state(t_ns))

    def close(self):
        self._stop.set()
        self._thread.join(2.0)
