"""ROS 2 (Jazzy) support: the DDS bridge of the interceptor's ``ros2`` role.

Nothing here imports rclpy at import time. :mod:`cryptoros.ros2.framing` (stdlib only)
is shared by both sides; :mod:`cryptoros.ros2.bridge_node` runs under the ROS 2 venv's
python as a child of ``cryptoros-interceptor``; :mod:`cryptoros.ros2.target` describes
what a stream between two interceptors carries; :mod:`cryptoros.ros2.record_node`
records a robot's topics for the runtime monitor. See docs/ros2.md.
"""

from __future__ import annotations

import os
from pathlib import Path

#: the environment variable naming the ROS 2 venv's python
ROS2_PYTHON_ENV = "CRYPTOROS_ROS2_PYTHON"


def default_ros2_python() -> Path:
    """``$CRYPTOROS_ROS2_PYTHON``, else the venv ``scripts/ros2-venv`` creates."""
    if os.environ.get(ROS2_PYTHON_ENV):
        return Path(os.environ[ROS2_PYTHON_ENV])
    return Path(__file__).resolve().parent.parent.parent / ".ros2-venv" / "bin" / "python"
