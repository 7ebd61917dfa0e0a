"""The ROS 1 role composed: its purposes served, its life cycle, status and the XML-RPC
serving loop every part uses."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import socket
import time
from collections.abc import Awaitable, Callable

from cryptoros.errors import CryptorosError, PolicyDenied, RemoteProtocolError
from cryptoros.memory import tune_malloc
from cryptoros.policy.hints import grant_hint
from cryptoros.policy.ros1 import (
    OWN_TOKEN_REASONS,
    refusal_answer,
    refusal_text,
    ros_error,
)
from cryptoros.ratelimit import OncePer, TokenBuckets
from cryptoros.ros1 import msgs
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
    split_multicall_response,
)
from cryptoros.grants import Grants
from cryptoros.tunnel import Preamble
from interceptor.exposure import NodeGuard, PortExposure
from interceptor.gate import Target
from interceptor.gateway import Gateway
from interceptor.gateway import Role as GatewayRole
from interceptor.name_holds import NameHolds
from interceptor.param_quota import ParamQuota
from interceptor.registrations import LocalRegistrations
from interceptor.ros1.answers import TopicAnswers
from interceptor.ros1.ledger import MasterLedger
from interceptor.ros1.master_side import MasterSide
from interceptor.ros1.notices import Notices
from interceptor.ros1.refusals import REFUSED_MEMORY, RefusedStreams
from interceptor.ros1.localcalls import LocalCalls
from interceptor.ros1.node_side import NodeSide
from interceptor.ros1.relays import Relays
from interceptor.ros1.state import PersistedState
from interceptor.ros1.tunnels import TunnelPool, XmlRpcTunnel
from interceptor.slots import KeyedSlots
from interceptor.ros1.wire import (
    CALL_TIMEOUT,
    IDLE_TIMEOUT,
    MASTER_DOWN_AFTER,
    MAX_POOLS,
    MULTICALL_ANSWERS,
    OPAQUE,
    RATE_LOG_INTERVAL,
    UNANSWERED,
    UNANSWERED_REASONS,
    log,
    read_xmlrpc,
    value_size,
)
from interceptor.streams import drain_within, read_into
from interceptor.translate import KIND_TCPROS, KIND_XMLRPC, Translator


#: calls a multicall forwards together: their answers are small whatever is stored
#: (roslaunch sets its parameters in one multicall). Every other call goes alone:
#: rosmaster builds a multicall's whole answer before a byte of it is checked (96 reads
#: of an insider's own 3.6 MB took rosmaster to 716 MB; 256 getParamNames of its 3,000
#: names, 438 MB); alone, each answer is bounded by one.
BATCHED_IN_MULTICALL = frozenset({
    "setParam", "deleteParam", "hasParam", "searchParam", "unsubscribeParam", "lookupNode", "lookupService",
    "getUri", "getPid", "registerService", "unregisterService", "unregisterPublisher", "unregisterSubscriber",
})


def _told(exc: BaseException) -> str | None:
    """The reason a refused caller may be told (:func:`refusal_text` shows it if it is
    one to show): a protocol error's reason (``malformed``, from our parser, the call's
    or an answer's) is not told, the caller gets the plain refusal."""
    return exc.reason if isinstance(exc, CryptorosError) and not isinstance(exc, RemoteProtocolError) else None


def _batches(allowed: list[tuple[int, Request]]) -> list[list[tuple[int, Request]]]:
    """The allowed calls of a multicall in the order given, as the multicalls forwarded
    one after the other: runs of :data:`BATCHED_IN_MULTICALL` calls together, every
    other call on its own."""
    out: list[list[tuple[int, Request]]] = []
    run: list[tuple[int, Request]] = []
    for item in allowed:
        if item[1].method in BATCHED_IN_MULTICALL:
            run.append(item)
            continue
        if run:
            out.append(run)
            run = []
        out.append([item])
    if run:
        out.append(run)
    return out


#: the most bytes of an XML-RPC answer handed to a stream at once (see _answer)
WRITE_SLICE = 256 << 10


async def _answer(
    request: Request,
    writer: asyncio.StreamWriter,
    conn: XmlRpcConnection,
    handle: Callable[[Request], Awaitable[Response | Fault]],
    admit: Callable[[Request, contextlib.AsyncExitStack], Awaitable[Response | None]] | None,
) -> None:
    """Answer one request of :meth:`Ros1Role._serve_xmlrpc` and write the answer out."""
    async with contextlib.AsyncExitStack() as held:
        response = await admit(request, held) if admit is not None else None
        if response is None:
            response = await handle(request)
        if not request.keep_alive:
            response = type(response)(**{**response.__dict__, "keep_alive": False})
        data = conn.send(response)
        del response
        # in slices, each written out before the next: a TLS connection's memory BIO keeps the
        # largest write it was given for the connection's life (each of 60 streams answered
        # 13.5 MB in one write held about 14 MB until it closed)
        for start in range(0, len(data), WRITE_SLICE):
            writer.write(data[start:start + WRITE_SLICE])
            await drain_within(writer, CALL_TIMEOUT)


