"""The policy decision: a verified token's grants x a ROS 1 request -> allow or deny.

Pure functions, no I/O, no clock: the interceptor asks, then acts. Every function
returns ``None`` to allow, or raises :class:`~cryptoros.errors.PolicyDenied` whose
``reason`` is a short code for logs and metrics (``not_granted``, ``shutdown_dropped``
...). What the peer is told is decided elsewhere and stays opaque.

What is checked (DESIGN.md, "Data flow (ROS 1)"):

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

from cryptoros.errors import PolicyDenied
from cryptoros.names import validate_graph_name
from cryptoros.tokens import Grants

#: Master-API methods that only read.
MASTER_READ_ONLY = frozenset(
    {
        "lookupNode",
        "lookupService",
        "getSystemState",
        "getTopicTypes",
        "getPublishedTopics",
        "getUri",
        "getPid",
        "getParam",
        "hasParam",
        "searchParam",
        "getParamNames",
        "subscribeParam",
        "unsubscribeParam",
    }
)
MASTER_REGISTER = frozenset({"registerPublisher", "registerSubscriber", "registerService"})
MASTER_UNREGISTER = frozenset({"unregisterPublisher", "unregisterSubscriber", "unregisterService"})
PARAM_WRITE = frozenset({"setParam", "deleteParam"})
#: Node-API methods that only read.
NODE_READ_ONLY = frozenset(
    {"getBusInfo", "getBusStats", "getPid", "getName", "getMasterUri", "getSubscriptions", "getPublications"}
)
FROM_MASTER_ONLY = frozenset({"publisherUpdate", "paramUpdate"})
ALWAYS_DROPPED = frozenset({"shutdown"})

ROSOUT = ("/rosout", "rosgraph_msgs/Log")
LOGGER_SERVICES = {"get_loggers": "roscpp/GetLoggers", "set_logger_level": "roscpp/SetLoggerLevel"}


def _deny(reason: str, detail: str) -> PolicyDenied:
    return PolicyDenied(reason, detail)


def _caller(call_params: tuple, method: str) -> str:
    if not call_params or not isinstance(call_params[0], str):
        raise _deny("malformed", f"{method} without a caller_id")
    try:
        return validate_graph_name(call_params[0], "caller_id")
    except Exception as exc:
        raise _deny("malformed", f"{method}: {exc}") from None


def _str_param(params: tuple, index: int, method: str, what: str) -> str:
    if len(params) <= index or not isinstance(params[index], str):
        raise _deny("malformed", f"{method} without {what}")
    return params[index]


def infrastructure_allows(action: str, node: str, name: str, type_name: str | None) -> bool:
    """``/rosout`` publishing and the node's own logger services."""
    if action == "publish" and (name, type_name) == ROSOUT:
        return True
    if action == "serve" and name.startswith(node + "/"):
        suffix = name[len(node) + 1 :]
        return suffix in LOGGER_SERVICES and type_name in (None, LOGGER_SERVICES[suffix])
    return False


def _granted(grants: Grants, action: str, node: str, name: str, type_name: str, infrastructure: bool) -> bool:
    if grants.allows(action, node, name, type_name):
        return True
    return infrastructure and grants.names_node(node) and infrastructure_allows(action, node, name, type_name)


