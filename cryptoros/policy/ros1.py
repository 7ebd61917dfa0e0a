"""The policy decision: a verified token's grants x a ROS 1 request -> allow or deny.

Pure functions, no I/O, no clock: the interceptor asks, then acts. Every function
returns ``None`` to allow, or raises :class:`~cryptoros.errors.PolicyDenied` whose
``reason`` is a short code for logs and metrics (``not_granted``, ``shutdown_dropped``
...). What the peer is told is decided elsewhere and stays opaque.

What is checked (docs/architecture.md, "How a stream travels"):

- master calls: a method allowlist; ``register*`` only for the caller's own nodes
  and granted topics, services and types; ``unregister*`` only for the caller's own
  nodes; a node name already registered by another manager is refused (name
  hijack); parameter writes only inside the caller's own private namespace;
  ``shutdown`` always dropped;
- node calls: ``requestTopic`` only for granted subscriptions of the topic's
  published type; ``publisherUpdate`` and ``paramUpdate`` only from the master's
  interceptor; ``shutdown`` dropped;
- TCPROS and service connection headers: ``callerid``, ``topic`` or ``service``,
  ``type`` and ``md5sum`` must match a grant of the token's subject.

ROS infrastructure that every rospy and roscpp node uses on its own behalf (the
``/rosout`` log topic, its own ``get_loggers`` / ``set_logger_level`` services) is
allowed for the manager's own nodes when ``infrastructure=True`` (the interceptor's
default); everything else needs an explicit grant.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import re

from cryptoros.errors import PolicyDenied
from cryptoros.policy.infrastructure import ROS1_DEFAULT_PARAM_READS, ros1_allows, ros1_topic_param
from cryptoros.names import validate_caller_id
from cryptoros.grants import Grants

#: Master-API methods that only read the graph.
MASTER_READ_ONLY = frozenset(
    {
        "lookupNode",
        "lookupService",
        "getSystemState",
        "getTopicTypes",
        "getPublishedTopics",
        "getUri",
        "getPid",
    }
)
#: The type a subscriber names to take any type (rosbag record, topic_tools): ROS 1's ``*``.
ANY_TYPE = "*"
MASTER_REGISTER = frozenset({"registerPublisher", "registerSubscriber", "registerService"})
MASTER_UNREGISTER = frozenset({"unregisterPublisher", "unregisterSubscriber", "unregisterService"})
#: Parameter-server methods, by the access they need; the key is parameter 1.
PARAM_READ = frozenset({"getParam", "hasParam", "searchParam", "subscribeParam", "unsubscribeParam"})
PARAM_WRITE = frozenset({"setParam", "deleteParam"})
#: parameter calls about one key whose path may name other nodes (their private namespaces)
_KEYED_PARAM_CALLS = PARAM_WRITE | {"getParam", "hasParam", "subscribeParam", "unsubscribeParam"}


def _key_index(method: str) -> int:
    """Where a parameter call's key is (after the caller, and the caller's API)."""
    return 2 if method in ("subscribeParam", "unsubscribeParam") else 1


#: Master calls that bind the caller's node name to its caller_api at rosmaster
#: (``_register_node_api`` in ros_comm's rosmaster/registrations.py, upstream): a name another manager
#: registered is refused, and the caller must be one of the manager's nodes.
NAME_BINDING = MASTER_REGISTER | frozenset({"subscribeParam"})
#: Parameters every node may read without a grant: what unmodified rospy, roscpp,
#: roslaunch, rosbag, actionlib, image_transport, nodelet and dynamic_reconfigure read
#: (one measured list: :data:`cryptoros.policy.infrastructure.ROS1_DEFAULT_PARAM_READS`).
#: A node may also read and write its own private namespace (``/<node name>/...``; not a
#: node covered only by ``*``) and that of any node its manager's grants name exactly (roslaunch sets a launched node's
#: ``<param>``, a nodelet manager reads its nodelets'); everything else needs a
#: ``read_param`` or ``write_param`` grant on a namespace holding the key.
DEFAULT_PARAM_READS = ROS1_DEFAULT_PARAM_READS
#: Caller ids stock tools use on every robot without registering a node: roslaunch's
#: parameter calls and rosservice's type probe (ros_comm 1.15). Every robot's tool
#: bundle names them, so they are no one manager's: no node may register under them (it
#: would hold the name against every other robot's roslaunch), and their namespaces are
#: not private to anyone (``/roslaunch/uris/*`` holds each robot's launch server): only
#: a ``write_param``/``read_param`` grant opens them.
SHARED_TOOL_NAMES = frozenset({"/roslaunch", "/rosservice"})
#: Node-API methods that only read.
NODE_READ_ONLY = frozenset(
    {"getBusInfo", "getBusStats", "getPid", "getName", "getMasterUri", "getSubscriptions", "getPublications"}
)
FROM_MASTER_ONLY = frozenset({"publisherUpdate", "paramUpdate"})
ALWAYS_DROPPED = frozenset({"shutdown"})



_PARAM_SEGMENT = re.compile(r"^[A-Za-z_~][A-Za-z0-9_-]*$")


def _deny(reason: str, detail: str, *, missing: tuple[str, str, str, str | None] | None = None) -> PolicyDenied:
    return PolicyDenied(reason, detail, missing=missing)


def _caller(call_params: tuple, method: str) -> str:
    if not call_params or not isinstance(call_params[0], str):
        raise _deny("malformed", f"{method} without a caller_id")
    try:
        return validate_caller_id(call_params[0])
    except Exception as exc:
        raise _deny("malformed", f"{method}: {exc}") from None


def _str_param(params: tuple, index: int, method: str, what: str) -> str:
    if len(params) <= index or not isinstance(params[index], str):
        raise _deny("malformed", f"{method} without {what}")
    return params[index]


# ---------------------------------------------------------------- parameters


def resolve_param_key(key: str, caller: str) -> str:
    """A parameter key as rosmaster resolves it for ``caller`` (rosgraph
    ``resolve_name``): global keys as they are, ``~private`` under the caller's name,
    relative keys in the caller's namespace; ``//`` collapsed, no trailing ``/``."""
    if not isinstance(key, str) or len(key) > 1024:
        raise _deny("malformed", "parameter key is not a string of at most 1024 characters")
    if key.startswith("~"):
        key = caller + "/" + key[1:]
    elif not key.startswith("/"):
        key = caller.rsplit("/", 1)[0] + "/" + key
    parts = [p for p in key.split("/") if p]
    for part in parts:
        if not _PARAM_SEGMENT.match(part):
            raise _deny("malformed", f"invalid parameter key {key[:80]!r}")
    return "/" + "/".join(parts)