class Ros1Role(MasterSide, NodeSide, Relays, PersistedState, GatewayRole):
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
            on_change=self._save_state_soon,
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
        #: master role: owners of node names (and names released, held for their owner a
        #: while), the registrations kept for a restarted rosmaster, relay counts
        self._master_ledger = MasterLedger(NameHolds(cfg.limits.max_nodes_per_peer),
                                           lambda endpoint: self.translator.relay_target(*endpoint) is not None)
        #: master role: master calls per peer manager ([limits] max_master_calls_per_second)
        self._master_calls = self._master_call_buckets()
        self._rate_log = OncePer(RATE_LOG_INTERVAL, max_keys=1024)
        #: master role: what each peer manager stored in rosmaster through setParam, and the
        #: lock its parameter writes go to rosmaster under (in the order they are charged)
        self._params = ParamQuota(cfg.limits.max_param_keys_per_peer, cfg.limits.max_param_bytes_per_peer)
        if "master" in cfg.roles:  # learning mode never widens a peer over another manager's values
            gateway.learner.state.param_owners = lambda key: self._params.owners(key)
        self._param_writes = asyncio.Lock()
        #: master role: each peer manager's calls in flight to rosmaster, and its parameter
        #: reads among them (wire.MASTER_CALLS_PER_PEER, PARAM_READS_PER_PEER)
        self._peer_master_calls = KeyedSlots()
        self._peer_param_reads = KeyedSlots()
        #: one per peer endpoint called, the least recently used first (see pool())
        self._pools: dict[tuple[str, int, str, str], TunnelPool] = {}
        self._tunnels_closed_idle = 0
        self._servers: list[asyncio.AbstractServer] = []
        #: connections kept alive to local XML-RPC servers (the master, local nodes' APIs)
        self._local_calls = LocalCalls(max_body=cfg.limits.max_xmlrpc_body)
        self._relay_socket_of: dict[tuple[str, int], socket.socket] = {}
        self._relay_servers: dict[tuple[str, int], asyncio.AbstractServer] = {}
        self._state_loaded = False
        self._state_dirty = False  # changed since last written
        self._save_task: asyncio.Task | None = None  # the write to come (_save_state_soon)
        self._state_saves = 0  # state files written (/status: a repeat registration writes none)
        self._local_subscribers: dict[str, dict[str, str]] = {}  # topic -> {node: local node API}
        #: publishers' requestTopic answers, shared by the subscribers starting at once
        self._topic_answers = TopicAnswers()
        #: master role: rosmaster's notifications to remote nodes, answered at once (notices.py)
        self._notices = Notices(self._deliver_notice, gateway.track) if "master" in cfg.roles else None
        self._resubscribing: set[str] = set()
        #: set (and replaced) when our own token changes: waits for a peer cut short (_wait_reachable)
        self._token_news: asyncio.Event | None = None
        #: node role: topic streams refused to this host's subscribers, by the manager whose
        #: side refused or would have sent them, and when to tell their subscribers again
        self._refused_streams = RefusedStreams()
        self._refusal_log = OncePer(REFUSED_MEMORY, max_keys=1024)
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
        #: master role: since when (monotonic) rosmaster has not answered the watch, and why
        self._master_silent_since: float | None = None
        self._master_silence = ""
        #: master role: nodes that registered with rosmaster directly, when each was last
        #: looked at, and those whose API other hosts reach (node -> status text)
        self._direct_checked: dict[str, float] = {}
        self._direct_exposed: dict[str, str] = {}
        self._owned_names_taken = False  # rosmaster told a robot's node to shut down (relays.py)
        self._exposed_ports: frozenset[int] = frozenset()  # ports other hosts reach, at the last look
        self._direct_looked_at = float("-inf")  # when (monotonic) the nodes were last looked at
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
        self.gw.source_listeners.append(self._save_state_soon)

    async def start(self) -> None:
        if "node" in self.cfg.roles:
            lm = self.cfg.local_master
            self._servers.append(await self.gw.start_local_server("local master", lm, self._on_local_master,
                                                                  host=lm.host, port=lm.port))
            with contextlib.suppress(CryptorosError):
                self._grants_seen = self.gw.own_access().grants
            self.gw.keeper.listeners.append(self._own_token_changed)
            self.verifier.fresh_listeners.append(self._peer_token_fresher)
            if self._ledger.refused_count:  # kept from before our restart: our token may cover them now
                self._own_token_changed()
            if not self.translator.export_count:
                self.gw.spawn(self._adopt_local_graph(), "adopt-graph")  # no state: ask rosmaster
            self.gw.spawn(self._sweep_dead_nodes(), "dead-node-sweep")
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
        self._local_calls.close()
        for sock in self._relay_socket_of.values():
            sock.close()
        self._relay_socket_of.clear()
        await self._flush_state()

    def reloaded(self) -> None:
        """The limits this role keeps a copy of: the next relay, held name, master call and
        parameter write count by the new ones."""
        limits = self.cfg.limits
        self.translator.max_relays_per_host = limits.max_relays_per_peer
        self._master_ledger.holds.per_manager = limits.max_nodes_per_peer
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
                         "state_saves": self._state_saves, "topic_answers_shared": self._topic_answers.shared,
                         **({"notices": {"delivered": self._notices.delivered, "replaced": self._notices.replaced,
                                         "dropped": self._notices.dropped, "pending": self._notices.pending()}}
                            if self._notices is not None else {}),
                         "state_save_pending": self._state_dirty or self._save_task is not None,
                         "param_usage": {m: list(u) for m, u in self._params.all_usage().items()}},
                "warnings": self._deployment_warnings()}

    def _deployment_warnings(self) -> list[str]:
        warnings = self._nodes_exposed.warnings()
        if self._master_exposed:
            what = ("allow_exposed_master = true, served anyway" if self.cfg.allow_exposed_master
                    else "master streams refused (exposed_master)")
            warnings.append(f"{what}: {self._master_exposed}")
        if self._direct_exposed:
            named = list(self._direct_exposed.values())
            warnings.append("nodes on this host registered with rosmaster directly, reachable from other hosts: "
                            + ", ".join(named[:8]) + (f" and {len(named) - 8} more" if len(named) > 8 else ""))
        return warnings

    def _count_idle_close(self) -> None:
        self._tunnels_closed_idle += 1

    # ================================================================ targets the gate checks
    def _check_master_target(self, preamble: Preamble) -> Target:
        """Master streams: each call is judged as it comes (no judge for the stream)."""
        if "master" not in self.cfg.roles:
            raise PolicyDenied("no_master_here", "this interceptor does not front a master")
        self._refuse_exposed_master()
        return Target()

    def _refuse_exposed_master(self) -> None:
        problem = self._exposure_problem()
        if problem is not None:
            raise problem

    def problem(self) -> PolicyDenied | None:
        """What health and status report: a deployment problem, or (master role) a
        rosmaster that has not answered the watch for MASTER_DOWN_AFTER seconds (robots'
        calls then fail one by one; status had said ok)."""
        problem = self._exposure_problem()
        if problem is None and self._master_silent_since is not None and \
                time.monotonic() - self._master_silent_since >= MASTER_DOWN_AFTER:
            problem = PolicyDenied("master_down", f"rosmaster at {self.cfg.master.upstream} does not answer "
                                                  f"({self._master_silence}): start it, on loopback "
                                                  f"(cryptoros run --config {self.cfg.source or 'FILE'} -- "
                                                  "rosmaster --core)")
        return problem

    def _exposure_problem(self) -> PolicyDenied | None:
        if self._master_exposed and not self.cfg.allow_exposed_master:
            return PolicyDenied("exposed_master", self._master_exposed)
        try:  # every local master call is refused meanwhile (NodeGuard.check_host): health says why
            self._nodes_exposed.check_host()
        except PolicyDenied as exc:
            return exc
        return None

    def _check_node_target(self, preamble: Preamble) -> Target:
        """An exported node API: each call is judged as it comes."""
        return Target(self.translator.resolve(KIND_XMLRPC, preamble.target))

    def _check_tcpros_target(self, preamble: Preamble) -> Target:
        """An exported TCPROS server: its judge is declared once the header is read
        (:meth:`~interceptor.ros1.node_side.NodeSide._serve_tcpros_stream`)."""
        return Target(self.translator.resolve(KIND_TCPROS, preamble.target))



    def pool(self, host: str, port: int, purpose: str, target: str) -> TunnelPool:
        """The tunnel pool to one peer endpoint (the least recently used of more than
        :data:`MAX_POOLS` is closed)."""
        key = (host, port, purpose, target)
        pool = self._pools.pop(key, None)
        if pool is None:
            limits = self.cfg.limits
            pool = TunnelPool(functools.partial(XmlRpcTunnel, self.gw.open_tunnel, host, port, purpose, target,
                                                max_body=limits.max_xmlrpc_body),
                              idle_timeout=limits.tunnel_idle_timeout, on_idle_close=self._count_idle_close)
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
        admit: Callable[[Request, contextlib.AsyncExitStack], Awaitable[Response | None]] | None = None,
    ) -> None:
        """Answer XML-RPC requests on a stream until it closes (``pending``: bytes
        already read from it, parsed first). A request that does not parse (bad head,
        oversized declared body, bad XML) is answered with one ROS error triple and the
        connection is cut without reading the rest. ``admit`` (if given) is awaited
        first for each request: it enters what the request holds into the stack, kept
        until its answer is written out (the peer has read all but the transport's
        high-water mark), or returns the answer that refuses it."""
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
            keep_alive = event.keep_alive
            await _answer(event, writer, conn, handle, admit)
            # neither the request nor its answer is kept while the stream waits for the
            # next (a kept-alive stream had held its last answer: 27 MB per stream after an
            # insider's getParam of 13.5 MB on each of 30 streams)
            del event
            if not keep_alive:
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
        # this host's own nodes and tools (its local master, its relays) are told why our
        # own token cannot be used (no_token ...); a peer never is
        own = kind in ("local-master", "relay")
        for i, call in enumerate(calls):
            try:
                allowed.append((i, decide(call)))
                self.metrics.allowed.labels(kind).inc()
            except CryptorosError as exc:  # a policy denial, a malformed call, no token of ours
                reason = exc.reason
                flood = reason == "rate_limited"
                self.gw.deny(kind, exc, f"{who} {call.method}", logged=not flood or self._rate_log(who),
                             hint=grant_hint(exc, call.method, call.params, manager))
                # as rosmaster answers an error ([-1, "denied by cryptoros: <reason>", 0], never
                # a fault, which tools print as a traceback); a probe of a parameter the caller
                # may not read as if it were not set
                results[i] = Response(value=refusal_answer(_told(exc), call.method, call.params, own=own))
        multicall = request.method == MULTICALL
        # a multicall's answers are kept until the last: together at most MULTICALL_ANSWERS
        # (an insider's one multicall of 256 reads of its own 13.5 MB took the master's
        # interceptor to 13.5 GB and held robot A's master calls 30 s)
        budget = max(MULTICALL_ANSWERS, self.cfg.limits.max_master_reply)
        for batch in (_batches(allowed) if multicall else [allowed] if allowed else []):
            if multicall and budget < 0:
                for i, _ in batch:
                    results[i] = Response(value=ros_error(refusal_text("answer_too_large")))
                continue
            outgoing = make_multicall([c for _, c in batch], like=request) if multicall else batch[0][1]
            answered = False
            try:
                reply = await forward(outgoing)
                answered = True
                parts = split_multicall_response(reply, len(batch)) if multicall else [reply]
                for (i, call), part in zip(batch, parts, strict=True):
                    results[i] = after(call, part)
                    if multicall:
                        budget -= value_size(getattr(results[i], "value", None), budget)
                if multicall and budget < 0:
                    self.gw.deny(kind, PolicyDenied("answer_too_large", f"a multicall's answers past "
                                                    f"{max(MULTICALL_ANSWERS, self.cfg.limits.max_master_reply)} B "
                                                    "together: its later calls refused"), f"{who} {MULTICALL}")
            except (CryptorosError, ConnectionError, OSError, asyncio.TimeoutError) as exc:
                unanswered = not isinstance(exc, CryptorosError) or exc.reason in UNANSWERED_REASONS
                if unanswered:
                    log.warning("%s call from %s got no answer: %s", kind, who, exc or type(exc).__name__)
                elif not answered and exc.reason not in OWN_TOKEN_REASONS:
                    # the answer itself was refused (too large, malformed): not the caller's doing;
                    # a refusal of our own (no token, a stale feed: no stream opened) is a denial
                    log.warning("%s call from %s: its answer was refused: %s", kind, who, exc)
                else:
                    self.gw.deny(kind, exc, who)
                for i, _ in batch:
                    results[i] = Response(value=ros_error(UNANSWERED if unanswered else refusal_text(_told(exc), own=own)))
        if request.method == MULTICALL:
            return assemble_multicall(results)  # type: ignore[arg-type]
        return results[0]  # type: ignore[return-value]

