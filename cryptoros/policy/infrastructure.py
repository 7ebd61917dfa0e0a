"""What ROS itself uses on a node's behalf, allowed without an explicit grant.

One list for both ROS versions:

- ROS 1: every rospy and roscpp node publishes ``/rosout`` and serves its own
  ``get_loggers`` / ``set_logger_level``; the libraries serve and publish a few more
  endpoints under the node's own name (dynamic_reconfigure, a nodelet manager, rosbag
  play); and they read a few global parameters at start-up and on every log call. All
  allowed for the manager's own nodes only.
- ROS 2: ``/rosout`` and ``/parameter_events`` and the parameter and type-description
  services every rclpy node serves are never bridged: they stay on the robot's domain.

The ROS 1 parameter list was measured, not guessed: each library was run against a
recording proxy in front of rosmaster (every parameter call logged with its caller and
key), on Debian 12's packages ros_comm 1.15.15+ds-2 (python3-rospy, libroscpp4d,
python3-roslaunch, python3-rosbag, librosbag4d), python3-actionlib 1.14.0-6,
python3-dynamic-reconfigure 1.7.3-1, libnodeletlib-tools 1.10.2-1+b7 and
image-transport-tools 1.12.0-12+b5 (docs/stock-tools.md, "How the list was measured";
``tests/system/test_stock_tools.py`` records it again and checks it is covered).
"""

from __future__ import annotations

ROS1_ROSOUT = ("/rosout", "rosgraph_msgs/Log")
ROS1_LOGGER_SERVICES = {"get_loggers": "roscpp/GetLoggers", "set_logger_level": "roscpp/SetLoggerLevel"}
#: Services the libraries serve under the node's own name (``<node>/<suffix>``): the
#: loggers, dynamic_reconfigure's server, a nodelet manager, rosbag play's pause.
ROS1_OWN_SERVICES = {
    **ROS1_LOGGER_SERVICES,
    "set_parameters": "dynamic_reconfigure/Reconfigure",
    "load_nodelet": "nodelet/NodeletLoad",
    "unload_nodelet": "nodelet/NodeletUnload",
    "list": "nodelet/NodeletList",
    "pause_playback": "std_srvs/SetBool",
}
#: Topics the libraries publish under the node's own name: dynamic_reconfigure's.
ROS1_OWN_TOPICS = {
    "parameter_descriptions": "dynamic_reconfigure/ConfigDescription",
    "parameter_updates": "dynamic_reconfigure/Config",
}

#: Global parameters stock ROS 1 libraries read at start-up and on logging, readable by
#: every node of a manager. Measured (see the module docstring): who read what.
ROS1_DEFAULT_PARAM_READS = frozenset({
    "/use_sim_time",                       # rospy, roscpp: every node at start
    "/rosout_disable_topics_generation",   # rospy: subscribeParam on every log call; roscpp at start
    "/tcp_keepalive",                      # rospy, roscpp: at the first connection
    "/enable_statistics",                  # rospy, roscpp: per subscription
    "/statistics_window_min_elements",     # roscpp (rospy when statistics are on)
    "/statistics_window_max_elements",
    "/statistics_window_min_size",
    "/statistics_window_max_size",
    "/run_id",                             # roslaunch: hasParam, then getParam
    "/rosdistro",                          # written by roslaunch, read by tools
    "/rosversion",
    "/actionlib_client_pub_queue_size",    # actionlib (python): ActionClient at start
    "/actionlib_client_sub_queue_size",
    "/actionlib_server_pub_queue_size",    # actionlib (python): ActionServer at start
    "/actionlib_server_sub_queue_size",
    "/actionlib_status_frequency",         # actionlib: searchParam upwards from the node
})
#: Parameters read under a topic's name by the node that publishes it: actionlib's
#: server under its action (``<action>/status``), image_transport under its base topic.
ROS1_TOPIC_PARAMS = {
    "status_frequency": "status",          # actionlib ActionServer: hasParam <action>/status_frequency
    "status_list_timeout": "status",       # actionlib ActionServer: getParam <action>/status_list_timeout
    "disable_pub_plugins": "",             # image_transport Publisher: <topic>/disable_pub_plugins
}

ROS2_LOCAL_TOPICS = frozenset({"/rosout", "/parameter_events"})
ROS2_LOCAL_SERVICE_TYPES = ("rcl_interfaces/srv/", "type_description_interfaces/srv/")


def ros1_allows(action: str, node: str, name: str, type_name: str | None) -> bool:
    """ROS 1: ``/rosout`` publishing, and the endpoints the libraries serve and publish
    under the node's own name (:data:`ROS1_OWN_SERVICES`, :data:`ROS1_OWN_TOPICS`)."""
    if action == "publish" and (name, type_name) == ROS1_ROSOUT:
        return True
    own = ros1_own_type(action, node, name)
    return own is not None and type_name in (None, own)


#: the action that opens a stream to an endpoint -> the action of the node that serves it
ROS1_OPENED_BY = {"call": "serve", "subscribe": "publish"}


def ros1_own_endpoint(action: str, name: str) -> tuple[str, str] | None:
    """``(node, type)`` when ``name`` is an endpoint the ROS 1 libraries serve or publish
    under a node's own name (``/cam/get_loggers`` -> ``("/cam", "roscpp/GetLoggers")``),
    for ``action`` on either end of it (``serve`` or ``call`` a service, ``publish`` or
    ``subscribe`` a topic); None for any other name or action."""
    node, _, suffix = name.rpartition("/")
    if not node or action not in ("serve", "call", "publish", "subscribe"):
        return None
    table = ROS1_OWN_SERVICES if action in ("serve", "call") else ROS1_OWN_TOPICS
    return (node, table[suffix]) if suffix in table else None


def ros1_own_type(action: str, node: str, name: str) -> str | None:
    """The type of an endpoint the ROS 1 libraries serve or publish under ``node``'s own
    name (``/cam/get_loggers`` -> ``roscpp/GetLoggers``), or None for any other name:
    what a service registration, which tells no type, has when it is ROS's own."""
    own = ros1_own_endpoint(action, name) if action in ("serve", "publish") else None
    return own[1] if own is not None and own[0] == node else None


def ros1_topic_param(key: str) -> tuple[str, str] | None:
    """For a key a library reads under a topic's name, ``(topic, suffix)`` whose
    publisher may read it (``/move_base/status_frequency`` -> ``("/move_base/status",
    "status_frequency")``); ``None`` for any other key."""
    base, _, suffix = key.rpartition("/")
    if suffix not in ROS1_TOPIC_PARAMS or not base:
        return None
    topic = base + "/" + ROS1_TOPIC_PARAMS[suffix] if ROS1_TOPIC_PARAMS[suffix] else base
    return topic, suffix


def ros2_stays_local(name: str, types: list[str] | tuple[str, ...]) -> bool:
    """ROS 2: a topic or service of every node's own infrastructure, never bridged."""
    return name in ROS2_LOCAL_TOPICS or any(t.startswith(ROS2_LOCAL_SERVICE_TYPES) for t in types)


__all__ = ["ROS1_DEFAULT_PARAM_READS", "ROS1_LOGGER_SERVICES", "ROS1_OPENED_BY", "ROS1_OWN_SERVICES", "ROS1_OWN_TOPICS",
           "ROS1_ROSOUT", "ROS1_TOPIC_PARAMS", "ROS2_LOCAL_SERVICE_TYPES", "ROS2_LOCAL_TOPICS", "ros1_allows",
           "ros1_own_endpoint", "ros1_own_type", "ros1_topic_param", "ros2_stays_local"]
