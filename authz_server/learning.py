"""Learning mode on the registry's side: what an interceptor may report, the grants a
manager's learned requests call for, and the grants nobody used.

Pure functions over observations (:class:`~authz_server.registry.ObservationRow`) and
grants (:class:`~authz_server.registry.GrantRow`); ``cryptoros-authz learn`` and
``unused`` (authz_server/learn_cli.py) do the reading, writing and printing.

A proposal is the smallest set of grants that would have allowed what was seen:

- node names exactly as seen (``/lidar_2048`` too), except the names ROS makes anew
  each run (rospy's anonymous ``/rostopic_4711_1795...``, roscpp's ``/record_<ns>``,
  ``/rosparam-4711``): those become the prefix pattern
  :func:`cryptoros.policy.ros1.node_pattern` gives (``/rostopic_*``), the only wildcard a
  proposal holds, and only where it was needed;
- topics and services exactly, with the type seen; a request that did not tell its
  type (a service registration, a subscriber of any type) takes the one type the rest
  of the registry knows for the name (another observation, a grant), and is reported,
  not guessed, when there is none or several;
- parameters by exact key (``/fleet/zone_1234`` too); a key whose last part changes
  each run (roslaunch's ``/roslaunch/uris/host_<address>__<port>``, an anonymous
  node's name) by the namespace above it; a read of a key the same node writes is
  covered by its ``write_param``;
- what ROS does without a grant once a node is the manager's (``/rosout``, its logger
  services) is left out when the proposal names the node otherwise.
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

from authz_server.registry import PARAM_ACTIONS, GrantRow, ObservationRow, grant_key
from cryptoros.errors import RegistryError
from cryptoros.names import PARAM_TYPE, validate_caller_id, validate_graph_name, validate_namespace, validate_type
from cryptoros.policy.infrastructure import ROS1_ROSOUT, ros1_own_type
from cryptoros.policy.ros1 import anonymous_prefix, node_pattern
from cryptoros.grants import ACTIONS, Grants, in_namespace, node_matches

#: rows one report may carry
MAX_OBSERVATION_ROWS = 64
#: a report's times may lie this far in the past or future of the server's clock (seconds)
CLOCK_SLACK = 24 * 3600
#: roslaunch's ``/roslaunch/uris/<host>__<port>``: its XML-RPC server's port, another each run
_LAUNCH_URI = re.compile(r"^/roslaunch/uris/[^/]+__[1-9]\d{0,4}$")


def checked_observations(body: object, *, now: float) -> list[dict]:
    """The rows of a ``POST /observations`` body, validated (RegistryError on any fault:
    nothing of a bad report is kept; the interceptor halves a refused report until the
    bad row stands alone, and drops it). A row's node is a caller ID as the interceptor
    records it (:func:`cryptoros.names.validate_caller_id`: stock tools' anonymous
    ``/rosparam-4711`` included), never a pattern."""
    rows = body.get("observations") if isinstance(body, Mapping) else None
    if not isinstance(rows, list) or len(rows) > MAX_OBSERVATION_ROWS:
        raise RegistryError(f"'observations' must be a list of at most {MAX_OBSERVATION_ROWS} rows")
    return [_checked(row, now, i) for i, row in enumerate(rows)]


def _checked(row: object, now: float, i: int) -> dict:
    where = f"observations[{i}]"
    keys = {"allowed", "action", "node", "name", "type", "count", "first", "last"}
    if not isinstance(row, Mapping) or set(row) != keys:
        raise RegistryError(f"{where} must have exactly the keys {', '.join(sorted(keys))}")
    allowed, action, type_, count = row["allowed"], row["action"], row["type"], row["count"]
    if not isinstance(allowed, bool) or action not in ACTIONS:
        raise RegistryError(f"{where}: 'allowed' must be a boolean and 'action' one of {', '.join(ACTIONS)}")
    validate_caller_id(row["node"])
    if action in PARAM_ACTIONS:
        validate_namespace(row["name"])
        if type_ is not None:
            raise RegistryError(f"{where}: a parameter has no type")
    else:
        validate_graph_name(row["name"])
        if type_ is not None:
            validate_type(type_)
    if not (isinstance(count, int) and not isinstance(count, bool) and 0 < count < 2**31):
        raise RegistryError(f"{where}: 'count' must be a positive integer")
    first, last = row["first"], row["last"]
    for t in (first, last):
        if not (isinstance(t, (int, float)) and not isinstance(t, bool) and abs(t - now) <= CLOCK_SLACK):
            raise RegistryError(f"{where}: 'first' and 'last' must be Unix times within a day of now")
    if first > last:
        raise RegistryError(f"{where}: 'first' is after 'last'")
    return {"allowed": allowed, "action": action, "node": row["node"], "name": row["name"], "type": type_,
            "count": count, "first": first, "last": last}


def granted(grants: Grants, row: Mapping) -> bool:
    """Whether a reported row of a request a grant allowed falls under one of ``grants``."""
    if row["action"] in PARAM_ACTIONS:
        return grants.param_allows("write" if row["action"] == "write_param" else "read", row["node"], row["name"])
    return row["type"] is not None and grants.allows(row["action"], row["node"], row["name"], row["type"])


# ---------------------------------------------------------------------- proposals
@dataclass(frozen=True)
class Proposed:
    """One proposed grant, with what calls for it."""

    grant: GrantRow
    count: int
    last_seen: int
    #: the requests it covers, as seen (node, name), when they differ from the grant's
    covers: tuple[str, ...] = ()


@dataclass
class _Seen:
    """What calls for one proposed grant, summed over the requests it covers."""

    count: int = 0
    last: int = 0
    covers: set[str] = field(default_factory=set)


@dataclass
class Proposal:
    manager: str
    grants: list[Proposed] = field(default_factory=list)
    #: what was seen but cannot be granted from what was seen (one line each)
    notes: list[str] = field(default_factory=list)


def _family(action: str) -> str:
    return "topic" if action in ("publish", "subscribe") else "service"


def known_types(observations: Iterable[ObservationRow], grants: Iterable[GrantRow]) -> dict[tuple[str, str], set[str]]:
    """(topic or service, name) -> the types anything in the registry knows it by."""
    out: dict[tuple[str, str], set[str]] = {}
    for o in observations:
        if o.type and o.action not in PARAM_ACTIONS:
            out.setdefault((_family(o.action), o.name), set()).add(o.type)
    for g in grants:
        if g.action not in PARAM_ACTIONS:
            out.setdefault((_family(g.action), g.name), set()).add(g.type)
    return out


def _covered(grants: Sequence[GrantRow], action: str, node: str, name: str, type_: str) -> bool:
    for g in grants:
        if not node_matches(g.node, node):
            continue
        if action in PARAM_ACTIONS:
            if (g.action == action or g.action == "write_param") and in_namespace(name, g.name):
                return True
        elif g.action == action and g.name == name and g.type == type_:
            return True
    return False


def _param_name(key: str) -> str:
    """The namespace to grant for a learned key: the key itself, but for a last part
    another each run (roslaunch's server URI, an anonymous node's name), which is left off."""
    if _LAUNCH_URI.match(key):
        return "/roslaunch/uris"
    parts = key.split("/")
    while len(parts) > 2 and anonymous_prefix("/" + parts[-1]) is not None:
        parts.pop()
    return "/".join(parts) or "/"


def propose(manager: str, learned: Iterable[ObservationRow], current: Iterable[GrantRow],
            types: Mapping[tuple[str, str], set[str]]) -> Proposal:
    """The grants ``manager``'s ``learned`` requests call for, beyond ``current``."""
    current = list(current)
    proposal = Proposal(manager)
    wanted: dict[GrantRow, _Seen] = {}
    #: grants for what ROS does on a node's behalf (/rosout, its logger services), and the others
    ros_own: set[GrantRow] = set()
    named: set[GrantRow] = set()
    typed = {(o.action, o.node, o.name) for o in learned if o.type}
    for o in sorted(learned, key=lambda o: (o.action, o.node, o.name, o.type or "")):
        node = node_pattern(o.node)
        own_type = ros1_own_type(o.action, o.node, o.name)
        is_own = o.action == "publish" and (o.name, o.type) == ROS1_ROSOUT or (
            own_type is not None and o.type in (None, own_type))
        if o.action in PARAM_ACTIONS:
            name, type_ = _param_name(o.name), PARAM_TYPE
        elif is_own:
            name, type_ = o.name, o.type or own_type
        else:
            name, type_ = o.name, o.type
            if type_ is None:
                if (o.action, o.node, o.name) in typed:
                    continue  # the same request told its type elsewhere (a subscriber of any type)
                seen = types.get((_family(o.action), o.name), set())
                if len(seen) != 1:
                    proposal.notes.append(
                        f"{o.node} {o.action} {o.name}: type {'not seen' if not seen else 'one of ' + ', '.join(sorted(seen))}"
                        f"; grant it by hand (cryptoros-authz grant {manager} {o.action} {node} {o.name} TYPE)")
                    continue
                type_ = next(iter(seen))
        grant = GrantRow(o.action, node, name, type_)
        if _covered(current, grant.action, o.node, o.name if o.action in PARAM_ACTIONS else name, type_):
            continue
        (ros_own if is_own else named).add(grant)
        entry = wanted.setdefault(grant, _Seen())
        entry.count += o.count
        entry.last = max(entry.last, o.last_seen)
        if node != o.node or name != o.name:
            entry.covers.add(f"{o.node} {o.name}")
    rows = list(wanted)
    for grant in rows:
        if grant.action == "read_param" and _covered([g for g in rows if g.action == "write_param"] + current,
                                                     "read_param", grant.node, grant.name, PARAM_TYPE):
            del wanted[grant]
    for grant in ros_own - named:
        if any(g.node == grant.node for g in named if g in wanted) or any(node_matches(c.node, grant.node)
                                                                         for c in current):
            del wanted[grant]  # the node is named otherwise: ROS's own topics and services need no grant
    proposal.grants = [Proposed(g, s.count, s.last, tuple(sorted(s.covers))) for g, s in sorted(wanted.items())]
    return proposal