def _own_private(grants: Grants, caller: str, key: str) -> bool:
    """``key`` is in the private namespace of ``caller``, one of the manager's nodes, or
    of a node the manager's grants name exactly (its own names: roslaunch writing a
    launched node's parameters, a nodelet manager reading its nodelets'). A caller
    covered only by the wildcard ``*`` has no private namespace: under ``*`` any name
    is the manager's, ``/fleet`` or another robot's ``/talker/rate`` as much as its own,
    so the caller's own name says nothing (a grant naming it, or a prefix pattern, does)."""
    if not grants.names_node(caller):
        return False
    if (key == caller or key.startswith(caller + "/")) and _has_private(grants, caller):
        return True
    parts = key.split("/")[1:]
    return any(grants.names_node_exactly(node) and node not in SHARED_TOOL_NAMES
               for node in ("/" + "/".join(parts[:n]) for n in range(1, len(parts) + 1)))


def _has_private(grants: Grants, caller: str) -> bool:
    """Whether ``caller`` has a private namespace of its own (:func:`_own_private`)."""
    return caller not in SHARED_TOOL_NAMES and grants.names_node_beyond_wildcard(caller)


def _topic_param(grants: Grants, caller: str, key: str) -> bool:
    """A parameter a library reads under a topic its node publishes (actionlib's
    ``<action>/status_frequency``, image_transport's ``<topic>/disable_pub_plugins``)."""
    found = ros1_topic_param(key)
    return found is not None and bool(grants.types_for("publish", caller, found[0]))


