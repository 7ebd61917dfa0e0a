"""A first-draft policy from a live ROS 1 graph (``cryptoros-authz policy from-graph``).

Two halves: :func:`read_graph` asks a master what the graph holds (``getSystemState``,
``getTopicTypes``, ``lookupNode``, ``getParamNames``, and each service's type through a
TCPROS probe header, as ``rosservice type`` does); :func:`draft_policy` is pure and turns
that :class:`Graph` into the ``import`` YAML document: exact node names, exact topics and
services with their types, never a wildcard. Each node goes to the manager the first
matching ``--manager-map`` entry names (:class:`ManagerMap`); a node no entry matches is
a warning and is granted nothing.

What a graph cannot show is a warning, never a guess: service clients (ROS 1 does not
register them), parameters outside a node's private namespace, names or types a grant
cannot hold. What ROS itself does without a grant (``/rosout``, each node's logger
services: :mod:`cryptoros.policy.infrastructure`) is left out.
"""

from __future__ import annotations

import asyncio
import fnmatch
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

from authz_server.registry import ACTIONS, PARAM_ACTIONS, POLICY_VERSION, GrantRow, grant_key, validate_manager_name
from cryptoros.errors import PEER_FAILURES, CryptorosError, RegistryError
from cryptoros.policy.infrastructure import ros1_allows
from cryptoros.policy.ros1 import DEFAULT_PARAM_READS, anonymous_prefix

#: the caller id the reader presents to the master and in its service probes
CALLER_ID = "/cryptoros_authz_graph"


# ---------------------------------------------------------------------- manager map
@dataclass(frozen=True)
class ManagerMap:
    """``PATTERN=MANAGER`` entries, first match wins. PATTERN is an fnmatch pattern on
    the subject's name (``/robot_a/*``: ``*`` matches ``/`` too), or ``@HOST`` (a
    pattern too) on the host of a ROS 1 node's XML-RPC URI."""

    entries: tuple[tuple[str, str], ...]

    @classmethod
    def parse(cls, values: Iterable[str], option: str = "--manager-map") -> ManagerMap:
        entries = []
        for value in values:
            pattern, sep, manager = value.rpartition("=")
            if not sep or not pattern or not manager:
                raise RegistryError(f"{option} {value!r}: expected PATTERN=MANAGER such as '/robot_a/*=robot_a'")
            validate_manager_name(manager)
            entries.append((pattern, manager))
        if not entries:
            raise RegistryError(f"give at least one {option} PATTERN=MANAGER")
        return cls(tuple(entries))

    def manager_for(self, name: str, host: str | None = None) -> str | None:
        for pattern, manager in self.entries:
            if pattern.startswith("@"):
                if host is not None and fnmatch.fnmatchcase(host, pattern[1:]):
                    return manager
            elif fnmatch.fnmatchcase(name, pattern):
                return manager
        return None

    @property
    def managers(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(m for _p, m in self.entries))


# ---------------------------------------------------------------------- the document
def policy_document(grants: Mapping[str, Iterable[GrantRow]]) -> dict:
    """The ``import`` YAML document (as ``export`` writes it: managers by name, grants by
    action then sorted) for managers without a certificate yet, enabled."""
    managers = []
    for name in sorted(grants):
        rows: dict[str, list[dict]] = {a: [] for a in ACTIONS}
        for g in sorted(set(grants[name])):
            row = {"node": g.node, grant_key(g.action): g.name}
            if g.action not in PARAM_ACTIONS:
                row["type"] = g.type
            rows[g.action].append(row)
        managers.append({"name": name, "fingerprint_sha256": None, "enabled": True,
                         "grants": {a: v for a, v in rows.items() if v}})
    return {"version": POLICY_VERSION, "managers": managers}


