"""The ``cryptoros-authz`` command that would allow a refused ROS 1 request: what the
interceptor's log and ``cryptoros denials`` show after ``to allow:``.

Pure functions. A hint is one command line, each argument shell-quoted where it needs
it (a node pattern such as ``/rosparam-*`` works pasted into bash with ``failglob`` and
into zsh). A stock tool's anonymous node (:data:`TOOL_NODES`) is pointed at its
``grant-tools`` bundle. A type the refusal tells, or the type of an endpoint ROS serves
under a node's own name (its loggers, dynamic_reconfigure), is filled in; any other
value the interceptor cannot know stays an upper-case placeholder (``TYPE``,
``TOPIC`` ...) explained after a ``#``: what to put there and where to find it.
"""

from __future__ import annotations

import shlex

from cryptoros.errors import PolicyDenied
from cryptoros.policy.infrastructure import ros1_allows, ros1_own_endpoint
from cryptoros.policy.ros1 import ANY_TYPE, node_pattern, resolve_param_key

PROG = "cryptoros-authz"
#: The anonymous node names stock ROS 1 tools run under (ros_comm 1.15), as node
#: patterns: what ``cryptoros-authz grant-tools`` grants.
TOOL_NODES = {
    "rostopic": "/rostopic_*",      # rostopic echo/hz/pub: init_node('rostopic', anonymous=True)
    "rosbag": "/record_*",          # rosbag record: the node 'record' with a number (any type: '*')
    "rosparam": "/rosparam-*",      # rosgraph.Master('/rosparam-<pid>')
    "rosservice_probe": "/rosservice",  # the service type probe of rosservice call/info
    "rosservice": "/rosservice_*",  # rosservice call: init_node('rosservice', anonymous=True)
    "rosbag_play": "/play_*",       # rosbag play: the node 'play' with a number
    "roslaunch": "/roslaunch",      # roslaunch's parameter calls (caller id /roslaunch)
}
#: (tool node pattern, action) -> the ``grant-tools`` option (``NAME:TYPE``) granting it
_BUNDLES = {
    (TOOL_NODES["rostopic"], "subscribe"): "--topic",
    (TOOL_NODES["rosbag"], "subscribe"): "--topic",
    (TOOL_NODES["rostopic"], "publish"): "--publish-topic",
    (TOOL_NODES["rosbag_play"], "publish"): "--publish-topic",
    (TOOL_NODES["rosservice_probe"], "call"): "--service",
    (TOOL_NODES["rosservice"], "call"): "--service",
}
#: where the type of a topic or service is found, by the action the grant is for
_TYPE_NOTES = {
    "publish": "TYPE: the topic's type (rostopic type NAME prints it)",
    "subscribe": "TYPE: the topic's type (rostopic type NAME prints it)",
    "call": "TYPE: the service's type, the one its server is granted "
            "(cryptoros-authz show-manager SERVER_ROBOT lists it)",
    "serve": "TYPE: the service's type, the srv the node serves it with (pkg/Name)",
}
#: a tool node no grant names yet: its bundle's option with placeholders, and what they are
_FIRST_GRANT = {
    TOOL_NODES["rostopic"]: ("--topic", "TOPIC:TYPE", "TOPIC: the topic rostopic echo/hz/bw reads (rostopic pub: "
                                                      "--publish-topic TOPIC:TYPE), TYPE: its type (rostopic type "
                                                      "TOPIC prints it)"),
    TOOL_NODES["rosbag"]: ("--topic", "TOPIC:TYPE", "TOPIC: a topic rosbag record records, TYPE: its type "
                                                    "(rostopic type TOPIC prints it)"),
    TOOL_NODES["rosbag_play"]: ("--publish-topic", "TOPIC:TYPE", "TOPIC: a topic of the bag rosbag play publishes, "
                                                                 "TYPE: its type (rosbag info BAG lists them)"),
    TOOL_NODES["rosservice"]: ("--service", "SERVICE:TYPE", "SERVICE: the service rosservice calls, TYPE: its type, "
                                                            "the one its server is granted (cryptoros-authz "
                                                            "show-manager SERVER_ROBOT lists it)"),
    TOOL_NODES["rosparam"]: ("--param-ns", "NS", "NS: the parameter namespace rosparam may use"),
}


def command(*argv: str, note: str | None = None) -> str:
    """``argv`` as one shell line, each argument quoted where it needs it; ``note``
    (what a placeholder stands for) after ``#``."""
    line = " ".join(shlex.quote(arg) for arg in argv)
    return f"{line}  # {note}" if note else line