def may_read_param(grants: Grants, caller: str, key: str) -> bool:
    """Read access to one resolved key (defaults, own names' private namespaces,
    parameters of its own topics, grants)."""
    if key in DEFAULT_PARAM_READS or _own_private(grants, caller, key) or _topic_param(grants, caller, key):
        return True
    return grants.param_allows("read", caller, key)


def may_write_param(grants: Grants, caller: str, key: str) -> bool:
    return _own_private(grants, caller, key) or grants.param_allows("write", caller, key)


def _may_read_below(grants: Grants, caller: str, key: str) -> bool:
    """Whether some readable key lies at or below the namespace ``key``."""
    from cryptoros.grants import in_namespace

    readable = set(DEFAULT_PARAM_READS) | grants.param_namespaces(caller)
    if _has_private(grants, caller):  # its private namespace (see _own_private)
        readable.add(caller)
    return any(in_namespace(ns, key) for ns in readable)


def check_param_call(method: str, params: tuple, *, grants: Grants) -> tuple:
    """Decide one parameter-server call; returns its params with the key resolved
    (what is sent on). ``getParam`` of a namespace the caller may read only partly
    is allowed here and pruned by :func:`filter_param_reply`; ``subscribeParam`` of
    one is refused (the updates that follow are not answers to prune)."""
    caller = _caller(params, method)
    if method == "getParamNames":
        return params
    index = _key_index(method)
    key = resolve_param_key(_str_param(params, index, method, "a key"), caller)
    if method in PARAM_WRITE:
        if not may_write_param(grants, caller, key):
            raise _deny("param_write_denied", f"{caller} may not write {key}")
    elif method == "getParam":
        if not (may_read_param(grants, caller, key) or _may_read_below(grants, caller, key)):
            raise _deny("param_read_denied", f"{caller} may not read {key}")
    elif method in ("hasParam", "subscribeParam", "unsubscribeParam"):
        # subscribeParam: rosmaster's later paramUpdates of the key (values under it
        # included) reach the node unpruned, so all of it must be readable
        if not may_read_param(grants, caller, key):
            raise _deny("param_read_denied", f"{caller} may not read {key}")
    # searchParam searches upwards from the caller's namespace: the answer is filtered
    return params[:index] + (key if method != "searchParam" else params[1],) + params[index + 1 :]


def prune_param_value(key: str, value: Any, readable: Callable[[str], bool]) -> Any:
    """What of the value at ``key`` (a namespace's dict, or a leaf) the caller may
    read; ``None`` when nothing."""
    if readable(key):
        return value
    if not isinstance(value, dict):
        return None
    out = {}
    for name, child in value.items():
        pruned = prune_param_value(key.rstrip("/") + "/" + name, child, readable)
        if pruned is not None:
            out[name] = pruned
    return out or None  # a namespace with nothing readable is not even named


def filter_param_reply(method: str, params: tuple, value: Any, *, grants: Grants) -> Any:
    """The reply value of a parameter call, narrowed to what the caller may read:
    ``getParam``/``subscribeParam`` of a namespace pruned, ``getParamNames`` filtered,
    ``searchParam``'s found key dropped if unreadable. ``value`` is ``[code, msg, v]``."""
    if not (isinstance(value, list) and len(value) == 3 and value[0] == 1):
        return value
    caller = params[0]

    def readable(key: str) -> bool:
        return may_read_param(grants, caller, key)

    if method == "getParamNames" and isinstance(value[2], list):
        return [1, value[1], [k for k in value[2] if isinstance(k, str) and readable(k)]]
    if method in ("getParam", "subscribeParam"):
        key = params[2 if method == "subscribeParam" else 1]
        pruned = prune_param_value(key, value[2], readable)
        return [1, value[1], {} if pruned is None else pruned]
    if method == "searchParam" and isinstance(value[2], str) and value[2] and not readable(value[2]):
        return unset_answer(method, params)
    return value


