"""The master role: peers' master calls judged and forwarded to rosmaster, who owns
which node name, parameter quotas, rosmaster watched and replayed after its restarts."""

from __future__ import annotations

import asyncio
import contextlib
import fnmatch
import time

from cryptoros.errors import PEER_FAILURES, CryptorosError, PolicyDenied
from cryptoros.policy.ros1 import (
    named_nodes,
    NAME_BINDING,
    check_master_call,
)
from cryptoros.ros1.rewrite import rewrite_call, rewrite_response
from cryptoros.ros1.xmlrpc import (
    Fault,
    Request,
    Response,
)
from cryptoros.grants import Grants
from cryptoros.exposure import ExposureError, read_listeners
from cryptoros.ros1.uri import UriError
from interceptor.exposure import is_this_host, lenient_host_port, master_problem, run_hint
from interceptor.ros1.localcalls import EXPOSED_SHUTDOWN_DELAY, MAX_IDLE, REPEAT_SHUTDOWN_DELAY, ask_to_shut_down
from interceptor.ros1.wire import (
    DIRECT_RECHECK,
    MASTER_CALL_WAIT,
    MASTER_CALLS_PER_PEER,
    MASTER_WATCH_INTERVAL,
    MASTER_WATCH_TIMEOUT,
    MAX_PARAM_SUBSCRIPTIONS_PER_NODE,
    PARAM_READS_PER_PEER,
    RATE_LOG_INTERVAL,
    RELEASING_CALLS,
    filtered_param_reply,
    local_endpoint,
    log,
    param_subscription_key,
    reads_param_values,
    resolved_param_call,
    rewrite_param_api,
    ros_ok,
    writes_params,
)
from interceptor.streams import InboundStream
from interceptor.translate import Canonical


