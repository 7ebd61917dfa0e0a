"""Pure URI rewriting for a drop-in ROS 1 proxy.

Each function takes a call or a response and a mapping function, and returns a new
object with the URIs a node advertises (or is handed) replaced; nothing else
changes but the status message of a rewritten reply, which rospy and rosmaster fill
with the URI itself (``ready on 127.0.0.1:39223``, ``rosrpc URI: [rosrpc://...]``):
it becomes fixed words, so no hidden endpoint leaks through it (insider audit). The interceptor maps local URIs to its public endpoints outbound, and
remote URIs to local relay endpoints inbound. ``system.multicall`` calls are
rewritten call by call.

Where the URIs sit (ROS 1 master and node APIs):

========================  ===================================================
call                      rewritten parameters
========================  ===================================================
registerPublisher         ``caller_api`` (index 3)
registerSubscriber        ``caller_api`` (index 3)
registerService           ``service_api`` (index 2), ``caller_api`` (index 3)
unregisterPublisher       ``caller_api`` (index 2)
unregisterSubscriber      ``caller_api`` (index 2)
unregisterService         ``service_api`` (index 2)
publisherUpdate           the publisher list (index 2)
========================  ===================================================

Responses: ``registerSubscriber`` and ``registerPublisher`` (a list of URIs),
``lookupNode``, ``lookupService``, ``getUri`` (one URI), ``requestTopic``
(``['TCPROS', host, port]``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from cryptoros.errors import PolicyDenied, RemoteProtocolError
from cryptoros.ros1.xmlrpc import (
    MULTICALL,
    Fault,
    Request,
    Response,
    assemble_multicall,
    expand_multicall,
    make_multicall,
    split_multicall_response,
)

__all__ = [
    "UriMap",
    "TcprosMap",
    "CALLER_API_INDEX",
    "SERVICE_API_INDEX",
    "rewrite_caller_api",
    "rewrite_service_api",
    "rewrite_call",
    "rewrite_publisher_list",
    "rewrite_publisher_update",
    "rewrite_register_response",
    "rewrite_uri_response",
    "rewrite_tcpros_reply",
    "rewrite_response",
    "tcpros_only",
    "redact_node_reply",
]

UriMap = Callable[[str], str]
TcprosMap = Callable[[str, int], tuple[str, int]]

CALLER_API_INDEX: dict[str, int] = {
    "registerPublisher": 3,
    "registerSubscriber": 3,
    "registerService": 3,
    "unregisterPublisher": 2,
    "unregisterSubscriber": 2,
}
SERVICE_API_INDEX: dict[str, int] = {
    "registerService": 2,
    "unregisterService": 2,
}


def _replace(params: tuple, index: int, fn: UriMap, what: str) -> tuple:
    if len(params) <= index or not isinstance(params[index], str):
        raise RemoteProtocolError(f"{what} missing or not a string")
    return params[:index] + (fn(params[index]),) + params[index + 1 :]


def _with_params(call: Request, params: tuple) -> Request:
    return Request(method=call.method, params=params, path=call.path, keep_alive=call.keep_alive, accept_gzip=call.accept_gzip)


def rewrite_caller_api(call: Request, fn: UriMap) -> Request:
    """Map ``caller_api`` of a ``register*``/``unregister*`` call (others unchanged)."""
    index = CALLER_API_INDEX.get(call.method)
    if index is None:
        return call
    return _with_params(call, _replace(call.params, index, fn, f"{call.method} caller_api"))


def rewrite_service_api(call: Request, fn: UriMap) -> Request:
    """Map ``service_api`` (``rosrpc://host:port``) of ``registerService``/``unregisterService``."""
    index = SERVICE_API_INDEX.get(call.method)
    if index is None:
        return call
    return _with_params(call, _replace(call.params, index, fn, f"{call.method} service_api"))


def rewrite_publisher_list(uris: Any, fn: UriMap) -> list[str]:
    """Map every URI of a publisher list."""
    if not isinstance(uris, list) or not all(isinstance(u, str) for u in uris):
        raise RemoteProtocolError("a publisher list is an array of strings")
    return [fn(u) for u in uris]


def rewrite_publisher_update(call: Request, fn: UriMap) -> Request:
    """Map the publisher URIs of a node-API ``publisherUpdate(caller, topic, [uris])``."""
    if call.method != "publisherUpdate":
        return call
    if len(call.params) != 3:
        raise RemoteProtocolError("publisherUpdate takes 3 parameters")
    return _with_params(call, call.params[:2] + (rewrite_publisher_list(call.params[2], fn),))


def rewrite_call(
    call: Request,
    *,
    caller_api: UriMap | None = None,
    service_api: UriMap | None = None,
    publisher_uri: UriMap | None = None,
) -> Request:
    """Apply every given mapping to a call; a multicall is rewritten call by call and
    re-assembled (a nested multicall is refused by :func:`expand_multicall`)."""
    if call.method == MULTICALL:
        calls = [
            rewrite_call(c, caller_api=caller_api, service_api=service_api, publisher_uri=publisher_uri)
            for c in expand_multicall(call)
        ]
        return make_multicall(calls, like=call)
    if caller_api is not None:
        call = rewrite_caller_api(call, caller_api)
    if service_api is not None:
        call = rewrite_service_api(call, service_api)
    if publisher_uri is not None:
        call = rewrite_publisher_update(call, publisher_uri)
    return call


def _ros_triple(response: Response | Fault, what: str) -> list | None:
    if isinstance(response, Fault):
        return None
    v = response.value
    if not isinstance(v, list) or len(v) != 3 or not isinstance(v[0], int):
        raise RemoteProtocolError(f"{what} reply is not [code, message, value]")
    return v


def rewrite_register_response(response: Response | Fault, fn: UriMap) -> Response | Fault:
    """``registerSubscriber`` (publisher URIs) or ``registerPublisher`` (subscriber
    URIs) replies: ``[1, msg, [uri, ...]]``; a failure code passes unchanged."""
    v = _ros_triple(response, "register")
    if v is None or v[0] != 1:
        return response
    return Response(value=[v[0], v[1], rewrite_publisher_list(v[2], fn)], keep_alive=response.keep_alive)


#: the status message of a rewritten reply, by method (the original repeats the URI)
STATUS_WORDS = {"lookupNode": "node api", "lookupService": "rosrpc URI", "getUri": "URI", "requestTopic": "ready"}


def rewrite_uri_response(response: Response | Fault, fn: UriMap, method: str = "lookupNode") -> Response | Fault:
    """``lookupNode``/``lookupService``/``getUri`` replies: ``[1, msg, uri]``."""
    v = _ros_triple(response, "lookup")
    if v is None or v[0] != 1:
        return response
    if not isinstance(v[2], str):
        raise RemoteProtocolError("lookup reply value is not a string")
    return Response(value=[v[0], STATUS_WORDS[method], fn(v[2])], keep_alive=response.keep_alive)


def rewrite_tcpros_reply(response: Response | Fault, fn: TcprosMap) -> Response | Fault:
    """``requestTopic`` reply ``[1, msg, ['TCPROS', host, port]]`` -> mapped host and port."""
    v = _ros_triple(response, "requestTopic")
    if v is None or v[0] != 1:
        return response
    proto = v[2]
    if (
        not isinstance(proto, list)
        or len(proto) != 3
        or proto[0] != "TCPROS"
        or not isinstance(proto[1], str)
        or not isinstance(proto[2], int)
        or isinstance(proto[2], bool)
        or not 0 < proto[2] < 65536
    ):
        raise RemoteProtocolError("requestTopic reply is not ['TCPROS', host, port]")
    host, port = fn(proto[1], proto[2])
    return Response(value=[v[0], STATUS_WORDS["requestTopic"], ["TCPROS", host, port]], keep_alive=response.keep_alive)


def rewrite_response(
    call: Request,
    response: Response | Fault,
    *,
    uri: UriMap | None = None,
    tcpros: TcprosMap | None = None,
) -> Response | Fault:
    """Rewrite the reply to ``call`` according to its method (multicalls included)."""
    if call.method == MULTICALL:
        calls = expand_multicall(call)
        parts = split_multicall_response(response, len(calls))
        return assemble_multicall(
            [rewrite_response(c, r, uri=uri, tcpros=tcpros) for c, r in zip(calls, parts, strict=True)],
            keep_alive=response.keep_alive,
        )
    if uri is not None and call.method in ("registerSubscriber", "registerPublisher"):
        return rewrite_register_response(response, uri)
    if uri is not None and call.method in ("lookupNode", "lookupService", "getUri"):
        return rewrite_uri_response(response, uri, call.method)
    if tcpros is not None and call.method == "requestTopic":
        return rewrite_tcpros_reply(response, tcpros)
    return response


def tcpros_only(call: Request) -> Request:
    """``requestTopic(caller, topic, protocols)`` -> the same call offering exactly
    ``[['TCPROS']]``: the only transport the interceptors carry. A subscriber that
    offers UDPROS with a TCPROS fallback gets TCPROS; one that offers no TCPROS is
    refused (``udpros_refused``), so no publisher ever sends a datagram because a
    peer asked. Other calls pass unchanged."""
    if call.method != "requestTopic":
        return call
    if len(call.params) != 3 or not isinstance(call.params[2], list):
        raise RemoteProtocolError("requestTopic takes caller_id, topic and a list of protocols")
    offered = [p[0] for p in call.params[2] if isinstance(p, list) and p and isinstance(p[0], str)]
    if "TCPROS" not in offered:
        raise PolicyDenied("udpros_refused", f"requestTopic offers {offered[:4]!r:.80}; only TCPROS is carried")
    return _with_params(call, call.params[:2] + ([["TCPROS"]],))


REDACTED = "[redacted]"


def redact_node_reply(call: Request, response: Response | Fault, master: str) -> Response | Fault:
    """Node-API replies sent to a peer name no host endpoint: ``getMasterUri``
    answers ``master`` (the canonical master), ``getBusInfo`` keeps connection id,
    direction, transport, topic and state but not the other end's address or the
    free-text info (roscpp writes ``127.0.0.1:port`` there). Their status messages,
    where rospy repeats the URI, become fixed words."""
    if call.method == "getMasterUri":
        v = _ros_triple(response, "getMasterUri")
        if v is None or v[0] != 1:
            return response
        return Response(value=[v[0], "master URI", master], keep_alive=response.keep_alive)
    if call.method == "getBusInfo":
        v = _ros_triple(response, "getBusInfo")
        if v is None or v[0] != 1:
            return response
        if not isinstance(v[2], list):
            raise RemoteProtocolError("getBusInfo value is not a list")
        rows = []
        for row in v[2]:
            if not isinstance(row, list) or len(row) < 6:
                raise RemoteProtocolError("getBusInfo row is not [id, destination, direction, transport, topic, connected, ...]")
            destination = row[1] if isinstance(row[1], str) and row[1].startswith("/") else REDACTED
            rows.append([row[0], destination, row[2], row[3], row[4], row[5]])
        return Response(value=[v[0], "bus info", rows], keep_alive=response.keep_alive)
    return response