def unset_answer(method: str, params: tuple) -> list[Any]:
    """What rosmaster answers a probe of a parameter that is not set (``hasParam``
    false, ``getParam`` "not set", ``searchParam`` "cannot find", ``subscribeParam``
    an empty value): a node asking for a parameter it may not read gets this, so a
    library falls back to its default (actionlib's ``has_param`` would raise on an
    error) and nobody learns whether the key is set."""
    index = _key_index(method)
    key = params[index] if len(params) > index and isinstance(params[index], str) else ""
    if method != "searchParam" and params and isinstance(params[0], str):
        try:  # rosmaster names the key as it resolved it (a refused call's key is as asked)
            key = resolve_param_key(key, params[0])
        except PolicyDenied:
            pass
    if method == "hasParam":
        return [1, key, False]
    if method == "searchParam":
        return [-1, f"Cannot find parameter [{key}] in an upwards search", ""]
    if method == "subscribeParam":
        return [1, f"Subscribed to parameter [{key}]", {}]
    if method == "unsubscribeParam":
        return [1, f"Unsubscribe to parameter [{key}]", 1]
    return [-1, f"Parameter [{key}] is not set", 0]


def infrastructure_allows(action: str, node: str, name: str, type_name: str | None) -> bool:
    """``/rosout`` publishing and the node's own logger services (one list:
    :mod:`cryptoros.policy.infrastructure`)."""
    return ros1_allows(action, node, name, type_name)


def _granted(grants: Grants, action: str, node: str, name: str, type_name: str, infrastructure: bool) -> bool:
    if grants.allows(action, node, name, type_name):
        return True
    return infrastructure and grants.names_node(node) and infrastructure_allows(action, node, name, type_name)


def named_nodes(method: str, params: tuple) -> tuple[str, ...]:
    """The node names whose owners a decision of this master call may consult: the
    caller, and for a parameter write each node its key's path names (roslaunch writing
    a launched node's parameter). The caller looks their owners up and passes them to
    :func:`check_master_call` as values."""
    if not params or not isinstance(params[0], str):
        return ()
    names = [params[0]]
    if method in _KEYED_PARAM_CALLS:
        try:
            key = resolve_param_key(_str_param(params, _key_index(method), method, "a key"), params[0])
        except PolicyDenied:
            return tuple(names)
        parts = key.split("/")[1:]
        names += ["/" + "/".join(parts[:n]) for n in range(1, len(parts) + 1)]
    return tuple(dict.fromkeys(names))


def _check_sibling_owner(method: str, params: tuple, caller: str, manager: str, grants: Grants,
                         owners: Mapping[str, str]) -> None:
    """A call on a key in the private namespace of another node its manager's grants
    name (roslaunch setting a launched node's parameter) is refused while that node is
    registered by another manager (one name granted to two robots)."""
    key = resolve_param_key(_str_param(params, _key_index(method), method, "a key"), caller)
    parts = key.split("/")[1:]
    for n in range(1, len(parts) + 1):
        node = "/" + "/".join(parts[:n])
        if node != caller and grants.names_node_exactly(node):
            owner = owners.get(node)
            if owner is not None and owner != manager:
                raise _deny("name_taken", f"node {node} is registered (or held) by manager {owner}")


