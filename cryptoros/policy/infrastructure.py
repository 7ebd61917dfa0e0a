"""What ROS itself uses on a node's behalf, allowed without an explicit grant.

One list for both ROS versions (the structure issue: it was written twice):

- ROS 1: every rospy and roscpp node publishes ``/rosout`` and serves its own
  ``get_loggers`` / ``set_logger_level``; allowed for the manager's own nodes.
- ROS 2: ``/rosout`` and ``/parameter_events`` and the parameter and type-description
  services every rclpy node serves are never bridged: they stay on the robot's domain.
"""

from __future__ import annotations

ROS1_ROSOUT = ("/rosout", "rosgraph_msgs/Log")
ROS1_LOGGER_SERVICES = {"get_loggers": "roscpp/GetLoggers", "set_logger_level": "roscpp/SetLoggerLevel"}

ROS2_LOCAL_TOPICS = frozenset({"/rosout", "/parameter_events"})
ROS2_LOCAL_SERVICE_TYPES = ("rcl_interfaces/srv/", "type_description_interfaces/srv/")


def ros1_allows(action: str, node: str, name: str, type_name: str | None) -> bool:
    """ROS 1: ``/rosout`` publishing and the node's own logger services."""
    if action == "publish" and (name, type_name) == ROS1_ROSOUT:
        return True
    if action == "serve" and name.startswith(node + "/"):
        suffix = name[len(node) + 1 :]
        return suffix in ROS1_LOGGER_SERVICES and type_name in (None, ROS1_LOGGER_SERVICES[suffix])
    return False


def ros2_stays_local(name: str, types: list[str] | tuple[str, ...]) -> bool:
    """ROS 2: a topic or service of every node's own infrastructure, never bridged."""
    return name in ROS2_LOCAL_TOPICS or any(t.startswith(ROS2_LOCAL_SERVICE_TYPES) for t in types)


__all__ = ["ROS1_LOGGER_SERVICES", "ROS1_ROSOUT", "ROS2_LOCAL_SERVICE_TYPES", "ROS2_LOCAL_TOPICS", "ros1_allows",
           "ros2_stays_local"]
