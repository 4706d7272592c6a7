"""What is read from and written to files and devices (issue #34): `images`, the one image reader and the
Source interface; `sources`, the stereo sources by kind (files, video, camera, the simulator); `recording`,
the format of `vergence record` and `replay`; `mcap_file`, ROS 2 MCAP files. The ROS 2 source is vergence.ros2."""