def check_master_call(
    method: str,
    params: tuple,
    *,
    manager: str,
    grants: Grants,
    owners: Mapping[str, str],
    infrastructure: bool = True,
) -> None:
    """Decide one master-API call (a multicall is decided call by call by the caller).
    ``owners``: the manager holding each name :func:`named_nodes` lists, where one does."""
    if method in ALWAYS_DROPPED:
        raise _deny("shutdown_dropped", "master shutdown is never forwarded")
    if method in MASTER_READ_ONLY:
        return
    caller = _caller(params, method)
    if method in NAME_BINDING and caller in SHARED_TOOL_NAMES:
        raise _deny("name_taken", f"node {caller} is the name a stock tool uses on every robot: no node may register it")
    # a parameter call names its caller too: its private namespace (and what it may read
    # there) is the node's that holds the name, not an impersonator's
    if method in NAME_BINDING or method in PARAM_WRITE or method in PARAM_READ or method == "getParamNames":
        owner = owners.get(caller)
        if owner is not None and owner != manager:
            raise _deny("name_taken", f"node {caller} is registered (or held) by manager {owner}")
    if method in ("subscribeParam", "unsubscribeParam") and not grants.names_node(caller):
        raise _deny("not_granted", f"{manager}: {caller} is not one of its nodes")
    if method in _KEYED_PARAM_CALLS:
        _check_sibling_owner(method, params, caller, manager, grants, owners)
    if method in PARAM_READ or method in PARAM_WRITE or method == "getParamNames":
        check_param_call(method, params, grants=grants)
        return
    if method in ("registerPublisher", "registerSubscriber"):
        topic = _str_param(params, 1, method, "a topic")
        type_name = _str_param(params, 2, method, "a type")
        action = "publish" if method == "registerPublisher" else "subscribe"
        if action == "subscribe" and type_name == ANY_TYPE:
            # rosbag record, topic_tools: any type. Each connection is then judged by the type
            # really published (check_subscriber_header, check_subscribed_type).
            if not grants.types_for("subscribe", caller, topic):
                raise _deny("not_granted", f"{manager}: {caller} may not subscribe {topic} (with any type)")
            return
        if not _granted(grants, action, caller, topic, type_name, infrastructure):
            raise _deny("not_granted", f"{manager}: {caller} may not {action} {topic} [{type_name}]")
        return
    if method == "registerService":
        service = _str_param(params, 1, method, "a service")
        if not grants.types_for("serve", caller, service) and not (
            infrastructure and grants.names_node(caller) and infrastructure_allows("serve", caller, service, None)
        ):
            raise _deny("not_granted", f"{manager}: {caller} may not serve {service}")
        return
    if method in MASTER_UNREGISTER:
        owner = owners.get(caller)
        if owner is not None and owner != manager:
            raise _deny("name_taken", f"node {caller} is registered (or held) by manager {owner}")
        if owner is None and not grants.names_node(caller):
            # another robot's node (rosnode cleanup of a dead one): no grant of this robot's
            # should allow it, so the refusal points at none (a day-2 audit: "not_granted ...
            # says what to grant" for a purge)
            raise _deny("not_its_node", f"{manager}: {caller} is not one of its nodes: the robot whose node it is "
                                        "purges it")
        return
    raise _deny("method_not_allowed", f"master method {method!r} is not on the allowlist")


def check_node_call(
    method: str,
    params: tuple,
    *,
    grants: Grants,
    peer_is_master: bool,
    topic_types: Mapping[str, str],
) -> None:
    """Decide one node-API call arriving from another interceptor."""
    if method in ALWAYS_DROPPED:
        raise _deny("shutdown_dropped", "node shutdown is never forwarded")
    if method in NODE_READ_ONLY:
        return
    if method in FROM_MASTER_ONLY:
        if not peer_is_master:
            raise _deny("not_from_master", f"{method} is accepted only from the master's interceptor")
        return
    if method == "requestTopic":
        caller = _caller(params, method)
        topic = _str_param(params, 1, method, "a topic")
        type_name = topic_types.get(topic)
        if type_name is None:
            raise _deny("unknown_topic", f"no local publisher of {topic}")
        if not grants.allows("subscribe", caller, topic, type_name):
            raise _deny("not_granted", f"{caller} may not subscribe {topic} [{type_name}]",
                        missing=("subscribe", caller, topic, type_name))
        return
    raise _deny("method_not_allowed", f"node method {method!r} is not on the allowlist")


#: header fields that only one kind of stream carries: rospy and roscpp pick a topic or a
#: service by which of them a header holds, so a header is checked for one purpose only
#: if it holds nothing of the other (a service header that also named a topic was judged
#: as a call and answered by the node as a subscription)
_TOPIC_ONLY = frozenset({"topic", "latching", "tcp_nodelay"})
_SERVICE_ONLY = frozenset({"service", "request_type", "response_type", "persistent", "probe"})


def _one_purpose(header: Mapping[str, str], purpose: str) -> None:
    other = _SERVICE_ONLY if purpose == "topic" else _TOPIC_ONLY
    mixed = sorted(other.intersection(header))
    if mixed:
        raise _deny("malformed", f"a {purpose} header also carries {', '.join(mixed)}")


