"""ROS 2 (Jazzy) support: the DDS bridge of the interceptor's ``ros2`` role.

Nothing here imports rclpy at import time. :mod:`cryptoros.ros2.framing` (stdlib only)
is shared by both sides; :mod:`cryptoros.ros2.bridge_node` runs under the ROS 2 venv's
python as a child of ``cryptoros-interceptor``; :mod:`cryptoros.ros2.target` describes
what a stream between two interceptors carries. See docs/ros2.md.
"""
