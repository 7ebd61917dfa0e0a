"""Validation of ROS graph names, node names and data type names.

The registry stores global names only (``/chatter``, ``/robot1/scan``): a relative or
private name means something different on every node, so it has no place in a grant.
A node name in a grant may also be the explicit wildcard ``*`` ("any node of this
manager") or a prefix pattern ending in ``*`` (``/rostopic_*``, ``/rosparam-*``,
``/robot1/*``): the anonymous names stock tools run under (``/rostopic_<pid>_<ms>``,
``/rosparam-<pid>``). Only a trailing ``*`` is a wildcard; whether a node matches a
granted name is decided by :func:`cryptoros.grants.node_matches` alone.
"""

from __future__ import annotations

import re

from cryptoros.errors import RegistryError

_SEGMENT = r"[A-Za-z][A-Za-z0-9_]*"
_GLOBAL_NAME = re.compile(rf"^(/{_SEGMENT})+$")
_ROS1_TYPE = re.compile(rf"^{_SEGMENT}/{_SEGMENT}$")
_ROS2_TYPE = re.compile(rf"^{_SEGMENT}/(msg|srv|action)/{_SEGMENT}$")

NODE_WILDCARD = "*"
MAX_NAME_LENGTH = 256


def validate_graph_name(name: str, what: str = "topic or service name") -> str:
    """Return ``name`` if it is a valid global ROS name, else raise RegistryError."""
    if not isinstance(name, str) or len(name) > MAX_NAME_LENGTH or not _GLOBAL_NAME.match(name):
        raise RegistryError(
            f"invalid {what} {name!r}: expected a global ROS name such as /chatter or /robot1/scan"
        )
    return name


#: The "type" of a parameter grant: parameters carry no declared type.
PARAM_TYPE = "param"


def validate_namespace(name: str) -> str:
    """A parameter namespace: ``/`` (every parameter) or a global name (``/robot1``
    covers ``/robot1`` and everything below it, not ``/robot10``)."""
    if name == "/":
        return name
    return validate_graph_name(name, "parameter namespace")


_CALLER_ID = re.compile(r"^(/[A-Za-z][A-Za-z0-9_-]*)+$")


def validate_caller_id(name: str) -> str:
    """The ``caller_id`` of an XML-RPC call: a global name, where stock tools'
    anonymous names (``/rosparam-4242``, ``/rostopic_4242_1700000000000``) may hold
    ``-`` too. Grants still name nodes by :func:`validate_node_name` rules."""
    if not isinstance(name, str) or len(name) > MAX_NAME_LENGTH or not _CALLER_ID.match(name):
        raise RegistryError(f"invalid caller_id {name!r}: expected a global ROS name such as /talker")
    return name


def is_node_pattern(name: str) -> bool:
    """Whether a granted node name is a prefix pattern (``/rostopic_*``), not ``*`` or an exact name."""
    return isinstance(name, str) and len(name) > 1 and name.endswith(NODE_WILDCARD)


def validate_node_name(name: str) -> str:
    """A global node name such as ``/talker``, the explicit wildcard ``*``, or a
    prefix pattern: a global name prefix (``-`` allowed, as in stock tools' anonymous
    names) followed by one trailing ``*`` such as ``/rostopic_*``, ``/rosparam-*`` or
    ``/robot1/*``. The ``*`` stands for one or more characters, ``/`` included."""
    if name == NODE_WILDCARD:
        return name
    if is_node_pattern(name):
        prefix = name[:-1]
        # prefix + "x" must be a caller_id: "/", a letter, then name characters, "-" or "/"
        if (NODE_WILDCARD in prefix or prefix == "/" or "//" in prefix or len(name) > MAX_NAME_LENGTH
                or not _CALLER_ID.match(prefix + "x")):
            raise RegistryError(
                f"invalid node pattern {name!r}: expected a global name prefix with one trailing '*', "
                "such as /rostopic_* or /rosparam-* (or '*' for any node)"
            )
        return name
    return validate_graph_name(name, "node name")


def validate_type(type_name: str) -> str:
    """``pkg/Name`` (ROS 1) or ``pkg/msg/Name``, ``pkg/srv/Name`` (ROS 2)."""
    if (
        not isinstance(type_name, str)
        or len(type_name) > MAX_NAME_LENGTH
        or not (_ROS1_TYPE.match(type_name) or _ROS2_TYPE.match(type_name))
    ):
        raise RegistryError(
            f"invalid data type {type_name!r}: expected pkg/Name (ROS 1) or pkg/msg/Name (ROS 2)"
        )
    return type_name


__all__ = ["NODE_WILDCARD", "PARAM_TYPE", "is_node_pattern", "validate_caller_id", "validate_graph_name", "validate_namespace", "validate_node_name",
           "validate_type"]