def check_subscriber_header(
    header: Mapping[str, str],
    *,
    grants: Grants,
    published_type: str | None,
    published_md5: str | None,
) -> None:
    """A subscriber's TCPROS header (``callerid``, ``topic``, ``type``, ``md5sum``)
    against the subscriber's grants and what is really published here."""
    caller, topic = header.get("callerid", ""), header.get("topic", "")
    type_name, md5 = header.get("type", ""), header.get("md5sum", "")
    if not (caller and topic and type_name and md5):
        raise _deny("malformed", "subscriber header lacks callerid, topic, type or md5sum")
    _one_purpose(header, "topic")
    if published_type is None:
        raise _deny("unknown_topic", f"no local publisher of {topic}")
    if type_name == ANY_TYPE and md5 == ANY_TYPE:  # a subscriber of any type gets what is published
        type_name, md5 = published_type, published_md5 or md5
    if type_name != published_type:
        raise _deny("type_mismatch", f"{caller} asks {topic} as {type_name}, published as {published_type}")
    if published_md5 is not None and md5 != published_md5:
        raise _deny("md5_mismatch", f"{caller} asks {topic} with md5sum {md5}, published with {published_md5}")
    if not grants.allows("subscribe", caller, topic, type_name):
        raise _deny("not_granted", f"{caller} may not subscribe {topic} [{type_name}]",
                    missing=("subscribe", caller, topic, type_name))


def check_local_subscriber_header(header: Mapping[str, str], *, grants: Grants) -> None:
    """A local subscriber's TCPROS header, before its stream leaves this host toward a
    remote publisher: its own node must be granted to subscribe the topic with that
    type (the publisher's interceptor checks the rest against what it publishes). A
    subscriber of any type (``*``) needs a grant for the topic with some type here and
    :func:`check_subscribed_type` once the publisher has answered."""
    caller, topic, type_name = header.get("callerid", ""), header.get("topic", ""), header.get("type", "")
    if not (caller and topic and type_name):
        raise _deny("malformed", "subscriber header lacks callerid, topic or type")
    _one_purpose(header, "topic")
    if type_name == ANY_TYPE:
        if not grants.types_for("subscribe", caller, topic):
            raise _deny("not_granted", f"{caller} may not subscribe {topic}", missing=("subscribe", caller, topic, None))
        return
    if not grants.allows("subscribe", caller, topic, type_name):
        raise _deny("not_granted", f"{caller} may not subscribe {topic}", missing=("subscribe", caller, topic, type_name))


def check_subscribed_type(header: Mapping[str, str], published_type: str, *, grants: Grants) -> None:
    """A local subscriber of any type, once the remote publisher answered: the type it
    will receive must be one its node is granted (a subscriber of one type was checked
    by :func:`check_local_subscriber_header` already)."""
    caller, topic = header.get("callerid", ""), header.get("topic", "")
    if header.get("type") == ANY_TYPE and not grants.allows("subscribe", caller, topic, published_type):
        raise _deny("not_granted", f"{caller} may not subscribe {topic} [{published_type}]",
                    missing=("subscribe", caller, topic, published_type))


def check_publisher_header(header: Mapping[str, str], *, grants: Grants, topic: str, infrastructure: bool = True) -> None:
    """A publisher's reply header against the publisher's grants."""
    caller, type_name = header.get("callerid", ""), header.get("type", "")
    if not (caller and type_name):  # an ``error`` reply included: the caller passes refusals on itself
        raise _deny("malformed", "publisher header lacks callerid or type")
    _one_purpose(header, "topic")
    if not _granted(grants, "publish", caller, topic, type_name, infrastructure):
        raise _deny("not_granted", f"{caller} may not publish {topic} [{type_name}]",
                    missing=("publish", caller, topic, type_name))


def check_service_client_header(header: Mapping[str, str], *, grants: Grants) -> frozenset[str]:
    """A service client's header: the caller must hold a ``call`` grant for the
    service. Returns the types it may call it with (checked against the server's
    reply by :func:`check_service_server_header`)."""
    caller, service = header.get("callerid", ""), header.get("service", "")
    if not (caller and service and header.get("md5sum")):
        raise _deny("malformed", "service client header lacks callerid, service or md5sum")
    _one_purpose(header, "service")
    types = grants.types_for("call", caller, service)
    if not types:
        raise _deny("not_granted", f"{caller} may not call {service}", missing=("call", caller, service, None))
    return types


