"""The interceptor's ``ros2`` role: the asyncio edge between a robot's DDS domain and
the other robots' interceptors.

The :class:`~interceptor.gateway.Gateway` owns everything a role shares: the
mutual-TLS public listener, the preamble, token verification bound to the
certificate, the revocation feed that cuts watched streams, reload, limits and
metrics. :class:`Ros2Role`, composed with it, serves one stream purpose (``ros2``)
and talks to a DDS bridge child (:mod:`cryptoros.ros2.bridge_node`, run by the ROS 2
venv's python) over a local socket; the child's life (start, restart, stop) is
:class:`~interceptor.ros2_bridge.DdsBridge`'s.

This module is the role and its outbound half (this robot's publishers and servers):
the bridge reports the local graph; every topic whose local publishers may all publish
it (this interceptor's own grants, per node) gets a raw subscription and one stream per
configured peer; a stream is used only once the peer's token (from the preamble reply)
shows its manager may subscribe. Services alike (``serve`` here, ``call`` there). An
offer whose publishers all left the graph is kept :data:`VANISHED_GRACE` first (a
process that stalled past its DDS lease comes back with the same writer); anything
decided against it ends it at once.

The inbound half (streams other robots open here, republished on this robot's domain or
offered as proxy services) is :class:`~interceptor.ros2_inbound.Ros2Inbound`, handed
the bridge, the channel numbers and the graph by the role.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import itertools
import logging
import time
from dataclasses import dataclass, field
from typing import Any

from cryptoros.memory import tune_malloc
from cryptoros.errors import PEER_FAILURES, CryptorosError, PolicyDenied, RemoteProtocolError, TokenError
from cryptoros.ros2 import framing as fr
from cryptoros.ros2.exposure import Exposed, ExposureScan, gid_pid16
from cryptoros.policy.infrastructure import ros2_stays_local
from cryptoros.policy.hints import PROG, command
from cryptoros.policy.ros2 import UNKNOWN_NODE_MARK, Offer, local_offer, manager_may, may_learn
from cryptoros.ros2.target import StreamTarget
from cryptoros.tokens import AccessToken
from cryptoros.exposure import ExposureError
from interceptor.config import Endpoint
from interceptor.exposure import PortExposure
from interceptor.verifier import StreamWatch
from interceptor.gate import FEED_REASONS
from interceptor.authz_client import PEER_TOKEN_WAIT
from interceptor.gateway import Gateway, Role
from interceptor.ros2_bridge import BridgeLink, DdsBridge
from interceptor.ros2_inbound import BACKLOG_HIGH, BACKLOG_LOW, BACKLOG_STALL, MAX_PENDING_CALLS, Ros2Inbound
from interceptor.ros2_partial import PartialFrames
from interceptor.streams import READ_SIZE, Peer, read_chunks

log = logging.getLogger("cryptoros.interceptor.ros2")

RECONCILE_INTERVAL = 1.0
#: an offer whose name has no named publisher or server left in the graph, with nothing
#: decided against it (its grant stands, the link is up), is kept this long before it is
#: withdrawn: a process that stalls past its DDS lease (3 s in the localhost profile)
#: drops out of the graph and comes back with the same writer, and withdrawing at once
#: lost what the bridge had taken of a reliable burst. A grant taken away, an exposed
#: participant, a changed node or QoS and a link down still withdraw at once.
VANISHED_GRACE = 6.0
#: a peer that may not receive a stream is looked at again when it shows a fresher token
#: (its grants changed: 0.2-0.3 s from a grant re-added to the flow), and asked for one
#: this often in any case; a token learnt within RECHECK_MARGIN before a recheck is fresh
#: enough for it
PEER_RECHECK = 5.0
RECHECK_MARGIN = 1.0
#: a peer whose token does not let it receive a stream, seen within PEER_SETTLE seconds of
#: our own token's change, is asked again every SETTLE_POLL seconds meanwhile, and not
#: denied: its token is narrowed to the grants ours held, and its successor (fetched when
#: the peer's feed tells it of the change) may still be on its way. A grant of ours given
#: back blamed the peer ("robot_b may not subscribe") and waited out PEER_RECHECK (a CI
#: run: the flow back after 5.2 s).
PEER_SETTLE = 3.0
SETTLE_POLL = 0.3
#: denials remembered (to log each once) before the memory starts over
MAX_NOTED = 10_000
#: Flow control of outbound topics (BACKLOG_* in :mod:`interceptor.ros2_inbound`): while a
#: peer stream's send buffer is above BACKLOG_HIGH, the interceptor stops reading from its
#: bridge (which then stops taking from DDS: the bridge's history depth decides what is
#: kept, as on a direct DDS path); reading resumes once every stream is under
#: BACKLOG_LOW, or after BACKLOG_STALL seconds (a stuck peer must not stall the others). A stream that stays above
#: BACKLOG_LOW for STUCK_AFTER seconds is stuck: its new messages are dropped (counted,
#: logged once) until it drains under BACKLOG_LOW, and it pauses nothing meanwhile (a
#: peer that stopped reading held every other peer's flows, a pause and a second's
#: stall on every batch: 66 s of silence in a run). STUCK_AFTER is over what a live
#: receiver may hold a stream (its bridge's two PUBLISH_PATIENCE waits, 6 s). A stream
#: above MAX_STREAM_BACKLOG drops new messages (counted).
STUCK_AFTER = 10.0
MAX_STREAM_BACKLOG = 32 * 1024 * 1024


@dataclass(eq=False)
class Outbound:
    """One local topic or service offered to the peers."""

    target: StreamTarget
    chan: int
    writers: dict[Endpoint, asyncio.StreamWriter] = field(default_factory=dict)
    tasks: dict[Endpoint, asyncio.Task] = field(default_factory=dict)
    #: transient_local topics: the last ``depth`` frames, replayed to every stream that
    #: opens later (a latched message must reach robots that connect after it was sent)
    history: collections.deque | None = None
    #: the granted local nodes: publishers whose samples the bridge forwards (topics),
    #: or servers (services); what keeps an absent one's offer through VANISHED_GRACE
    granted_writers: frozenset[str] = frozenset()
    #: when (monotonic) its name left the graph (None: on the air): see VANISHED_GRACE
    vanished_at: float | None = None


def withdrawal_reason(key: tuple[str, str, str], out: Outbound, want: dict, on_air: set[str],
                      withheld: dict[tuple[str, str], str]) -> str:
    """Why ``out`` (offered as ``key``: kind, name, type) is withdrawn while the bridge's
    link is up and the host private, given this round's ``want``, the names ``on_air`` and
    the reasons ``withheld`` by :meth:`Ros2Role._desired`."""
    if key in want:
        return "its publisher's node or QoS changed"
    if out.vanished_at is not None and out.target.name not in on_air:
        return f"no named publisher or server in the graph for {VANISHED_GRACE:g} s"
    retyped = sorted(other[2] for other in want if other[:2] == key[:2])
    if retyped:
        return f"its type is now {', '.join(retyped)}"
    return withheld.get(key[:2], "its publisher, its server or the grant that carried it is gone")


class Ros2Role(Role):
    """The ``ros2`` role of one interceptor: the DDS bridge and the ``ros2`` purpose."""

    def __init__(self, gateway: Gateway) -> None:
        super().__init__(gateway)
        cfg = gateway.cfg
        if cfg.ros2 is None:
            raise CryptorosError("the ros2 role needs a [ros2] section")
        self._chans = itertools.count(1)
        self._call_ids = itertools.count(1)
        self.bridge = DdsBridge(cfg.ros2, self._on_bridge_frame, self._on_bridge_messages)
        self._graph: dict[str, Any] = {"topics": [], "services": []}
        self._outbound: dict[tuple[str, str, str], Outbound] = {}  # (kind, name, type)
        self._out_by_chan: dict[int, Outbound] = {}
        self._calls: dict[int, tuple[asyncio.StreamWriter, int, set[int]]] = {}
        self._noted: set[tuple] = set()
        #: (kind, name) the last graph shows but :meth:`_desired` did not offer, and why
        self._withheld: dict[tuple[str, str], str] = {}
        #: why this robot has nothing to offer: its own token gone (past its grace), or None
        self._no_token: TokenError | None = None
        self._partial = PartialFrames()  # each peer's unfinished frames, across its streams both ways
        self._peer_learnt: dict[Endpoint, float] = {}  # when (monotonic) a peer's token was last asked for
        self._peer_lookups: dict[Endpoint, tuple[float, asyncio.Future]] = {}  # (started, exchange)
        #: set when a peer manager shows a fresher token (a grant of its changed): the streams
        #: waiting out PEER_RECHECK for it look again at once
        self._peer_changed: dict[str, asyncio.Event] = {}
        self._stopping = False
        self._started = False  # start() ran: the bridge is supervised from then on
        self.dropped = 0
        self._exposure = ExposureScan(cfg.ros2.domain_id)
        self._exposed: tuple[Exposed, ...] = ()
        self._exposed_nodes: frozenset[str] = frozenset()
        self._paused: asyncio.Task | None = None
        self._stuck: set[asyncio.StreamWriter] = set()  # peer streams that stopped draining (flow control)
        self._high_since: dict[asyncio.StreamWriter, float] = {}  # undrained at a stall's end since (loop time)
        #: whether this host's loopback answers other hosts (``route_localnet``), read at
        #: each reconcile: the robot's domain is then open to strangers (its samples read,
        #: samples injected as its nodes'), and nothing is carried, either way
        self._ports = PortExposure()
        self._loopback: str | None = None
        self.inbound = Ros2Inbound(gateway, self.bridge, next_chan=lambda: next(self._chans),
                                   graph=lambda: self._graph, problem=self.problem, partial=self._partial)
        gateway.serve("ros2", self.inbound.check_target, self.inbound.serve)

    # ================================================================ life cycle
    async def prepare(self) -> None:
        # Frames of images are read, checked and copied in buffers of 80 KB to 1 MiB: keep
        # glibc from mmap-ing (and page-faulting, zeroing, unmapping) each one (docs/ros2.md)
        tune_malloc()
        await self.bridge.start()

    async def start(self) -> None:
        self._started = True
        self.gw.spawn(self.bridge.supervise(self._reset_local_state, lambda: self._stopping), "ros2-bridge")
        self.gw.spawn(self._reconcile_loop(), "ros2-reconcile")
        self.verifier.fresh_listeners.append(self._peer_token_fresher)
        log.info("ros2 role up: domain %d, peers %s", self.cfg.ros2.domain_id,
                 ", ".join(map(str, self.cfg.ros2.peers)) or "none")

    async def stopping(self) -> None:
        self._stopping = True
        for out in list(self._outbound.values()):
            self._withdraw(out)
        self.inbound.abort_idle_proxies()

    async def stopped(self) -> None:
        await self.bridge.stop()

    def reloaded(self) -> None:
        self._noted.clear()
        self._reconcile()

    def _reset_local_state(self) -> None:
        for out in list(self._outbound.values()):
            self._withdraw(out, tell_bridge=False)
        self.inbound.close_all()
        self._graph = {"topics": [], "services": []}

    # ================================================================ bridge frames
    def _on_bridge_messages(self, chan: int, count: int, frames: bytearray) -> None:
        """``count`` MESSAGE frames of one outbound topic (checked, whole), as one batch:
        relabelled DATA in place, one TLS write per peer stream."""
        out = self._out_by_chan.get(chan)
        if out is None:
            return
        data = fr.retag(frames, fr.DATA, 0)
        if out.history is not None:
            out.history.extend(fr.encode(fr.DATA, 0, p) for p in fr.payloads(data))
        high = False
        for writer in out.writers.values():
            transport = writer.transport
            backlog = transport.get_write_buffer_size()
            if writer in self._stuck:
                if backlog > BACKLOG_LOW:
                    self.dropped += count
                    continue
                self._stuck.discard(writer)
                log.warning("a peer stream of %s drains again: its messages are sent again", out.target.name)
            if backlog > MAX_STREAM_BACKLOG:
                self.dropped += count
                continue
            transport.write(data)
            high = high or backlog + len(data) > BACKLOG_HIGH
        self.metrics.bytes.labels("tx").inc(len(data) * len(out.writers))
        if high and self._paused is None and self.bridge.link is not None and self.bridge.link.transport is not None:
            self.bridge.link.transport.pause_reading()
            self._paused = asyncio.get_running_loop().create_task(self._resume_link(self.bridge.link))

    async def _resume_link(self, link: BridgeLink) -> None:
        """Read the bridge again once every peer stream drained (or after BACKLOG_STALL)."""
        loop = asyncio.get_running_loop()
        until = loop.time() + BACKLOG_STALL
        try:
            while loop.time() < until:
                await asyncio.sleep(0.002)
                if all(w.transport.get_write_buffer_size() <= BACKLOG_LOW
                       for out in self._outbound.values() for w in out.writers.values()
                       if not w.transport.is_closing() and w not in self._stuck):
                    self._high_since.clear()  # every stream drained: none has been high since
                    break
            else:  # a stream that has not drained for STUCK_AFTER is stuck: it pauses nothing from now on
                now = loop.time()
                high_since, self._high_since = self._high_since, {}
                for out in self._outbound.values():
                    for endpoint, w in out.writers.items():
                        if w in self._stuck or w.transport.is_closing() \
                                or w.transport.get_write_buffer_size() <= BACKLOG_LOW:
                            continue
                        since = self._high_since[w] = high_since.get(w, now - BACKLOG_STALL)
                        if now - since >= STUCK_AFTER:
                            self._stuck.add(w)
                            del self._high_since[w]
                            log.warning("the stream of %s to peer %s has not drained for %.0f s: its messages are "
                                        "dropped until it does; the other streams go on (%d dropped so far)",
                                        out.target.name, endpoint, now - since, self.dropped)
        finally:
            self._paused = None
            if link.transport is not None and not link.transport.is_closing():
                link.transport.resume_reading()

    def _on_bridge_frame(self, kind: int, chan: int, payload: bytes) -> None:
        if kind == fr.MESSAGE:
            self._on_bridge_messages(chan, 1, bytearray(fr.encode(fr.MESSAGE, chan, payload)))
        elif kind == fr.REQUEST:  # a local client called a proxy of a remote service
            self.inbound.request(chan, payload)
        elif kind == fr.RESULT:  # the local server answered a remote caller
            bid = fr.ID.unpack_from(payload)[0]
            entry = self._calls.pop(bid, None)
            log.debug("result of call %d: %s", bid, "ok" if payload[4:5] == b"\x01" else "failed")
            if entry is not None:
                writer, rid, pending = entry
                pending.discard(bid)
                if not writer.transport.is_closing():
                    writer.write(fr.encode(fr.SRV_RESPONSE, rid, payload[4:]))
        elif kind == fr.CONTROL:
            try:
                body = fr.decode_control(payload)
            except fr.FrameError as exc:
                log.error("bad control frame from the DDS bridge: %s", exc)
                return
            op = body["op"]
            if op == "graph":
                self._graph = body
                self._reconcile()
            elif op == "hello":
                self.bridge.said_hello(body)
            elif op == "refused_writer":  # a sample on a forwarded topic from a publisher under no grant
                exc = PolicyDenied("not_granted", f"{body.get('node')} (writer {body.get('gid')}) may not publish "
                                   f"{body.get('topic')}: its samples are dropped")
                self.gw.deny("ros2_sample", exc, f"local domain {self.cfg.ros2.domain_id}")
            elif op == "error":
                log.error("DDS bridge: %s", body.get("detail"))
        else:
            log.error("unexpected frame kind %d from the DDS bridge", kind)

    # ================================================================ outbound
    def _note_deny(self, key: tuple, kind: str, exc: PolicyDenied, who: str, hint: str | None = None) -> None:
        """Log a local denial once (the graph is re-read every half second); ``hint``: the
        grant that would allow it (the log line and ``cryptoros denials`` show it)."""
        if key not in self._noted:
            if len(self._noted) >= MAX_NOTED:  # a process inventing names by the thousand: log again, never grow
                self._noted.clear()
            self._noted.add(key)
            self.gw.deny(kind, exc, who, hint=hint)

    @staticmethod
    def _grant_hint(manager: str, action: str, node: str | None, name: str, type_name: str) -> str:
        """The ``cryptoros-authz grant`` that would allow ``node`` (None: a node of
        ``manager``'s robot this one cannot name) to ``action`` ``name``, shell-quoted."""
        note = None if node else (f"NODE: the node of {manager}'s robot that would {action} it (its rclpy "
                                  "create_node name, with its namespace), or '*' for any of them")
        return command(PROG, "grant", manager, action, node or "NODE", name, type_name, note=note)

    def _desired(self) -> dict[tuple[str, str, str], Offer]:
        """What this robot may offer now, decided by :func:`cryptoros.policy.ros2.local_offer`."""
        withheld: dict[tuple[str, str], str] = {}
        self._withheld = withheld
        try:
            grants = self.gw.own_access_in_grace().grants
        except TokenError as exc:
            self._no_token = exc
            return {}
        self._no_token = None
        me = f"local domain {self.cfg.ros2.domain_id}"
        want: dict[tuple[str, str, str], Offer] = {}
        entries = [("topic", t, t.get("publishers", [])) for t in self._graph.get("topics", [])]
        entries += [("service", s, [{"node": n} for n in s.get("servers", [])]) for s in self._graph.get("services", [])]
        exposed = self._check_exposure()
        if not self.cfg.ros2.require_private_domain:
            exposed = frozenset()

        def suspect(node: str) -> bool:
            return "*" in exposed or node in exposed

        for kind, entry, sources in entries:
            name, types = entry["name"], entry["types"]
            if self.cfg.ros2.is_local(name):  # [ros2] local: stays on this robot, by the operator's choice
                withheld[(kind, name)] = "its name is local to this robot ([ros2] local)"
                continue
            action = "publish" if kind == "topic" else "serve"
            held = sorted({s["node"] for s in sources if suspect(s["node"])}) if exposed else []
            named = [node for node in held if UNKNOWN_NODE_MARK not in node]  # the others: not named by discovery yet
            if held and not ros2_stays_local(name, types):
                # a participant reachable from the network: its names are not carried (for a
                # service, none of its servers is: a call cannot be steered to one server)
                for node in named:
                    exc = PolicyDenied("exposed_participant", f"{node} on this robot's domain is reachable from the "
                                       f"network (not started with the localhost DDS settings): {name} from it is "
                                       "not carried ([ros2] require_private_domain)")
                    self._note_deny((kind, name, node, "exposed"), f"ros2_{action}", exc, me)
                sources = [] if kind == "service" else [s for s in sources if not suspect(s["node"])]
            try:
                offer = local_offer(kind, name, types, sources, grants=grants, depth=self.cfg.ros2.depth)
            except PolicyDenied as exc:
                hint = None
                if exc.reason == "not_granted" and sources and len(types) == 1:
                    hint = self._grant_hint(self.cfg.manager, action, sources[0]["node"], name, types[0])
                self._note_deny((kind, name, tuple(types), exc.reason), f"ros2_{action}", exc, me, hint)
                withheld[(kind, name)] = str(exc)
                continue
            except CryptorosError as exc:  # a name we cannot carry (hidden topics, relative names)
                log.debug("not bridging %s %s: %s", kind, name, exc)
                continue
            if offer is None:
                continue
            for node in offer.refused:  # forwarded without them: their samples are dropped
                types_of = sorted({s.get("type", offer.target.type) for s in sources if s["node"] == node}) \
                    or [offer.target.type]
                exc = PolicyDenied("not_granted", f"{node} may not {action} {name} [{', '.join(types_of)}] "
                                   "(its samples are dropped; the granted publishers' still flow)")
                self._note_deny((kind, name, node, "not_granted"), f"ros2_{action}", exc, me,
                                self._grant_hint(self.cfg.manager, action, node, name, types_of[0]))
            want[(kind, name, offer.target.type)] = offer
        self._note_local_receivers(grants)
        return want

    def _note_local_receivers(self, grants) -> None:
        """Ask the own grants about every local subscriber and service client the graph
        shows: nothing is decided by it (the receiving side is decided per manager), but
        a learning robot records what its nodes would need, and any robot which of its
        grants are used (cryptoros-authz learn propose, unused)."""
        receivers = [("subscribe", entry, entry.get("subscribers", [])) for entry in self._graph.get("topics", [])]
        receivers += [("call", entry, entry.get("clients", [])) for entry in self._graph.get("services", [])]
        for action, entry, nodes in receivers:
            name, types = entry["name"], entry["types"]
            if self.cfg.ros2.is_local(name) or ros2_stays_local(name, types):
                continue
            for node in nodes:
                if UNKNOWN_NODE_MARK not in node:
                    for type_name in types:
                        grants.allows(action, node, name, type_name)

    def _check_exposure(self) -> frozenset[str]:
        """The nodes of this robot's domain whose participant is reachable from the
        network (``*``: one whose process this user cannot read, so any node may be);
        each such participant logged once as it appears."""
        found = self._exposure.scan()
        if found != self._exposed:
            for item in set(found) - set(self._exposed):
                log.warning("DDS participant on domain %d reachable from the network: %s (not started with the "
                            "localhost DDS settings: %s); %s", self.cfg.ros2.domain_id, item.describe(),
                            "FASTRTPS_DEFAULT_PROFILES_FILE, see docs/ros2.md",
                            "its topics and services are not carried" if self.cfg.ros2.require_private_domain
                            else "carried anyway ([ros2] require_private_domain = false)")
            self._exposed = found
        if not found:
            self._exposed_nodes = frozenset()
            return self._exposed_nodes
        pids = {item.pid16 for item in found}
        nodes = {"*"} if None in pids else set()
        for topic in self._graph.get("topics", []):
            for pub in topic.get("publishers", []):
                if gid_pid16(pub.get("gid", "")) in pids:
                    nodes.add(pub["node"])
        self._exposed_nodes = frozenset(nodes)
        return self._exposed_nodes

    def _check_loopback(self) -> str | None:
        """Why this host's loopback answers other hosts now (or cannot be told), else None;
        a change is logged once."""
        try:
            problem = self._ports.loopback_problem()
        except ExposureError as exc:
            problem = f"cannot tell whether it does: {exc}"
        if problem != self._loopback:
            if problem is not None:
                log.error("this host's loopback answers other hosts: %s; nothing is carried, either way, until it "
                          "does not", problem)
            else:
                log.warning("this host's loopback answers this host only again: carrying resumes")
            self._loopback = problem
        return problem

    def problem(self) -> PolicyDenied | None:
        if self._loopback is not None:
            return PolicyDenied("exposed_endpoint", f"this host's loopback answers other hosts: {self._loopback}")
        if self._started and not self._stopping and not self.bridge.ready:  # nothing crosses either way meanwhile
            return PolicyDenied("bridge_down", "the DDS bridge is not running: it is being restarted (see the log)")
        return None

    def status(self) -> dict:
        carried = ("not carried" if self.cfg.ros2.require_private_domain
                   else "carried anyway ([ros2] require_private_domain = false)")
        return {
            "ros2": {
                "domain": self.cfg.ros2.domain_id,
                "require_private_domain": self.cfg.ros2.require_private_domain,
                "exposed_participants": [{"pid": e.pid, "command": e.command, "sockets": list(e.sockets)}
                                         for e in self._exposed],
                "exposed_nodes": sorted(self._exposed_nodes),
            },
            "warnings": [f"DDS participant on domain {self.cfg.ros2.domain_id} reachable from the network: "
                         f"{e.describe()}; its topics are {carried} (start it with the localhost profile: "
                         "docs/ros2.md)" for e in self._exposed],
        }

    def _reconcile(self) -> None:
        if self._stopping or self.bridge.link is None or not self.bridge.ready:
            return
        if self.gw.keeper.replacing(PEER_TOKEN_WAIT):  # decided again on its successor, due in a moment
            return
        link_down = self.bridge.link.transport is None or self.bridge.link.transport.is_closing()
        exposed = self._check_loopback() is not None
        want = {} if link_down or exposed else self._desired()
        on_air = set() if link_down else self._on_air()
        now = time.monotonic()
        for key, out in list(self._outbound.items()):
            if key in want and want[key].target == out.target:
                if out.vanished_at is not None:  # back: the bridge held its writers, told again below
                    out.vanished_at, out.granted_writers = None, frozenset()
                    log.info("%s %s [%s] is back in the graph: offered on", out.target.kind, out.target.name,
                             out.target.type)
                continue
            if key not in want and not link_down and not exposed and out.target.name not in on_air \
                    and self._still_granted(out):
                if out.vanished_at is None:
                    out.vanished_at = now
                    if out.target.kind == "topic":  # a writer let through goes on; a new one waits for
                        self.bridge.link.control(op="hold", chan=out.chan)  # the offer's next decision
                    log.info("%s %s [%s] has no named %s in the graph: offered %g s more, for a process that "
                             "missed its DDS lease to come back", out.target.kind, out.target.name, out.target.type,
                             "publisher" if out.target.kind == "topic" else "server", VANISHED_GRACE)
                if now - out.vanished_at < VANISHED_GRACE:
                    continue
            why = ("the bridge's link is down" if link_down else
                   "this host's loopback answers other hosts" if exposed else
                   f"this robot holds no access token now ({self._no_token})" if self._no_token is not None else
                   withdrawal_reason(key, out, want, on_air, self._withheld))
            log.info("no longer offering %s %s [%s]: %s", out.target.kind, out.target.name, out.target.type, why)
            self._withdraw(out)
        peers = set(self.cfg.ros2.peers)
        for key, offer in want.items():
            target = offer.target
            out = self._outbound.get(key)
            if out is not None and offer.writers != out.granted_writers:  # a server's too: see _still_granted
                out.granted_writers = offer.writers
                if target.kind == "topic":
                    self.bridge.link.control(op="writers", chan=out.chan, nodes=sorted(offer.writers))
            if out is None:
                out = self._outbound[key] = Outbound(target=target, chan=next(self._chans), granted_writers=offer.writers)
                if target.qos.durability == "transient_local":
                    out.history = collections.deque(maxlen=target.qos.depth)
                self._out_by_chan[out.chan] = out
                if target.kind == "topic":
                    self.bridge.link.control(op="subscribe", chan=out.chan, topic=target.name, type=target.type,
                                       qos=target.qos.to_dict(), nodes=sorted(offer.writers))
                else:
                    self.bridge.link.control(op="client", chan=out.chan, service=target.name, type=target.type)
                log.info("offering %s %s [%s] to %d peer(s)", target.kind, target.name, target.type, len(peers))
            for endpoint in peers - set(out.tasks):
                out.tasks[endpoint] = asyncio.create_task(self._forward(out, endpoint))
            for endpoint in set(out.tasks) - peers:
                out.tasks.pop(endpoint).cancel()
        if self.inbound.writers:
            try:
                self.gw.own_access_in_grace()
                why = "this host's loopback answers other hosts" if exposed else None
            except TokenError as exc:  # our own token is gone (past its grace): nothing comes in either
                why = f"this robot holds no access token now ({exc.detail})"
            if why is not None:
                log.warning("closing %d inbound stream(s): %s", len(self.inbound.writers), why)
                self.inbound.close_all()

    def _on_air(self) -> set[str]:
        """The topics with a publisher and the services with a server that the graph names
        (a publisher whose node discovery has not named yet does not count)."""
        names = {t["name"] for t in self._graph.get("topics", [])
                 if any(UNKNOWN_NODE_MARK not in p["node"] for p in t.get("publishers", []))}
        return names | {s["name"] for s in self._graph.get("services", [])
                        if any(UNKNOWN_NODE_MARK not in n for n in s.get("servers", []))}

    def _still_granted(self, out: Outbound) -> bool:
        """Whether this robot's own token still lets one of ``out``'s nodes publish or
        serve it (an offer kept through its publisher's absence never outlives its grant)."""
        try:
            grants = self.gw.own_access_in_grace().grants
        except TokenError:
            return False
        return any(grants.allows(out.target.action, node, out.target.name, out.target.type)
                   for node in out.granted_writers)

    def _own_grant_gone(self, out: Outbound) -> PolicyDenied | None:
        """Why ``out`` is no longer this robot's to send (its own token lets none of its
        nodes publish or serve it), or None: it still is, or our token cannot be read now."""
        try:
            own = self.gw.own_access()
        except TokenError:
            return None
        target = out.target
        nodes = sorted(out.granted_writers or {target.node})
        if any(own.grants.allows(target.action, node, target.name, target.type) for node in nodes):
            return None
        return PolicyDenied("not_granted_here", f"this robot's manager {own.subject} may not {target.action} "
                                                f"{target.name} [{target.type}] as {', '.join(nodes)}")

    def _withdraw(self, out: Outbound, *, tell_bridge: bool = True) -> None:
        key = (out.target.kind, out.target.name, out.target.type)
        if self._outbound.get(key) is out:
            del self._outbound[key]
        self._out_by_chan.pop(out.chan, None)
        for task in out.tasks.values():
            task.cancel()
        for writer in out.writers.values():
            writer.transport.abort()
        if tell_bridge and self.bridge.link is not None:
            self.bridge.link.control(op="unsubscribe" if out.target.kind == "topic" else "unclient", chan=out.chan)

    async def _reconcile_loop(self) -> None:
        while True:
            await asyncio.sleep(RECONCILE_INTERVAL)
            self._reconcile()

    async def _forward(self, out: Outbound, endpoint: Endpoint) -> None:
        """Keep one stream to one peer for one outbound topic or service."""
        target = out.target
        backoff = 0.25
        recheck: float | None = None  # after a recheck's wait: when (monotonic) it ended
        while True:
            try:
                # need to know: the target (name, type, node, QoS) goes only to a peer whose
                # grants let it receive the stream, learnt from its token first
                known = await self._peer_token(endpoint, target, recheck=recheck)
                recheck = None
                if not may_learn(known.grants, target):
                    # the peer's token is narrowed to names our own grants hold: our grant
                    # removed takes the peer's out of it too; the offer's withdrawal says so
                    if self._own_grant_gone(out) is not None:
                        await asyncio.sleep(RECONCILE_INTERVAL)
                        continue
                    if self.gw.keeper.taken_within(PEER_SETTLE):
                        await asyncio.sleep(SETTLE_POLL)
                        recheck = time.monotonic() + RECHECK_MARGIN  # a token learnt from now on
                        continue
                    key = ("not_offered", endpoint, target.name)
                    if key not in self._noted:
                        self._noted.add(key)
                        self.gw.deny(f"ros2_{target.kind}_out", PolicyDenied(
                            "not_granted", f"{known.subject} may not {target.peer_action} {target.name} "
                            f"[{target.type}]: not offered to it"), f"{known.subject}@{endpoint}",
                            hint=self._grant_hint(known.subject, target.peer_action, None, target.name, target.type))
                    await self._peer_change(known.subject, PEER_RECHECK)
                    recheck = time.monotonic()
                    continue
                self._noted.discard(("not_offered", endpoint, target.name))
                tunnel = await self.gw.open_tunnel(endpoint.host, endpoint.port, "ros2", target.encode())
                reader, writer, peer = tunnel.reader, tunnel.writer, tunnel.peer
            except PEER_FAILURES as exc:
                key = ("unreachable", endpoint, target.name)
                if isinstance(exc, PolicyDenied) and exc.reason in FEED_REASONS:  # ours: a denial, aggregated
                    self.gw.deny(f"ros2_{target.kind}_out", exc, str(endpoint))
                elif key not in self._noted:
                    self._noted.add(key)
                    log.warning("cannot open the %s stream for %s to %s: %s", target.kind, target.name, endpoint, exc)
                await asyncio.sleep(backoff)
                backoff = min(backoff * 2, 5.0)
                continue
            self._noted.discard(("unreachable", endpoint, target.name))
            watch: StreamWatch | None = None
            refused_by: str | None = None
            pending: set[int] = set()
            try:
                def judge(grants, manager=peer.manager) -> None:
                    if not manager_may(grants, target.peer_action, target.name, target.type):
                        # the peer's token is narrowed to names our own grants hold: a
                        # grant of ours removed is named as ours, not blamed on the peer
                        own_gone = self._own_grant_gone(out)
                        if own_gone is not None:
                            raise own_gone
                        raise PolicyDenied(
                            "not_granted", f"{manager} may not {target.peer_action} {target.name} [{target.type}]")

                def cut(reason: str, writer=writer) -> None:
                    writer.transport.abort()  # counted by the verifier, with its reason

                judge(peer.access.grants)
                # judged again on each fresher token the peer shows: its grant removed cuts
                # the stream here too, whatever its own interceptor does
                watch = self.verifier.watch(peer.access, cut, judge)
                self.metrics.allowed.labels(f"ros2_{target.kind}_out").inc()
                self.metrics.open_streams.labels("ros2").inc()
                for frame in out.history or ():
                    writer.write(frame)
                out.writers[endpoint] = writer
                backoff = 0.25
                try:
                    if target.kind == "topic":
                        if tunnel.pending:
                            raise RemoteProtocolError("the receiver of a topic stream sent data")
                        while await reader.read(READ_SIZE):
                            raise RemoteProtocolError("the receiver of a topic stream sent data")
                    else:
                        await self._serve_calls(reader, writer, out, pending, peer, first=tunnel.pending)
                finally:
                    out.writers.pop(endpoint, None)
                    self._stuck.discard(writer)
                    self._high_since.pop(writer, None)
                    self.metrics.open_streams.labels("ros2").dec()
            except PolicyDenied as exc:
                self.gw.deny(f"ros2_{target.kind}_out", exc, f"{peer.manager}@{endpoint}")
                backoff = 5.0
                refused_by = peer.manager
            except PEER_FAILURES as exc:
                if isinstance(exc, CryptorosError):
                    self.gw.deny(f"ros2_{target.kind}_out", exc, f"{peer.manager}@{endpoint}")
            finally:
                if watch is not None:
                    watch.close()
                writer.close()
                for bid in pending:
                    self._calls.pop(bid, None)
            if refused_by is not None:  # a fresher token of the peer's may allow it: looked at then
                await self._peer_change(refused_by, backoff)
            else:
                await asyncio.sleep(backoff)

    def _peer_token_fresher(self, access: AccessToken) -> None:
        event = self._peer_changed.pop(access.subject, None)
        if event is not None:
            event.set()

    async def _peer_change(self, manager: str, timeout: float) -> None:
        """Until ``manager`` shows a fresher token (its grants may have changed: a grant
        given back to it is carried in well under a second, not after the recheck's wait),
        at most ``timeout`` seconds."""
        event = self._peer_changed.get(manager)
        if event is None:
            event = self._peer_changed[manager] = asyncio.Event()
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(event.wait(), timeout)

    async def _peer_token(self, endpoint: Endpoint, target: StreamTarget, *,
                          recheck: float | None = None) -> AccessToken:
        """The peer's freshest verified token: the last one it showed us (any stream, any
        purpose) while unexpired and either granting ``target`` or learnt recently enough
        (:func:`reusable`; ``recheck``: the monotonic time a recheck's wait ended); else
        one token exchange (purpose ``refresh``: tokens both ways, no target), shared by
        every stream waiting on that peer."""
        known = self.gw.peer_token(endpoint.host, endpoint.port)
        if known is not None:
            known = self.verifier.freshest(known)
            fresh = known.expires_at > time.time() + 5
            if fresh and (may_learn(known.grants, target)
                          or reusable(self._peer_learnt.get(endpoint), now=time.monotonic(), recheck=recheck)):
                return known
        started, task = self._peer_lookups.get(endpoint, (None, None))
        if task is None or not reusable(started, now=time.monotonic(), recheck=recheck):
            started = time.monotonic()  # the token it brings is at least this fresh

            async def exchange() -> AccessToken:
                try:
                    access = await self.gw.exchange_tokens(endpoint.host, endpoint.port)
                    self._peer_learnt[endpoint] = max(started, self._peer_learnt.get(endpoint, started))
                    return access
                finally:
                    if self._peer_lookups.get(endpoint, (None, None))[1] is task:
                        del self._peer_lookups[endpoint]

            task = asyncio.ensure_future(exchange())
            self._peer_lookups[endpoint] = (started, task)
        return await asyncio.shield(task)

    async def _serve_calls(self, reader, writer, out: Outbound, pending: set[int], peer: Peer,
                           first: bytes = b"") -> None:
        """Requests from the calling robot to a local server (through the bridge's client),
        each checked against the service's request type (CdrError ends the stream) and
        paced by the peer's message budget, as its topic samples are (a peer pipelining
        requests had 4.3 million refused in 15 s, 12.7 s of this interceptor's CPU);
        ``first``: bytes the peer sent behind its preamble reply."""
        check_request, _response = self.inbound.service_checks(out.target.type)
        budget = self.gw.budget(peer)
        decoder = fr.FrameDecoder(max_size=self.cfg.ros2.max_message_size, kinds=frozenset({fr.SRV_REQUEST}))
        with self._partial.charge(peer.manager, self.cfg.ros2.max_message_size) as charge:
            async for data in read_chunks(reader, READ_SIZE, first):
                try:
                    decoder.feed(data)
                    frames = decoder.frames()
                except fr.FrameError as exc:
                    raise RemoteProtocolError(str(exc)) from None
                charge(decoder.buffered)
                for _kind, _rid, cdr in frames:
                    check_request(cdr)
                if budget is not None and frames:
                    while (wait := budget.delay(len(frames))) > 0:
                        budget.throttled += 1
                        await asyncio.sleep(wait)
                self._call_local(frames, writer, out, pending, peer)

    def _call_local(self, frames: list[tuple[int, int, bytes]], writer, out: Outbound, pending: set[int],
                    peer: Peer) -> None:
        for _, rid, cdr in frames:
            if len(pending) >= MAX_PENDING_CALLS:
                writer.write(fr.encode(fr.SRV_RESPONSE, rid, b"\x00"))
                key = ("calls_over", peer.manager, out.target.name)
                if key not in self._noted:
                    self._noted.add(key)
                    log.warning("%s calls %s with %d calls under way: further calls are answered failed at once "
                                "(logged once)", peer.manager, out.target.name, MAX_PENDING_CALLS)
                continue
            bid = next(self._call_ids)
            log.debug("call %d (request %d) to the local server of %s", bid, rid, out.target.name)
            pending.add(bid)
            self._calls[bid] = (writer, rid, pending)
            self.bridge.link.send(fr.encode(fr.CALL, out.chan, fr.ID.pack(bid) + cdr))


def reusable(learnt_at: float | None, *, now: float, recheck: float | None) -> bool:
    """Whether a peer token learnt at ``learnt_at`` (monotonic) may answer "may it receive
    this stream?" without asking the peer again. Between rechecks, one learnt within
    PEER_RECHECK; at a recheck (``recheck``: when its wait ended), only one learnt at most
    RECHECK_MARGIN before it, whatever the timer's precision: a grant re-added during the
    wait is never answered by a token older than the wait."""
    if learnt_at is None:
        return False
    if recheck is not None:
        return learnt_at >= recheck - RECHECK_MARGIN
    return now - learnt_at < PEER_RECHECK


__all__ = ["Ros2Role", "reusable"]