def proposal_yaml(proposal: Proposal) -> str:
    """The proposal as the ``import`` YAML (``import --merge`` adds it), each grant with
    how often and when last it was seen."""
    lines = ["version: 1", "managers:", f"- name: {proposal.manager}", "  grants:"]
    by_action: dict[str, list[Proposed]] = {}
    for p in proposal.grants:
        by_action.setdefault(p.grant.action, []).append(p)
    if not by_action:
        lines[-1] = "  grants: {}"
    for action in ACTIONS:
        if action not in by_action:
            continue
        lines.append(f"    {action}:")
        for p in by_action[action]:
            g = p.grant
            fields = f"node: '{g.node}', {grant_key(action)}: '{g.name}'"
            if action not in PARAM_ACTIONS:
                fields += f", type: '{g.type}'"
            lines.append(f"    - {{{fields}}}  # {_seen(p)}")
    return "\n".join(lines) + "\n"


def _seen(p: Proposed) -> str:
    when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(p.last_seen))
    covers = f"; covers {', '.join(p.covers[:3])}{' ...' if len(p.covers) > 3 else ''}" if p.covers else ""
    return f"seen {p.count} times, last {when}{covers}"


def proposal_diff(proposal: Proposal, current: Iterable[GrantRow]) -> list[str]:
    """``+`` the grants the proposal adds, ``=`` the manager's grants it keeps."""
    lines = [f"+ {p.grant.action} {p.grant.node} {p.grant.name}"
             f"{'' if p.grant.action in PARAM_ACTIONS else ' ' + p.grant.type}  ({_seen(p)})" for p in proposal.grants]
    lines += [f"= {g.action} {g.node} {g.name}{'' if g.action in PARAM_ACTIONS else ' ' + g.type}"
              for g in sorted(current)]
    return lines


# ---------------------------------------------------------------------- unused grants
def unused(grants: Iterable[GrantRow], used: Iterable[ObservationRow]) -> list[GrantRow]:
    """The grants no allowed request in ``used`` (one manager's) falls under."""
    used = list(used)
    out = []
    for g in grants:
        if not any(o.action == g.action and node_matches(g.node, o.node) and (
                in_namespace(o.name, g.name) if g.action in PARAM_ACTIONS else o.name == g.name and o.type == g.type)
                or g.action == "write_param" and o.action == "read_param" and node_matches(g.node, o.node)
                and in_namespace(o.name, g.name) for o in used):
            out.append(g)
    return out


__all__ = ["MAX_OBSERVATION_ROWS", "Proposal", "Proposed", "checked_observations", "granted", "known_types", "propose",
           "proposal_diff", "proposal_yaml", "unused"]