def check_master_call(
    method: str,
    params: tuple,
    *,
    manager: str,
    grants: Grants,
    owner_of: Callable[[str], str | None],
    infrastructure: bool = True,
) -> None:
    """Decide one master-API call (a multicall is decided call by call by the caller)."""
    if method in ALWAYS_DROPPED:
        raise _deny("shutdown_dropped", "master shutdown is never forwarded")
    if method in MASTER_READ_ONLY:
        return
    caller = _caller(params, method)
    if method in MASTER_REGISTER or method in PARAM_WRITE:
        owner = owner_of(caller)
        if owner is not None and owner != manager:
            raise _deny("name_taken", f"node {caller} is registered by manager {owner}")
    if method in ("registerPublisher", "registerSubscriber"):
        topic = _str_param(params, 1, method, "a topic")
        type_name = _str_param(params, 2, method, "a type")
        action = "publish" if method == "registerPublisher" else "subscribe"
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
        owner = owner_of(caller)
        if owner is not None and owner != manager:
            raise _deny("name_taken", f"node {caller} is registered by manager {owner}")
        if owner is None and not grants.names_node(caller):
            raise _deny("not_granted", f"{manager}: {caller} is not one of its nodes")
        return
    if method in PARAM_WRITE:
        key = _str_param(params, 1, method, "a key")
        if not grants.names_node(caller) or not (key == caller or key.startswith(caller + "/")):
            raise _deny("param_write_denied", f"{caller} may only write parameters under {caller}/, not {key}")
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
            raise _deny("not_granted", f"{caller} may not subscribe {topic} [{type_name}]")
        return
    raise _deny("method_not_allowed", f"node method {method!r} is not on the allowlist")


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
    if published_type is None:
        raise _deny("unknown_topic", f"no local publisher of {topic}")
    if type_name != published_type:
        raise _deny("type_mismatch", f"{caller} asks {topic} as {type_name}, published as {published_type}")
    if published_md5 is not None and md5 != published_md5:
        raise _deny("md5_mismatch", f"{caller} asks {topic} with md5sum {md5}, published with {published_md5}")
    if not grants.allows("subscribe", caller, topic, type_name):
        raise _deny("not_granted", f"{caller} may not subscribe {topic} [{type_name}]")


def check_publisher_header(header: Mapping[str, str], *, grants: Grants, topic: str, infrastructure: bool = True) -> None:
    """A publisher's reply header against the publisher's grants."""
    caller, type_name = header.get("callerid", ""), header.get("type", "")
    if "error" in header:
        return  # the publisher refused on its own; relayed as is
    if not (caller and type_name):
        raise _deny("malformed", "publisher header lacks callerid or type")
    if not _granted(grants, "publish", caller, topic, type_name, infrastructure):
        raise _deny("not_granted", f"{caller} may not publish {topic} [{type_name}]")


def check_service_client_header(header: Mapping[str, str], *, grants: Grants) -> frozenset[str]:
    """A service client's header: the caller must hold a ``call`` grant for the
    service. Returns the types it may call it with (checked against the server's
    reply by :func:`check_service_server_header`)."""
    caller, service = header.get("callerid", ""), header.get("service", "")
    if not (caller and service and header.get("md5sum")):
        raise _deny("malformed", "service client header lacks callerid, service or md5sum")
    types = grants.types_for("call", caller, service)
    if not types:
        raise _deny("not_granted", f"{caller} may not call {service}")
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
    one the server may serve."""
    if "error" in header:
        return
    caller, type_name = header.get("callerid", ""), header.get("type", "")
    if not (caller and type_name):
        raise _deny("malformed", "service server header lacks callerid or type")
    if type_name not in client_types:
        raise _deny("type_mismatch", f"{service} is served as {type_name}, the caller may call {sorted(client_types)}")
    if not _granted(server_grants, "serve", caller, service, type_name, infrastructure):
        raise _deny("not_granted", f"{caller} may not serve {service} [{type_name}]")


def ros_error(message: str) -> list[Any]:
    """A ROS API error triple, as master and nodes answer a refused call."""
    return [-1, message, 0]


__all__ = [
    "ALWAYS_DROPPED",
    "FROM_MASTER_ONLY",
    "MASTER_READ_ONLY",
    "MASTER_REGISTER",
    "MASTER_UNREGISTER",
    "NODE_READ_ONLY",
    "check_master_call",
    "check_node_call",
    "check_publisher_header",
    "check_service_client_header",
    "check_service_server_header",
    "check_subscriber_header",
    "infrastructure_allows",
    "ros_error",
]
