"""ROS 2 (issue #34: the three ROS 2 modules in one room): `convert`, the conversions without ROS (stamps, the
master's view, the fixated point, look_at, diagnostics, images; importable with no ROS installed); `node`, an
rclpy node in a thread; `source`, the `--source ros2:LEFT,RIGHT` stereo source. The motor driver is
vergence.motors.ros2, the bridge services/bridges/ros2.py. Nothing is imported here: rclpy loads only with
`node` or `source`."""
