"""The DDS bridge: a child process of ``cryptoros-interceptor`` running rclpy.

Runs under the ROS 2 venv's python (the wheels' bootstrapper re-executes that
interpreter, so rclpy never enters the interceptor's own process). It joins its
robot's localhost-only domain as one node, reports the local graph, and does what the
interceptor tells it over one local socket (inherited descriptor ``--fd``), framed by
:mod:`cryptoros.ros2.framing`:

- ``subscribe`` (+ ``writers``): a raw subscription whose serialized messages go to the
  interceptor, each only when its writer (GID) belongs to one of the granted publisher
  nodes the interceptor named;
- ``advertise`` + PUBLISH frames: serialized messages republished as they came;
- ``serve``: a proxy service whose requests go to the interceptor, answered by REPLY;
- ``client`` + CALL frames: requests for a local service, answered by RESULT.

It decides nothing: every grant is checked by the interceptor, which names the
granted publisher nodes of each forwarded topic; the bridge maps each sample's writer
GID to its node through the graph and drops the samples of every other writer from the
first one (a rogue publisher, and this bridge's own republications, so two robots
bridging each other do not loop). Imports only rclpy, message packages and the
standard library.
"""

from __future__ import annotations

import argparse
import importlib
import itertools
import os
import queue
import re
import socket
import sys
import threading
import time
from typing import NoReturn

try:
    from cryptoros.ros2 import framing as fr
except ImportError:  # run as a script by the ROS 2 venv's python: import the sibling module
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import framing as fr  # type: ignore[no-redef]
try:
    from cryptoros.ros2.rawtake import RawTaker
except ImportError:
    from rawtake import RawTaker  # type: ignore[no-redef]

import rclpy
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message
from rclpy.task import Future

_TYPE = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)/(msg|srv)/([A-Za-z][A-Za-z0-9_]*)$")
#: writer decisions remembered per topic before the table starts over (a rogue creating
#: writers by the thousand costs lookups, never unbounded memory)
MAX_WRITERS_PER_TOPIC = 1024
#: a writer the graph does not show yet is looked up again after this long (its samples dropped meanwhile)
UNKNOWN_WRITER_RETRY = 0.1
#: a writer's node name is remembered while the writer is in the graph and this long after:
#: a process that missed its participant lease (stalled) comes back with the same writer but
#: often without its node name (its discovery data is not sent again), and would stay
#: unknown, so neither offered nor let through
NAME_MEMORY_S = 60.0
MAX_NAMED_WRITERS = 4096
CALL_TIMEOUT = 30.0
#: how long a republished message may wait for a full local reader before it is dropped
PUBLISH_PATIENCE = 3.0
#: once a topic's local reader has been full for PUBLISH_PATIENCE, its messages are dropped
#: at once and the reader is probed (one publish attempt) only this often, so the other
#: topics arriving through this bridge do not wait behind every message of a stuck one
STALLED_PROBE_INTERVAL = 1.0
#: a topic's writer is made anew at most this often: a reader that really stopped taking
#: fills every new writer, and would otherwise cost the other topics a patience each time
REMAKE_INTERVAL = 10.0
SERVICE_THREADS = 16
#: calls to one remote service waiting for their answers at once: a server that never
#: answers (an insider's) holds at most this many of the SERVICE_THREADS; more calls to
#: it get no answer at once (their clients time out) instead of a thread (an insider's
#: hanging service held all 8 threads, and robot A's service waited 30 s behind it)
MAX_CALLS_PER_SERVICE = 4
#: and the remote services one peer manager offers hold at most this many together, so
#: half the threads stay for other robots and a peer's hung service leaves room for its
#: others (ROS 2 re-audit: an insider serving four never-answering services held all 16
#: threads, and robot A's service waited 28 s)
MAX_CALLS_PER_PEER = 8
#: seconds between two reports of one kind of bad call on one channel (the rest counted):
#: an insider's malformed requests as fast as it could send them logged 5,800 lines a second
ERROR_INTERVAL = 10.0


class NoAnswer(Exception):
    """A proxied call was refused or failed: the local client gets no answer at all."""


def _unused(_msg) -> None:  # raw subscriptions of the data node: RawTaker takes, never a callback
    pass


READ_SIZE = 1 << 20