def check_service_server_header(
    header: Mapping[str, str],
    *,
    service: str,
    server_grants: Grants,
    client_types: frozenset[str],
    infrastructure: bool = True,
) -> None:
    """A service server's reply: its ``type`` must be one the client may call and
    one the server may serve (an ``error`` reply is the caller's to pass on: here it is
    malformed)."""
    caller, type_name = header.get("callerid", ""), header.get("type", "")
    if not (caller and type_name):
        raise _deny("malformed", "service server header lacks callerid or type")
    _one_purpose(header, "service")
    if type_name not in client_types:
        raise _deny("type_mismatch", f"{service} is served as {type_name}, the caller may call {sorted(client_types)}")
    if not _granted(server_grants, "serve", caller, service, type_name, infrastructure):
        raise _deny("not_granted", f"{caller} may not serve {service} [{type_name}]",
                    missing=("serve", caller, service, type_name))


def ros_error(message: str) -> list[Any]:
    """A ROS API error triple, as master and nodes answer a refused call."""
    return [-1, message, 0]


#: How a refused ROS 1 call begins, whatever the reason.
REFUSED = "denied by cryptoros"
#: Reason codes a refused caller is told after :data:`REFUSED`: each says what kind of
#: grant is missing (or that nothing can allow it), none names another manager, a
#: grant or a policy. A reason not listed is not shown.
SHOWN_REASONS = frozenset({
    "not_granted", "param_write_denied", "param_read_denied", "shutdown_dropped", "not_from_master",
    "method_not_allowed", "name_taken", "node_limit", "param_quota", "rate_limited", "malformed", "unknown_topic",
    "unknown_endpoint", "endpoint_not_peer", "answer_too_large", "not_its_node",
    # the master host's rosmaster reachable from the network: every robot's tools say why
    # nothing answers, over a tunnel opened before it too (a README deployment audit and a
    # fresh-clone run: `rosnode list` said only "denied by cryptoros"); a stranger's port
    # scan finds that rosmaster anyway
    "exposed_master",
})


#: Why this host's own token cannot be used (none held: the manager removed or disabled,
#: the certificate revoked, the authorization server out of reach past its expiry...) or
#: no new stream is opened (its revocation feed stale, or refused to it):
#: shown to this host's own nodes and tools (:func:`refusal_text` with ``own=True``),
#: never to a peer, which learns nothing of our token.
OWN_TOKEN_REASONS = frozenset({
    "no_token", "wrong_manager", "expired", "not_yet_valid", "revoked", "certificate_revoked", "subject_disabled",
    "feed_stale", "authz_refused",
})


#: Reasons a grant would take away: this host's own nodes and tools are told where the
#: operator finds it (:data:`SEE_DENIALS`; the interceptor's denial table holds the command).
GRANT_REASONS = frozenset({"not_granted", "param_write_denied"})
SEE_DENIALS = "(cryptoros denials says what to grant)"


def refusal_text(reason: str | None, *, own: bool = False) -> str:
    """``denied by cryptoros: <reason code>`` (the code only when it is one of
    :data:`SHOWN_REASONS`, or for ``own`` callers, this host's own nodes and tools, of
    :data:`OWN_TOKEN_REASONS`): what ROS tools print as their one error line. ``own``
    callers refused for a grant (:data:`GRANT_REASONS`) are pointed at ``cryptoros denials``."""
    shown = reason in SHOWN_REASONS or own and reason in OWN_TOKEN_REASONS
    if not shown:
        return REFUSED
    return f"{REFUSED}: {reason} {SEE_DENIALS}" if own and reason in GRANT_REASONS else f"{REFUSED}: {reason}"


