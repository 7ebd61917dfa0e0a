"""What a manager's nodes may do: the grant rows a registry holds and a token carries,
and the one matching of node names every interceptor and the authorization server use.

Pure and free of cryptography: :mod:`cryptoros.tokens` carries these in signed claims;
the registry's command line, the policy linter and the policy functions read them
without loading a JWT library.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

from cryptoros.errors import TokenError
from cryptoros.names import (
    NODE_WILDCARD,
    PARAM_TYPE,
    is_node_pattern,
    validate_graph_name,
    validate_namespace,
    validate_node_name,
    validate_type,
)

#: Parameter grants: ``name`` is a namespace, ``type`` is always :data:`PARAM_TYPE`;
#: ``write_param`` implies ``read_param``.
PARAM_ACTIONS = ("read_param", "write_param")
ACTIONS = ("publish", "subscribe", "serve", "call", *PARAM_ACTIONS)


@dataclass(frozen=True, kw_only=True, order=True)
class Grant:
    """One registry row: ``node`` may ``action`` the topic or service ``name`` of ``type``."""

    node: str
    action: str
    name: str
    type: str

    def __post_init__(self) -> None:
        if self.action not in ACTIONS:
            raise ValueError(f"unknown action {self.action!r}; expected one of {', '.join(ACTIONS)}")
        validate_node_name(self.node)
        if self.action in PARAM_ACTIONS:
            validate_namespace(self.name)
            if self.type != PARAM_TYPE:
                raise ValueError(f"a parameter grant has type {PARAM_TYPE!r}, not {self.type!r}")
        else:
            validate_graph_name(self.name)
            validate_type(self.type)


def node_matches(granted: str, node: str) -> bool:
    """Whether the node name of a grant covers the caller ``node``: the one decision,
    used by every :class:`Grants` method (so every interceptor decides alike).

    ``*`` covers every node; a prefix pattern ``/rostopic_*`` covers every name that
    starts with ``/rostopic_`` and has at least one character more (``/`` included);
    any other grant covers exactly its own name (``/talker`` never ``/talker2``)."""
    if granted == NODE_WILDCARD:
        return True
    if is_node_pattern(granted):
        return len(node) >= len(granted) and node.startswith(granted[:-1])
    return granted == node


def nodes_overlap(a: str, b: str) -> bool:
    """Whether two grants' node names can name one node: equal names, a pattern and a
    name it covers, or two patterns one of whose prefixes starts the other's. ``*`` (any
    node of its own manager) overlaps nothing here: it names no node another manager
    could register."""
    if NODE_WILDCARD in (a, b):
        return False
    if is_node_pattern(a) and is_node_pattern(b):
        return a[:-1].startswith(b[:-1]) or b[:-1].startswith(a[:-1])
    if is_node_pattern(b):
        a, b = b, a
    return node_matches(a, b)


class Grants:
    """An immutable set of grants, as carried in a token."""

    __slots__ = ("_grants", "_index")

    def __init__(self, grants: Iterable[Grant] = ()) -> None:
        self._grants = frozenset(grants)
        index: dict[tuple[str, str, str], list[str]] = {}
        for g in self._grants:
            index.setdefault((g.action, g.name, g.type), []).append(g.node)
        #: (action, name, type) -> granted node names (exact, ``*`` or patterns)
        self._index = {k: tuple(v) for k, v in index.items()}

    def __iter__(self) -> Iterator[Grant]:
        return iter(sorted(self._grants))

    def __len__(self) -> int:
        return len(self._grants)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Grants) and other._grants == self._grants

    def __hash__(self) -> int:
        return hash(self._grants)

    def __repr__(self) -> str:
        return f"Grants({sorted(self._grants)!r})"

    def allows(self, action: str, node: str, name: str, type: str) -> bool:
        """Exact match on action, name and type; the node by :func:`node_matches`."""
        return any(node_matches(granted, node) for granted in self._index.get((action, name, type), ()))

    def any_node_allows(self, action: str, name: str, type_name: str) -> bool:
        """Whether some node of the manager may ``action`` ``name`` with ``type_name``."""
        return (action, name, type_name) in self._index

    def types_for(self, action: str, node: str, name: str) -> frozenset[str]:
        """The types ``node`` may ``action`` the topic or service ``name`` with."""
        return frozenset(
            g.type
            for g in self._grants
            if g.action == action and g.name == name and node_matches(g.node, node)
        )

    def param_allows(self, access: str, node: str, key: str) -> bool:
        """Whether ``node`` may ``access`` ("read" or "write") the global parameter
        ``key`` under a granted namespace (``write_param`` implies read)."""
        actions = ("write_param",) if access == "write" else ("read_param", "write_param")
        return any(
            g.action in actions and node_matches(g.node, node) and in_namespace(key, g.name) for g in self._grants
        )

    def param_namespaces(self, node: str) -> frozenset[str]:
        """The namespaces ``node`` may read (for pruning namespace reads)."""
        return frozenset(g.name for g in self._grants if g.action in PARAM_ACTIONS and node_matches(g.node, node))

    def names_node(self, node: str) -> bool:
        """Whether any grant covers ``node`` (exactly, ``*`` or a prefix pattern): the
        node is this manager's, so it may register that name at the master."""
        return any(node_matches(g.node, node) for g in self._grants)

    def names_node_beyond_wildcard(self, node: str) -> bool:
        """Whether a grant other than the bare wildcard ``*`` covers ``node`` (its exact
        name or a prefix pattern)."""
        return any(g.node != NODE_WILDCARD and node_matches(g.node, node) for g in self._grants)

    def names_node_exactly(self, node: str) -> bool:
        """Whether a grant names ``node`` itself (not through ``*`` or a pattern): the
        registry gives this manager that very name."""
        return any(g.node == node for g in self._grants)

    def names(self) -> frozenset[str]:
        """The topics and services named by any grant (parameter namespaces excluded)."""
        return frozenset(g.name for g in self._grants if g.action not in PARAM_ACTIONS)

    def narrowed_to(self, peer: Grants) -> Grants:
        """What a peer holding ``peer`` needs to judge streams with this manager, and no
        more (no parameter grants, nothing on a name the peer holds no grant on):

        - the topic and service grants on names ``peer`` holds a grant on;
        - the calls and subscriptions of endpoints ROS serves under a node's own name
          (``<node>/get_loggers``, ``<node>/set_parameters`` ...: allowed to any node a
          grant names) of nodes ``peer``'s grants name (``/cam_*`` names ``/cam_front``);
        - for each such endpoint ``peer`` calls or subscribes of a node these grants
          name, the serve or publish grant that node has without a grant row."""
        from cryptoros.policy.infrastructure import ROS1_OPENED_BY, ros1_own_endpoint

        keep = peer.names()
        kept = [g for g in self._grants if g.action not in PARAM_ACTIONS and g.name in keep]
        for mine, theirs, implied in ((self, peer, False), (peer, self, True)):
            for g in mine._grants:
                own = ros1_own_endpoint(g.action, g.name) if g.action in ROS1_OPENED_BY else None
                if own is None or own[1] != g.type or not theirs.names_node(own[0]):
                    continue
                kept.append(Grant(node=own[0], action=ROS1_OPENED_BY[g.action], name=g.name, type=g.type)
                            if implied else g)
        return Grants(kept)

    def to_claim(self) -> dict[str, dict[str, list[list[str]]]]:
        claim: dict[str, dict[str, list[list[str]]]] = {}
        for g in sorted(self._grants):
            claim.setdefault(g.node, {}).setdefault(g.action, []).append([g.name, g.type])
        return claim

    @classmethod
    def from_claim(cls, claim: Any) -> Grants:
        """Parse the ``grants`` claim strictly; anything unexpected is ``malformed``."""
        if not isinstance(claim, Mapping):
            raise TokenError("malformed", "grants claim is not an object")
        grants = []
        try:
            for node, actions in claim.items():
                if not isinstance(actions, Mapping):
                    raise TokenError("malformed", f"grants for {node!r} are not an object")
                for action, rows in actions.items():
                    if not isinstance(rows, list):
                        raise TokenError("malformed", f"grants {node!r}/{action!r} are not a list")
                    for row in rows:
                        if not (isinstance(row, list) and len(row) == 2 and all(isinstance(x, str) for x in row)):
                            raise TokenError("malformed", f"grant row {row!r} is not [name, type]")
                        grants.append(Grant(node=node, action=action, name=row[0], type=row[1]))
        except TokenError:
            raise
        except Exception as exc:  # invalid names, types or actions
            raise TokenError("malformed", f"invalid grant: {exc}") from exc
        return cls(grants)


def in_namespace(key: str, namespace: str) -> bool:
    """``/a/b`` is in ``/a`` and in ``/``; ``/ab`` is not in ``/a``."""
    return namespace == "/" or key == namespace or key.startswith(namespace + "/")
