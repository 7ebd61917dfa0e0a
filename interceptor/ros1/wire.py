"""What every part of the ROS 1 role shares: the constants, reading one XML-RPC
message or TCPROS header with a deadline, and the small pure helpers over master calls
(which registration a call makes, where its relay URIs sit, parameter calls resolved
and their replies narrowed)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable
from typing import Any

from cryptoros.errors import PolicyDenied, RemoteProtocolError
from cryptoros.policy.ros1 import (
    PARAM_READ,
    PARAM_WRITE,
    check_param_call,
    filter_param_reply,
)
from cryptoros.policy.hints import missing_grant_hint
from cryptoros.ros1 import msgs
from cryptoros.ros1.tcpros import ConnectionHeader, TCPROSConnection, encode_header
from cryptoros.ros1.uri import UriError, host_port
from cryptoros.ros1.xmlrpc import (
    MULTICALL,
    Fault,
    Request,
    Response,
    XmlRpcConnection,
)
from cryptoros.sansio import NEED_DATA
from interceptor.config import XMLRPC_IDLE_TIMEOUT
from interceptor.streams import read_into

log = logging.getLogger("cryptoros.interceptor")

OPAQUE = "denied by cryptoros"
#: XML-RPC calls in flight per tunnel pool before the next waits for a tunnel to come back
POOL_BUSY = 8
#: how long (seconds) such a call waits before it opens a tunnel of its own (a slow call
#: on every tunnel delays the others by at most this)
POOL_WAIT = 0.2
#: What a caller is told when its call was allowed but nobody answered (the ROS master
#: or the peer's interceptor down): not a denial, so not worded as one.
UNANSWERED = "cryptoros: no answer from the ROS master or the peer (not a denial)"
UNANSWERED_REASONS = frozenset({"peer_unreachable", "tunnel_failed"})
CALL_TIMEOUT = 30.0
#: an inbound XML-RPC stream idle this long between requests is closed (a pooled tunnel
#: of ours is closed sooner: [limits] tunnel_idle_timeout)
IDLE_TIMEOUT = XMLRPC_IDLE_TIMEOUT
#: tunnel pools kept (one per peer endpoint called: the master, each remote node API);
#: the least recently used is closed past this. A pool's relay released closes it too.
MAX_POOLS = 1024
#: master role: a master call refused as rate_limited is logged once per manager this
#: often (seconds); every one is counted (cryptoros_interceptor_denied_total)
RATE_LOG_INTERVAL = 10.0
PARAM_CALLER_API_INDEX = {"subscribeParam": 1, "unsubscribeParam": 1}
#: master role: one peer manager's calls in flight to rosmaster at once (a robot's own
#: interceptor sends at most POOL_BUSY before it waits POOL_WAIT), and of those, calls
#: reading parameter values (answers as large as what was stored: an insider's 120 reads
#: of its own 13.5 MB at once took the master's interceptor to 4.8 GB and stalled other
#: robots' master calls for 20 s). A call holds its slots until its answer is written out
#: (what the peer does not read counts too); further calls wait up to MASTER_CALL_WAIT
#: seconds, then are refused as rate_limited.
MASTER_CALLS_PER_PEER = POOL_BUSY
PARAM_READS_PER_PEER = 2
MASTER_CALL_WAIT = 10.0
#: the most bytes of answers a multicall keeps together for its reply (or [limits]
#: max_master_reply, if larger); its later calls are refused as answer_too_large
MULTICALL_ANSWERS = 64 << 20
#: master role: registrations kept for a restarted rosmaster (bounded: each costs ~300 B)
MAX_REGISTRATIONS = 65_536
#: parameter subscriptions of one node counted for its relay (more: freed by the export limit)
MAX_PARAM_SUBSCRIPTIONS_PER_NODE = 4096
#: how often, and how patiently, the master role asks rosmaster for its pid
MASTER_WATCH_INTERVAL = 1.0
#: master role: seconds rosmaster may leave the watch unanswered before health says master_down
MASTER_DOWN_AFTER = 3.0
#: master role: seconds between two looks at one node registered with rosmaster directly
#: (is its API exposed?); a node is looked at when it first appears
DIRECT_RECHECK = 30.0
MASTER_WATCH_TIMEOUT = 5.0
#: how long a local node's call waits for this interceptor's token when it holds none
LOCAL_TOKEN_WAIT = 3.0
#: Master calls that release a registration: their URIs must already have a relay.
RELEASING_CALLS = frozenset({"unregisterPublisher", "unregisterSubscriber", "unregisterService", "unsubscribeParam"})



async def read_xmlrpc(reader: asyncio.StreamReader, conn: XmlRpcConnection, timeout: float):
    """The next XML-RPC event of ``conn``, reading from ``reader`` as needed, within
    ``timeout`` seconds overall (``asyncio.TimeoutError``): a peer that dribbles a
    byte at a time cannot hold a call, and the caller waiting on it, for longer."""
    deadline = time.monotonic() + timeout
    while True:
        event = conn.next_event()
        if event is not NEED_DATA:
            return event
        await read_into(reader, conn.receive_data, max(0.01, deadline - time.monotonic()))


async def read_tcpros_header(
    reader: asyncio.StreamReader, timeout: float, max_size: int, max_fields: int = 32, *, pending: bytes = b""
) -> tuple[ConnectionHeader, bytes]:
    """One TCPROS connection header and whatever bytes followed it (within
    ``timeout`` overall; at most ``max_size`` bytes and ``max_fields`` fields).
    ``pending``: bytes already read from the stream (parsed first)."""
    conn = TCPROSConnection(max_header_size=max_size, max_header_fields=max_fields)
    if pending:
        conn.receive_data(pending)
    deadline = time.monotonic() + timeout
    while True:
        event = conn.next_event()
        if isinstance(event, ConnectionHeader):
            rest, _eof = conn.trailing_data
            return event, rest
        if event is not NEED_DATA:
            raise RemoteProtocolError("connection closed before its header")
        await read_into(reader, conn.receive_data, max(0.01, deadline - time.monotonic()))


def ros_ok(response: Response | Fault) -> bool:
    return isinstance(response, Response) and isinstance(response.value, list) and response.value[:1] == [1]



async def pass_refusal(writer: asyncio.StreamWriter, error: str) -> None:
    """A TCPROS server refused a stream with an ``error`` header: the refusal goes on to
    the client, rebuilt from the parsed text, and nothing after it (the stream ends)."""
    writer.write(encode_header({"error": error}))
    with contextlib.suppress(Exception):
        await asyncio.wait_for(writer.drain(), 1)


def monitor_hooks(watched: Any, gated: bool) -> dict[str, Any]:
    """How the pump hands a peer's messages to the monitor: a gated topic's are scored
    before they go on (``left_gate``), every other watched one's are queued after."""
    if watched is None:
        return {}
    return {"left_gate": watched.gate} if gated else {"left_tap": watched.feed}


