"""The ROS 1 role of the interceptor: XML-RPC and TCPROS over the gateway.

Composed with :class:`~interceptor.gateway.Gateway`, which owns the public listener,
tokens, limits, cut-off and reload. This role serves the stream purposes

  ``master``  XML-RPC for the master this interceptor fronts (master role);
  ``node``    XML-RPC for one exported local node API;
  ``topic``/``service``  TCPROS for one exported local TCPROS server: the
  connection header is checked, then bytes are pumped,

and opens its own loopback listeners:

- **local master** (plain HTTP, node role): the ``ROS_MASTER_URI`` of this host's
  unmodified nodes. Calls are checked against this interceptor's own grants, their
  URIs exported, and forwarded over a tunnel to the master's interceptor.
- **relays** (created on demand): one per remote endpoint a local process was
  handed; each tunnels to the endpoint's owner.

Every decision is a pure function of :mod:`cryptoros.policy.ros1`; this module does
the I/O. Everything fails closed: a call or stream that cannot be decided is refused,
the log gets who, what and why, the peer gets an opaque denial.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import json
import logging
import socket
import time
from collections.abc import Awaitable, Callable
from typing import Any

from cryptoros.errors import CryptorosError, PolicyDenied, RemoteProtocolError
from cryptoros.ratelimit import OncePer, TokenBuckets
from cryptoros.policy.ros1 import (
    NAME_BINDING,
    PARAM_READ,
    PARAM_WRITE,
    check_local_subscriber_header,
    check_master_call,
    check_node_call,
    check_param_call,
    check_publisher_header,
    check_service_client_header,
    check_service_server_header,
    check_subscribed_type,
    check_subscriber_header,
    filter_param_reply,
    grant_hint,
    refusal_answer,
    refusal_text,
    ros_error,
)
from cryptoros.ros1 import msgs
from cryptoros.sansio import NEED_DATA
from cryptoros.ros1.node import tune_malloc
from cryptoros.ros1.rewrite import redact_node_reply, rewrite_call, rewrite_response, tcpros_only
from cryptoros.ros1.uri import UriError, host_port, split_uri
from cryptoros.ros1.tcpros import ConnectionHeader, TCPROSConnection, canonical_header, encode_header
from cryptoros.ros1.xmlrpc import (
    MULTICALL,
    ConnectionClosed,
    Fault,
    Request,
    Response,
    Role,
    XmlRpcConnection,
    assemble_multicall,
    expand_multicall,
    make_multicall,
    request_path,
    split_multicall_response,
)
from cryptoros.tokens import Grants
from cryptoros.tunnel import Preamble
from interceptor.gateway import READ_SIZE, Gateway, InboundStream, Tunnel, read_into
from interceptor.gateway import Role as GatewayRole
from interceptor.config import XMLRPC_IDLE_TIMEOUT
from interceptor.exposure import NodeGuard, PortExposure, master_problem
from interceptor.gate import REFRESH
from interceptor.name_holds import NameHolds
from interceptor.param_quota import ParamQuota
from interceptor.pump import FrameCounter
from interceptor.registrations import REGISTER, RELEASE, LocalRegistrations, Registration, covers
from interceptor.statefile import write_private_json
from interceptor.translate import KIND_TCPROS, KIND_XMLRPC, MASTER, Canonical, LocalEndpoint, Translator

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
_UNANSWERED_REASONS = frozenset({"peer_unreachable", "tunnel_failed"})
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
#: master role: registrations kept for a restarted rosmaster (bounded: each costs ~300 B)
MAX_REGISTRATIONS = 65_536
#: parameter subscriptions of one node counted for its relay (more: freed by the export limit)
MAX_PARAM_SUBSCRIPTIONS_PER_NODE = 4096
#: how often, and how patiently, the master role asks rosmaster for its pid
MASTER_WATCH_INTERVAL = 1.0
MASTER_WATCH_TIMEOUT = 5.0
#: how long a local node's call waits for this interceptor's token when it holds none
LOCAL_TOKEN_WAIT = 3.0
#: Master calls that release a registration: their URIs must already have a relay.
_RELEASING_CALLS = frozenset({"unregisterPublisher", "unregisterSubscriber", "unregisterService", "unsubscribeParam"})


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


def _ros_ok(response: Response | Fault) -> bool:
    return isinstance(response, Response) and isinstance(response.value, list) and response.value[:1] == [1]


class XmlRpcTunnel:
    """XML-RPC calls over one tunnel stream to a peer interceptor (opened lazily,
    reopened once if the peer closed an idle keep-alive stream)."""

    def __init__(self, owner: Ros1Role, host: str, port: int, purpose: str, target: str) -> None:
        self._owner = owner
        self._address = (host, port)
        self._purpose = purpose
        self._target = target
        self._stream: Tunnel | None = None
        self._conn: XmlRpcConnection | None = None
        self._lock = asyncio.Lock()

    async def call(self, request: Request) -> Response | Fault:
        async with self._lock:
            for attempt in (0, 1):
                fresh = self._stream is None
                if fresh:
                    # The first request rides with the preamble: no extra round trip.
                    self._conn = XmlRpcConnection(Role.CLIENT, max_body_size=self._owner.cfg.limits.max_xmlrpc_body)
                    self._stream = await self._owner.gw.open_tunnel(
                        *self._address, self._purpose, self._target, first=self._conn.send(request), settles=True
                    )
                    if self._stream.pending:
                        self._conn.receive_data(self._stream.pending)
                reader, writer = self._stream.reader, self._stream.writer
                try:
                    if not fresh:
                        writer.write(self._conn.send(request))
                        await asyncio.wait_for(writer.drain(), CALL_TIMEOUT)
                    try:
                        event = await read_xmlrpc(reader, self._conn, CALL_TIMEOUT)
                    finally:
                        if fresh:
                            self._stream.settle()
                    if isinstance(event, ConnectionClosed):
                        raise ConnectionResetError("tunnel closed")
                    return event
                except (ConnectionError, RemoteProtocolError) as exc:
                    await self.close_locked()
                    if fresh or attempt:
                        raise PolicyDenied("tunnel_failed", f"{self._purpose} tunnel: {exc}") from exc
            raise AssertionError("unreachable")

    async def close_locked(self) -> None:
        self.close_now()

    def close_now(self) -> None:
        """Close the stream of a tunnel not in use (idle in its pool)."""
        if self._stream is not None:
            self._stream.writer.close()
            self._stream = None

    async def close(self) -> None:
        async with self._lock:
            await self.close_locked()


class TunnelPool:
    """Reusable XML-RPC tunnels to one peer endpoint: rospy opens a new connection for
    every node-API call, and a TLS handshake per call would cost about 8 KB and
    10 ms; idle tunnels are kept (up to ``max_idle``) and reused. With ``max_busy``
    calls in flight, the next one waits up to :data:`POOL_WAIT` for a tunnel to come
    back before it opens one of its own: a burst of calls (a robot's nodes registering
    at once) shares a few tunnels instead of paying a handshake each.

    A tunnel unused for ``idle_timeout`` seconds is closed (a peer closes an idle stream
    after :data:`IDLE_TIMEOUT`: this side closes first). A closed pool (:meth:`close`:
    its relay released, or evicted) keeps no tunnel: a call still under way, or made
    later through a connection that holds the pool, closes its own."""

    def __init__(self, owner: Ros1Role, host: str, port: int, purpose: str, target: str, max_idle: int = 4,
                 max_busy: int = POOL_BUSY, idle_timeout: float = 60.0,
                 on_idle_close: Callable[[], None] = lambda: None):
        self._args = (owner, host, port, purpose, target)
        self._on_idle_close = on_idle_close
        #: idle tunnels and when each was put back (the loop's clock), oldest first
        self._idle: list[tuple[XmlRpcTunnel, float]] = []
        self._max_idle = max_idle
        self._max_busy = max_busy
        self._idle_timeout = idle_timeout
        self._sweep: asyncio.TimerHandle | None = None
        self._busy = 0
        self.closed = False
        #: calls waiting for a tunnel: each gets one handed back, or None (open your own)
        self._waiters: list[asyncio.Future] = []

    @property
    def idle_count(self) -> int:
        return len(self._idle)

    async def _acquire(self) -> XmlRpcTunnel:
        if self._idle:
            return self._idle.pop()[0]  # the most recently used: the others may go idle
        if self._busy >= self._max_busy:
            waiter = asyncio.get_running_loop().create_future()
            self._waiters.append(waiter)
            try:
                tunnel = await asyncio.wait_for(waiter, POOL_WAIT)
            except asyncio.TimeoutError:
                tunnel = None
            finally:
                if waiter in self._waiters:
                    self._waiters.remove(waiter)
            if tunnel is not None:
                return tunnel
        return XmlRpcTunnel(*self._args)

    def _hand_over(self, tunnel: XmlRpcTunnel | None) -> bool:
        """Give ``tunnel`` (None: leave to open one) to the first call still waiting."""
        while self._waiters:
            waiter = self._waiters.pop(0)
            if not waiter.done():
                waiter.set_result(tunnel)
                return True
        return False

    async def call(self, request: Request) -> Response | Fault:
        tunnel = await self._acquire()
        self._busy += 1
        try:
            response = await tunnel.call(request)
        except BaseException:
            self._busy -= 1
            self._hand_over(None)
            await tunnel.close()
            raise
        self._busy -= 1
        if self._hand_over(tunnel):
            return response
        self._park(tunnel)
        return response

    def _park(self, tunnel: XmlRpcTunnel) -> None:
        """Keep an unused tunnel for the next call (closed after ``idle_timeout``)."""
        if self.closed or len(self._idle) >= self._max_idle:
            tunnel.close_now()
            return
        loop = asyncio.get_running_loop()
        self._idle.append((tunnel, loop.time()))
        if self._sweep is None:
            self._sweep = loop.call_later(self._idle_timeout, self._close_idle)

    def _close_idle(self) -> None:
        """Close the tunnels idle for ``idle_timeout``; come back for the next one."""
        self._sweep = None
        loop = asyncio.get_running_loop()
        due = loop.time() - self._idle_timeout + 0.01  # the loop may wake a little early
        while self._idle and self._idle[0][1] <= due:
            self._idle.pop(0)[0].close_now()
            self._on_idle_close()
        if self._idle:
            self._sweep = loop.call_at(self._idle[0][1] + self._idle_timeout, self._close_idle)

    def close(self) -> None:
        """Close the idle tunnels now, and every tunnel that comes back from then on."""
        self.closed = True
        if self._sweep is not None:
            self._sweep.cancel()
            self._sweep = None
        while self._idle:
            self._idle.pop()[0].close_now()




class Ros1Role(GatewayRole):
    """The ROS 1 purposes and listeners of one interceptor (node role, master role, or both)."""

    def __init__(self, gateway: Gateway) -> None:
        super().__init__(gateway)
        cfg = gateway.cfg
        local_master = (
            f"http://{cfg.local_master.host}:{cfg.local_master.port}/" if cfg.local_master is not None else None
        )
        self.translator = Translator(
            public_host=cfg.public.host,
            public_port=cfg.public.port,
            local_master_uri=local_master,
            open_relay=self._open_relay,
            max_relays_per_host=cfg.limits.max_relays_per_peer,
            on_change=self._save_state,
        )
        if local_master:
            self.translator.add_master_uri(local_master)
        if "master" in cfg.roles and cfg.master.upstream:
            self.translator.add_master_uri(cfg.master.upstream)
        self.topic_types: dict[str, str] = {}  # topics published by this host's nodes
        #: topics first known from a publisher registration still on its way to the master:
        #: rosmaster tells subscribers at once, and their requestTopic can come back before
        #: the master's answer does (refused as unknown_topic, the subscriber never connected)
        self._topics_registering: set[str] = set()
        self._owners: dict[str, list] = {}  # master role: node -> [manager, registrations]
        #: master role: names released by their owner, kept for it a while (a restart)
        self._holds = NameHolds(cfg.limits.max_nodes_per_peer)
        #: master role: master calls per peer manager ([limits] max_master_calls_per_second)
        self._master_calls = self._master_call_buckets()
        self._rate_log = OncePer(RATE_LOG_INTERVAL, max_keys=1024)
        #: master role: what each peer manager stored in rosmaster through setParam, and the
        #: lock its parameter writes go to rosmaster under (in the order they are charged)
        self._params = ParamQuota(cfg.limits.max_param_keys_per_peer, cfg.limits.max_param_bytes_per_peer)
        self._param_writes = asyncio.Lock()
        #: one per peer endpoint called, the least recently used first (see pool())
        self._pools: dict[tuple[str, int, str, str], TunnelPool] = {}
        self._tunnels_closed_idle = 0
        self._servers: list[asyncio.AbstractServer] = []
        self._relay_socket_of: dict[tuple[str, int], socket.socket] = {}
        self._relay_servers: dict[tuple[str, int], asyncio.AbstractServer] = {}
        self._relay_refs: dict[tuple[str, int], int] = {}  # master role: registrations behind each relay
        self._state_loaded = False
        self._save_pending = False
        self._state_saves = 0  # state files written (/status: a repeat registration writes none)
        self._local_subscribers: dict[str, dict[str, str]] = {}  # topic -> {node: local node API}
        self._resubscribing: set[str] = set()
        #: master role: the registrations rosmaster holds through us, as forwarded, so a
        #: restarted rosmaster gets them replayed: (kind, node, name) -> (method, params)
        self._registrations: dict[tuple[str, str, str], tuple[str, tuple]] = {}
        self._registrations_full_logged = False
        #: master role: each registered node's API as rosmaster has it (its relay here) and
        #: the keys of its kept registrations. A node that registers from another API was
        #: restarted or replaced: rosmaster then drops all the old API had registered, and
        #: so do we (with the relays behind it)
        self._api_of_node: dict[str, str] = {}
        self._keys_of_node: dict[str, set[tuple[str, str, str]]] = {}
        #: master role: nodes whose owner holds the name only through ``*`` or a pattern (a
        #: manager whose grants name the node itself takes it from such an owner)
        self._owned_by_pattern: set[str] = set()
        #: master role: each node's parameter subscriptions (key -> the call as forwarded),
        #: not replayed to a restarted rosmaster but counted behind their relays
        self._param_subs_of_node: dict[str, dict[str, tuple]] = {}
        self._master_pid: int | None = None
        #: node role: each local node's API export, and the exports (TCPROS servers,
        #: service servers) that came from it: released when the node registers again
        #: from new ports (restarted), so restarts do not use up export_limit
        self._node_apis: dict[str, str] = {}
        self._export_children: dict[str, set[str]] = {}
        #: node role: what each local node has registered now ((kind, name): pub, sub, srv,
        #: param); a node whose last registration goes (it shut down cleanly) has its
        #: exports released, so nodes that come and go under new names (rostopic, rosbag)
        #: do not use up export_limit either
        self._node_registrations: dict[str, set[tuple[str, str]]] = {}
        #: deployment checks (interceptor/exposure.py): which ports answer other hosts, and
        #: (master role) why rosmaster must not be served now, or None
        self._exposure = PortExposure()
        self._nodes_exposed = NodeGuard(self._exposure)
        self._master_exposed: str | None = None
        #: node role: each registration a local node made or had refused, as it sent it, so a
        #: grant that comes while it runs is made for it (:meth:`_regrant`)
        self._ledger = LocalRegistrations()
        self._grants_seen: Grants | None = None  # the grants of our token the ledger was last judged by
        self._regrant_wanted = False
        self._regranting = False
        gateway.serve("master", self._check_master_target, self._serve_master_stream)
        gateway.serve("node", self._check_node_target, self._serve_node_stream)
        gateway.serve("topic", self._check_tcpros_target, self._serve_tcpros_stream)
        gateway.serve("service", self._check_tcpros_target, self._serve_tcpros_stream)

    # ================================================================ life cycle (Role)
    async def prepare(self) -> None:
        # Large reads are copied out of the pump's buffer: keep glibc from mmap-ing
        # (and page-faulting) each one (measured on 2 cores: +30 to 100 % on 1 MB frames).
        tune_malloc()
        # The message typestore (md5sums of published types) loads in ~50 ms: now, not
        # during the first TCPROS stream (measured: the first set-up 62-97 ms, the rest 2-3).
        msgs.typestore()
        self._load_state()

    async def start(self) -> None:
        if "node" in self.cfg.roles:
            lm = self.cfg.local_master
            self._servers.append(await self.gw.start_local_server("local master", lm, self._on_local_master,
                                                                  host=lm.host, port=lm.port))
            with contextlib.suppress(CryptorosError):
                self._grants_seen = self.gw.own_access().grants
            self.gw.keeper.listeners.append(self._own_token_changed)
            if self._ledger.refused_count:  # kept from before our restart: our token may cover them now
                self._own_token_changed()
            if not self.translator.export_count:
                self.gw.spawn(self._adopt_local_graph(), "adopt-graph")  # no state: ask rosmaster
        for topic in list(self._local_subscribers):  # restarted: local subscribers lost their streams
            self._resubscribe_soon(topic, delay=0.5)
        if "master" in self.cfg.roles and self.cfg.master.upstream:
            self.gw.spawn(self._watch_master(), "rosmaster-watch")

    async def stopping(self) -> None:
        for server in (*self._servers, *self._relay_servers.values()):
            server.close()

    async def stopped(self) -> None:
        for server in self._servers:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(server.wait_closed(), 1)
        for pool in self._pools.values():
            pool.close()
        for sock in self._relay_socket_of.values():
            sock.close()
        self._relay_socket_of.clear()

    def reloaded(self) -> None:
        """The limits this role keeps a copy of: the next relay, held name, master call and
        parameter write count by the new ones."""
        limits = self.cfg.limits
        self.translator.max_relays_per_host = limits.max_relays_per_peer
        self._holds.per_manager = limits.max_nodes_per_peer
        if (self._master_calls.rate, self._master_calls.burst) != (limits.max_master_calls_per_second,
                                                                   float(limits.master_call_burst)):
            self._master_calls = self._master_call_buckets()
        self._params.max_keys, self._params.max_bytes = limits.max_param_keys_per_peer, limits.max_param_bytes_per_peer

    def _master_call_buckets(self) -> TokenBuckets:
        limits = self.cfg.limits
        return TokenBuckets(limits.max_master_calls_per_second, limits.master_call_burst, max_keys=4096)

    def status(self) -> dict:
        pools = list(self._pools.values())
        return {"ros1": {"tunnel_pools": len(pools), "idle_tunnels": sum(p.idle_count for p in pools),
                         "tunnels_closed_idle": self._tunnels_closed_idle, "relays": self.translator.relay_count,
                         "state_saves": self._state_saves,
                         "param_usage": {m: list(u) for m, u in self._params.all_usage().items()}},
                "warnings": self._deployment_warnings()}

    def _deployment_warnings(self) -> list[str]:
        warnings = self._nodes_exposed.warnings()
        if self._master_exposed:
            what = ("allow_exposed_master = true, served anyway" if self.cfg.allow_exposed_master
                    else "master streams refused (exposed_master)")
            warnings.append(f"{what}: {self._master_exposed}")
        return warnings

    def _count_idle_close(self) -> None:
        self._tunnels_closed_idle += 1

    # ================================================================ targets the gate checks
    def _check_master_target(self, preamble: Preamble) -> None:
        if "master" not in self.cfg.roles:
            raise PolicyDenied("no_master_here", "this interceptor does not front a master")
        self._refuse_exposed_master()

    def _refuse_exposed_master(self) -> None:
        problem = self.problem()
        if problem is not None:
            raise problem

    def problem(self) -> PolicyDenied | None:
        if self._master_exposed and not self.cfg.allow_exposed_master:
            return PolicyDenied("exposed_master", self._master_exposed)
        return None

    def _check_node_target(self, preamble: Preamble) -> LocalEndpoint:
        return self.translator.resolve(KIND_XMLRPC, preamble.target)

    def _check_tcpros_target(self, preamble: Preamble) -> LocalEndpoint:
        return self.translator.resolve(KIND_TCPROS, preamble.target)


    def _open_relay(self, target: Canonical, port: int = 0) -> tuple[str, int]:
        """Bind a loopback listener for ``target`` now (so its URI exists at once), on
        ``port`` if given and free (a relay kept across a restart); it starts
        accepting on the next turn of the loop."""
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(("127.0.0.1", port))
        except OSError:
            if not port:
                sock.close()
                raise
            sock.bind(("127.0.0.1", 0))
        sock.listen(128)
        sock.setblocking(False)
        handler = self._on_xmlrpc_relay if target.kind == KIND_XMLRPC else self._on_tcpros_relay

        host, port = sock.getsockname()[:2]

        async def serve() -> None:
            server = await self.gw.start_local_server("relay", f"{host}:{port}", lambda r, w: handler(r, w, target),
                                                      sock=sock, limit=READ_SIZE)
            if sock.fileno() < 0:  # released before it started
                server.close()
            else:
                self._relay_servers[(host, port)] = server

        self._relay_socket_of[(host, port)] = sock
        asyncio.get_running_loop().create_task(serve())
        log.debug("relay %s:%d -> %s", host, port, target)
        return host, port

    # ---------------------------------------------------------------- state across restarts
    def _state_path(self):
        return None if self.cfg.state_dir is None else self.cfg.state_dir / f"{self.cfg.manager}.state.json"

    def _save_state(self) -> None:
        """Keep the tables a restart would otherwise lose (written atomically)."""
        path = self._state_path()
        if path is None or not self._state_loaded:
            return
        data = {"version": 1, "translator": self.translator.snapshot(), "topic_types": self.topic_types,
                "owners": self._owners, "owned_by_pattern": sorted(self._owned_by_pattern),
                "local_subscribers": self._local_subscribers,
                "node_apis": self._node_apis,
                "export_children": {api: sorted(ids) for api, ids in self._export_children.items()},
                "registrations": [[method, list(params)] for method, params in self._registrations.values()],
                "waiting": [[method, list(params)] for method, params in self._ledger.refused_items()]}
        try:
            write_private_json(path, data)
            self._state_saves += 1
        except OSError as exc:
            log.error("cannot keep state in %s: %s", path, exc)

    def _save_state_soon(self) -> None:
        """Save once after this turn of the loop (a multicall changes many owners)."""
        if self._state_path() is not None and not self._save_pending:
            self._save_pending = True

            def save() -> None:
                self._save_pending = False
                self._save_state()

            asyncio.get_running_loop().call_soon(save)

    def _load_state(self) -> None:
        path = self._state_path()
        self._state_loaded = True
        if path is None or not path.exists():
            return
        try:
            data = json.loads(path.read_text())
            if data.get("version") != 1:
                raise ValueError(f"unknown state version {data.get('version')!r}")
            problems = self.translator.restore(data["translator"])
            self.topic_types.update({str(k): str(v) for k, v in data.get("topic_types", {}).items()})
            self._owners.update({str(k): [str(v[0]), int(v[1])] for k, v in data.get("owners", {}).items()})
            self._owned_by_pattern.update(str(n) for n in data.get("owned_by_pattern", ()) if str(n) in self._owners)
            for method, params in data.get("registrations", [])[:MAX_REGISTRATIONS]:
                self._record_registration(str(method), tuple(str(p) for p in params))
            for method, params in self._registrations.values():  # the counts behind each restored relay
                self._count_relay_refs(method, params, +1)
            for method, params in data.get("waiting", [])[:self._ledger.max_refused]:
                self._ledger.refused(str(method), tuple(str(p) for p in params))
            for topic, subscribers in data.get("local_subscribers", {}).items():
                self._local_subscribers[str(topic)] = {str(n): str(api) for n, api in subscribers.items()}
            self._node_apis.update({str(n): str(i) for n, i in data.get("node_apis", {}).items()})
            for api, ids in data.get("export_children", {}).items():
                self._export_children[str(api)] = {str(i) for i in ids}
        except (OSError, ValueError, KeyError, TypeError) as exc:
            log.error("state in %s not used (%s): nodes of this host may need a restart", path, exc)
            return
        for problem in problems:
            log.warning("state: %s", problem)
        log.info("state restored from %s: %d exports, %d relays, %d published topics", path,
                 len(data["translator"].get("exports", {})), self.translator.relay_count, len(self.topic_types))
        self._save_state()

    def pool(self, host: str, port: int, purpose: str, target: str) -> TunnelPool:
        """The tunnel pool to one peer endpoint (the least recently used of more than
        :data:`MAX_POOLS` is closed)."""
        key = (host, port, purpose, target)
        pool = self._pools.pop(key, None)
        if pool is None:
            pool = TunnelPool(self, host, port, purpose, target, idle_timeout=self.cfg.limits.tunnel_idle_timeout,
                              on_idle_close=self._count_idle_close)
        self._pools[key] = pool
        while len(self._pools) > MAX_POOLS:
            self._pools.pop(next(iter(self._pools))).close()
        return pool


    async def _serve_xmlrpc(
        self,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        handle: Callable[[Request], Awaitable[Response | Fault]],
        pending: bytes = b"",
    ) -> None:
        """Answer XML-RPC requests on a stream until it closes (``pending``: bytes
        already read from it, parsed first). A request that does not parse (bad head,
        oversized declared body, bad XML) is answered with one ROS error triple and the
        connection is cut without reading the rest."""
        limits = self.cfg.limits
        conn = XmlRpcConnection(Role.SERVER, max_body_size=limits.max_xmlrpc_body, gzip_threshold=1400)
        if pending:
            conn.receive_data(pending)
        while True:
            try:
                if not conn.trailing_data.data:  # between requests: a stop need not wait for this stream
                    with self.gw.cuttable():
                        await read_into(reader, conn.receive_data, IDLE_TIMEOUT)
                event = await read_xmlrpc(reader, conn, CALL_TIMEOUT)  # the request's first bytes are in
            except RemoteProtocolError:
                writer.transport.pause_reading()
                with contextlib.suppress(Exception):
                    writer.write(conn.send(Response(value=ros_error(OPAQUE), keep_alive=False)))
                    await asyncio.wait_for(writer.drain(), 1)
                writer.transport.abort()
                raise
            if isinstance(event, ConnectionClosed):
                return
            response = await handle(event)
            if not event.keep_alive:
                response = type(response)(**{**response.__dict__, "keep_alive": False})
            writer.write(conn.send(response))
            await asyncio.wait_for(writer.drain(), CALL_TIMEOUT)
            if not event.keep_alive:
                return

    async def _decide_calls(
        self,
        request: Request,
        decide: Callable[[Request], Request],
        forward: Callable[[Request], Awaitable[Response | Fault]],
        after: Callable[[Request, Response | Fault], Response | Fault],
        kind: str,
        who: str,
    ) -> Response | Fault:
        """Decide each call of a request (a multicall call by call), forward the
        allowed ones in one request, and answer refused ones with a ROS error."""
        try:
            calls = expand_multicall(request, max_calls=self.cfg.limits.max_multicall)
        except RemoteProtocolError as exc:
            self.gw.deny(kind, exc, who)
            return Response(value=ros_error(refusal_text("malformed")))
        results: list[Response | Fault | None] = [None] * len(calls)
        allowed: list[tuple[int, Request]] = []
        # whose grants a refusal lacks: the calling peer's, or (local nodes) our own manager's
        manager = who if kind in ("master", "node") else self.cfg.manager if kind == "local-master" else None
        for i, call in enumerate(calls):
            try:
                allowed.append((i, decide(call)))
                self.metrics.allowed.labels(kind).inc()
            except CryptorosError as exc:  # a policy denial, a malformed call, no token of ours
                reason = getattr(exc, "reason", None)
                flood = reason == "rate_limited"
                self.gw.deny(kind, exc, f"{who} {call.method}", logged=not flood or self._rate_log(who),
                             hint=grant_hint(reason, call.method, call.params, manager))
                # as rosmaster answers an error ([-1, "denied by cryptoros: <reason>", 0], never
                # a fault, which tools print as a traceback); a probe of a parameter the caller
                # may not read as if it were not set
                results[i] = Response(value=refusal_answer(reason, call.method, call.params))
        if allowed:
            multicall = request.method == MULTICALL
            outgoing = make_multicall([c for _, c in allowed], like=request) if multicall else allowed[0][1]
            try:
                reply = await forward(outgoing)
                parts = split_multicall_response(reply, len(allowed)) if multicall else [reply]
                for (i, call), part in zip(allowed, parts, strict=True):
                    results[i] = after(call, part)
            except (CryptorosError, ConnectionError, OSError, asyncio.TimeoutError) as exc:
                unanswered = getattr(exc, "reason", None) in _UNANSWERED_REASONS or not isinstance(exc, CryptorosError)
                if unanswered:
                    log.warning("%s call from %s got no answer: %s", kind, who, exc or type(exc).__name__)
                else:
                    self.gw.deny(kind, exc, who)
                for i, _ in allowed:
                    results[i] = Response(value=ros_error(UNANSWERED if unanswered else
                                                          refusal_text(getattr(exc, "reason", None))))
        if request.method == MULTICALL:
            return assemble_multicall(results)  # type: ignore[arg-type]
        return results[0]  # type: ignore[return-value]

    # ---------------------------------------------------------------- master role
    def _owner_of(self, node: str, grants: Grants | None = None) -> str | None:
        """The manager that has ``node`` registered, or released it within
        ``[limits] name_hold_seconds`` (:mod:`interceptor.name_holds`). A hold does not
        stand against a caller whose ``grants`` name that very node (the registry gives
        it the name: one tool name granted to two robots): it keeps the name from
        managers that would take it through ``*`` or a pattern. Nor does a registration
        made through ``*`` or a pattern: a manager holding such a grant cannot squat a
        name the registry gives another manager before that one's node starts (rosmaster
        then drops the squatter's registrations, :meth:`_forget_replaced_node`)."""
        entry = self._owners.get(node)
        if entry:
            if node in self._owned_by_pattern and grants is not None and grants.names_node_exactly(node):
                return None
            return entry[0]
        holder = self._holds.holder(node)
        if holder is not None and grants is not None and grants.names_node_exactly(node):
            return None
        return holder

    def _check_node_limit(self, call: Request, manager: str) -> None:
        """A peer registers at most ``max_nodes_per_peer`` node names at the master."""
        if call.method not in NAME_BINDING or not call.params or call.params[0] in self._owners:
            return
        cap = self.cfg.limits.max_nodes_per_peer
        if sum(1 for owner, _count in self._owners.values() if owner == manager) >= cap:
            raise PolicyDenied("node_limit", f"{manager} has {cap} nodes registered already (max_nodes_per_peer)")

    def _check_param_subscription(self, call: Request, manager: str) -> None:
        """A peer holds at most ``max_param_keys_per_peer`` parameter subscriptions (rosmaster
        keeps each), and one node at most :data:`MAX_PARAM_SUBSCRIPTIONS_PER_NODE`."""
        key = _param_subscription_key(call.method, call.params) if call.method == "subscribeParam" else None
        if key is None:
            return
        _kind, node, name = key
        subs = self._param_subs_of_node.get(node, {})
        if name in subs:
            return  # a repeat: nothing more is kept
        cap = self.cfg.limits.max_param_keys_per_peer
        held = sum(len(s) for n, s in self._param_subs_of_node.items() if self._owners.get(n, ("",))[0] == manager)
        if held >= cap or len(subs) >= MAX_PARAM_SUBSCRIPTIONS_PER_NODE:
            raise PolicyDenied("param_quota", f"{manager} holds {held} parameter subscriptions ({len(subs)} of {node}): "
                               f"max_param_keys_per_peer {cap}, {MAX_PARAM_SUBSCRIPTIONS_PER_NODE} per node")

    def _charge_param_write(self, call: Request, manager: str) -> None:
        """A parameter write allowed (key resolved): charged to ``manager`` before it is
        sent, refused past its quota (:mod:`interceptor.param_quota`)."""
        if call.method == "setParam" and len(call.params) >= 3:
            self._params.set(manager, call.params[1], call.params[2])
        elif call.method == "deleteParam" and len(call.params) >= 2:
            self._params.delete(call.params[1])

    def _note_registration(self, call: Request, response: Response | Fault, manager: str,
                           exact: bool = True) -> None:
        """What a call rosmaster accepted changes: owners, kept registrations, relay
        counts (and the state file, when one of them changed). ``exact``: the caller's
        grants name the node itself (not ``*`` or a pattern).

        rosmaster keeps one registration per node and topic (service, parameter key):
        the same registration made again changes nothing, here either (it used to count
        again, keeping the node's name and relays after its one unregister, and to
        rewrite the state file each time)."""
        if not _ros_ok(response) or not call.params:
            return
        node = call.params[0]
        registering = call.method.startswith("register") or call.method == "subscribeParam"
        if registering:
            api = _caller_api(call.method, call.params)
            if api is not None and self._api_of_node.setdefault(node, api) != api:
                self._forget_replaced_node(node)
                self._api_of_node[node] = api
        kept = self._kept(call.method, call.params)
        if registering and node in self._owners and kept == (call.method, tuple(call.params)):
            return  # an identical repeat
        self._record_registration(call.method, call.params)
        if registering:
            self._count_relay_refs(call.method, call.params, +1)
            if kept is not None and node in self._owners:
                # made again with other values (a topic's type, a service's URI): it
                # replaces the one kept, and the relays behind that one lose its count
                self._count_relay_refs(kept[0], kept[1], -1)
            else:
                entry = self._owners.setdefault(node, [manager, 0])
                if entry[1] == 0 and exact:
                    self._owned_by_pattern.discard(node)
                elif entry[1] == 0:
                    self._owned_by_pattern.add(node)
                entry[1] += 1
                self._holds.claim(node)
            self._note_param_subscription(call.method, call.params)
            self._save_state_soon()
        elif (call.method.startswith("unregister") or call.method == "unsubscribeParam") and \
                isinstance(response.value[2], int) and response.value[2] > 0:
            entry = self._owners.get(node)
            if entry is not None:
                entry[1] -= 1
                if entry[1] <= 0:
                    del self._owners[node]
                    self._owned_by_pattern.discard(node)
                    self._api_of_node.pop(node, None)
                    self._param_subs_of_node.pop(node, None)
                    self._holds.release(node, entry[0], self.cfg.limits.name_hold_seconds)
            if entry is not None or kept is not None:
                self._save_state_soon()
            # the relays behind the registration as it was made: unregisterService names
            # the service's URI, not the node API its registration counted too
            self._count_relay_refs(*(kept or (call.method, call.params)), -1)
            self._note_param_subscription(call.method, call.params)

    def _kept(self, method: str, params: tuple) -> tuple[str, tuple] | None:
        """The registration (or parameter subscription) a master call makes or releases,
        as it was forwarded when made ((method, params)), if it is kept."""
        key = _registration_key(method, params)
        if key is not None:
            return self._registrations.get(key)
        key = _param_subscription_key(method, params)
        if key is not None:
            params = self._param_subs_of_node.get(key[1], {}).get(key[2])
            return None if params is None else ("subscribeParam", params)
        return None

    def _note_param_subscription(self, method: str, params: tuple) -> None:
        key = _param_subscription_key(method, params)
        if key is None:
            return
        _kind, node, name = key
        if method == "subscribeParam":
            subs = self._param_subs_of_node.setdefault(node, {})
            if name in subs or len(subs) < MAX_PARAM_SUBSCRIPTIONS_PER_NODE:
                subs[name] = tuple(params)
        else:
            subs = self._param_subs_of_node.get(node)
            if subs is not None:
                subs.pop(name, None)
                if not subs:
                    del self._param_subs_of_node[node]

    def _record_registration(self, method: str, params: tuple) -> None:
        """Keep (or drop) one registration as it was forwarded to rosmaster."""
        key = _registration_key(method, params)
        if key is None:
            return
        node = key[1]
        if method.startswith("register"):
            if key not in self._registrations and len(self._registrations) >= MAX_REGISTRATIONS:
                if not self._registrations_full_logged:
                    self._registrations_full_logged = True
                    log.warning("%d registrations kept for rosmaster replay: more are not kept "
                                "(a restarted rosmaster will not learn them)", MAX_REGISTRATIONS)
                return
            self._registrations[key] = (method, tuple(params))
            self._keys_of_node.setdefault(node, set()).add(key)
            api = _caller_api(method, params)
            if api is not None:
                self._api_of_node.setdefault(node, api)
        elif self._registrations.pop(key, None) is not None:
            keys = self._keys_of_node.get(node)
            if keys is not None:
                keys.discard(key)
                if not keys:
                    del self._keys_of_node[node]

    def _forget_replaced_node(self, node: str) -> None:
        """``node`` registered from another API: rosmaster dropped every registration of
        the old one (a restarted node, or a name taken from a ``*`` holder), so the kept
        registrations, its parameter subscriptions, the relay counts behind them and the
        owner go too."""
        for key in self._keys_of_node.pop(node, ()):
            kept = self._registrations.pop(key, None)
            if kept is not None:
                self._count_relay_refs(kept[0], kept[1], -1)
        for params in self._param_subs_of_node.pop(node, {}).values():
            self._count_relay_refs("subscribeParam", params, -1)
        entry = self._owners.pop(node, None)
        self._owned_by_pattern.discard(node)
        log.info("node %s registered from another API: rosmaster dropped what it had registered before%s", node,
                 f" (by {entry[0]})" if entry else "")

    async def _watch_master(self) -> None:
        """Go past plain ROS: when rosmaster comes back with a new pid (restarted), every
        registration it held through this interceptor is replayed, so the graph comes
        back without restarting a node (rosmaster then tells subscribers their
        publishers with ``publisherUpdate``, as at first)."""
        while True:
            if self._judge_master_exposure():  # nothing replayed to a rosmaster other hosts reach
                await asyncio.sleep(MASTER_WATCH_INTERVAL)
                continue
            try:
                reply = await asyncio.wait_for(
                    self._call_upstream_master(Request(method="getPid", params=("/cryptoros",))), MASTER_WATCH_TIMEOUT)
                pid = reply.value[2] if _ros_ok(reply) and isinstance(reply.value[2], int) else None
            except (CryptorosError, OSError, asyncio.TimeoutError):
                pid = None
            if pid is not None and pid != self._master_pid:
                # a new pid, or the first one seen after a restart of ours with registrations
                # from state_dir (a repeated registration is harmless to rosmaster)
                if self._master_pid is not None:  # a new rosmaster holds no parameter
                    await self._replay_parameters(pid)
                if self._master_pid is not None or self._registrations:
                    await self._replay_registrations(pid)
                elif not self._relay_refs:  # restarted with no state: rosmaster still names our relays
                    await self._adopt_master_state()
                self._master_pid = pid
            await asyncio.sleep(MASTER_WATCH_INTERVAL)

    def _judge_master_exposure(self) -> bool:
        """Deployment check, each turn of the watch: True while rosmaster answers other
        hosts and ``allow_exposed_master`` is not set (master streams are refused then)."""
        problem = master_problem(self.cfg.master.upstream, self._exposure, self.cfg.source)
        if problem != self._master_exposed:
            if problem is None:
                log.warning("rosmaster answers on loopback only now: master streams are served again")
            elif self.cfg.allow_exposed_master:
                log.warning("allow_exposed_master = true, serving anyway: %s", problem)
            else:
                log.error("master streams refused (exposed_master) until fixed: %s", problem)
            self._master_exposed = problem
        return problem is not None and not self.cfg.allow_exposed_master

    async def _adopt_master_state(self) -> None:
        """Restarted with no state (master role): open again, on their old ports, the
        relays whose names rosmaster holds (every node API and service URI carries its
        canonical name, :meth:`Translator.from_master`), each counted once per
        registration behind it, so rosmaster reaches every node again at once. Who owns
        each name is not known again until the node registers anew."""
        try:
            state = await self._call_upstream_master(Request(method="getSystemState", params=("/cryptoros",)))
            if not _ros_ok(state):
                return
            publishers, subscribers, services = state.value[2]
            counts: dict[str, int] = {}
            for _name, nodes in (*publishers, *subscribers, *services):
                for node in nodes:
                    counts[node] = counts.get(node, 0) + 1
            uris = []
            for node, count in counts.items():
                reply = await self._call_upstream_master(Request(method="lookupNode", params=("/cryptoros", node)))
                if _ros_ok(reply) and isinstance(reply.value[2], str):
                    uris.append((reply.value[2], count))
            for service, _nodes in services:
                reply = await self._call_upstream_master(Request(method="lookupService", params=("/cryptoros", service)))
                if _ros_ok(reply) and isinstance(reply.value[2], str):
                    uris.append((reply.value[2], 1))
        except (CryptorosError, OSError, asyncio.TimeoutError, ValueError, TypeError) as exc:
            log.warning("cannot read rosmaster's graph to re-open our relays: %s", exc)
            return
        adopted = 0
        for uri, count in uris:
            with contextlib.suppress(CryptorosError):
                self.translator.from_master(uri)
            endpoint = _local_endpoint(uri)
            if endpoint is not None and self.translator.relay_target(*endpoint) is not None:
                self._relay_refs[endpoint] = self._relay_refs.get(endpoint, 0) + count
                adopted += 1
        if uris:
            log.warning("restarted with no state: %d relays rosmaster names re-opened (%d nodes, %d services)",
                        adopted, len(counts), len(services))

    async def _replay_parameters(self, pid: int) -> None:
        """Set again what peers set through us and did not delete (the parameter quota's
        table, :meth:`ParamQuota.items`: bounded per peer), in the order of the tree,
        before any new write of a peer."""
        async with self._param_writes:
            items = self._params.items()
            failed = 0
            for key, value in items:
                try:
                    reply = await self._call_upstream_master(Request(method="setParam", params=("/cryptoros", key, value)))
                    failed += not _ros_ok(reply)
                except (CryptorosError, OSError, asyncio.TimeoutError):
                    failed += 1
        log.warning("rosmaster (pid %d) is new: %d parameters replayed%s", pid, len(items),
                    f", {failed} failed" if failed else "")

    async def _replay_registrations(self, pid: int) -> None:
        calls = [Request(method=method, params=params) for method, params in self._registrations.values()]
        calls.sort(key=lambda c: c.method != "registerService")  # services, then topics
        failed = 0
        for call in calls:
            try:
                reply = await self._call_upstream_master(call)
                failed += not _ros_ok(reply)
            except (CryptorosError, OSError, asyncio.TimeoutError):
                failed += 1
        log.warning("rosmaster (pid %d) is new: %d registrations replayed%s", pid, len(calls),
                    f", {failed} failed" if failed else "")

    def _count_relay_refs(self, method: str, params: tuple, delta: int) -> None:
        """Relays the master holds URIs of: one count per registration behind each;
        a relay whose last registration was released is closed (its fd freed)."""
        for index in _RELAY_URI_INDEX.get(method, ()):
            uri = params[index] if len(params) > index else None
            endpoint = _local_endpoint(uri)
            if endpoint is None or self.translator.relay_target(*endpoint) is None:
                continue
            count = self._relay_refs.get(endpoint, 0) + delta
            if count > 0:
                self._relay_refs[endpoint] = count
                continue
            self._relay_refs.pop(endpoint, None)
            if delta < 0:
                self._release_relay(endpoint)

    def _release_relay(self, endpoint: tuple[str, int]) -> None:
        target = self.translator.relay_target(*endpoint)
        self.translator.forget_relay(*endpoint)
        pool = self._pools.pop((target.host, target.port, "node", target.id), None) if target else None
        if pool is not None:  # its tunnels to the node's interceptor are closed with it
            pool.close()
        server = self._relay_servers.pop(endpoint, None)
        if server is not None:
            server.close()
        sock = self._relay_socket_of.pop(endpoint, None)
        if sock is not None:
            sock.close()
        log.debug("relay %s:%d released (no registration behind it)", *endpoint)

    async def _serve_master_stream(self, stream: InboundStream) -> None:
        peer = stream.peer

        def to_local_from_peer(uri: str) -> str:
            target = Canonical.parse(uri)
            if target is None or target.host not in peer.hosts:
                raise PolicyDenied("endpoint_not_peer", f"{uri!r:.80} is not an endpoint of {peer.manager}")
            return self.translator.to_local(uri, named=True)  # named: rosmaster keeps it across our restarts

        def existing_from_peer(uri: str) -> str:
            # unregister*/unsubscribeParam never open a relay: an endpoint no relay was
            # opened for was never registered, so the call could match nothing.
            target = Canonical.parse(uri)
            if target is None or target.host not in peer.hosts:
                raise PolicyDenied("endpoint_not_peer", f"{uri!r:.80} is not an endpoint of {peer.manager}")
            local = self.translator.existing_local(uri, named=True)
            if local is None:
                raise PolicyDenied("unknown_endpoint", f"{uri!r:.80} was never registered through this interceptor")
            return local

        def decide(call: Request) -> Request:
            self._refuse_exposed_master()  # on streams opened before rosmaster was exposed too
            if not self._master_calls.allow(peer.manager):
                limits = self.cfg.limits
                raise PolicyDenied("rate_limited", f"{peer.manager} makes master calls faster than "
                                   f"{limits.max_master_calls_per_second:g} a second after {limits.master_call_burst} "
                                   f"(max_master_calls_per_second, master_call_burst; this is logged once per "
                                   f"{RATE_LOG_INTERVAL:g} s, every refusal counted)")
            grants = self.verifier.freshest(peer.access).grants  # decisions use the peer's freshest token
            check_master_call(call.method, call.params, manager=peer.manager, grants=grants,
                              owner_of=functools.partial(self._owner_of, grants=grants))
            call = _resolved_param_call(call, grants)
            self._check_node_limit(call, peer.manager)
            self._check_param_subscription(call, peer.manager)
            uri_map = existing_from_peer if call.method in _RELEASING_CALLS else to_local_from_peer
            call = rewrite_call(call, caller_api=uri_map, service_api=uri_map)
            call = _rewrite_param_api(call, uri_map)
            self._charge_param_write(call, peer.manager)  # last: only a call sent on is charged
            return call

        def after(call: Request, response: Response | Fault) -> Response | Fault:
            grants = self.verifier.freshest(peer.access).grants
            self._note_registration(call, response, peer.manager, exact=bool(call.params) and
                                    isinstance(call.params[0], str) and grants.names_node_exactly(call.params[0]))
            response = _filtered_param_reply(call, response, self.verifier.freshest(peer.access).grants)
            return rewrite_response(call, response, uri=self.translator.from_master)

        async def handle(request: Request) -> Response | Fault:
            if not _writes_params(request):
                return await self._decide_calls(request, decide, self._call_upstream_master, after, "master",
                                                peer.manager)
            # parameter writes reach rosmaster one request at a time, in the order they
            # were charged: a deleteParam racing a setParam cannot free what rosmaster keeps
            async with self._param_writes:
                return await self._decide_calls(request, decide, self._call_upstream_master, after, "master",
                                                peer.manager)

        await self._serve_xmlrpc(stream.reader, stream.writer, handle, stream.pending)

    async def _call_upstream_master(self, request: Request) -> Response | Fault:
        return await self._call_plain(self.cfg.master.upstream, request)

    async def _call_plain(self, uri: str, request: Request) -> Response | Fault:
        """One XML-RPC call to a local process (one connection per call)."""
        where = split_uri(uri, ("http",))
        host, port = where.host, where.port
        reader, writer = await asyncio.wait_for(asyncio.open_connection(host, port, limit=READ_SIZE), CALL_TIMEOUT)
        try:
            conn = XmlRpcConnection(Role.CLIENT, host=f"{host}:{port}", max_body_size=self.cfg.limits.max_xmlrpc_body)
            # The path is the one the node advertised, never one a peer wrote.
            outgoing = Request(method=request.method, params=request.params,
                               path=request_path(where.path), keep_alive=False, accept_gzip=True)
            writer.write(conn.send(outgoing))
            await asyncio.wait_for(writer.drain(), CALL_TIMEOUT)
            event = await read_xmlrpc(reader, conn, CALL_TIMEOUT)
            if isinstance(event, ConnectionClosed):
                raise RemoteProtocolError(f"{uri} closed without answering")
            return type(event)(**{**event.__dict__, "keep_alive": True})
        finally:
            writer.close()

    # ---------------------------------------------------------------- node side
    async def _serve_node_stream(self, stream: InboundStream) -> None:
        peer = stream.peer
        endpoint = stream.resolved  # resolved once, by the gate's target check

        def decide(call: Request) -> Request:
            check_node_call(
                call.method,
                call.params,
                grants=self.verifier.freshest(peer.access).grants,
                peer_is_master=peer.manager == self.cfg.master.manager,
                topic_types=self.topic_types,
            )
            return tcpros_only(rewrite_call(call, publisher_uri=self.translator.to_local))

        def tcpros_to_canonical(host: str, port: int) -> tuple[str, int]:
            self._check_local_port(lambda: self._node_of_api(stream.target), port, "TCPROS port")
            canonical, public_port = self.translator.tcpros_to_canonical(host, port)
            child = self.translator.own_id(canonical)
            if child is not None:  # this node's TCPROS server: released with its API
                self._note_export_child(stream.target, child)
            return canonical, public_port

        def after(call: Request, response: Response | Fault) -> Response | Fault:
            response = redact_node_reply(call, response, MASTER)
            return rewrite_response(call, response, tcpros=tcpros_to_canonical)

        async def handle(request: Request) -> Response | Fault:
            return await self._decide_calls(
                request, decide, lambda r: self._call_plain(endpoint.uri, r), after, "node", peer.manager
            )

        await self._serve_xmlrpc(stream.reader, stream.writer, handle, stream.pending)

    async def _serve_tcpros_stream(self, stream: InboundStream) -> None:
        reader, writer, peer, purpose = stream.reader, stream.writer, stream.peer, stream.purpose
        endpoint = stream.resolved  # resolved once, by the gate's target check
        limits = self.cfg.limits
        header, rest = await read_tcpros_header(
            reader, limits.handshake_timeout, limits.max_header_size, limits.max_header_fields, pending=stream.pending
        )
        fields = header.as_dict()

        def judge(grants) -> frozenset[str] | None:
            """The peer's side of this stream against its grants (again whenever it shows
            a fresher token: a removed grant cuts exactly the streams it covered)."""
            if purpose == "topic":
                if "topic" not in fields:
                    raise PolicyDenied("malformed", "topic stream without a topic header")
                published = self.topic_types.get(fields["topic"])
                check_subscriber_header(
                    fields, grants=grants, published_type=published, published_md5=_md5_or_none(published)
                )
                return None
            if "service" not in fields:
                raise PolicyDenied("malformed", "service stream without a service header")
            return check_service_client_header(fields, grants=grants)

        try:
            client_types = judge(self.verifier.freshest(peer.access).grants)
            if peer.watch is not None:
                peer.watch.set_recheck(lambda fresh: judge(fresh.grants))
        except PolicyDenied:
            writer.write(encode_header({"error": OPAQUE}))
            with contextlib.suppress(Exception):
                await asyncio.wait_for(writer.drain(), 1)
            raise
        local_reader, local_writer = await asyncio.wait_for(
            asyncio.open_connection(endpoint.host, endpoint.port, limit=READ_SIZE), limits.handshake_timeout
        )
        try:
            # Only the known fields, rebuilt from the parsed values, reach the node; what
            # followed the header (a service request) goes through the frame check below.
            local_writer.write(encode_header(canonical_header(header)))
            reply, reply_rest = await read_tcpros_header(local_reader, CALL_TIMEOUT, limits.max_header_size)
            reply_fields = reply.as_dict()
            if "error" in reply_fields:  # the node refused the stream on its own
                await _pass_refusal(writer, reply_fields["error"])
                local_writer.close()
                return
            own = self.gw.own_access()
            if purpose == "topic":
                check_publisher_header(reply_fields, grants=own.grants, topic=fields["topic"])
            else:
                check_service_server_header(
                    reply_fields, service=fields["service"], server_grants=own.grants, client_types=client_types
                )
        except BaseException as exc:
            local_writer.close()
            if isinstance(exc, PolicyDenied):
                writer.write(encode_header({"error": OPAQUE}))
            raise
        self.metrics.allowed.labels(purpose).inc()
        writer.write(encode_header(canonical_header(reply)))
        if purpose == "topic":
            # A subscriber sends nothing after its header: whatever it sends is dropped.
            # The monitor reads this host's own beacons (what its peers' poses are checked against).
            monitor = self.gw.monitor
            reference = monitor.watch_reference(
                manager=self.cfg.manager, publisher=reply_fields.get("callerid", "?"), topic=fields["topic"],
                typename=reply_fields.get("type", ""),
            ) if monitor is not None else None
            try:
                await self.gw.pump(reader, writer, local_reader, local_writer, left_pending=b"",
                                   right_pending=reply_rest, left_discard=True, endless=True,
                                   right_tap=reference.feed if reference is not None else None)
            finally:
                if reference is not None:
                    reference.close()
        else:
            # Service requests from the peer: size-checked, and counted against its budget.
            name = fields["service"]
            frames = FrameCounter(max_size=limits.message_size_for(name), what=f"{peer.manager} {name}")
            await self.gw.pump(reader, writer, local_reader, local_writer, left_pending=rest, right_pending=reply_rest,
                             left_budget=self.gw.budget(peer), left_frames=frames,
                             on_deny=lambda exc: self.gw.deny(purpose, exc, peer.manager))

    # ---------------------------------------------------------------- local master
    async def _on_local_master(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            await self._serve_xmlrpc(reader, writer, self._local_master_request)
        except (RemoteProtocolError, asyncio.TimeoutError, ConnectionError) as exc:
            log.warning("local master connection dropped: %s", exc)
        finally:
            writer.close()

    def _exposed_registration(self, request: Request) -> Response | None:
        """A local node registering endpoints other hosts reach: one ROS error line to
        it (each call of a multicall), naming the node, the port and the fix."""
        try:
            calls = expand_multicall(request, max_calls=self.cfg.limits.max_multicall)
            for warning in self._nodes_exposed.check_registrations(calls, allow=self.cfg.allow_exposed_nodes,
                                                                   config=self.cfg.source):
                log.warning("%s", warning)
        except RemoteProtocolError:
            return None  # _decide_calls refuses it
        except PolicyDenied as exc:
            self.gw.deny("local-master", exc, "local node")
            error = Response(value=ros_error(f"{OPAQUE}: {exc}"))
            return assemble_multicall([error] * len(calls)) if request.method == MULTICALL else error
        return None

    def _check_local_port(self, node: Callable[[], str], port: int, what: str) -> None:
        warning = self._nodes_exposed.check_port(node, port, what, allow=self.cfg.allow_exposed_nodes,
                                                 config=self.cfg.source)
        if warning:
            log.warning("%s", warning)

    def _node_of_api(self, api_id: str) -> str:
        return next((node for node, api in self._node_apis.items() if api == api_id), f"with API export {api_id}")

    async def _local_master_request(self, request: Request) -> Response | Fault:
        """One request of a local node to its master (a registration made again on a
        node's behalf goes the same way: :meth:`_regrant`)."""
        refusal = self._exposed_registration(request)
        if refusal is not None:
            return refusal
        # no token this instant (our manager re-enabled a moment ago): wait for one
        # refresh attempt rather than refuse a node that starts now
        await self.gw.keeper.ensure(LOCAL_TOKEN_WAIT)
        master = self.cfg.master.interceptor or self.cfg.public
        tunnel = self.pool(master.host, master.port, "master", "")
        return await self._decide_calls(request, self._local_decide, tunnel.call, self._local_after, "local-master",
                                        "local node")

    def _local_decide(self, call: Request) -> Request:
        own = self.gw.own_access()
        try:
            check_master_call(
                call.method, call.params, manager=own.subject, grants=own.grants, owner_of=lambda _node: None
            )
        except PolicyDenied as exc:
            if exc.reason == "not_granted" and self._ledger.refused(call.method, call.params):
                self._save_state_soon()  # kept: made if a grant comes while the node runs
            raise
        call = _resolved_param_call(call, own.grants)
        if call.method == "registerPublisher" and call.params[1] not in self.topic_types:
            self.topic_types[call.params[1]] = call.params[2]  # checked strings (check_master_call)
            self._topics_registering.add(call.params[1])
        call = rewrite_call(call, caller_api=self.translator.to_canonical, service_api=self.translator.to_canonical)
        return _rewrite_param_api(call, self.translator.to_canonical)

    def _local_after(self, call: Request, response: Response | Fault) -> Response | Fault:
        if call.method == "registerPublisher":
            registering = call.params[1] in self._topics_registering
            self._topics_registering.discard(call.params[1])
            if not _ros_ok(response):
                if registering:  # the master refused it: not published here after all
                    self.topic_types.pop(call.params[1], None)
            elif registering or self.topic_types.get(call.params[1]) != call.params[2]:
                self.topic_types[call.params[1]] = call.params[2]
                self._save_state()
        elif call.method in ("registerSubscriber", "unregisterSubscriber") and _ros_ok(response):
            self._note_local_subscriber(call)
        if call.method in _LOCAL_REGISTRATIONS and _ros_ok(response):
            self._note_local_node(call)
        if _ros_ok(response):
            self._track_local_registration(call)
        self._note_ledger(call, response)
        response = _filtered_param_reply(call, response, self.gw.own_access().grants)
        return rewrite_response(call, response, uri=self.translator.to_local)

    # ---------------------------------------------------------------- exports of restarted nodes
    def _note_local_node(self, call: Request) -> None:
        """A local node registered (call as forwarded: canonical URIs). A node that
        registers from a new API export was restarted: its old exports are released."""
        if len(call.params) < 4:
            return
        node, api_id = call.params[0], self.translator.own_id(call.params[3])
        if api_id is None:
            return
        if call.method == "registerService":
            service_id = self.translator.own_id(call.params[2])
            if service_id is not None:
                self._note_export_child(api_id, service_id)
        previous = self._node_apis.get(node)
        if previous == api_id:
            return
        if previous is not None:
            self._release_node_exports(previous)
        if len(self._node_apis) < self.translator.MAX_EXPORTS:
            self._node_apis[node] = api_id
        self._save_state_soon()

    def _track_local_registration(self, call: Request) -> None:
        """Count a local node's registrations; when the last one is released (a clean
        shutdown unregisters everything), its exports are released too."""
        key = _registration_key(call.method, call.params) or _param_subscription_key(call.method, call.params)
        if key is None:
            return
        kind, node, name = key
        if call.method.startswith(("register", "subscribe")):
            regs = self._node_registrations.setdefault(node, set())
            if len(regs) < 4096 and len(self._node_registrations) <= self.translator.MAX_EXPORTS:
                regs.add((kind, name))
            return
        regs = self._node_registrations.get(node)
        if regs is None:
            return
        regs.discard((kind, name))
        if regs:
            return
        del self._node_registrations[node]
        api_id = self._node_apis.get(node)
        if api_id is not None:
            self._release_node_exports(api_id, why="unregistered everything")
            self._save_state_soon()

    def _note_export_child(self, api_id: str, child: str) -> None:
        children = self._export_children.setdefault(api_id, set())
        if len(children) < 1024:  # a node's own servers; more is not remembered (kept, not released)
            children.add(child)

    def _release_node_exports(self, api_id: str, why: str = "restarted") -> None:
        released = [i for i in (*self._export_children.pop(api_id, ()), api_id) if self.translator.release(i)]
        for node in [n for n, i in self._node_apis.items() if i == api_id]:
            del self._node_apis[node]
        if released:
            log.info("released %d exports of a node that %s (API export %s)", len(released), why, api_id)

    # ---------------------------------------------------------------- a restart with no state
    async def _adopt_local_graph(self, patience: float = 120.0) -> None:
        """Started with no state (node role): this host's nodes may be running, registered
        under names of ours that rosmaster still holds. Take back their exports (an id
        says which loopback endpoint it names, :meth:`Translator.adopt`), the topics they
        publish, their subscriptions and registrations, and tell each subscriber its
        publishers, as after a restart with state. Only what the master's interceptor
        answers is adopted."""
        master = self.cfg.master.interceptor or self.cfg.public
        tunnel = self.pool(master.host, master.port, "master", "")

        async def ask(method: str, *params):
            reply = await tunnel.call(Request(method=method, params=("/cryptoros", *params)))
            return reply.value[2] if _ros_ok(reply) else None

        deadline, backoff = time.monotonic() + patience, 0.25
        while True:
            try:
                state = await ask("getSystemState")
                if state is None:
                    raise PolicyDenied("master_refused", "getSystemState")
                break
            except (CryptorosError, OSError, asyncio.TimeoutError) as exc:
                if time.monotonic() + backoff > deadline:
                    log.warning("started with no state, and rosmaster's graph cannot be read (%s): running nodes "
                                "of this host are not reached until they register again", exc)
                    return
                await asyncio.sleep(backoff)
                backoff = min(backoff * 2, 4.0)
        started = time.monotonic()
        try:
            publishers, subscribers, services = state
            types = dict(await ask("getTopicTypes") or [])
            own: dict[str, str] = {}  # node -> its local API
            for node in {n for _name, nodes in (*publishers, *subscribers, *services) for n in nodes}:
                uri = await ask("lookupNode", node)
                endpoint = self.translator.adopt(uri) if isinstance(uri, str) else None
                if endpoint is not None:
                    own[node] = endpoint.uri
                    self._node_apis.setdefault(node, self.translator.own_id(uri))
            for service, nodes in services:
                mine = [n for n in nodes if n in own]
                uri = await ask("lookupService", service) if mine else None
                if isinstance(uri, str) and self.translator.adopt(uri) is not None:
                    for node in mine:
                        self._node_registrations.setdefault(node, set()).add(("srv", service))
            for kind, section in (("pub", publishers), ("sub", subscribers)):
                for topic, nodes in section:
                    for node in (n for n in nodes if n in own):
                        self._node_registrations.setdefault(node, set()).add((kind, topic))
                        if kind == "pub" and topic in types:
                            self.topic_types.setdefault(topic, types[topic])
                            self._ledger.made("registerPublisher", (node, topic, types[topic], own[node]))
                        elif kind == "sub":
                            self._local_subscribers.setdefault(topic, {}).setdefault(node, own[node])
                            if topic in types:
                                self._ledger.made("registerSubscriber", (node, topic, types[topic], own[node]))
        except (CryptorosError, OSError, asyncio.TimeoutError, ValueError, TypeError) as exc:
            log.warning("started with no state; rosmaster's graph could not be read whole (%s)", exc)
            return
        log.log(logging.WARNING if own else logging.INFO,
                "started with no state: %d running nodes of this host adopted from rosmaster's graph "
                "(%d subscribed topics) in %.2f s", len(own), len(self._local_subscribers), time.monotonic() - started)
        self._save_state_soon()
        for topic in list(self._local_subscribers):
            self._resubscribe_soon(topic, delay=0.0)

    # ---------------------------------------------------------------- grants for running nodes
    def _note_ledger(self, call: Request, response: Response | Fault) -> None:
        """Keep a local node's registration (as the node sent it) made or refused by the
        master, and forget one it released (:mod:`interceptor.registrations`)."""
        if call.method in RELEASE:
            self._ledger.released(call.method, call.params)
        elif call.method in REGISTER:
            try:
                local = rewrite_call(call, caller_api=self.translator.to_local, service_api=self.translator.to_local)
            except CryptorosError:
                return
            if _ros_ok(response):
                waiting = self._ledger.get(local.method, local.params)
                self._ledger.made(local.method, local.params)
                if waiting is not None and waiting.refused:
                    self._save_state_soon()
            elif self._ledger.refused(local.method, local.params):
                self._save_state_soon()

    def _own_token_changed(self) -> None:
        """Our token changed (keeper listener): the grants it carries may cover
        registrations of running nodes they did not cover before."""
        if self.gw.started:
            self._regrant_wanted = True
            if not self._regranting:
                self._regranting = True
                self.gw.spawn(self._regrant(), "regrant")

    async def _regrant(self) -> None:
        """Make again, on their nodes' behalf, the registrations our new grants cover and
        the old ones did not (a grant added, or removed and added back), and every one
        refused that they cover now; tell each subscriber its publishers
        (``publisherUpdate``, as rosmaster does for a registration it accepts). Nodes
        that do not answer any more are forgotten."""
        try:
            while self._regrant_wanted:
                self._regrant_wanted = False
                try:
                    own = self.gw.own_access()
                except CryptorosError:
                    return
                before, self._grants_seen = self._grants_seen, own.grants
                if before == own.grants and not self._ledger.refused_count:
                    continue
                todo = self._ledger.to_resend(
                    lambda reg: covers(own.grants, own.subject, reg.method, reg.params),
                    None if before is None else lambda reg: covers(before, own.subject, reg.method, reg.params))
                if not todo:
                    continue
                started = time.monotonic()
                master = self.cfg.master.interceptor or self.cfg.public
                try:  # the master's interceptor judges by our freshest whole token: show it first
                    shown = await self.gw.open_tunnel(master.host, master.port, REFRESH, "", whole=True)
                    shown.writer.close()
                except (CryptorosError, OSError, asyncio.TimeoutError) as exc:
                    log.warning("cannot show the master's interceptor our new token (%s): %d registrations of "
                                "running nodes wait for the next one", exc, len(todo))
                    self._grants_seen = before
                    return
                made = 0
                for reg in todo:
                    made += await self._make_again(reg)
                log.warning("our grants changed: %d of %d registrations of running nodes made again in %.2f s",
                            made, len(todo), time.monotonic() - started)
        finally:
            self._regranting = False

    async def _make_again(self, reg: Registration) -> bool:
        api = reg.node_api
        try:
            if api is None or not _ros_ok(await self._call_plain(api, Request(method="getPid", params=("/master",)))):
                raise ConnectionError("no answer")
        except (CryptorosError, OSError, asyncio.TimeoutError):
            log.info("%s %s of %s not made again: the node does not answer", reg.method, reg.params[1], reg.params[0])
            self._ledger.released(reg.method, reg.params)
            return False
        response = await self._local_master_request(Request(method=reg.method, params=reg.params))
        if not _ros_ok(response):
            log.info("%s %s of %s made again: refused (%s)", reg.method, reg.params[1], reg.params[0],
                     response.value[1] if isinstance(response, Response) else response)
            return False
        if reg.method == "registerSubscriber":
            await self._tell_publishers(api, reg.params[1], response.value[2])
        return True

    async def _tell_publishers(self, api: str, topic: str, uris: list) -> None:
        """``publisherUpdate`` to a local subscriber, once each publisher's interceptor
        has our freshest token (it judges the subscriber's requestTopic by it)."""
        peers = {(t.host, t.port) for t in (self.translator.relay_target(*e) for e in map(_local_endpoint, uris) if e)
                 if t is not None}
        for peer in peers:
            with contextlib.suppress(CryptorosError, OSError, asyncio.TimeoutError):
                await self.gw.exchange_tokens(*peer)
        try:
            await self._call_plain(api, Request(method="publisherUpdate", params=("/master", topic, list(uris))))
        except (CryptorosError, OSError, asyncio.TimeoutError) as exc:
            log.info("publisherUpdate of %s to %s failed: %s", topic, api, exc)

    # ---------------------------------------------------------------- subscribers reconnect
    def _note_local_subscriber(self, call: Request) -> None:
        """Which local nodes subscribe what, and their node APIs (to nudge them)."""
        node, topic = call.params[0], call.params[1]
        api = call.params[3] if call.method == "registerSubscriber" else call.params[2]
        subscribers = self._local_subscribers.setdefault(topic, {})
        before = subscribers.get(node)
        if call.method == "registerSubscriber":
            subscribers[node] = self.translator.to_local(api)
        else:
            subscribers.pop(node, None)
            if not subscribers:
                del self._local_subscribers[topic]
        if subscribers.get(node) != before:  # a repeat changes nothing, and writes nothing
            self._save_state()

    def _resubscribe_soon(self, topic: str, delay: float = 0.5, via: tuple[str, int] | None = None) -> None:
        """A topic stream into this host ended: tell the topic's local subscribers the
        current publishers (``publisherUpdate``, as the master would), so rospy and
        roscpp connect again once the publisher's side is back (they retry a failed
        connect by themselves, but not a connection the other side closed). ``via``
        is the publisher's interceptor: waited for (a token exchange, backing off up
        to a minute) before the subscribers are told."""
        if topic not in self._local_subscribers or topic in self._resubscribing or not self.gw.started:
            return
        self._resubscribing.add(topic)

        async def nudge() -> None:
            try:
                await asyncio.sleep(delay)
                if via is not None:
                    await self._wait_reachable(via)
                uris = await self._publishers_of(topic)
                for node, api in list(self._local_subscribers.get(topic, {}).items()):
                    try:
                        await self._call_plain(api, Request(method="publisherUpdate", params=("/master", topic, uris)))
                    except (CryptorosError, OSError, asyncio.TimeoutError) as exc:
                        log.info("publisherUpdate of %s to %s failed: %s", topic, node, exc)
            except (CryptorosError, OSError, asyncio.TimeoutError) as exc:
                log.info("cannot list the publishers of %s: %s", topic, exc)
            finally:
                self._resubscribing.discard(topic)

        self.gw.spawn(nudge())

    async def _wait_reachable(self, endpoint: tuple[str, int], patience: float = 60.0) -> None:
        """Until a token exchange with a peer interceptor succeeds (or ``patience`` ends)."""
        deadline = time.monotonic() + patience
        backoff = 0.25
        while True:
            try:
                await self.gw.exchange_tokens(*endpoint)
                return
            except (CryptorosError, OSError, asyncio.TimeoutError):
                if time.monotonic() + backoff > deadline:
                    raise
                await asyncio.sleep(backoff)
                backoff = min(backoff * 2, 4.0)

    async def _publishers_of(self, topic: str) -> list[str]:
        """The topic's publishers as the master knows them, as URIs local nodes can call."""
        master = self.cfg.master.interceptor or self.cfg.public
        tunnel = self.pool(master.host, master.port, "master", "")
        state = await tunnel.call(Request(method="getSystemState", params=("/cryptoros",)))
        if not _ros_ok(state):
            raise PolicyDenied("master_refused", f"getSystemState: {state!r:.80}")
        nodes = next((names for name, names in state.value[2][0] if name == topic), [])
        uris = []
        for node in nodes:
            reply = await tunnel.call(Request(method="lookupNode", params=("/cryptoros", node)))
            if _ros_ok(reply) and isinstance(reply.value[2], str):
                uris.append(self.translator.to_local(reply.value[2]))
        return uris

    # ---------------------------------------------------------------- relays
    async def _on_xmlrpc_relay(self, reader, writer, target: Canonical) -> None:
        """A local process calls a remote node's API (or the master calls a node's)."""
        tunnel = self.pool(target.host, target.port, "node", target.id)

        def decide(call: Request) -> Request:
            if call.method == "shutdown":
                raise PolicyDenied("shutdown_dropped", "node shutdown is never forwarded")
            # rosmaster's publisherUpdate through the relay of a subscriber: its relay names
            return tcpros_only(rewrite_call(call, publisher_uri=self.translator.from_master))

        # the publisher's address must be the answering interceptor's own (see tcpros_to_local)
        tcpros = functools.partial(self.translator.tcpros_to_local, via=(target.host, target.port))

        def after(call: Request, response: Response | Fault) -> Response | Fault:
            return rewrite_response(call, response, tcpros=tcpros)

        async def handle(request: Request) -> Response | Fault:
            return await self._decide_calls(request, decide, tunnel.call, after, "relay", str(target))

        try:
            await self._serve_xmlrpc(reader, writer, handle)
        except (RemoteProtocolError, asyncio.TimeoutError, ConnectionError) as exc:
            log.warning("relay %s dropped: %s", target, exc)
        finally:
            writer.close()

    async def _on_tcpros_relay(self, reader, writer, target: Canonical) -> None:
        """A local subscriber or service client connects to a remote TCPROS server."""
        self.gw.track(self._tcpros_relay(reader, writer, target))

    async def _tcpros_relay(self, reader, writer, target: Canonical) -> None:
        limits = self.cfg.limits
        tunnel_writer = None
        tunnel: Tunnel | None = None
        unwatch: Callable[[], None] = lambda: None  # noqa: E731  (until the peer's stream is watched)
        try:
            header, rest = await read_tcpros_header(
                reader, limits.handshake_timeout, limits.max_header_size, limits.max_header_fields
            )
            fields = header.as_dict()
            own = self.gw.own_access()
            if "topic" in fields:
                purpose = "topic"
                check_local_subscriber_header(fields, grants=own.grants)
            elif "service" in fields:
                purpose = "service"
                client_types = check_service_client_header(fields, grants=own.grants)
            else:
                raise PolicyDenied("malformed", "TCPROS header with neither topic nor service")
            tunnel = await self.gw.open_tunnel(
                target.host, target.port, purpose, target.id, first=encode_header(canonical_header(header)) + rest,
                settles=True,
            )
            tunnel_reader, tunnel_writer, peer = tunnel.reader, tunnel.writer, tunnel.peer
            unwatch = self.verifier.watch(peer.access, lambda _r: tunnel_writer.transport.abort())
            reply, reply_rest = await read_tcpros_header(
                tunnel_reader, CALL_TIMEOUT, limits.max_header_size, limits.max_header_fields, pending=tunnel.pending
            )
            reply_fields = reply.as_dict()
            if "error" in reply_fields:  # the far side refused the stream: nothing is pumped
                await _pass_refusal(writer, reply_fields["error"])
                tunnel_writer.close()
                writer.close()
                return

            if purpose == "topic":  # a subscriber of any type: what it gets
                check_subscribed_type(fields, reply_fields.get("type", ""), grants=own.grants)

            def judge(grants) -> None:
                """The publisher's (server's) side against its grants, again on each fresher token."""
                if purpose == "topic":
                    check_publisher_header(reply_fields, grants=grants, topic=fields["topic"])
                else:
                    check_service_server_header(
                        reply_fields, service=fields["service"], server_grants=grants, client_types=client_types
                    )

            judge(self.verifier.freshest(peer.access).grants)
            unwatch.set_recheck(lambda fresh: judge(fresh.grants))
            monitor, watched, unregister = self.gw.monitor, None, None
            if monitor is not None and purpose == "topic":
                publisher = reply_fields["callerid"]
                monitor.check_admission(peer.manager, publisher)
                unregister = monitor.register(peer.manager, publisher, tunnel_writer.transport.abort)
                watched = monitor.watch(manager=peer.manager, publisher=publisher, topic=fields["topic"],
                                        typename=reply_fields.get("type") or fields["type"],
                                        cut=tunnel_writer.transport.abort)
                if watched is None and monitor.settings.gates(fields["topic"]):  # never unscored
                    raise PolicyDenied("monitor_busy", f"{fields['topic']} is gated by the monitor, which "
                                                       "watches as many streams as it may")
            writer.write(encode_header(canonical_header(reply)))
            tunnel.settle()  # set up: the spare for the next stream to this peer may be made now
            self.metrics.open_streams.labels(purpose).inc()
            try:
                # What the peer sends into this host (messages it publishes, replies of
                # its service) is size-checked frame by frame before a byte is relayed;
                # published messages count against its budget.
                name = fields.get("topic") or fields["service"]
                frames = FrameCounter(
                    max_size=limits.message_size_for(name), service_response=purpose == "service",
                    what=f"{peer.manager} {name}",
                )
                budget = self.gw.budget(peer) if purpose == "topic" else None
                await self.gw.pump(tunnel_reader, tunnel_writer, reader, writer, left_pending=reply_rest,
                                 right_pending=b"", left_budget=budget, left_frames=frames,
                                 on_deny=lambda exc: self.gw.deny("relay", exc, str(target)),
                                 endless=purpose == "topic",
                                 **_monitor_hooks(watched, monitor is not None and monitor.settings.gates(name)))
            finally:
                if watched is not None:
                    watched.close()
                if unregister is not None:
                    unregister()
                unwatch()
                self.metrics.open_streams.labels(purpose).dec()
                if purpose == "topic":
                    self._resubscribe_soon(fields["topic"], via=(target.host, target.port))
        except (CryptorosError, asyncio.TimeoutError, ConnectionError, OSError) as exc:
            if isinstance(exc, CryptorosError):
                self.gw.deny("relay", exc, str(target))
                with contextlib.suppress(Exception):
                    writer.write(encode_header({"error": OPAQUE}))
            if tunnel_writer is not None:
                tunnel_writer.close()
            writer.close()
        finally:
            if tunnel is not None:
                tunnel.settle()
            # a stream refused after its peer's token was watched (a publisher header not
            # granted, a quarantined publisher) must not stay in the verifier's watch list:
            # a subscriber retries such a stream every few seconds, for as long as it runs
            unwatch()


async def _pass_refusal(writer: asyncio.StreamWriter, error: str) -> None:
    """A TCPROS server refused a stream with an ``error`` header: the refusal goes on to
    the client, rebuilt from the parsed text, and nothing after it (the stream ends)."""
    writer.write(encode_header({"error": error}))
    with contextlib.suppress(Exception):
        await asyncio.wait_for(writer.drain(), 1)


def _monitor_hooks(watched: Any, gated: bool) -> dict[str, Any]:
    """How the pump hands a peer's messages to the monitor: a gated topic's are scored
    before they go on (``left_gate``), every other watched one's are queued after."""
    if watched is None:
        return {}
    return {"left_gate": watched.gate} if gated else {"left_tap": watched.feed}


#: Local registrations whose caller_api (index 3) names the registering node's API.
_LOCAL_REGISTRATIONS = frozenset({"registerPublisher", "registerSubscriber", "registerService"})

#: Where the URIs of a master call sit that are relays at the master's interceptor.
_RELAY_URI_INDEX = {
    "registerPublisher": (3,), "registerSubscriber": (3,), "registerService": (2, 3), "subscribeParam": (1,),
    "unregisterPublisher": (2,), "unregisterSubscriber": (2,), "unregisterService": (2,), "unsubscribeParam": (1,),
}


def _caller_api(method: str, params: tuple) -> str | None:
    """The node API a registration gives rosmaster (None: not a registration): the last
    of the URIs :data:`_RELAY_URI_INDEX` names (a service's own URI comes before it)."""
    indexes = _RELAY_URI_INDEX.get(method) if method.startswith("register") or method == "subscribeParam" else None
    value = params[indexes[-1]] if indexes and len(params) > indexes[-1] else None
    return value if isinstance(value, str) else None


def _registration_key(method: str, params: tuple) -> tuple[str, str, str] | None:
    """Which registration a master call makes or releases: (kind, node, name)."""
    kind = {"registerPublisher": "pub", "unregisterPublisher": "pub", "registerSubscriber": "sub",
            "unregisterSubscriber": "sub", "registerService": "srv", "unregisterService": "srv"}.get(method)
    if kind is None or len(params) < 2 or not all(isinstance(p, str) for p in params):
        return None
    return kind, params[0], params[1]


def _param_subscription_key(method: str, params: tuple) -> tuple[str, str, str] | None:
    """A parameter subscription made or released: ("param", node, key)."""
    if method not in ("subscribeParam", "unsubscribeParam") or len(params) < 3:
        return None
    if not all(isinstance(p, str) for p in params[:3]):
        return None
    return "param", params[0], params[2]


def _local_endpoint(uri) -> tuple[str, int] | None:
    try:
        return host_port(uri)
    except UriError:
        return None


def _writes_params(request: Request) -> bool:
    """Whether a request (a multicall: one of its calls) is setParam or deleteParam."""
    if request.method in PARAM_WRITE:
        return True
    calls = request.params[0] if request.method == MULTICALL and request.params else None
    return isinstance(calls, list) and any(isinstance(c, dict) and c.get("methodName") in PARAM_WRITE for c in calls)


def _resolved_param_call(call: Request, grants) -> Request:
    """A parameter call sent on with its key resolved as rosmaster would (checked)."""
    if call.method not in PARAM_READ and call.method not in PARAM_WRITE:
        return call
    params = check_param_call(call.method, call.params, grants=grants)
    return Request(method=call.method, params=params, path=call.path, keep_alive=call.keep_alive,
                   accept_gzip=call.accept_gzip)


def _filtered_param_reply(call: Request, response: Response | Fault, grants) -> Response | Fault:
    """Parameter replies narrowed to what the caller may read."""
    if not isinstance(response, Response) or (call.method not in PARAM_READ and call.method != "getParamNames"):
        return response
    value = filter_param_reply(call.method, call.params, response.value, grants=grants)
    return response if value is response.value else Response(value=value, keep_alive=response.keep_alive)


def _rewrite_param_api(call: Request, fn: Callable[[str], str]) -> Request:
    index = PARAM_CALLER_API_INDEX.get(call.method)
    if index is None or len(call.params) <= index or not isinstance(call.params[index], str):
        return call
    params = call.params[:index] + (fn(call.params[index]),) + call.params[index + 1 :]
    return Request(method=call.method, params=params, path=call.path, keep_alive=call.keep_alive,
                   accept_gzip=call.accept_gzip)


def _md5_or_none(type_name: str | None) -> str | None:
    if type_name is None:
        return None
    try:
        return msgs.md5sum(type_name)
    except Exception:  # a type outside the known typestore: the publisher itself checks md5
        return None


__all__ = ["Ros1Role", "TunnelPool", "XmlRpcTunnel", "read_tcpros_header", "read_xmlrpc"]