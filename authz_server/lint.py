"""Warnings about a registry that it takes but a running robot would trip on.

Pure functions over managers and their grants, for ``grant`` and ``import`` to print:
two managers naming one node (who then holds the name),
and one topic or service granted with two types (it carries one; a stream of the other
is refused). Nothing here refuses anything: each is a line for the operator.
"""

from __future__ import annotations

from authz_server.registry import PARAM_ACTIONS
from cryptoros.names import is_node_pattern
from cryptoros.policy.ros1 import SHARED_TOOL_NAMES
from cryptoros.grants import nodes_overlap

#: overlaps named per grant at most (the rest are counted)
OVERLAPS_SHOWN = 5


def _ros2(type_name: str | None) -> bool:
    """A ROS 2 type (``pkg/msg/Name``): ROS 2 has no master, so no node name is held."""
    return isinstance(type_name, str) and type_name.count("/") == 2


def node_overlaps(manager: str, node: str, managers, type_name: str | None = None) -> list[str]:
    """One line per other manager's grant node that ``node`` can name too, saying who
    then holds the name (docs/interceptor.md, "Stock tools"): two exact names, whichever
    manager registers it first (the other's node is refused, ``name_taken``); a pattern
    and an exact name, always the manager whose grants name it exactly (the pattern's
    node is dropped when that one registers). Two patterns are not named: the names
    registered under them are anonymous ones (stock tools) no two processes share. Nor
    are the names every robot's tools use (:data:`~cryptoros.policy.ros1.SHARED_TOOL_NAMES`,
    ``/roslaunch``): no node registers them, so no one holds them. Nor a grant of a ROS 2
    type (``type_name``), on either side: two robots' ``/listener`` both run."""
    if node in SHARED_TOOL_NAMES or _ros2(type_name):
        return []
    hits = sorted({(m.name, g.node) for m in managers if m.name != manager for g in m.grants
                   if nodes_overlap(node, g.node) and not (is_node_pattern(node) and is_node_pattern(g.node))
                   and g.node not in SHARED_TOOL_NAMES and not _ros2(g.type)})
    lines = []
    for other, theirs in hits:
        if not is_node_pattern(node) and not is_node_pattern(theirs):
            lines.append(f"node {node} is named by {other}'s grants too: whichever registers it first holds it, and "
                         f"the other's node is refused (name_taken); give each robot node names of its own")
        elif is_node_pattern(node):
            lines.append(f"pattern {node} covers node {theirs}, which {other}'s grants name exactly: {other}'s node "
                         f"always holds that name, and a node of {manager} registered under it is dropped")
        else:
            lines.append(f"node {node} is covered by {other}'s pattern {theirs} too: {manager}'s node always holds "
                         f"that name, and a node of {other} registered under it is dropped")
    if len(lines) > OVERLAPS_SHOWN:
        lines = lines[:OVERLAPS_SHOWN] + [f"... and {len(lines) - OVERLAPS_SHOWN} more overlaps of node {node}"]
    return lines


def kind_of(action: str) -> str:
    """``topic`` for publish and subscribe grants, ``service`` for serve and call."""
    return "topic" if action in ("publish", "subscribe") else "service"


def type_conflicts(kind: str, name: str, held) -> list[str]:
    """A line when the topic or service ``name`` is granted with more than one type among
    ``held`` ((manager, grant) pairs): it carries one type, so a stream of any other is
    refused; a typo (``sensor_msgs/LaserScn``) or a ROS 1 and a ROS 2 spelling of one
    type (``std_msgs/String``, ``std_msgs/msg/String``: cryptoros carries no stream between
    ROS 1 and ROS 2) is usually why."""
    types: dict[str, set[str]] = {}
    for manager, g in held:
        if g.name == name and g.action not in PARAM_ACTIONS and kind_of(g.action) == kind and g.type != "*":
            types.setdefault(g.type, set()).add(manager)
    if len(types) < 2:
        return []
    listed = "; ".join(f"{t} ({', '.join(sorted(ms))})" for t, ms in sorted(types.items()))
    return [f"{kind} {name} is granted with {len(types)} types: {listed}; it carries one, and a stream of "
            "another is refused: a typo, or a ROS 1 and a ROS 2 spelling of one type?"]


__all__ = ["OVERLAPS_SHOWN", "kind_of", "node_overlaps", "type_conflicts"]