#: Local registrations whose caller_api (index 3) names the registering node's API.
LOCAL_REGISTRATIONS = frozenset({"registerPublisher", "registerSubscriber", "registerService"})

#: Where the URIs of a master call sit that are relays at the master's interceptor.
RELAY_URI_INDEX = {
    "registerPublisher": (3,), "registerSubscriber": (3,), "registerService": (2, 3), "subscribeParam": (1,),
    "unregisterPublisher": (2,), "unregisterSubscriber": (2,), "unregisterService": (2,), "unsubscribeParam": (1,),
}


def released_uri(method: str, params: tuple) -> str | None:
    """The URI an ``unregister*``/``unsubscribeParam`` call names (rosmaster releases
    only what was registered under it); None for other calls."""
    index = PARAM_CALLER_API_INDEX.get(method, 2) if method in RELEASING_CALLS else None
    value = params[index] if index is not None and len(params) > index else None
    return value if isinstance(value, str) else None


def caller_api(method: str, params: tuple) -> str | None:
    """The node API a registration gives rosmaster (None: not a registration): the last
    of the URIs :data:`RELAY_URI_INDEX` names (a service's own URI comes before it)."""
    indexes = RELAY_URI_INDEX.get(method) if method.startswith("register") or method == "subscribeParam" else None
    value = params[indexes[-1]] if indexes and len(params) > indexes[-1] else None
    return value if isinstance(value, str) else None


def registration_key(method: str, params: tuple) -> tuple[str, str, str] | None:
    """Which registration a master call makes or releases: (kind, node, name)."""
    kind = {"registerPublisher": "pub", "unregisterPublisher": "pub", "registerSubscriber": "sub",
            "unregisterSubscriber": "sub", "registerService": "srv", "unregisterService": "srv"}.get(method)
    if kind is None or len(params) < 2 or not all(isinstance(p, str) for p in params):
        return None
    return kind, params[0], params[1]


def param_subscription_key(method: str, params: tuple) -> tuple[str, str, str] | None:
    """A parameter subscription made or released: ("param", node, key)."""
    if method not in ("subscribeParam", "unsubscribeParam") or len(params) < 3:
        return None
    if not all(isinstance(p, str) for p in params[:3]):
        return None
    return "param", params[0], params[2]


def local_endpoint(uri) -> tuple[str, int] | None:
    try:
        return host_port(uri)
    except UriError:
        return None


def _calls_any(request: Request, methods: frozenset[str]) -> bool:
    """Whether a request (a multicall: one of its calls) calls one of ``methods``."""
    if request.method in methods:
        return True
    calls = request.params[0] if request.method == MULTICALL and request.params else None
    return isinstance(calls, list) and any(isinstance(c, dict) and c.get("methodName") in methods for c in calls)