# ---------------------------------------------------------------------- the graph
@dataclass(frozen=True)
class Graph:
    """What a ROS 1 master reports. Lists as ``getSystemState`` gives them."""

    publishers: Mapping[str, Sequence[str]]
    subscribers: Mapping[str, Sequence[str]]
    services: Mapping[str, Sequence[str]]
    topic_types: Mapping[str, str]
    #: service -> type from its probe header, or None when the probe failed
    service_types: Mapping[str, str | None]
    #: node -> its XML-RPC URI (None when lookupNode failed)
    node_uris: Mapping[str, str | None]
    param_names: Sequence[str]

    @property
    def nodes(self) -> list[str]:
        found = {n for table in (self.publishers, self.subscribers, self.services)
                 for nodes in table.values() for n in nodes}
        return sorted(found | set(self.node_uris))


@dataclass
class Draft:
    doc: dict
    warnings: list[str] = field(default_factory=list)
    #: grants ROS needs that every node has without one (/rosout, logger services)
    infrastructure: int = 0


def _host(uri: str | None) -> str | None:
    from cryptoros.ros1.uri import split_uri

    if not uri:
        return None
    try:
        return split_uri(uri).host
    except CryptorosError:
        return None


def draft_policy(graph: Graph, managers: ManagerMap, *, param_access: str = "read_param") -> Draft:
    """The draft for ``graph``: pure, deterministic (sorted) and complete in its warnings."""
    if param_access not in PARAM_ACTIONS:
        raise RegistryError(f"parameter access must be one of {', '.join(PARAM_ACTIONS)}")
    draft = Draft(doc={})
    owner: dict[str, str] = {}
    for node in graph.nodes:
        manager = managers.manager_for(node, _host(graph.node_uris.get(node)))
        if manager is None:
            draft.warnings.append(f"node {node} matches no --manager-map entry: granted nothing")
        elif anonymous_prefix(node) is not None:  # another run will not have this name
            draft.warnings.append(f"node {node} has an anonymous name (another each run: a stock tool or "
                                  "init_node(anonymous=True)): granted nothing; grant it by a pattern by hand "
                                  "(cryptoros-authz grant-tools for stock tools)")
        else:
            owner[node] = manager
    grants: dict[str, set[GrantRow]] = {}

    def add(action: str, node: str, name: str, type_: str | None) -> None:
        manager = owner.get(node)
        if manager is None:
            return
        if ros1_allows(action, node, name, type_):
            draft.infrastructure += 1
            return
        try:
            row = GrantRow.checked(action, node, name, type_)
        except RegistryError as exc:
            draft.warnings.append(f"{node} {action} {name} [{type_}]: not granted: {exc}")
            return
        grants.setdefault(manager, set()).add(row)

    for action, table in (("publish", graph.publishers), ("subscribe", graph.subscribers)):
        for topic, nodes in sorted(table.items()):
            type_ = graph.topic_types.get(topic)
            if type_ is None or type_ == "*":
                mapped = [n for n in nodes if n in owner]
                if mapped:
                    draft.warnings.append(f"topic {topic} has no known type: {action} not granted to "
                                          f"{', '.join(mapped)}")
                continue
            for node in sorted(nodes):
                add(action, node, topic, type_)
    served: list[str] = []
    for service, nodes in sorted(graph.services.items()):
        type_ = graph.service_types.get(service)
        mapped = sorted(n for n in nodes if n in owner)
        if not mapped:
            continue
        if all(ros1_allows("serve", n, service, None) for n in mapped):
            draft.infrastructure += len(mapped)
            continue
        if type_ is None:
            draft.warnings.append(f"service {service}: its type probe failed: serve not granted to {', '.join(mapped)}")
            continue
        for node in mapped:
            add("serve", node, service, type_)
        served.append(f"{service} [{type_}]")
    if served:
        draft.warnings.append("ROS 1 does not register service clients: grant 'call' by hand to the nodes that "
                              f"call {', '.join(served)}")
    granted_ns: set[str] = set()
    stray: list[str] = []
    longest_first = sorted(owner, key=len, reverse=True)  # /a/b's keys are not /a's
    for key in sorted(graph.param_names):
        node = next((n for n in longest_first if key.startswith(n + "/")), None)
        if node is not None:
            if node not in granted_ns:
                granted_ns.add(node)
                add(param_access, node, node, None)
        elif key not in DEFAULT_PARAM_READS:
            stray.append(key)
    if stray:
        draft.warnings.append(f"{len(stray)} parameter(s) outside any mapped node's private namespace are not "
                              f"granted (add read_param grants by hand): {', '.join(stray)}")
    draft.doc = policy_document(grants)
    return draft