def stream_grant_hint(manager: str, action: str, node: str, name: str, type_name: str | None) -> str:
    """What lets ``manager``'s ``node`` ``action`` the topic or service ``name`` (of
    ``type_name``; None or ``*`` when the refusal does not tell it): a tool's bundle or
    a ``grant``, the type filled in when known."""
    pattern = node_pattern(node)
    if type_name in (None, ANY_TYPE):
        own = ros1_own_endpoint(action, name)
        type_name = own[1] if own is not None else None
    note = None if type_name else _TYPE_NOTES[action]
    type_name = type_name or "TYPE"
    option = _BUNDLES.get((pattern, action))
    if option == "--publish-topic" and pattern == TOOL_NODES["rosbag_play"] and name == "/clock":
        return command(PROG, "grant-tools", manager, "--clock")
    if option:
        return command(PROG, "grant-tools", manager, option, f"{name}:{type_name}", note=note)
    return command(PROG, "grant", manager, action, pattern, name, type_name, note=note)


def unnamed_node_hint(manager: str, node: str) -> str:
    """What lets ``manager``'s ``node``, which no grant names, use ROS's own endpoints
    (``/rosout``, its loggers): any grant naming it; for a stock tool, its bundle."""
    pattern = node_pattern(node)
    if pattern == TOOL_NODES["roslaunch"]:
        return command(PROG, "grant-tools", manager, "--roslaunch")
    first = _FIRST_GRANT.get(pattern)
    if first is not None:
        option, value, note = first
        return command(PROG, "grant-tools", manager, option, value, note=f"no grant names {pattern}; {note}")
    return command(PROG, "grant", manager, "ACTION", pattern, "NAME", "TYPE",
                   note=f"no grant names {pattern}; ACTION: publish, subscribe, serve or call, NAME: the topic or "
                        "service it uses, TYPE: its type (rostopic type NAME prints a topic's)")


def param_hint(manager: str, node: str, key: str, write: bool) -> str:
    """What lets ``manager``'s ``node`` read (``write``: write) the parameter ``key``."""
    pattern = node_pattern(node)
    if pattern == TOOL_NODES["roslaunch"]:  # its own keys and the launched nodes' (named by grants): one bundle
        own = any(key == ns or key.startswith(ns + "/") for ns in ("/run_id", "/roslaunch", "/rosdistro", "/rosversion"))
        return command(PROG, "grant-tools", manager, "--roslaunch", *(() if own else ("--launch-param-ns", key)))
    if pattern == TOOL_NODES["rosparam"]:
        return command(PROG, "grant-tools", manager, "--param-ns", key, *(() if write else ("--params-read-only",)))
    return command(PROG, "grant", manager, "write_param" if write else "read_param", pattern, key)


def grant_hint(exc: PolicyDenied, method: str, params: tuple, manager: str | None) -> str | None:
    """The command that would allow a refused master or node call of ``manager``'s node,
    or None when no grant would (or it cannot be told)."""
    if not manager or not params or not isinstance(params[0], str) or not isinstance(exc, PolicyDenied):
        return None
    node, reason = params[0], exc.reason
    if reason in ("param_write_denied", "param_read_denied"):
        index = 2 if method in ("subscribeParam", "unsubscribeParam") else 1
        if len(params) <= index or not isinstance(params[index], str):
            return None
        try:
            key = resolve_param_key(params[index], node)
        except PolicyDenied:
            return None
        return param_hint(manager, node, key, reason == "param_write_denied")
    if reason != "not_granted":
        return None
    if exc.missing is not None:
        return missing_grant_hint(exc, manager)
    if method in ("registerPublisher", "registerSubscriber", "registerService") and len(params) > 2 and \
            all(isinstance(p, str) for p in params[1:3]):
        action = {"registerPublisher": "publish", "registerSubscriber": "subscribe"}.get(method, "serve")
        name, type_name = params[1], params[2] if action != "serve" else None
        if ros1_allows(action, node, name, type_name):
            return unnamed_node_hint(manager, node)  # /rosout, its own loggers: refused only to a node no grant names
        return stream_grant_hint(manager, action, node, name, type_name)
    return None


def missing_grant_hint(exc: PolicyDenied, manager: str | None) -> str | None:
    """The command that would allow a stream refused for a grant ``manager`` lacks
    (``exc.missing``: a TCPROS header's check, a topic request), or None."""
    if exc.reason != "not_granted" or exc.missing is None or not manager:
        return None
    return stream_grant_hint(manager, *exc.missing)


__all__ = ["PROG", "TOOL_NODES", "command", "grant_hint", "missing_grant_hint", "param_hint", "stream_grant_hint",
           "unnamed_node_hint"]