def writes_params(request: Request) -> bool:
    """Whether a request (a multicall: one of its calls) is setParam or deleteParam."""
    return _calls_any(request, PARAM_WRITE)


#: master calls whose answer holds parameter values or names: as large as what was stored
PARAM_VALUE_READS = frozenset({"getParam", "subscribeParam", "getParamNames"})


def reads_param_values(request: Request) -> bool:
    """Whether a request (a multicall: one of its calls) reads parameter values or names."""
    return _calls_any(request, PARAM_VALUE_READS)


def resolved_param_call(call: Request, grants) -> Request:
    """A parameter call sent on with its key resolved as rosmaster would (checked)."""
    if call.method not in PARAM_READ and call.method not in PARAM_WRITE:
        return call
    params = check_param_call(call.method, call.params, grants=grants)
    return Request(method=call.method, params=params, path=call.path, keep_alive=call.keep_alive,
                   accept_gzip=call.accept_gzip)


def filtered_param_reply(call: Request, response: Response | Fault, grants) -> Response | Fault:
    """Parameter replies narrowed to what the caller may read."""
    if not isinstance(response, Response) or (call.method not in PARAM_READ and call.method != "getParamNames"):
        return response
    value = filter_param_reply(call.method, call.params, response.value, grants=grants)
    return response if value is response.value else Response(value=value, keep_alive=response.keep_alive)


def rewrite_param_api(call: Request, fn: Callable[[str], str]) -> Request:
    index = PARAM_CALLER_API_INDEX.get(call.method)
    if index is None or len(call.params) <= index or not isinstance(call.params[index], str):
        return call
    params = call.params[:index] + (fn(call.params[index]),) + call.params[index + 1 :]
    return Request(method=call.method, params=params, path=call.path, keep_alive=call.keep_alive,
                   accept_gzip=call.accept_gzip)


#: the grants a stream's two ends need: the end that opens it (subscriber, service
#: client) and the end that serves it (publisher, service server)
OPENING_ACTIONS = frozenset({"subscribe", "call"})


def header_hint(exc: BaseException, *, opener: str | None, server: str | None) -> str | None:
    """The ``cryptoros-authz grant ...`` that would allow a TCPROS stream refused for a
    missing grant: of ``opener``'s manager (its subscriber's or client's grant missing) or
    of ``server``'s (its publisher's or service's)."""
    if not isinstance(exc, PolicyDenied) or exc.missing is None:
        return None
    return missing_grant_hint(exc, opener if exc.missing[0] in OPENING_ACTIONS else server)


def value_size(value: Any, limit: int) -> int:
    """About how many bytes ``value`` (a parsed XML-RPC value) holds: its strings' and
    binaries' lengths and 16 a scalar, counted until past ``limit``."""
    size, stack = 0, [value]
    while stack and size <= limit:
        item = stack.pop()
        if isinstance(item, (str, bytes, bytearray)):
            size += len(item)
        elif isinstance(item, dict):
            size += sum(len(k) for k in item)
            stack.extend(item.values())
        elif isinstance(item, (list, tuple)):
            stack.extend(item)
        else:
            size += 16
    return size


def md5_or_none(type_name: str | None) -> str | None:
    if type_name is None:
        return None
    try:
        return msgs.md5sum(type_name)
    except Exception:  # a type outside the known typestore: the publisher itself checks md5
        return None


__all__ = ["CALL_TIMEOUT", "DIRECT_RECHECK", "IDLE_TIMEOUT", "LOCAL_REGISTRATIONS", "LOCAL_TOKEN_WAIT", "MASTER_CALLS_PER_PEER", "MASTER_CALL_WAIT", "MASTER_DOWN_AFTER", "MASTER_WATCH_INTERVAL", "MASTER_WATCH_TIMEOUT", "MAX_PARAM_SUBSCRIPTIONS_PER_NODE", "MAX_POOLS", "MAX_REGISTRATIONS", "MULTICALL_ANSWERS", "OPAQUE", "OPENING_ACTIONS", "PARAM_CALLER_API_INDEX", "PARAM_READS_PER_PEER", "PARAM_VALUE_READS", "POOL_BUSY", "POOL_WAIT", "RATE_LOG_INTERVAL", "RELAY_URI_INDEX", "RELEASING_CALLS", "UNANSWERED", "UNANSWERED_REASONS", "caller_api", "filtered_param_reply", "header_hint", "local_endpoint", "log", "md5_or_none", "monitor_hooks", "param_subscription_key", "pass_refusal", "read_tcpros_header", "read_xmlrpc", "reads_param_values", "registration_key", "released_uri", "resolved_param_call", "rewrite_param_api", "ros_ok", "value_size", "writes_params"]