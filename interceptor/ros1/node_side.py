"""The node role: this host's nodes behind the local master, their exported node APIs
and TCPROS servers judged per peer stream, grants reaching running nodes, subscribers
reconnected after restarts."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable

from cryptoros.errors import PEER_FAILURES, CryptorosError, PolicyDenied, RemoteProtocolError
from cryptoros.exposure import ExposureError, read_listeners
from cryptoros.policy.ros1 import (
    check_master_call,
    check_node_call,
    check_publisher_header,
    check_service_client_header,
    check_service_server_header,
    check_subscriber_header,
    refused_reason,
    ros_error,
)
from cryptoros.ros1.rewrite import (
    redact_node_reply,
    rewrite_call,
    rewrite_response,
    tcpros_only,
)
from cryptoros.ros1.tcpros import canonical_header, encode_header
from cryptoros.ros1.xmlrpc import (
    MULTICALL,
    Fault,
    Request,
    Response,
    assemble_multicall,
    expand_multicall,
)
from cryptoros.tokens import AccessToken
from interceptor.exposure import is_this_host
from interceptor.gate import REFRESH
from interceptor.pump import FrameCounter
from interceptor.ros1.refusals import TELLINGS_PER_SECOND
from interceptor.ros1.localcalls import (
    EXPOSED_SHUTDOWN_DELAY,
    REPEAT_SHUTDOWN_DELAY,
    ask_to_shut_down,
    shut_down_replaced,
)
from interceptor.registrations import REGISTER, RELEASE, Registration, covers
from interceptor.ros1.wire import (
    CALL_TIMEOUT,
    LOCAL_REGISTRATIONS,
    LOCAL_TOKEN_WAIT,
    OPAQUE,
    RELEASING_CALLS,
    filtered_param_reply,
    header_hint,
    local_endpoint,
    log,
    md5_or_none,
    param_subscription_key,
    pass_refusal,
    read_tcpros_header,
    registration_key,
    released_uri,
    resolved_param_call,
    rewrite_param_api,
    ros_ok,
)
from interceptor.streams import READ_SIZE, InboundStream
from interceptor.translate import KIND_XMLRPC, MASTER


#: seconds a node left with only parameter subscriptions has to stop answering before they
#: are taken for a live node's and kept (a rospy node that exits stops at once)
NODE_EXIT_PATIENCE = 5.0


class NodeSide:
    """The node role of :class:`~interceptor.ros1.role.Ros1Role` (a part of it)."""

    # ---------------------------------------------------------------- node side
    async def _serve_node_stream(self, stream: InboundStream) -> None:
        peer = stream.peer
        endpoint = stream.resolved  # resolved once, by the gate's target check

        def decide(call: Request) -> Request:
            try:
                check_node_call(
                    call.method,
                    call.params,
                    grants=self.verifier.freshest(peer.access).grants,
                    peer_is_master=peer.manager == self.cfg.master.manager,
                    topic_types=self.topic_types,
                )
            except PolicyDenied as exc:
                if call.method == "requestTopic":
                    raise self._subscription_refused(exc, str(call.params[1])) from None
                raise
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

    def _subscription_refused(self, exc: PolicyDenied, topic: str) -> PolicyDenied:
        """The refusal of a peer's subscription of ``topic``: ``exc``, or, for a grant
        missing when no node of our manager may publish the topic now, ours: the peer's
        token, narrowed to the names our grants hold, lost its subscription with our grant
        (a day-2 audit: a publish grant removed was logged as the subscriber's, with a
        grant to add that it already held)."""
        if exc.reason != "not_granted":
            return exc
        try:
            own = self.gw.own_access()
        except CryptorosError:  # our token cannot be read now: the peer's refusal stands
            return exc
        type_name = self.topic_types.get(topic)
        if type_name is None or own.grants.any_node_allows("publish", topic, type_name):
            return exc
        return PolicyDenied("not_granted_here", f"this robot's manager {own.subject} may not publish {topic} "
                                                f"[{type_name}]")

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
                try:
                    check_subscriber_header(
                        fields, grants=grants, published_type=published, published_md5=md5_or_none(published)
                    )
                except PolicyDenied as exc:
                    raise self._subscription_refused(exc, fields["topic"]) from None
                return None
            if "service" not in fields:
                raise PolicyDenied("malformed", "service stream without a service header")
            return check_service_client_header(fields, grants=grants)

        try:
            client_types = judge(self.verifier.freshest(peer.access).grants)
            if stream.watch is not None:
                stream.watch.judge_by(judge)
        except PolicyDenied as exc:
            self._refuse_stream(stream, exc)
            with contextlib.suppress(Exception):
                await asyncio.wait_for(writer.drain(), 1)
            return
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
                await pass_refusal(writer, reply_fields["error"])
                local_writer.close()
                return
            await self.gw.keeper.ensure(LOCAL_TOKEN_WAIT)  # our token revoked by a grant change: its successor
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
                self._refuse_stream(stream, exc)
                return
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

    def _refuse_stream(self, stream: InboundStream, exc: PolicyDenied) -> None:
        """Refuse a peer's TCPROS stream by its header (the peer is told no more than
        ``denied by cryptoros``); the log names the grant that would allow it."""
        peername = stream.writer.get_extra_info("peername")
        who = f"{stream.peer.manager}@{peername[0]}:{peername[1]}" if peername else stream.peer.manager
        self.gw.deny(stream.purpose, exc, who, hint=header_hint(exc, opener=stream.peer.manager,
                                                                server=self.cfg.manager))
        stream.writer.write(encode_header({"error": OPAQUE}))

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
            for node, port, host, repeat in self._nodes_exposed.exposed_apis(calls, allow=self.cfg.allow_exposed_nodes):
                if port != self.cfg.public.port:
                    self.gw.spawn(self._shut_down_exposed(node, port, host, exc.detail, repeat), "shutdown-exposed")
            error = Response(value=ros_error(f"{OPAQUE}: {exc}"))
            return assemble_multicall([error] * len(calls)) if request.method == MULTICALL else error
        return None

    async def _shut_down_exposed(self, node: str, port: int, host: str, why: str, repeat: bool) -> None:
        """:func:`ask_to_shut_down` at loopback, then at the address the node announced
        when that is this host's (a node bound to that address alone), never elsewhere;
        at once when the node name was found exposed before (``repeat``)."""
        hosts = ("127.0.0.1", host) if await is_this_host(host) else ("127.0.0.1",)
        delay = REPEAT_SHUTDOWN_DELAY if repeat else EXPOSED_SHUTDOWN_DELAY
        if not await ask_to_shut_down(self._local_calls, node, port, why, hosts=hosts, delay=delay):
            self._nodes_exposed.still_running(node, port)  # named in status while it listens

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
                call.method, call.params, manager=own.subject, grants=own.grants, owners={}
            )
        except PolicyDenied as exc:
            if exc.reason == "not_granted" and self._ledger.refused(call.method, call.params):
                self._save_state_soon()  # kept: made if a grant comes while the node runs
            raise
        call = resolved_param_call(call, own.grants)
        if call.method == "registerPublisher" and call.params[1] not in self.topic_types:
            self.topic_types[call.params[1]] = call.params[2]  # checked strings (check_master_call)
            self._topics_registering.add(call.params[1])
        # a release names its URI without exporting it: a node's replaced process may
        # unregister late, from an endpoint released when its new process registered
        name = self.translator.name_of if call.method in RELEASING_CALLS else self.translator.to_canonical
        call = rewrite_call(call, caller_api=name, service_api=name)
        return rewrite_param_api(call, name)

    def _local_after(self, call: Request, response: Response | Fault) -> Response | Fault:
        reason = refused_reason(getattr(response, "value", None))
        if reason is not None and "master" not in self.cfg.roles and call.params and isinstance(call.params[0], str):
            # refused by the master's interceptor (a name another manager holds, its quotas):
            # counted here too, so that this robot's operator finds it in cryptoros denials
            self.gw.deny("local-master", PolicyDenied(reason, f"the master's interceptor refused {call.method} of "
                                                        f"{call.params[0][:200]} (its log has the detail)"),
                         "local node")
        if call.method in RELEASING_CALLS and not self.translator.exported(released_uri(call.method, call.params)):
            # from a process that is gone (its endpoint released): the node's name now
            # belongs to its new process, whose registrations this must not forget
            log.debug("%s from a released endpoint of %s changes nothing here", call.method, call.params[:1])
            return rewrite_response(call, response, uri=self.translator.to_local)
        if call.method == "registerPublisher":
            registering = call.params[1] in self._topics_registering
            self._topics_registering.discard(call.params[1])
            if not ros_ok(response):
                if registering:  # the master refused it: not published here after all
                    self.topic_types.pop(call.params[1], None)
            elif registering or self.topic_types.get(call.params[1]) != call.params[2]:
                self.topic_types[call.params[1]] = call.params[2]
                self._save_state_soon()
        elif call.method in ("registerSubscriber", "unregisterSubscriber") and ros_ok(response):
            self._note_local_subscriber(call)
        if call.method in LOCAL_REGISTRATIONS and ros_ok(response):
            self._note_local_node(call)
        if ros_ok(response):
            self._track_local_registration(call)
        self._note_ledger(call, response)
        response = filtered_param_reply(call, response, self.gw.own_access().grants)
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
            self._shut_down_previous(node, previous)
            self._release_node_exports(previous)
        if len(self._node_apis) < self.translator.MAX_EXPORTS:
            self._node_apis[node] = api_id
        self._save_state_soon()

    def _shut_down_previous(self, node: str, api_id: str) -> None:
        """``node`` registered from a new process (rosmaster accepted it): its previous
        process is told to shut down, unless another node now holds that API (its port
        taken again)."""
        if any(api == api_id and name != node for name, api in self._node_apis.items()):
            return
        try:
            endpoint = self.translator.resolve(KIND_XMLRPC, api_id)
        except PolicyDenied:
            return
        self.gw.spawn(shut_down_replaced(self._local_calls, node, endpoint.uri), "shutdown-replaced")

    def _track_local_registration(self, call: Request) -> None:
        """Count a local node's registrations; when the last one is released (a clean
        shutdown unregisters everything), its exports are released too."""
        key = registration_key(call.method, call.params) or param_subscription_key(call.method, call.params)
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
        if regs and kind != "param" and all(k == "param" for k, _ in regs):
            # Only parameter subscriptions left: the node shut down (a live one keeps its
            # /rosout), and rospy never withdraws them (ros_comm 1.15: a node that logged
            # once subscribed /rosout_disable_topics_generation). Withdrawn for it, the last
            # answer releases its exports here, and its name and relay at the master's host;
            # kept, each such node held them for good (a script run every minute: the
            # export limit within days).
            self._withdraw_param_subscriptions(node, sorted(n for _, n in regs))
        if regs:
            return
        del self._node_registrations[node]
        api_id = self._node_apis.get(node)
        if api_id is not None:
            self._release_node_exports(api_id, why="unregistered everything")
            self._save_state_soon()

    def _withdraw_param_subscriptions(self, node: str, keys: list[str]) -> None:
        """``unsubscribeParam`` of each of ``keys`` to the master, on behalf of ``node``
        (through :meth:`_local_master_request`: judged and counted as the node's own)."""
        api_id = self._node_apis.get(node)
        if api_id is None:
            return
        try:
            uri = self.translator.resolve(KIND_XMLRPC, api_id).uri
        except PolicyDenied:
            return

        async def withdraw() -> None:
            # It shut down only once its API stops answering (a clean rospy exit: at once);
            # a node that answers on was only left with them (a client of its own making)
            deadline = time.monotonic() + NODE_EXIT_PATIENCE
            while await self._answers(uri):
                if time.monotonic() >= deadline:
                    log.info("%s unregistered all but %d parameter subscription(s) and its API still answers: "
                             "kept for it", node, len(keys))
                    return
                await asyncio.sleep(0.1)
            regs = self._node_registrations.get(node)
            if not regs or any(kind != "param" for kind, _ in regs):
                return  # it registered again meanwhile (a node restarted under the name)
            log.info("%s unregistered all but %d parameter subscription(s), which rospy never withdraws, and "
                     "its API no longer answers: withdrawn for it", node, len(keys))
            for key in keys:
                with contextlib.suppress(*PEER_FAILURES, CryptorosError):
                    await self._local_master_request(Request(method="unsubscribeParam", params=(node, uri, key)))

        self.gw.spawn(withdraw(), "param-withdraw")

    async def _sweep_dead_nodes(self) -> None:
        """Forever: withdraw the registrations of this host's nodes that died without
        unregistering (SIGKILL, a crash), as ``rosnode cleanup`` would, so that their
        exports here, and their relays and names at the master's host, are released.
        Dead means nothing listens on its API's port any more (this host's listening
        sockets, read once a round: no node is connected to); a node that is slow to
        answer, or whose port another process took, is left alone."""
        while True:
            every = self.cfg.limits.dead_node_check  # read again after a reload
            await asyncio.sleep(every or 10.0)
            if not every:
                continue
            # the nodes first: each one's API listened before it registered, so before this read
            nodes = [(node, api_id) for node, api_id in self._node_apis.items()
                     if node in self._node_registrations or self._ledger.of_node(node)]
            if not nodes:
                continue
            try:
                listening = {one.port for one in read_listeners()}
            except ExposureError as exc:
                log.debug("this host's listening sockets cannot be read (%s): no dead-node check this round", exc)
                continue
            for node, api_id in nodes:
                try:
                    uri = self.translator.resolve(KIND_XMLRPC, api_id).uri
                except PolicyDenied:
                    continue
                endpoint = local_endpoint(uri)
                if endpoint is None or endpoint[1] in listening or self._node_apis.get(node) != api_id:
                    continue
                try:
                    await self._withdraw_dead(node, uri)
                except Exception:  # a sweep that stopped for good would leave every dead node's hold
                    log.exception("withdrawing the registrations of %s, which died, failed", node)

    async def _withdraw_dead(self, node: str, uri: str) -> None:
        calls = []
        for reg in self._ledger.of_node(node):
            if reg.refused:
                self._ledger.released(reg.method, reg.params)
            elif reg.method == "registerService":
                calls.append(Request(method="unregisterService", params=(node, reg.params[1], reg.params[2])))
            else:
                calls.append(Request(method="un" + reg.method, params=(node, reg.params[1], reg.params[3])))
        calls += [Request(method="unsubscribeParam", params=(node, uri, key))
                  for kind, key in sorted(self._node_registrations.get(node, ())) if kind == "param"]
        if not calls:
            return
        log.warning("%s died without unregistering (nothing listens on its API %s): its %d registration(s) "
                    "withdrawn for it, as rosnode cleanup would", node, uri, len(calls))
        for call in calls:
            with contextlib.suppress(*PEER_FAILURES, CryptorosError):
                await self._local_master_request(call)
        self._save_state_soon()

    async def _answers(self, uri: str) -> bool:
        """Whether the node API at ``uri`` (on this host) answers ``getPid``."""
        try:
            return ros_ok(await self._call_plain(uri, Request(method="getPid", params=("/cryptoros",))))
        except (*PEER_FAILURES, CryptorosError):
            return False

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
            return reply.value[2] if ros_ok(reply) else None

        deadline, backoff = time.monotonic() + patience, 0.25
        while True:
            try:
                state = await ask("getSystemState")
                if state is None:
                    raise PolicyDenied("master_refused", "getSystemState")
                break
            except PEER_FAILURES as exc:
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
                endpoint = self.translator.adopt(uri) if isinstance(uri, str) else None
                if endpoint is not None:
                    for node in mine:  # (kept as made: a node dead meanwhile has it withdrawn)
                        self._node_registrations.setdefault(node, set()).add(("srv", service))
                        self._ledger.made("registerService", (node, service, endpoint.uri, own[node]))
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
        except (*PEER_FAILURES, ValueError, TypeError) as exc:
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
            if self._ledger.get(call.method, call.params) is not None:
                self._ledger.released(call.method, call.params)
                self._save_state_soon()
        elif call.method in REGISTER:
            try:
                local = rewrite_call(call, caller_api=self.translator.to_local, service_api=self.translator.to_local)
            except CryptorosError:
                return
            if ros_ok(response):
                known = self._ledger.get(local.method, local.params)
                self._ledger.made(local.method, local.params)
                if known is None or known.refused or known.params != tuple(local.params):
                    self._save_state_soon()  # a repeat changes nothing, and writes nothing
            elif self._ledger.refused(local.method, local.params):
                self._save_state_soon()

    def _own_token_changed(self) -> None:
        """Our token changed (keeper listener): the grants it carries may cover
        registrations of running nodes they did not cover before."""
        news, self._token_news = self._token_news, None
        if news is not None:
            news.set()
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
                except PEER_FAILURES as exc:
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
            if api is None or not ros_ok(await self._call_plain(api, Request(method="getPid", params=("/master",)))):
                raise ConnectionError("no answer")
        except PEER_FAILURES:
            log.info("%s %s of %s not made again: the node does not answer", reg.method, reg.params[1], reg.params[0])
            self._ledger.released(reg.method, reg.params)
            self._save_state_soon()
            return False
        response = await self._local_master_request(Request(method=reg.method, params=reg.params))
        if not ros_ok(response):
            log.info("%s %s of %s made again: refused (%s)", reg.method, reg.params[1], reg.params[0],
                     response.value[1] if isinstance(response, Response) else response)
            return False
        if reg.method == "registerSubscriber":
            await self._tell_publishers(api, reg.params[1], response.value[2])
        return True

    async def _tell_publishers(self, api: str, topic: str, uris: list) -> None:
        """``publisherUpdate`` to a local subscriber, once each publisher's interceptor
        has our freshest token (it judges the subscriber's requestTopic by it)."""
        peers = {(t.host, t.port) for t in (self.translator.relay_target(*e) for e in map(local_endpoint, uris) if e)
                 if t is not None}
        for peer in peers:
            with contextlib.suppress(CryptorosError, OSError, asyncio.TimeoutError):
                await self.gw.exchange_tokens(*peer)
        try:
            await self._call_plain(api, Request(method="publisherUpdate", params=("/master", topic, list(uris))))
        except PEER_FAILURES as exc:
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
            self._save_state_soon()

    def _note_refused_stream(self, manager: str, topic: str, why: str | None = None) -> None:
        """A topic stream from ``manager``'s side to a local subscriber was refused (or
        closed before its answer): remembered; ``why`` its side's refusal, logged once a
        minute per manager and topic (None: refused here, a DENY logged already)."""
        self._refused_streams.refused(manager, topic)
        if why is not None and self._refusal_log((manager, topic)):
            log.info("the %s stream from %s to a subscriber here was refused by its side: %s (said once a minute "
                     "per topic)", topic, manager, why)

    def _peer_token_fresher(self, access: AccessToken) -> None:
        """A peer showed a fresher token (its grants may have changed): the topics whose
        streams its side refused lately are told their publishers again, once rospy's
        own check after each refusal is over, and later each time the same topic's
        streams are refused again (:mod:`interceptor.ros1.refusals`)."""
        due = self._refused_streams.due(access.subject)
        if not due:
            return
        if self._refusal_log(access.subject):
            waits = [wait for _topic, wait in due]
            log.info("%s showed a fresher token: the subscribers of %d topic(s) its side refused are told their "
                     "publishers again in %.1f to %.1f s (said once a minute)", access.subject, len(due), min(waits),
                     max(waits))
        for topic, wait in due:
            self.gw.spawn(self._resubscribe_after(topic, wait + self._paced(access.subject)))

    async def _resubscribe_after(self, topic: str, delay: float) -> None:
        await asyncio.sleep(max(0.0, delay))
        self._resubscribe_soon(topic, delay=0.0)

    def _paced(self, manager: str) -> float:
        """The turn of one more telling of ``manager``'s topics (:meth:`RefusedStreams.paced`);
        a manager whose tellings wait is logged once a minute."""
        wait = self._refused_streams.paced(manager)
        if wait > 0 and self._refusal_log(("paced", manager)):
            log.warning("%s's topic streams to subscribers here end or are refused faster than %g a second: their "
                        "subscribers are told the publishers again at that pace (said once a minute)", manager,
                        TELLINGS_PER_SECOND)
        return wait

    def _resubscribe_soon(self, topic: str, delay: float = 0.5, via: tuple[str, int] | None = None,
                          paced_by: str | None = None) -> None:
        """A topic stream into this host ended: tell the topic's local subscribers the
        current publishers (``publisherUpdate``, as the master would), so rospy and
        roscpp connect again once the publisher's side is back (they retry a failed
        connect by themselves, but not a connection the other side closed). ``via``
        is the publisher's interceptor: waited for (a token exchange, backing off up
        to 8 s between tries) for as long as the topic has local subscribers, before
        they are told (a publisher's interceptor down over a minute, or kept from
        answering by a stranger's flood, otherwise left them silent for good)."""
        if topic not in self._local_subscribers or topic in self._resubscribing or not self.gw.started:
            return
        self._resubscribing.add(topic)
        if paced_by is not None:  # after a stream of that manager's ended
            delay += self._paced(paced_by)

        async def nudge() -> None:
            try:
                await asyncio.sleep(delay)
                if via is not None:
                    await self._wait_reachable(via, lambda: topic in self._local_subscribers)
                uris = await self._publishers_of(topic)
                for node, api in list(self._local_subscribers.get(topic, {}).items()):
                    try:
                        await self._call_plain(api, Request(method="publisherUpdate", params=("/master", topic, uris)))
                    except PEER_FAILURES as exc:
                        log.info("publisherUpdate of %s to %s failed: %s", topic, node, exc)
            except PEER_FAILURES as exc:
                log.info("cannot list the publishers of %s: %s", topic, exc)
            finally:
                self._resubscribing.discard(topic)

        self.gw.spawn(nudge())

    async def _wait_reachable(self, endpoint: tuple[str, int], wanted: Callable[[], bool]) -> None:
        """Until a token exchange with a peer interceptor succeeds, while ``wanted()``
        (the last failure is raised once it is not). The back-off is cut short when our own
        token changes: a robot whose manager was disabled and enabled again waited out its
        8 s back-off with its token back (a day-2 audit: its flows back 7.9 s after)."""
        backoff = 0.25
        while True:
            try:
                await self.gw.exchange_tokens(*endpoint)
                return
            except PEER_FAILURES:
                if not wanted():
                    raise
                if self._token_news is None:
                    self._token_news = asyncio.Event()
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(self._token_news.wait(), backoff)
                backoff = min(backoff * 2, 8.0)

    async def _publishers_of(self, topic: str) -> list[str]:
        """The topic's publishers as the master knows them, as URIs local nodes can call."""
        master = self.cfg.master.interceptor or self.cfg.public
        tunnel = self.pool(master.host, master.port, "master", "")
        state = await tunnel.call(Request(method="getSystemState", params=("/cryptoros",)))
        if not ros_ok(state):
            raise PolicyDenied("master_refused", f"getSystemState: {state!r:.80}")
        nodes = next((names for name, names in state.value[2][0] if name == topic), [])
        uris = []
        for node in nodes:
            reply = await tunnel.call(Request(method="lookupNode", params=("/cryptoros", node)))
            if ros_ok(reply) and isinstance(reply.value[2], str):
                uris.append(self.translator.to_local(reply.value[2]))
        return uris
