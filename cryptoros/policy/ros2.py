"""The ROS 2 role's decisions: pure functions over a token's grants and the DDS graph.

- :func:`local_offer`: what a robot offers its peers for one topic or service of its
  own domain, from the publishers or servers the graph shows and its own grants. A
  topic is offered when at least one local publisher node is granted; only the samples
  of granted publishers' writers are forwarded (the DDS bridge filters each sample by
  its writer GID), so a rogue publisher under an ungranted name is refused from its
  first sample and never takes the topic off the air. Services cannot be filtered per
  server: one ungranted server withholds the service.
- :func:`manager_may`: the receiving side, decided per manager.
- :func:`may_learn`: need to know: a peer is told about a stream (its name, type,
  node, QoS) only when its own grants let it receive that stream.

A DDS node name is self-chosen: a process on the robot's domain that names itself
like a granted node is that node to this module (docs/ros2.md, "Trust zone").
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from cryptoros.errors import PolicyDenied
from cryptoros.names import validate_graph_name
from cryptoros.policy.infrastructure import ros2_stays_local
from cryptoros.ros2.target import QoS, StreamTarget
from cryptoros.grants import Grants

#: a node name the graph reports before discovery has told it the real one
UNKNOWN_NODE_MARK = "_UNKNOWN_"


@dataclass(frozen=True, slots=True)
class Offer:
    """One local topic or service this robot may offer its peers."""

    target: StreamTarget
    #: the local publisher nodes whose samples are forwarded (topics)
    writers: frozenset[str]
    #: local publisher nodes under no grant: their samples are dropped (topics)
    refused: tuple[str, ...] = ()


def local_offer(kind: str, name: str, types: Sequence[str], sources: Sequence[Mapping[str, Any]], *,
                grants: Grants, depth: int) -> Offer | None:
    """``kind`` ("topic" or "service") ``name`` as the graph shows it: ``types`` and its
    ``sources`` (publishers: ``node``, ``reliability``, ``durability``; servers: ``node``).

    Returns ``None`` for what is never bridged (ROS infrastructure, nothing published)
    or not decidable yet (discovery has told no publisher's node name); raises
    :class:`PolicyDenied` (``type_conflict``, ``not_granted``) or, for a name that cannot
    be carried, :class:`~cryptoros.errors.RegistryError`."""
    if not sources or ros2_stays_local(name, types):
        return None
    validate_graph_name(name)
    action = "publish" if kind == "topic" else "serve"
    if kind == "topic" and all("type" in s for s in sources):
        # each publisher with its own type: a subscriber's type (any local node may
        # subscribe with another one) or an ungranted publisher's decides nothing (ROS 2
        # audit: an ungranted node subscribing /chatter as Int32 took it off the air)
        return _topic_offer(name, sources, grants=grants, depth=depth)
    if len(types) != 1:
        raise PolicyDenied("type_conflict", f"{name} is offered with several types {list(types)}")
    type_name = types[0]
    # A publisher whose node name discovery has not told yet is neither granted nor
    # refused: it is decided next round (the bridge drops its samples meanwhile, as it
    # drops any writer it cannot map to a granted node), and the topic stays on the air.
    nodes = sorted({s["node"] for s in sources if UNKNOWN_NODE_MARK not in s["node"]})
    if not nodes:
        return None
    granted = [n for n in nodes if grants.allows(action, n, name, type_name)]
    refused = tuple(n for n in nodes if n not in granted)
    if not granted or (kind == "service" and refused):
        raise PolicyDenied("not_granted", f"{refused[0]} may not {action} {name} [{type_name}]")
    qos = QoS()
    if kind == "topic":
        mine = [s for s in sources if s["node"] in granted]
        qos = QoS(
            reliability="best_effort" if any(s["reliability"] == "best_effort" for s in mine) else "reliable",
            durability="transient_local" if all(s["durability"] == "transient_local" for s in mine) else "volatile",
            depth=depth,
        )
    target = StreamTarget(kind=kind, name=name, type=type_name, node=granted[0], qos=qos)
    return Offer(target=target, writers=frozenset(granted), refused=refused)


def _topic_offer(name: str, sources: Sequence[Mapping[str, Any]], *, grants: Grants, depth: int) -> Offer | None:
    """A topic whose publishers each carry their ``type``: the granted ones must agree on
    one type (``type_conflict`` names them otherwise); the others are refused."""
    named = [s for s in sources if UNKNOWN_NODE_MARK not in s["node"]]
    if not named:
        return None
    mine = [s for s in named if grants.allows("publish", s["node"], name, s["type"])]
    refused = tuple(sorted({f"{s['node']}" for s in named if s not in mine}))
    if not mine:
        first = sorted(named, key=lambda s: (s["node"], s["type"]))[0]
        raise PolicyDenied("not_granted", f"{first['node']} may not publish {name} [{first['type']}]")
    kinds = sorted({s["type"] for s in mine})
    if len(kinds) != 1:
        who = ", ".join(f"{s['node']} [{s['type']}]" for s in sorted(mine, key=lambda s: (s["type"], s["node"])))
        raise PolicyDenied("type_conflict", f"{name} is published with several types by granted nodes: {who}")
    granted = sorted({s["node"] for s in mine})
    refused = tuple(n for n in refused if n not in granted)
    qos = QoS(
        reliability="best_effort" if any(s["reliability"] == "best_effort" for s in mine) else "reliable",
        durability="transient_local" if all(s["durability"] == "transient_local" for s in mine) else "volatile",
        depth=depth,
    )
    target = StreamTarget(kind="topic", name=name, type=kinds[0], node=granted[0], qos=qos)
    return Offer(target=target, writers=frozenset(granted), refused=refused)


def manager_may(grants: Grants, action: str, name: str, type_name: str) -> bool:
    """Whether any node of the token's manager may ``action`` ``name`` with ``type_name``.

    A receiving robot cannot tell DDS which of its own nodes may read a republished
    topic (its domain is one trust zone), so the receiving side is decided per manager."""
    return grants.any_node_allows(action, name, type_name)


def may_learn(peer_grants: Grants, target: StreamTarget) -> bool:
    """Need to know: whether a peer whose manager holds ``peer_grants`` may be told of
    ``target`` at all (it may receive it: subscribe a topic, call a service)."""
    return manager_may(peer_grants, target.peer_action, target.name, target.type)


__all__ = ["Offer", "UNKNOWN_NODE_MARK", "local_offer", "manager_may", "may_learn"]
