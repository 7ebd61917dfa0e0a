"""The inbound half of the interceptor's ``ros2`` role: streams other robots open to
this one, republished on the robot's domain or offered as a proxy service.

A ``ros2`` stream's target (:class:`~cryptoros.ros2.target.StreamTarget`) is checked
against the sender's grants for the node it names and against this robot's own
manager's grants (:meth:`Ros2Inbound.check_target`, run by the gate before the reply and
again on each fresher token the sender shows); then every sample's CDR is checked
against its type, the monitor scores or gates it, the sender's rate budget paces it,
and it is handed to the DDS bridge, on a publisher of the stream's own, with the QoS
the sender saw capped by this robot's. A remote service is offered on the domain as a
proxy: local calls go down the serving robot's stream, answers come back up it, each
checked against the service's ``.srv`` (:meth:`Ros2Inbound.service_checks`, which the
role's outbound half uses for the requests peers send to this robot's servers).

:class:`Ros2Inbound` owns what the peers' streams hold here: the open streams, the
proxies and the bytes kept for late joiners. The role (:class:`~interceptor.ros2.Ros2Role`)
owns the bridge, the channel numbers, the graph and each peer's unfinished frames (its
calls to this robot's services count too), and hands them in; it closes the streams
when the robot may receive nothing.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import os
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cryptoros.errors import PolicyDenied, RemoteProtocolError, TokenError
from cryptoros.policy.infrastructure import ros2_stays_local
from cryptoros.policy.ros2 import manager_may
from cryptoros.ros2 import framing as fr
from cryptoros.ros2.cdr import CdrError, checker_for, service_checkers
from cryptoros.ros2.target import QoS, StreamTarget, receiver_qos
from cryptoros.tunnel import Preamble
from interceptor.authz_client import PEER_TOKEN_WAIT
from interceptor.gate import Target
from interceptor.gateway import Gateway
from interceptor.monitor import WatchedStream
from interceptor.ros2_bridge import BridgeLink, DdsBridge
from interceptor.ros2_partial import PartialFrames
from interceptor.streams import READ_SIZE, InboundStream, Peer, read_chunks, widen_reader

log = logging.getLogger("cryptoros.interceptor.ros2")

#: Flow control between a peer stream and the bridge's local socket, both ways: above
#: BACKLOG_HIGH bytes unsent the reading side stops reading (TLS and TCP, or the bridge,
#: then hold the sender back) until the backlog is under BACKLOG_LOW, or for at most
#: BACKLOG_STALL seconds (nothing waits without bound)
BACKLOG_HIGH = 8 * 1024 * 1024
BACKLOG_LOW = 4 * 1024 * 1024
BACKLOG_STALL = 1.0
#: service calls under way on one stream, either way; past it a call is answered failed
MAX_PENDING_CALLS = 64
TOPIC_READ_SIZE = 1024 * 1024


@dataclass(eq=False)
class Proxy:
    """A remote service offered on this domain: requests go down one inbound stream."""

    chan: int
    writer: asyncio.StreamWriter
    pending: set[int] = field(default_factory=set)


class Ros2Inbound:
    """The streams other robots open to this one (purpose ``ros2``)."""

    def __init__(self, gateway: Gateway, bridge: DdsBridge, *, next_chan: Callable[[], int],
                 graph: Callable[[], dict[str, Any]], problem: Callable[[], PolicyDenied | None],
                 partial: PartialFrames) -> None:
        self.gw = gateway
        self.bridge = bridge
        self._next_chan = next_chan
        self._graph = graph  # the local graph the bridge last reported
        self._problem = problem  # why this robot carries nothing now (exposed, bridge down), or None
        self.writers: set[asyncio.StreamWriter] = set()  # the open streams
        self._proxies: dict[str, Proxy] = {}
        self._proxy_by_chan: dict[int, Proxy] = {}
        self._kept: dict[str, int] = {}  # peer manager -> bytes its streams make this robot keep
        self._partial = partial  # each peer's unfinished frames, across its streams both ways (the role's)
        self._prefixes = install_prefixes(self.cfg.ros2.python)

    @property
    def cfg(self):
        return self.gw.cfg  # the configuration in force (a reload replaces it)

    @property
    def metrics(self):
        return self.gw.metrics

    def service_checks(self, type_name: str) -> tuple[Callable[[bytes], None], Callable[[bytes], None]]:
        """Checks of ``type_name``'s requests and responses (:func:`cryptoros.ros2.cdr.service_checkers`,
        from the ``.srv`` file of the ROS 2 install the bridge runs on); PolicyDenied
        (``type_not_checkable``) when there is none or it cannot be read: a service whose
        bodies cannot be checked is not carried either way."""
        try:
            return service_checkers(type_name, service_definition(type_name, self._prefixes))
        except CdrError as exc:
            raise PolicyDenied("type_not_checkable", str(exc)) from None

    def close_all(self) -> None:
        """Cut every stream (the robot may receive nothing now, or the bridge restarted)."""
        for writer in list(self.writers):
            writer.transport.abort()

    def abort_idle_proxies(self) -> None:
        """A stopping interceptor: a proxy with no call under way has nothing to wait for
        (a stop gave each such stream its 5 s grace: a restart's gap)."""
        for proxy in list(self._proxies.values()):
            if not proxy.pending:
                proxy.writer.transport.abort()

    def request(self, chan: int, payload: bytes) -> None:
        """A local client called the proxy on ``chan``: the request goes to the serving robot
        (or is answered failed: no such proxy, too many calls under way)."""
        rid, cdr = fr.ID.unpack_from(payload)[0], payload[4:]
        proxy = self._proxy_by_chan.get(chan)
        if proxy is None or len(proxy.pending) >= MAX_PENDING_CALLS:
            self.bridge.link.send(fr.encode(fr.REPLY, chan, fr.ID.pack(rid) + b"\x00"))
            return
        proxy.pending.add(rid)
        log.debug("request %d for proxy channel %d goes to the serving robot", rid, chan)
        proxy.writer.write(fr.encode(fr.SRV_REQUEST, rid, cdr))

    def check_target(self, preamble: Preamble) -> Target:
        """The stream's target (malformed ones refused before the reply) and its judge:
        the peer's grant for the node, name and type it names, run before the reply and
        again on each fresher token the peer shows."""
        target = StreamTarget.decode(preamble.target)
        if ros2_stays_local(target.name, (target.type,)) or self.cfg.ros2.is_local(target.name):
            # what this robot never offers is never taken either, whatever a grant says
            raise PolicyDenied("local_name", f"{target.name} [{target.type}] stays on each robot (ROS 2's own, or "
                                             "[ros2] local here): not carried between robots")
        if not self.bridge.ready:
            raise PolicyDenied("bridge_down", "the DDS bridge is not running")
        problem = self._problem()
        if problem is not None:
            raise problem

        def judge(grants) -> None:
            if grants.allows(target.action, target.node, target.name, target.type):
                return
            # the peer's token is narrowed to what our grants need of it: our grant removed
            # takes its grant out of its next token too, and the refusal names ours (a ROS 2
            # audit: "/talker may not publish" was logged for robot B's removed subscribe)
            with contextlib.suppress(TokenError):
                own = self.gw.own_access()
                if not manager_may(own.grants, target.peer_action, target.name, target.type):
                    raise PolicyDenied("not_granted_here", f"this robot's manager {own.subject} may not "
                                                           f"{target.peer_action} {target.name} [{target.type}]")
            raise PolicyDenied("not_granted", f"{target.node} may not {target.action} {target.name} [{target.type}]")

        return Target(target, judge)

    async def serve(self, stream: InboundStream) -> None:
        reader, writer, peer = stream.reader, stream.writer, stream.peer
        target: StreamTarget = stream.resolved  # decoded and judged by the gate (check_target)
        await self.gw.keeper.ensure(PEER_TOKEN_WAIT)  # our token revoked by a grant change: its successor
        own = self.gw.own_access()
        if not manager_may(own.grants, target.peer_action, target.name, target.type):
            raise PolicyDenied(
                "not_granted_here", f"this robot's manager {own.subject} may not {target.peer_action} {target.name}"
            )
        link = self.bridge.link
        if link is None or not self.bridge.ready:
            raise PolicyDenied("bridge_down", "the DDS bridge is not running")
        monitor, watched, unregister = self.gw.monitor, None, None
        if monitor is not None and target.kind == "topic":
            monitor.check_admission(peer.manager, target.node)
            unregister = monitor.register(peer.manager, target.node, writer.transport.abort)
            watched = monitor.watch(manager=peer.manager, publisher=target.node, topic=target.name,
                                    typename=target.type, cut=writer.transport.abort, codec="cdr")
            if watched is None and monitor.settings.gates(target.name):  # never unscored
                unregister()
                raise PolicyDenied("monitor_busy", f"{target.name} is gated by the monitor, which watches as "
                                                   "many streams as it may")
        self.metrics.allowed.labels(f"ros2_{target.kind}").inc()
        self.writers.add(writer)
        try:
            if target.kind == "topic":
                with self.gw.cuttable():  # a topic stream never ends by itself: a stop cuts it at once
                    await self._republish(reader, peer, target, link, writer, stream.pending, watched)
            else:
                await self._offer_service(reader, writer, peer, target, link, stream.pending)
        finally:
            self.writers.discard(writer)
            if watched is not None:
                watched.close()
            if unregister is not None:
                unregister()

    async def _republish(self, reader, peer: Peer, target: StreamTarget, link: BridgeLink, writer,
                         first: bytes = b"", watched: WatchedStream | None = None) -> None:
        qos = self._receiver_qos(target)
        kept_depth = qos.depth if qos.durability == "transient_local" else 0
        kept = 0  # what this stream makes this robot keep for late joiners: depth x largest sample
        kept_limit = self.cfg.ros2.max_kept_bytes_per_peer
        log.info("republishing %s [%s] from %s (%s)", target.name, target.type, peer.manager, target.node)
        decoder = fr.FrameDecoder(max_size=self.cfg.ros2.max_message_size, kinds=frozenset({fr.DATA}))
        try:
            check = checker_for(target.type)
        except CdrError as exc:
            raise PolicyDenied("type_not_checkable", f"{target.type}: {exc}") from None
        refused = 0
        # a gated topic: each sample is scored before it is republished, a suspicious one dropped
        gate = watched.gate if watched is not None and self.gw.monitor.settings.gates(target.name) else None
        budget = self.gw.budget(peer)
        rx = self.metrics.bytes.labels("rx")
        # The shared public listener's readers pause the TLS transport at 2 x 64 KiB:
        # an 80 KB image would cost a pause/resume per message. Topic streams read big.
        widen_reader(reader, TOPIC_READ_SIZE)
        # Each inbound stream has a DDS publisher of its own on this robot's domain, never
        # one shared by every peer sending the topic: what one peer's stream does to its
        # writer (a flood that wedges it and its readers: docs/ros2.md, samples kept for
        # late joiners) is its own, and ends with the stream (its publisher is destroyed).
        chan = self._next_chan()
        link.control(op="advertise", chan=chan, topic=target.name, type=target.type, qos=qos.to_dict())
        partial = contextlib.ExitStack()
        charge = partial.enter_context(self._partial.charge(peer.manager, self.cfg.ros2.max_message_size))
        try:
            async for data in read_chunks(reader, TOPIC_READ_SIZE, first):
                rx.inc(len(data))
                try:
                    decoder.feed(data)
                    runs = decoder.runs()  # DATA frames, checked and kept whole: relabelled in place
                except fr.FrameError as exc:
                    raise RemoteProtocolError(str(exc)) from None
                charge(decoder.buffered)
                runs, bad = _checked_runs(runs, check)
                if gate is not None and runs:
                    runs, _dropped = _checked_runs(runs, functools.partial(_gated_sample, gate))
                if bad:
                    if not refused:
                        log.warning("DENY ros2 sample from %s on %s [%s]: %s (dropped; logged once per stream)",
                                    peer.manager, target.name, target.type, bad[0])
                    refused += len(bad)
                    self.metrics.denied.labels("ros2_sample", "malformed_sample").inc(len(bad))
                if writer.transport.is_closing():
                    break  # cut (revoked, reloaded away): what is still buffered is not republished
                if runs and kept_depth:
                    largest = max(len(p) for run in runs for p in fr.payloads(run[3]))
                    if largest * kept_depth > kept:
                        held = self._kept.get(peer.manager, 0) - kept + largest * kept_depth
                        if held > kept_limit:
                            raise PolicyDenied("kept_budget", (
                                f"{peer.manager}'s samples kept for late joiners would take {held} bytes here "
                                f"({kept_depth} x {largest} B on {target.name}); the limit is {kept_limit} "
                                "([ros2] max_kept_bytes_per_peer)"))
                        self._kept[peer.manager] = held
                        kept = largest * kept_depth
                if runs and watched is not None and gate is None:  # the monitor queues them; it scores later
                    watched.feed_messages([bytes(p) for run in runs for p in fr.payloads(run[3])])
                if not runs:
                    continue
                blocks = [fr.retag(frames, fr.PUBLISH, chan) for _, _, _, frames in runs]
                whole = blocks[0] if len(blocks) == 1 else bytearray(b"".join(blocks))
                n = sum(run[2] for run in runs)
                # throttled, never stalled: a read of a flood holds thousands of messages, and
                # handing them to the domain at once is a flood of the local readers in itself
                # (a reliable reader overrun by one writer stops delivering every writer's
                # samples: docs/ros2.md). So a read goes on in pieces of at most the bucket,
                # each when the peer's budget lets it; the rate holds within every second.
                for count, piece in fr.pieces(whole, n, max(1, int(budget.burst)) if budget else n):
                    if budget is not None:
                        while (wait := budget.delay(count)) > 0:
                            budget.throttled += 1
                            await asyncio.sleep(wait)
                    if writer.transport.is_closing():
                        break  # cut while it waited: the rest is not republished
                    link.send(piece)
                    # flow control: while the bridge is behind, stop reading this stream (TLS and
                    # TCP then hold the sender back) instead of buffering without bound
                    transport = link.transport
                    if transport is not None and transport.get_write_buffer_size() > BACKLOG_HIGH:
                        until = asyncio.get_running_loop().time() + BACKLOG_STALL
                        while (transport.get_write_buffer_size() > BACKLOG_LOW and not transport.is_closing()
                               and asyncio.get_running_loop().time() < until):
                            await asyncio.sleep(0.002)
        except PolicyDenied:
            raise
        finally:
            partial.close()
            # its publisher goes with it, and with it every sample it kept for late joiners
            link.control(op="unadvertise", chan=chan)
            if kept:
                left = self._kept.get(peer.manager, 0) - kept
                if left > 0:
                    self._kept[peer.manager] = left
                else:
                    self._kept.pop(peer.manager, None)

    def _receiver_qos(self, target: StreamTarget) -> QoS:
        """The sender's QoS is a request: this robot caps the depth at its own ``depth``
        and keeps samples for late joiners only on its ``transient_local`` topics."""
        settings = self.cfg.ros2
        return receiver_qos(target.qos, depth=settings.depth,
                            keep_for_late_joiners=settings.keeps_for_late_joiners(target.name))

    async def _offer_service(self, reader, writer, peer: Peer, target: StreamTarget, link: BridgeLink,
                             first: bytes = b"") -> None:
        if target.name in self._proxies:
            raise PolicyDenied("already_offered", f"{target.name} is already offered by another robot")
        if any(s["name"] == target.name and s.get("servers") for s in self._graph().get("services", [])):
            raise PolicyDenied("served_here", f"{target.name} has a server on this robot's domain: a second one "
                                              "would race its answers")
        _request, check_response = self.service_checks(target.type)
        proxy = Proxy(chan=self._next_chan(), writer=writer)
        self._proxies[target.name] = proxy
        self._proxy_by_chan[proxy.chan] = proxy
        link.control(op="serve", chan=proxy.chan, service=target.name, type=target.type, peer=peer.manager)
        log.info("offering remote service %s [%s] on the local domain", target.name, target.type)
        decoder = fr.FrameDecoder(max_size=self.cfg.ros2.max_message_size, kinds=frozenset({fr.SRV_RESPONSE}))
        try:
            with self._partial.charge(peer.manager, self.cfg.ros2.max_message_size) as charge:
                async for data in read_chunks(reader, READ_SIZE, first):
                    self._proxy_replies(proxy, decoder, data, link, check_response)
                    charge(decoder.buffered)
        finally:
            del self._proxies[target.name]
            del self._proxy_by_chan[proxy.chan]
            link.control(op="unserve", chan=proxy.chan)
            for rid in proxy.pending:
                link.send(fr.encode(fr.REPLY, proxy.chan, fr.ID.pack(rid) + b"\x00"))

    @staticmethod
    def _proxy_replies(proxy: Proxy, decoder: fr.FrameDecoder, data: bytes, link: BridgeLink,
                       check: Callable[[bytes], None]) -> None:
        """The answers a remote server sent for the proxy's calls, each checked against the
        service's response type (CdrError ends the stream), handed to the bridge."""
        try:
            decoder.feed(data)
            frames = decoder.frames()
            for _, rid, body in frames:
                ok, cdr = fr.split_status(body)
                if ok:
                    check(cdr)
                if rid not in proxy.pending:
                    raise RemoteProtocolError(f"response to request {rid}, which was never sent")
                proxy.pending.discard(rid)
                link.send(fr.encode(fr.REPLY, proxy.chan, fr.ID.pack(rid) + body))
        except fr.FrameError as exc:
            raise RemoteProtocolError(str(exc)) from None


_SERVICE_TYPE = re.compile(r"[A-Za-z][A-Za-z0-9_]*/srv/[A-Za-z][A-Za-z0-9_]*")


def install_prefixes(python: Path | str) -> tuple[Path, ...]:
    """Where the ROS 2 install the bridge runs on keeps its interface files: the venv of
    ``python`` (``<venv>/share/<pkg>/srv``, the PyPI wheels' layout) and every prefix of
    ``AMENT_PREFIX_PATH`` (a sourced ROS 2 install)."""
    venv = Path(python).parent.parent  # the venv's bin/python, not the interpreter it links to
    ament = [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(":") if p]
    return tuple(dict.fromkeys([venv, *ament]))


@functools.lru_cache(maxsize=256)
def service_definition(type_name: str, prefixes: tuple[Path, ...]) -> str:
    """The ``.srv`` text of ``pkg/srv/Name`` under one of ``prefixes``; CdrError if none."""
    if not _SERVICE_TYPE.fullmatch(type_name):
        raise CdrError(f"{type_name!r} is not a service type (pkg/srv/Name)")
    pkg, _srv, name = type_name.split("/")
    for prefix in prefixes:
        path = prefix / "share" / pkg / "srv" / f"{name}.srv"
        with contextlib.suppress(OSError, UnicodeDecodeError):
            return path.read_text(encoding="utf-8")
    raise CdrError(f"{type_name}: no share/{pkg}/srv/{name}.srv in the ROS 2 install "
                   f"({', '.join(map(str, prefixes))}): its bodies cannot be checked")


class _Gated(CdrError):
    """A sample the monitor's gate dropped (counted by the monitor, not as malformed)."""


def _gated_sample(gate: Callable[[bytes], bool], sample: memoryview) -> None:
    if not gate(bytes(sample)):
        raise _Gated("suspicious: dropped by the monitor's gate")


def _checked_runs(runs: list, check) -> tuple[list, list[str]]:
    """Runs of DATA frames with every sample whose CDR does not check out removed;
    the reasons of the removed ones."""
    bad: list[str] = []
    out = []
    head = fr.HEAD.size
    for kind, chan, count, frames in runs:
        pos, keep, kept, dropped = 0, [], 0, False
        view = memoryview(frames)
        while pos < len(frames):
            (length,) = fr.ID.unpack_from(frames, pos)  # u32 LE length, as the frame head starts
            stop = pos + 4 + length
            try:
                check(view[pos + head : stop])
                keep.append((pos, stop))
                kept += 1
            except CdrError as exc:
                bad.append(str(exc))
                dropped = True
            pos = stop
        view.release()
        if not dropped:
            out.append((kind, chan, count, frames))
        elif kept:
            out.append((kind, chan, kept, bytearray(b"".join(frames[a:b] for a, b in keep))))
    return out, bad


__all__ = ["BACKLOG_HIGH", "BACKLOG_LOW", "BACKLOG_STALL", "MAX_PENDING_CALLS", "Proxy", "Ros2Inbound"]