class MasterSide:
    """The master role of :class:`~interceptor.ros1.role.Ros1Role` (a part of it)."""

    # ---------------------------------------------------------------- master role
    def _owner_of(self, node: str, grants: Grants | None = None) -> str | None:
        """The manager that has ``node`` registered, or released it within
        ``[limits] name_hold_seconds`` (:mod:`interceptor.name_holds`). A hold does not
        stand against a caller whose ``grants`` name that very node (the registry gives
        it the name: one tool name granted to two robots): it keeps the name from
        managers that would take it through ``*`` or a pattern. Nor does a registration
        made through ``*`` or a pattern: a manager holding such a grant cannot squat a
        name the registry gives another manager before that one's node starts (rosmaster
        then drops the squatter's registrations: :class:`~interceptor.ros1.ledger.MasterLedger`)."""
        return self._master_ledger.owner_of(node, grants is not None and grants.names_node_exactly(node))

    def _owners_named(self, call: Request, grants: Grants) -> dict[str, str]:
        """The owners of the names a decision of ``call`` may consult, as values."""
        return {node: owner for node in named_nodes(call.method, call.params)
                if (owner := self._owner_of(node, grants)) is not None}

    def _check_node_limit(self, call: Request, manager: str) -> None:
        """A peer registers at most ``max_nodes_per_peer`` node names at the master."""
        if call.method not in NAME_BINDING or not call.params or call.params[0] in self._master_ledger.owners:
            return
        cap = self.cfg.limits.max_nodes_per_peer
        if self._master_ledger.nodes_of(manager) >= cap:
            raise PolicyDenied("node_limit", f"{manager} has {cap} nodes registered already (max_nodes_per_peer)")

    def _check_param_subscription(self, call: Request, manager: str) -> None:
        """A peer holds at most ``max_param_keys_per_peer`` parameter subscriptions (rosmaster
        keeps each), and one node at most :data:`MAX_PARAM_SUBSCRIPTIONS_PER_NODE`."""
        key = param_subscription_key(call.method, call.params) if call.method == "subscribeParam" else None
        if key is None:
            return
        _kind, node, name = key
        subs = self._master_ledger.param_subs_of_node.get(node, {})
        if name in subs:
            return  # a repeat: nothing more is kept
        cap = self.cfg.limits.max_param_keys_per_peer
        held = self._master_ledger.param_subscriptions_of(manager)
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
        """What a call rosmaster accepted changes in the ledger (owners, kept registrations,
        relay counts); the relays left with no registration are released, the state file
        written when something changed. ``exact``: the caller's grants name the node itself."""
        ok = ros_ok(response)
        released = response.value[2] if ok and isinstance(response.value[2], int) else 0
        ledger = self._master_ledger
        not_kept = ledger.not_kept
        noted = ledger.note(call.method, call.params, ok=ok, released=released, manager=manager, exact=exact,
                            hold_seconds=self.cfg.limits.name_hold_seconds)
        if noted.replaced is not None:
            log.info("node %s registered from another API: rosmaster dropped what it had registered before%s",
                     call.params[0], f" (by {noted.replaced})" if noted.replaced else "")
        if ledger.not_kept and not not_kept:
            log.warning("%d registrations kept for rosmaster replay: more are not kept "
                        "(a restarted rosmaster will not learn them)", ledger.max_registrations)
        for endpoint in noted.released:
            self._release_relay(endpoint)
        if noted.changed:
            self._save_state_soon()

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
                pid = reply.value[2] if ros_ok(reply) and isinstance(reply.value[2], int) else None
                silence = "" if pid is not None else "getPid failed"
            except (*PEER_FAILURES, asyncio.TimeoutError) as exc:
                pid, silence = None, str(exc) or type(exc).__name__
            if pid is None and self._master_silent_since is None:
                self._master_silent_since = time.monotonic()
            elif pid is not None:
                self._master_silent_since = None
            self._master_silence = silence
            if pid is not None and pid != self._master_pid:
                # a new pid, or the first one seen after a restart of ours with registrations
                # from state_dir (a repeated registration is harmless to rosmaster)
                if self._master_pid is not None:  # a new rosmaster holds no parameter
                    await self._replay_parameters(pid)
                if self._master_pid is not None or self._master_ledger.registrations:
                    await self._replay_registrations(pid)
                elif not self._master_ledger.relay_refs:  # restarted with no state: rosmaster still names our relays
                    await self._adopt_master_state()
                self._master_pid = pid
            if pid is not None and self._direct_check_due():
                with contextlib.suppress(*PEER_FAILURES, asyncio.TimeoutError):
                    await asyncio.wait_for(self._judge_direct_nodes(), MASTER_WATCH_TIMEOUT * 4)
            await asyncio.sleep(MASTER_WATCH_INTERVAL)

    def _direct_check_due(self) -> bool:
        """Whether :meth:`_judge_direct_nodes` should run this turn: a port other hosts
        reach opened on this host since the last look (one netlink dump, about 0.2 ms),
        rosmaster told a robot's node to shut down, or DIRECT_RECHECK passed; not
        rosmaster's whole graph every second."""
        try:
            ports = frozenset(one.port for one in read_listeners() if one.exposed)
        except ExposureError:
            ports = None
        now = time.monotonic()
        opened = ports is None or not ports <= self._exposed_ports
        if opened:  # each node looked at again: one that registered first may have opened it
            self._direct_checked.clear()
        due = opened or self._owned_names_taken or now - self._direct_looked_at >= DIRECT_RECHECK
        self._exposed_ports = ports or frozenset()
        if due:
            self._direct_looked_at = now
        return due

    async def _judge_direct_nodes(self) -> None:
        """Deployment check of the nodes on this host that register with rosmaster
        directly (tools run on the master host, which no interceptor's local master sees):
        one whose XML-RPC API other hosts reach is asked to shut down and named in status,
        as a robot's interceptor does with its own nodes; one in ``allow_exposed_nodes``
        is named only. A stranger had read a topic from such a node, and robots'
        subscribers of its topic were refused (``foreign_uri``). Run when
        :meth:`_direct_check_due` says; a node looked up less than DIRECT_RECHECK ago is
        skipped, and a robot's node is looked up only once its name may have been taken."""
        state = await self._call_upstream_master(Request(method="getSystemState", params=("/cryptoros",)))
        if not ros_ok(state):
            return
        nodes = {node for entries in state.value[2] for _name, names in entries for node in names}
        now = time.monotonic()
        self._direct_checked = {n: t for n, t in self._direct_checked.items() if n in nodes}
        self._direct_exposed = {n: w for n, w in self._direct_exposed.items() if n in nodes}
        taken, self._owned_names_taken = self._owned_names_taken, False
        for node in sorted(nodes):
            # a robot's node is looked at only once a process here may have taken its name
            # (rosmaster then sends the robot's node shutdown, which a relay drops): the
            # deployment re-audit's impostor, which had been skipped for good; unconditional
            # lookups would cost a robot's bring-up one per node
            if node in self._master_ledger.owners and not taken:
                continue
            if now - self._direct_checked.get(node, -DIRECT_RECHECK) < DIRECT_RECHECK and not taken:
                continue
            self._direct_checked[node] = now
            reply = await self._call_upstream_master(Request(method="lookupNode", params=("/cryptoros", node)))
            if not ros_ok(reply):
                continue
            try:
                host, port = lenient_host_port(reply.value[2])
                addresses = self._exposure.exposed(port)
            except (UriError, ExposureError):
                continue
            if not addresses or port == self.cfg.public.port or not await is_this_host(host):
                self._direct_exposed.pop(node, None)
                continue
            where = f"{', '.join(addresses)} port {port}"
            if any(fnmatch.fnmatchcase(node, p) for p in self.cfg.allow_exposed_nodes):
                self._direct_exposed[node] = f"{node} ({where}, allow_exposed_nodes: its firewall must close it)"
                continue
            repeat = self._nodes_exposed.to_ask(node, port)  # None: this process was just asked
            if repeat is not None:
                why = (f"node {node}'s XML-RPC API listens on {where}, reachable from other hosts: start it with "
                       f"ROS_IP=127.0.0.1 ({run_hint(self.cfg.source, 'CMD')})")
                log.error("DENY master-host node: exposed_endpoint: %s", why)
                self._direct_exposed[node] = f"{node} ({where})"
                self.gw.spawn(self._shut_down_direct(node, port, why, host, repeat), "shutdown-exposed")

    async def _shut_down_direct(self, node: str, port: int, why: str, host: str, repeat: bool) -> None:
        """Ask an exposed node registered here directly to shut down (at once when a
        process of that name was asked before: a launch file's respawn); if it had taken
        a robot's node name, rosmaster dropped that robot's registrations for it: made again."""
        await ask_to_shut_down(self._local_calls, node, port, why, hosts=("127.0.0.1", host),
                               delay=REPEAT_SHUTDOWN_DELAY if repeat else EXPOSED_SHUTDOWN_DELAY)
        if node in self._master_ledger.owners:
            await asyncio.sleep(MASTER_WATCH_INTERVAL)  # its unregistrations first
            await self._replay_registrations(self._master_pid or 0, why=f"{node}'s name was taken here")

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
            if not ros_ok(state):
                return
            publishers, subscribers, services = state.value[2]
            counts: dict[str, int] = {}
            for _name, nodes in (*publishers, *subscribers, *services):
                for node in nodes:
                    counts[node] = counts.get(node, 0) + 1
            uris = []
            for node, count in counts.items():
                reply = await self._call_upstream_master(Request(method="lookupNode", params=("/cryptoros", node)))
                if ros_ok(reply) and isinstance(reply.value[2], str):
                    uris.append((reply.value[2], count))
            for service, _nodes in services:
                reply = await self._call_upstream_master(Request(method="lookupService", params=("/cryptoros", service)))
                if ros_ok(reply) and isinstance(reply.value[2], str):
                    uris.append((reply.value[2], 1))
        except (*PEER_FAILURES, ValueError, TypeError) as exc:
            log.warning("cannot read rosmaster's graph to re-open our relays: %s", exc)
            return
        counted = []
        for uri, count in uris:
            with contextlib.suppress(CryptorosError):
                self.translator.from_master(uri)
            endpoint = local_endpoint(uri)
            if endpoint is not None:
                counted.append((endpoint, count))
        adopted = self._master_ledger.adopt(counted)
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
                    failed += not ros_ok(reply)
                except PEER_FAILURES:
                    failed += 1
        log.warning("rosmaster (pid %d) is new: %d parameters replayed%s", pid, len(items),
                    f", {failed} failed" if failed else "")

    async def _replay_registrations(self, pid: int, why: str = "") -> None:
        calls = [Request(method=method, params=params) for method, params in self._master_ledger.registrations.values()]
        calls.sort(key=lambda c: c.method != "registerService")  # services, then topics
        failed = 0
        for call in calls:
            try:
                reply = await self._call_upstream_master(call)
                failed += not ros_ok(reply)
            except PEER_FAILURES:
                failed += 1
        log.warning("%s: %d registrations replayed%s", why or f"rosmaster (pid {pid}) is new", len(calls),
                    f", {failed} failed" if failed else "")

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
                              owners=self._owners_named(call, grants))
            call = resolved_param_call(call, grants)
            self._check_node_limit(call, peer.manager)
            self._check_param_subscription(call, peer.manager)
            uri_map = existing_from_peer if call.method in RELEASING_CALLS else to_local_from_peer
            call = rewrite_call(call, caller_api=uri_map, service_api=uri_map)
            call = rewrite_param_api(call, uri_map)
            self._charge_param_write(call, peer.manager)  # last: only a call sent on is charged
            return call

        def after(call: Request, response: Response | Fault) -> Response | Fault:
            grants = self.verifier.freshest(peer.access).grants
            self._note_registration(call, response, peer.manager, exact=bool(call.params) and
                                    isinstance(call.params[0], str) and grants.names_node_exactly(call.params[0]))
            response = filtered_param_reply(call, response, self.verifier.freshest(peer.access).grants)
            return rewrite_response(call, response, uri=self.translator.from_master)

        def busy() -> PolicyDenied:
            return PolicyDenied("rate_limited", f"{peer.manager} has {MASTER_CALLS_PER_PEER} master calls "
                                f"({PARAM_READS_PER_PEER} reading parameter values) under way, and the next "
                                f"waited {MASTER_CALL_WAIT:g} s")

        async def admit(request: Request, held: contextlib.AsyncExitStack) -> Response | Fault | None:
            # held until the answer is written out: what a peer does not read counts too
            try:
                await held.enter_async_context(
                    self._peer_master_calls.hold(peer.manager, MASTER_CALLS_PER_PEER, MASTER_CALL_WAIT, busy))
                if reads_param_values(request):
                    await held.enter_async_context(
                        self._peer_param_reads.hold(peer.manager, PARAM_READS_PER_PEER, MASTER_CALL_WAIT, busy))
            except PolicyDenied as exc:
                denied = exc
            else:
                return None

            def refuse(_call: Request) -> Request:
                raise denied
            return await self._decide_calls(request, refuse, self._call_upstream_master, after, "master", peer.manager)

        async def handle(request: Request) -> Response | Fault:
            if not writes_params(request):
                return await self._decide_calls(request, decide, self._call_upstream_master, after, "master",
                                                peer.manager)
            # parameter writes reach rosmaster one request at a time, in the order they
            # were charged: a deleteParam racing a setParam cannot free what rosmaster keeps
            async with self._param_writes:
                return await self._decide_calls(request, decide, self._call_upstream_master, after, "master",
                                                peer.manager)

        await self._serve_xmlrpc(stream.reader, stream.writer, handle, stream.pending, admit)

    async def _call_upstream_master(self, request: Request) -> Response | Fault:
        # a burst of peers' registrations: up to MAX_IDLE connections kept to the master
        return await self._local_calls.call(self.cfg.master.upstream, request, max_idle=MAX_IDLE,
                                            max_body=max(self.cfg.limits.max_master_reply,
                                                         self.cfg.limits.max_xmlrpc_body))

    async def _call_plain(self, uri: str, request: Request) -> Response | Fault:
        """One XML-RPC call to a local process (a local node's API), over a connection
        kept alive to it."""
        return await self._local_calls.call(uri, request)