def load_type(name: str, kind: str):
    match = _TYPE.match(name)
    if not match or match.group(2) != kind:
        raise ValueError(f"not a ROS 2 {kind} type: {name!r}")
    module = importlib.import_module(f"{match.group(1)}.{kind}")
    cls = getattr(module, match.group(3), None)
    if cls is None or not hasattr(cls, "_TYPE_SUPPORT" if kind == "msg" else "Request"):
        raise ValueError(f"{name} is not an installed ROS 2 {kind} type")
    return cls


def make_qos(q: dict) -> QoSProfile:
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=int(q.get("depth", 10)),
        reliability=ReliabilityPolicy.BEST_EFFORT if q.get("reliability") == "best_effort" else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if q.get("durability") == "transient_local" else DurabilityPolicy.VOLATILE,
    )


def _fqn(name: str, namespace: str) -> str:
    return (namespace.rstrip("/") + "/" + name) if namespace else "/" + name


class Bridge:
    def __init__(self, sock: socket.socket, name: str, graph_interval: float, max_size: int) -> None:
        self.sock = sock
        self.node = rclpy.create_node(name, start_parameter_services=False, enable_rosout=False)
        self.own = self.node.get_fully_qualified_name()
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        # Proxy services block a thread each until the remote answer arrives, so they
        # live on a second node with its own multi-threaded executor: topics never wait.
        self.srv_node = rclpy.create_node(f"{name}_srv", start_parameter_services=False, enable_rosout=False)
        self.srv_executor = MultiThreadedExecutor(num_threads=SERVICE_THREADS)
        self.srv_executor.add_node(self.srv_node)
        self.srv_group = ReentrantCallbackGroup()
        # Forwarded topics are taken by a lean wait-set loop (RawTaker, own thread), in
        # batches, from raw subscriptions of a third node that no executor spins.
        self.data_node = rclpy.create_node(f"{name}_data", start_parameter_services=False, enable_rosout=False)
        self.taker = RawTaker(self.data_node.context)
        # The peers' samples are published by writers the link thread makes and destroys as
        # streams open and close, on a fourth node no executor spins: made on ``self.node``,
        # a writer destroyed while the executor built its wait set (the writer's QoS event
        # handlers are in it) raised InvalidHandle there and aborted the bridge (an insider
        # opening and closing 200 streams at a time: 4 aborts in 90 s; ROS 2 audit).
        self.pub_node = rclpy.create_node(f"{name}_pub", start_parameter_services=False, enable_rosout=False)
        self.own_names = {node.get_fully_qualified_name()
                          for node in (self.node, self.srv_node, self.data_node, self.pub_node)}
        self.commands: queue.SimpleQueue = queue.SimpleQueue()
        self.guard = self.node.create_guard_condition(self._drain)
        self.send_lock = threading.Lock()
        self.writers_lock = threading.Lock()
        self.max_size = max_size
        #: chan -> (publisher, topic, its C publish_raw, message class, QoS)
        self.pubs: dict[int, tuple[object, str, object, type, QoSProfile]] = {}
        self.remade = 0  # writers made anew after they waited PUBLISH_PATIENCE
        self.remade_at: dict[int, float] = {}  # chan -> when its writer was last made anew
        self.calls_lock = threading.Lock()
        self.calls_in_flight: dict[int, int] = {}  # proxied service chan -> calls waiting for answers
        self.peer_calls: dict[str, int] = {}  # peer manager -> its proxied services' calls waiting
        self.reported: dict[tuple[int, str], list] = {}  # (chan, kind) -> [last report, held back]
        self.subs: dict[int, tuple[object, str]] = {}  # chan -> (raw subscription, topic)
        #: chan -> the granted publisher nodes whose writers' samples are forwarded
        self.writer_nodes: dict[int, frozenset[str]] = {}
        #: chan -> writer GID -> forwarded? (decided once per writer from the graph)
        self.writer_ok: dict[int, dict[bytes, bool]] = {}
        self.refused_noted: set[tuple[int, bytes]] = set()
        self.unknown_until: dict[tuple[int, bytes], float] = {}  # writers the graph did not show yet
        #: writer GID -> (its node, when the graph last showed the writer): see NAME_MEMORY_S
        self.named: dict[bytes, tuple[str, float]] = {}
        self.names_lock = threading.Lock()
        self.servers: dict[int, object] = {}
        self.clients: dict[int, tuple[object, type]] = {}
        self.pending: dict[int, list] = {}  # request id -> [threading.Event, (ok, cdr) or None]
        self.ids = itertools.count(1)
        self.last_graph: dict | None = None
        self.dropped = 0
        self.stalled: dict[int, float] = {}  # chan -> when to probe its full local reader again
        self.node.create_timer(graph_interval, self._report_graph)

    # ------------------------------------------------------------ to the interceptor
    def send(self, data: bytes) -> None:
        """Write to the interceptor; a link that failed ends the bridge, as in :meth:`read_loop`
        (a topics thread that raised here printed half a traceback as the interceptor stopped)."""
        try:
            with self.send_lock:
                self.sock.sendall(data)
        except OSError as exc:
            _link_lost(exc)

    def error(self, detail: str, **extra) -> None:
        self.send(fr.encode_control({"op": "error", "detail": detail, **extra}))

    def error_limited(self, chan: int, kind: str, detail: str) -> None:
        """:meth:`error`, at most once per ERROR_INTERVAL per channel and kind; the reports
        held back are counted in the next one."""
        now = time.monotonic()
        with self.calls_lock:
            if len(self.reported) > 4096 and (chan, kind) not in self.reported:
                self.reported.clear()  # channels come and go: bounded, not kept for good
            entry = self.reported.setdefault((chan, kind), [-ERROR_INTERVAL, 0])
            if now - entry[0] < ERROR_INTERVAL:
                entry[1] += 1
                return
            held, entry[0], entry[1] = entry[1], now, 0
        self.error(detail + (f" ({held} more like it since the last report)" if held else ""), chan=chan)

    def _node_of(self, info) -> str:
        """The node of a writer the graph shows (``info``): its own name, or the name it had
        when discovery has lost it (:data:`NAME_MEMORY_S`)."""
        node, gid, now = _fqn(info.node_name, info.node_namespace), bytes(info.endpoint_gid), time.monotonic()
        with self.names_lock:
            if "_UNKNOWN_" not in node:
                if gid not in self.named and len(self.named) >= MAX_NAMED_WRITERS:
                    for old in [g for g, (_n, seen) in self.named.items() if now - seen > NAME_MEMORY_S] \
                            or list(self.named)[: MAX_NAMED_WRITERS // 4]:
                        del self.named[old]
                self.named[gid] = (node, now)
                return node
            known = self.named.get(gid)
            if known is None or now - known[1] > NAME_MEMORY_S:
                return node
            self.named[gid] = (known[0], now)
            return known[0]

    def _report_graph(self) -> None:
        node = self.node
        topics = []
        for name, types in node.get_topic_names_and_types():
            pubs = [
                {
                    "node": self._node_of(i),
                    "reliability": "best_effort" if i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT else "reliable",
                    "durability": "transient_local" if i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL else "volatile",
                    "gid": bytes(i.endpoint_gid)[:8].hex(),  # its participant's GUID prefix starts it
                    "type": i.topic_type,  # its own: the topic's types include its subscribers'
                }
                for i in node.get_publishers_info_by_topic(name)
                if _fqn(i.node_name, i.node_namespace) not in self.own_names
            ]
            subs = sorted(
                {_fqn(i.node_name, i.node_namespace) for i in node.get_subscriptions_info_by_topic(name)} - self.own_names
            )
            if pubs or subs:
                topics.append({"name": name, "types": sorted(types), "publishers": sorted(pubs, key=str), "subscribers": subs})
        services: dict[str, dict] = {}
        for n, ns in node.get_node_names_and_namespaces():
            fqn = _fqn(n, ns)
            if fqn in self.own_names:
                continue
            try:
                served = node.get_service_names_and_types_by_node(n, ns)
                called = node.get_client_names_and_types_by_node(n, ns)
            except Exception:  # the node left between the two calls
                continue
            for names, role in ((served, "servers"), (called, "clients")):
                for sname, stypes in names:
                    entry = services.setdefault(sname, {"name": sname, "types": set(), "servers": [], "clients": []})
                    entry["types"].update(stypes)
                    entry[role].append(fqn)
        graph = {
            "op": "graph",
            "topics": sorted(topics, key=lambda t: t["name"]),
            "services": [
                {"name": s["name"], "types": sorted(s["types"]), "servers": sorted(s["servers"]),
                 "clients": sorted(s["clients"])}
                for s in sorted(services.values(), key=lambda s: s["name"])
            ],
        }
        if graph != self.last_graph:
            self.last_graph = graph
            self.send(fr.encode_control(graph))

    # ------------------------------------------------------------ from the interceptor
    def read_loop(self) -> None:
        decoder = fr.FrameDecoder(max_size=self.max_size + fr.LINK_SLACK)  # (ids before service bodies)
        try:
            while True:
                data = self.sock.recv(READ_SIZE)
                if not data:
                    break
                decoder.feed(data)
                for kind, chan, payload in decoder.frames():
                    if kind == fr.PUBLISH:
                        self._publish(chan, payload)
                    elif kind == fr.REPLY:
                        (rid,) = fr.ID.unpack_from(payload)
                        slot = self.pending.pop(rid, None)
                        if slot is not None:
                            slot[1] = fr.split_status(payload[4:])
                            slot[0].set()
                    elif kind == fr.CONTROL and fr.decode_control(payload)["op"] in ("advertise", "unadvertise"):
                        self._pub_control(fr.decode_control(payload))
                    else:
                        self.commands.put((kind, chan, payload))
                        self.guard.trigger()
        except (OSError, fr.FrameError) as exc:
            _link_lost(exc)
        _link_lost(None)

    def _publish(self, chan: int, payload: bytes) -> None:
        entry = self.pubs.get(chan)
        if entry is None:
            return
        topic, publish_raw = entry[1], entry[2]
        now = time.monotonic()
        probe_at = self.stalled.get(chan)
        if probe_at is not None and now < probe_at:
            self._drop(chan, topic, "stalled")
            return
        # a stalled topic gets one attempt (it blocks for the DDS max_blocking_time), others the
        # patience; then the same again on a writer made anew (:meth:`_remake`, at most every
        # REMAKE_INTERVAL), else the topic is stalled
        give_up = now if probe_at is not None else now + PUBLISH_PATIENCE
        remade = False
        while True:
            try:
                # the C publisher itself: rclpy's Publisher.publish only adds a type check and the
                # handle guard, and publishers are created and destroyed in this thread only
                publish_raw(payload)
                if probe_at is not None:
                    del self.stalled[chan]
                return
            except Exception as exc:  # KEEP_ALL: a local reader stayed full for the blocking time
                now = time.monotonic()
                if now < give_up:
                    continue
                if not remade and now >= self.remade_at.get(chan, -REMAKE_INTERVAL) + REMAKE_INTERVAL \
                        and self._remake(chan):
                    remade, publish_raw = True, self.pubs[chan][2]
                    give_up = now if probe_at is not None else now + PUBLISH_PATIENCE
                    continue
                self.stalled[chan] = now + STALLED_PROBE_INTERVAL
                self._drop(chan, topic, str(exc))
                return

    def _remake(self, chan: int) -> bool:
        """A writer that waited PUBLISH_PATIENCE for its readers is destroyed and made
        anew (False if it could not be). Fast DDS can wedge a reliable reader that one
        KEEP_ALL writer overran: the reader then waits for a repair that never comes and
        delivers nobody's samples (every writer's on that topic), and the writer waits for
        its acknowledgement, until the writer is gone (measured: docs/ros2.md). The message
        that waited goes to the new writer, which waits the patience again: a reader
        killed without a goodbye (held until the profile's 3 s lease ends, a race with
        the first patience) is forgotten by then, and nothing is lost; a reader that really
        stopped taking fills the new writer too, and its topic is then dropped and probed
        (a new writer again once REMAKE_INTERVAL has passed)."""
        publisher, topic, _, cls, qos = self.pubs[chan]
        self.pub_node.destroy_publisher(publisher)
        try:
            fresh = self.pub_node.create_publisher(cls, topic, qos)
        except Exception as exc:
            del self.pubs[chan]
            self.error(f"cannot advertise {topic} again: {exc}", chan=chan)
            return False
        self.pubs[chan] = (fresh, topic, fresh.handle.publish_raw, cls, qos)
        self.remade_at[chan] = time.monotonic()
        self.remade += 1
        if self.remade in (1, 10, 100) or self.remade % 1000 == 0:
            self.error(f"{topic}: a writer waited {PUBLISH_PATIENCE:g} s for its local readers and was made anew "
                       f"({self.remade} so far)", chan=chan)
        return True

    def _drop(self, chan: int, topic: str, why: str) -> None:
        self.dropped += 1
        if self.dropped in (1, 10, 100) or self.dropped % 1000 == 0:
            self.error(f"{topic}: a local subscriber is not taking messages ({why}); "
                       f"{self.dropped} message(s) dropped so far", chan=chan)

    def _pub_control(self, cmd: dict) -> None:
        chan = int(cmd["chan"])
        if cmd["op"] == "advertise":
            try:
                cls = load_type(cmd["type"], "msg")
                qos = make_qos(cmd.get("qos", {}))
                if qos.reliability == ReliabilityPolicy.BEST_EFFORT:
                    # a reliable writer (KEEP_LAST: never waits) serves best-effort and reliable
                    # subscribers alike; a best-effort one matched no reliable subscriber, which
                    # then got nothing while a best-effort publisher of the topic ran (ROS 2 audit)
                    qos.reliability = ReliabilityPolicy.RELIABLE
                elif qos.durability == DurabilityPolicy.VOLATILE:
                    # paced by the local readers like a direct KEEP_ALL publisher (the interceptor,
                    # then the sending robot, are held back) instead of overwriting unsent messages
                    qos.history = HistoryPolicy.KEEP_ALL
                publisher = self.pub_node.create_publisher(cls, cmd["topic"], qos)
            except Exception as exc:
                self.error(f"cannot advertise {cmd.get('topic')}: {exc}", chan=chan)
                return
            self.pubs[chan] = (publisher, cmd["topic"], publisher.handle.publish_raw, cls, qos)
        else:
            entry = self.pubs.pop(chan, None)
            self.stalled.pop(chan, None)
            if entry is not None:
                self.pub_node.destroy_publisher(entry[0])

    def _drain(self) -> None:
        """Guard-condition callback: run queued commands in the executor's thread."""
        while True:
            try:
                kind, chan, payload = self.commands.get_nowait()
            except queue.Empty:
                return
            try:
                if kind == fr.CONTROL:
                    self._control(fr.decode_control(payload))
                elif kind == fr.CALL:
                    self._call(chan, payload)
            except Exception as exc:  # one bad command must not stop the bridge
                self.error(f"command {kind} on channel {chan} failed: {type(exc).__name__}: {exc}", chan=chan)

    def _control(self, cmd: dict) -> None:
        op, chan = cmd["op"], int(cmd.get("chan", 0))
        if op == "subscribe":
            cls = load_type(cmd["type"], "msg")
            topic = cmd["topic"]
            qos = make_qos(cmd.get("qos", {}))
            if qos.reliability == ReliabilityPolicy.RELIABLE and qos.durability == DurabilityPolicy.VOLATILE:
                # Like a direct reliable subscriber with KEEP_ALL: a KEEP_ALL publisher is paced by
                # what the path takes instead of losing messages in this reader (the interceptor
                # stops reading this bridge while a peer stream is backed up); a KEEP_LAST
                # publisher still overwrites only its own history, as it would on a direct path.
                qos.history = HistoryPolicy.KEEP_ALL
            # the filter exists before the reader: its first sample is already decided
            self._set_writers(chan, cmd.get("nodes", ()))
            try:
                sub = self.data_node.create_subscription(cls, topic, _unused, qos, raw=True)
            except Exception:
                self._set_writers(chan, None)
                raise
            self.subs[chan] = (sub, topic)
            self.taker.add(chan, sub)
        elif op == "unsubscribe":
            entry = self.subs.pop(chan, None)
            if entry is not None:
                self.taker.remove(chan)
                self.data_node.destroy_subscription(entry[0])
            self._set_writers(chan, None)
        elif op == "writers":
            self._set_writers(chan, cmd.get("nodes", ()))
        elif op == "hold":
            self._hold_writers(chan)
        elif op == "serve":
            cls = load_type(cmd["type"], "srv")
            self.servers[chan] = self.srv_node.create_service(
                cls, cmd["service"], self._proxy(chan, cls, str(cmd.get("peer", ""))), callback_group=self.srv_group
            )
            self.srv_executor.wake()
        elif op == "unserve":
            srv = self.servers.pop(chan, None)
            if srv is not None:
                self.srv_node.destroy_service(srv)
                self.srv_executor.wake()
        elif op == "client":
            cls = load_type(cmd["type"], "srv")
            self.clients[chan] = (self.node.create_client(cls, cmd["service"]), cls)
        elif op == "unclient":
            entry = self.clients.pop(chan, None)
            if entry is not None:
                self.node.destroy_client(entry[0])
        else:
            raise ValueError(f"unknown op {op!r}")

    def _set_writers(self, chan: int, nodes) -> None:
        """The granted publisher nodes of ``chan`` (None: the channel is gone)."""
        with self.writers_lock:
            if nodes is None:
                self.writer_nodes.pop(chan, None)
            else:
                self.writer_nodes[chan] = frozenset(str(n) for n in nodes) - self.own_names
            self.writer_ok.pop(chan, None)  # decided again from the graph, writer by writer

    def _hold_writers(self, chan: int) -> None:
        """``chan``'s publishers left the graph and the interceptor keeps the offer a while
        (a stalled process comes back with the same writer): the writers already let
        through go on, a new one is refused, silently, until the interceptor has decided
        on it again (``writers``)."""
        with self.writers_lock:
            if chan in self.writer_nodes:
                self.writer_nodes[chan] = frozenset()

    def _writer_granted(self, chan: int, topic: str, gid: bytes) -> bool:
        """Whether ``gid`` is the writer of a granted publisher node of ``chan``: looked up
        in the graph on its first sample (discovery tells the graph about a writer before
        its first sample can match), remembered while the grant stands. A writer the
        graph does not show (yet) is refused and looked up again on a later sample."""
        with self.writers_lock:
            known = self.writer_ok.get(chan, {}).get(gid)
            nodes = self.writer_nodes.get(chan)
        if known is not None:
            return known
        if nodes is None:
            return False
        now = time.monotonic()
        if self.unknown_until.get((chan, gid), 0.0) > now:  # looked up a moment ago: not in the graph yet
            return False
        node = None
        for info in self.data_node.get_publishers_info_by_topic(topic):
            if bytes(info.endpoint_gid)[: len(gid)] == gid:
                node = self._node_of(info)
                break
        if node is None or "_UNKNOWN_" in node:  # not (fully) discovered yet: ask again a little later
            if len(self.unknown_until) >= MAX_WRITERS_PER_TOPIC:
                self.unknown_until.clear()
            self.unknown_until[(chan, gid)] = now + UNKNOWN_WRITER_RETRY
            return False
        ok = node in nodes
        with self.writers_lock:
            decided = self.writer_ok.setdefault(chan, {})
            if len(decided) >= MAX_WRITERS_PER_TOPIC:  # a flood of short-lived writers: start over
                decided.clear()
            decided[gid] = ok
        if not ok and nodes and node not in self.own_names and (chan, gid) not in self.refused_noted:
            if len(self.refused_noted) < MAX_WRITERS_PER_TOPIC:
                self.refused_noted.add((chan, gid))
                self.send(fr.encode_control({"op": "refused_writer", "chan": chan, "topic": topic, "node": node,
                                             "gid": gid.hex()}))
        return ok

    def forward(self, batch: list) -> None:
        """RawTaker batch -> MESSAGE frames of granted writers' samples, one write."""
        pack, kind, out = fr.HEAD.pack, fr.MESSAGE, []
        topics: dict[int, str] | None = None
        decided: dict[tuple[int, bytes], bool] = {}
        for chan, data, gid in batch:
            ok = decided.get((chan, gid))
            if ok is None:
                if topics is None:
                    topics = {c: entry[1] for c, entry in list(self.subs.items())}
                topic = topics.get(chan)
                ok = decided[(chan, gid)] = topic is not None and self._writer_granted(chan, topic, gid)
            if ok:
                out.append(pack(5 + len(data), kind, chan))
                out.append(data)
        if out:
            self.send(b"".join(out))

    def _proxy(self, chan: int, cls, peer: str):
        def handle(request, _response):
            with self.calls_lock:
                if self.calls_in_flight.get(chan, 0) >= MAX_CALLS_PER_SERVICE:
                    raise NoAnswer(f"channel {chan}: {MAX_CALLS_PER_SERVICE} calls wait for answers already")
                if self.peer_calls.get(peer, 0) >= MAX_CALLS_PER_PEER:
                    raise NoAnswer(f"{peer}'s services: {MAX_CALLS_PER_PEER} calls wait for answers already")
                self.calls_in_flight[chan] = self.calls_in_flight.get(chan, 0) + 1
                self.peer_calls[peer] = self.peer_calls.get(peer, 0) + 1
            try:
                rid = next(self.ids)
                slot = [threading.Event(), None]
                self.pending[rid] = slot
                self.send(fr.encode(fr.REQUEST, chan, fr.ID.pack(rid) + serialize_message(request)))
                if not slot[0].wait(CALL_TIMEOUT) or not slot[1][0]:
                    self.pending.pop(rid, None)
                    # Refused or failed: no answer at all (the client times out), never a made-up one.
                    raise NoAnswer(f"call {rid} of channel {chan}")
                try:
                    return deserialize_message(slot[1][1], cls.Response)
                except Exception as exc:  # the remote server's answer is not a response of the type
                    self.error_limited(chan, "bad answer", f"the answer to call {rid} of channel {chan} is not a "
                                       f"{cls.__name__} response ({type(exc).__name__}: {exc}): the client gets none")
                    raise NoAnswer(f"call {rid} of channel {chan}") from None
            finally:
                with self.calls_lock:
                    for table, key in ((self.calls_in_flight, chan), (self.peer_calls, peer)):
                        left = table.get(key, 1) - 1
                        if left > 0:
                            table[key] = left
                        else:
                            table.pop(key, None)

        return handle

    def spin_services(self) -> None:
        """The proxies' thread. It outlives every call: one that raised had ended it, and
        with it every remote service on this robot (ROS 2 audit: one malformed answer)."""
        while rclpy.ok():
            try:
                self.srv_executor.spin_once(timeout_sec=0.5)
            except NoAnswer:
                pass
            except ExternalShutdownException:
                return
            except Exception as exc:
                self.error(f"a proxied call failed: {type(exc).__name__}: {exc}")

    def _call(self, chan: int, payload: bytes) -> None:
        (rid,) = fr.ID.unpack_from(payload)
        entry = self.clients.get(chan)
        if entry is None or not entry[0].service_is_ready():
            self.send(fr.encode(fr.RESULT, chan, fr.ID.pack(rid) + b"\x00"))
            return
        client, cls = entry
        try:
            request = deserialize_message(payload[4:], cls.Request)
        except Exception as exc:  # a caller's request that is not one of the type: answered as failed
            self.send(fr.encode(fr.RESULT, chan, fr.ID.pack(rid) + b"\x00"))
            self.error_limited(chan, "bad request", f"call {rid} of channel {chan} is not a {cls.__name__} request "
                               f"({type(exc).__name__}: {exc}): not passed to the server")
            return
        future = client.call_async(request)

        def done(f: Future) -> None:
            result = f.result() if not f.cancelled() and f.exception() is None else None
            body = b"\x01" + serialize_message(result) if result is not None else b"\x00"
            self.send(fr.encode(fr.RESULT, chan, fr.ID.pack(rid) + body))

        future.add_done_callback(done)


def _link_lost(exc: Exception | None) -> NoReturn:
    """The interceptor is gone (``exc`` None: it closed the link): so is its bridge, at
    once, from whichever thread saw it."""
    if exc is not None:
        sys.stderr.write(f"cryptoros bridge: link to the interceptor failed: {exc}\n")
        sys.stderr.flush()
    os._exit(0)


def main() -> None:
    parser = argparse.ArgumentParser(description="cryptoros DDS bridge (started by cryptoros-interceptor)")
    parser.add_argument("--fd", type=int, required=True)
    parser.add_argument("--name", default="cryptoros_bridge")
    parser.add_argument("--graph-interval", type=float, default=0.5)
    parser.add_argument("--max-size", type=int, default=fr.DEFAULT_MAX_SIZE)
    args = parser.parse_args()
    sock = socket.socket(fileno=args.fd)
    sock.setblocking(True)
    rclpy.init()
    bridge = Bridge(sock, args.name, args.graph_interval, args.max_size)
    bridge.send(
        fr.encode_control(
            {"op": "hello", "pid": os.getpid(), "rmw": rclpy.get_rmw_implementation_identifier(),
             "domain": int(os.environ.get("ROS_DOMAIN_ID", "0")), "node": bridge.own}
        )
    )
    threading.Thread(target=bridge.read_loop, name="link", daemon=True).start()
    threading.Thread(target=bridge.spin_services, name="services", daemon=True).start()
    threading.Thread(target=bridge.taker.run, args=(bridge.forward,), name="topics", daemon=True).start()
    try:
        bridge.executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    # The link, services and topics threads are inside rclpy's C++ code now: an interpreter
    # finalizing around them aborted ("terminate called without an active exception", once
    # in eight stops, measured). The interceptor removes what DDS leaves in /dev/shm.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


if __name__ == "__main__":
    main()