# ---------------------------------------------------------------------- reading a master
async def _probe_service_type(service: str, uri: str, timeout: float) -> str | None:
    """The ``type`` field of a service's TCPROS probe reply (rosservice's
    ``get_service_headers``: ``probe=1``, ``md5sum=*``)."""
    import struct

    from cryptoros.ros1 import tcpros
    from cryptoros.ros1.uri import host_port

    try:
        host, port = host_port(uri, ("rosrpc",))
    except CryptorosError:
        return None
    writer = None
    try:
        reader, writer = await asyncio.wait_for(asyncio.open_connection(host, port), timeout)
        writer.write(tcpros.encode_header({"probe": "1", "md5sum": "*", "callerid": CALLER_ID, "service": service}))
        await writer.drain()
        (size,) = struct.unpack("<I", await asyncio.wait_for(reader.readexactly(4), timeout))
        if size > 65536:
            return None
        header = tcpros.decode_header(await asyncio.wait_for(reader.readexactly(size), timeout))
        return header.get("type")
    except (*PEER_FAILURES, asyncio.IncompleteReadError):
        return None
    finally:
        if writer is not None:
            writer.close()


async def read_graph(master_uri: str, *, timeout: float = 5.0) -> Graph:
    """Ask the master at ``master_uri`` for the graph; raises RegistryError (one line)
    when the master cannot be reached or answers what is not a ROS master's answer."""
    from cryptoros.ros1.rpc import XmlRpcClient

    try:
        client = XmlRpcClient(master_uri, timeout=timeout)
    except CryptorosError as exc:
        raise RegistryError(f"--master-uri {master_uri!r}: {exc}") from None
    try:
        def table(rows) -> dict[str, list[str]]:
            return {_text(name): [_text(n) for n in nodes] for name, nodes in rows}

        try:
            pubs, subs, srvs = (table(rows) for rows in await client.call("getSystemState", CALLER_ID))
            types = {_text(k): _text(v) for k, v in await client.call("getTopicTypes", CALLER_ID)}
            params = [_text(p) for p in await client.call("getParamNames", CALLER_ID)]
        except (OSError, asyncio.TimeoutError) as exc:
            raise RegistryError(f"cannot read the graph from {master_uri}: {exc or type(exc).__name__}") from None
        except (CryptorosError, ValueError, TypeError) as exc:
            raise RegistryError(f"{master_uri} did not answer as a ROS master: {exc}") from None
        graph_nodes = {n for t in (pubs, subs, srvs) for nodes in t.values() for n in nodes}
        node_uris: dict[str, str | None] = {}
        for node in sorted(graph_nodes):
            try:
                node_uris[node] = await client.call("lookupNode", CALLER_ID, node)
            except PEER_FAILURES:
                node_uris[node] = None
        service_types: dict[str, str | None] = {}
        for service in srvs:
            try:
                uri = await client.call("lookupService", CALLER_ID, service)
            except PEER_FAILURES:
                service_types[service] = None
                continue
            service_types[service] = await _probe_service_type(service, uri, timeout)
    finally:
        await client.close()
    return Graph(publishers=pubs, subscribers=subs, services=srvs, topic_types=types,
                 service_types=service_types, node_uris=node_uris, param_names=params)


def _text(value: object) -> str:
    if not isinstance(value, str):
        raise TypeError(f"expected a string, got {type(value).__name__}")
    return value


__all__ = ["CALLER_ID", "Draft", "Graph", "ManagerMap", "draft_policy", "policy_document", "read_graph"]