def refused_reason(value: Any) -> str | None:
    """The reason code of a ROS answer that is a refusal by an interceptor
    (``[-1, "denied by cryptoros: <reason>", ...]``, :func:`refusal_text`), else None."""
    if not (isinstance(value, list) and len(value) == 3 and value[0] == -1 and isinstance(value[1], str)):
        return None
    head, _, rest = value[1].partition(": ")
    reason = rest.split(" ", 1)[0]
    return reason if head == REFUSED and reason in SHOWN_REASONS else None


def refusal_answer(reason: str | None, method: str, params: tuple, *, own: bool = False) -> list[Any]:
    """The XML-RPC value a refused master or node call is answered with, as rosmaster
    and nodes answer an error: ``[-1, "denied by cryptoros: <reason>", 0]``; a probe of
    a parameter the caller may not read is answered as if it were not set
    (:func:`unset_answer`). Never an XML-RPC fault: stock tools print a fault as a
    traceback. ``own``: as :func:`refusal_text`."""
    if reason == "param_read_denied" and method in PARAM_READ:
        return unset_answer(method, params)
    return ros_error(refusal_text(reason, own=own))


#: The tails ROS 1 (ros_comm 1.15) appends to a name it makes anew each run, and nothing
#: else: a stable name ending in a number (``/lidar_2048``, ``/robot_1001``) stays exact.
#: rospy's ``init_node(anonymous=True)`` (rostopic, rosservice call): ``_<pid>_<ms since
#: epoch>``, 13 digits; roslib's ``anonymous_name`` (roslaunch's ``$(anon id)``):
#: ``_<host>_<pid>_<random below 2**63>``, 19 digits but for one name in ten (and one in
#: 10**6 shorter than 13); roscpp's ``AnonymousName`` (rosbag record/play):
#: ``_<ns since epoch>``, 19 digits. A pid has at most 7 digits (pid_max is 2**22), and
#: none of these numbers starts with 0.
_ANONYMOUS_TAIL = re.compile(r"^(.*?_)(?:[1-9]\d{0,6}_)?[1-9]\d{12,18}$")
#: rosparam's caller ID ``rosparam-<pid>``: the one anonymous name with a ``-``
_ROSPARAM = re.compile(r"^(/(?:.*/)?rosparam-)[1-9]\d{0,6}$")


def anonymous_prefix(name: str) -> str | None:
    """What stays of an anonymous ROS 1 name from one run to the next
    (``/rostopic_4711_1795791784006`` -> ``/rostopic_``, ``/rosparam-4711`` ->
    ``/rosparam-``), or None for a name that is the same each run."""
    m = _ANONYMOUS_TAIL.match(name) or _ROSPARAM.match(name)
    return m.group(1) if m else None


def node_pattern(node: str) -> str:
    """The node pattern to grant for an anonymous node name (``/rostopic_4711_1795...``
    -> ``/rostopic_*``, ``/rosparam-4711`` -> ``/rosparam-*``); other names as they are."""
    prefix = anonymous_prefix(node)
    return node if prefix is None else prefix + "*"


__all__ = [
    "ANY_TYPE",
    "ALWAYS_DROPPED",
    "FROM_MASTER_ONLY",
    "MASTER_READ_ONLY",
    "MASTER_REGISTER",
    "MASTER_UNREGISTER",
    "NODE_READ_ONLY",
    "DEFAULT_PARAM_READS",
    "NAME_BINDING",
    "check_local_subscriber_header",
    "PARAM_READ",
    "check_master_call",
    "named_nodes",
    "check_param_call",
    "filter_param_reply",
    "may_read_param",
    "may_write_param",
    "prune_param_value",
    "resolve_param_key",
    "check_node_call",
    "check_publisher_header",
    "check_service_client_header",
    "check_service_server_header",
    "check_subscribed_type",
    "check_subscriber_header",
    "infrastructure_allows",
    "ros_error",
    "REFUSED",
    "SHARED_TOOL_NAMES",
    "SHOWN_REASONS",
    "GRANT_REASONS",
    "SEE_DENIALS",
    "OWN_TOKEN_REASONS",
    "anonymous_prefix",
    "node_pattern",
    "refusal_answer",
    "refusal_text",
    "refused_reason",
    "unset_answer",
]
