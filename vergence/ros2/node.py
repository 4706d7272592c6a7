"""One rclpy node in a thread of its own, for the bridge, the ros2 source and the ros2 motor driver.

    ros = RosNode("vergence_bridge", namespace="/vergence/head")
    pub = ros.node.create_publisher(JointState, "joint_states", 10)
    ...
    ros.close()

rclpy is imported here only (require() says how to get it: a sourced ROS 2, or the `ros2` extra's PyPI wheels
of Jazzy). The context is the node's own and installs no signal handler: SIGINT and SIGTERM stay the
process's (services.runtime.session.Stop), which closes the node on its way out. The executor spins in a
daemon thread until close().
"""

from __future__ import annotations

import threading

__all__ = ["RosUnavailable", "require", "RosNode"]

SPIN_S = 0.05  # one spin's wait: how soon close() is noticed


class RosUnavailable(RuntimeError):
    """rclpy (or a message package) cannot be imported; the message says how to install it."""


def require():
    """The rclpy module; RosUnavailable saying how to get it."""
    try:
        import rclpy  # noqa: F401
        import sensor_msgs.msg  # noqa: F401
        import std_msgs.msg  # noqa: F401
    except ImportError as e:
        raise RosUnavailable(
            f"ROS 2's rclpy cannot be imported ({e}): source your ROS 2 install (`source /opt/ros/jazzy/setup.bash`), "
            "or, without ROS, install the community build of Jazzy from PyPI with `pip install 'vergence[ros2]'`"
        ) from None
    return rclpy


def _qos():
    from rclpy.qos import QoSProfile, qos_profile_sensor_data

    return qos_profile_sensor_data, QoSProfile(depth=10)


class RosNode:
    """An rclpy node with its own context, spun in a daemon thread (callbacks run there)."""

    def __init__(self, name: str, namespace: str = "", domain_id: int | None = None):
        rclpy = require()
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id, signal_handler_options=SignalHandlerOptions.NO)
        try:
            self.node = rclpy.create_node(name, namespace=namespace, context=self.context)
            self.executor = SingleThreadedExecutor(context=self.context)
            self.executor.add_node(self.node)
        except BaseException:
            self.context.try_shutdown()
            raise
        self.sensor_qos, self.reliable_qos = _qos()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name=f"rclpy-{name}", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set() and self.context.ok():
            try:
                self.executor.spin_once(timeout_sec=SPIN_S)
            except Exception as e:  # a callback's error: logged, the node goes on
                if self._stop.is_set() or not self.context.ok():
                    return
                self.node.get_logger().error(f"callback failed: {type(e).__name__}: {e}")

    def now_ns(self) -> int:
        return self.node.get_clock().now().nanoseconds

    def close(self) -> None:
        """Stop the spinning thread, destroy the node, shut the context down; again: nothing."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._thread.join(2.0)
        try:
            self.executor.shutdown(timeout_sec=1.0)
            self.node.destroy_node()
        finally:
            self.context.try_shutdown()

