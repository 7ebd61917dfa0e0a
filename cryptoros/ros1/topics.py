"""ROS 1 topics on asyncio: the node's TCPROS server, :class:`Publisher`, :class:`Subscriber`.

The TCPROS server accepts subscribers and service clients on the node's one port and
demultiplexes on the connection header (a service client is handed to
:mod:`cryptoros.ros1.services`). The data path writes frames without awaiting,
coalescing the frames published within one loop iteration into one write; the
subscriber walks frames in place with :class:`~cryptoros.ros1.tcpros.FrameWalker`.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import socket
import struct
from collections.abc import AsyncIterator, Callable
from typing import Any

from cryptoros.errors import LocalProtocolError, RemoteProtocolError
from cryptoros.ros1 import msgs, tcpros
from cryptoros.ros1.rpc import RosApiError
from cryptoros.ros1.services import _ServiceConn
from cryptoros.ros1.tcpros import ConnectionHeader, FrameKind, TCPROSConnection

#: The owning :class:`cryptoros.ros1.node.Node` (not imported: the node imports this module).
Node = Any

log = logging.getLogger("cryptoros.ros1.node")  # one logger for every part of the node
_U32 = struct.Struct("<I")

__all__ = ["Publisher", "Subscriber"]


# ================================================================= TCPROS server side


class _Outgoing(asyncio.Protocol):
    """One subscriber connected to one of our publishers (after the header)."""

    def __init__(self, pub: Publisher, transport: asyncio.Transport, peer: str) -> None:
        self.pub = pub
        self.transport = transport
        self.peer = peer
        self.pending: list[bytes] = []
        self.pending_size = 0
        self.scheduled = False
        self.paused = False
        self.drain_waiters: list[asyncio.Future] = []
        self.dropped = 0
        self.sent = 0
        self.loop = asyncio.get_running_loop()

    def write(self, frame: bytes) -> None:
        scheduled = self.scheduled
        if not scheduled and not self.paused and len(frame) < 65536:
            # latency path: the first frame of a loop iteration is written at once,
            # before any bookkeeping; the rest of a burst is coalesced into one write
            # at the end of the iteration (flush)
            transport = self.transport
            if transport.is_closing():
                return
            transport.write(frame)
            self.sent += 1
            self.scheduled = True
            self.loop.call_soon(self.flush)
            return
        if self.transport.is_closing():
            return
        if self.paused and self.transport.get_write_buffer_size() > self.pub.max_buffer:
            self.dropped += 1
            return
        self.sent += 1
        if len(frame) >= 65536:
            self.flush()
            self.transport.write(frame)
            return
        if not scheduled:
            self.scheduled = True
            self.loop.call_soon(self.flush)
            self.transport.write(frame)
            return
        self.pending.append(frame)
        self.pending_size += len(frame)
        if self.pending_size >= 262144:
            self.flush()
            self.scheduled = True

    def write_large(self, head: bytes, data: bytes | bytearray | memoryview) -> None:
        """A large frame: written as header and payload, with no concatenation copy."""
        if self.transport.is_closing():
            return
        if self.paused and self.transport.get_write_buffer_size() > self.pub.max_buffer:
            self.dropped += 1
            return
        self.sent += 1
        self.flush()
        self.transport.write(head)
        self.transport.write(data)

    def flush(self) -> None:
        self.scheduled = False
        if self.pending:
            data = self.pending[0] if len(self.pending) == 1 else b"".join(self.pending)
            self.pending = []
            self.pending_size = 0
            if not self.transport.is_closing():
                self.transport.write(data)

    def pause_writing(self) -> None:
        self.paused = True

    def resume_writing(self) -> None:
        self.paused = False
        for f in self.drain_waiters:
            if not f.done():
                f.set_result(None)
        self.drain_waiters.clear()

    async def wait_writable(self) -> None:
        if self.paused and not self.transport.is_closing():
            f = asyncio.get_running_loop().create_future()
            self.drain_waiters.append(f)
            await f

    def data_received(self, data: bytes) -> None:
        pass  # subscribers send nothing after their header

    def connection_lost(self, exc) -> None:
        self.pub.remove_link(self)
        self.resume_writing()


class _TcprosServerProtocol(asyncio.Protocol):
    """Accepts connections on the node's TCPROS port and demultiplexes on the header."""

    def __init__(self, node: Node) -> None:
        self.node = node
        self.conn = TCPROSConnection(max_header_size=node.max_header_size, max_frame_size=node.max_frame_size)
        self.transport: asyncio.Transport | None = None
        self.delegate: _Outgoing | _ServiceConn | None = None

    def connection_made(self, transport) -> None:  # type: ignore[override]
        self.transport = transport
        self.node.track_tcpros(transport)

    def connection_lost(self, exc) -> None:
        self.node.untrack_tcpros(self.transport)
        if isinstance(self.delegate, _Outgoing):
            self.delegate.connection_lost(exc)
        elif isinstance(self.delegate, _ServiceConn):
            self.delegate.queue.put_nowait(None)

    def pause_writing(self) -> None:
        if isinstance(self.delegate, _Outgoing):
            self.delegate.pause_writing()

    def resume_writing(self) -> None:
        if isinstance(self.delegate, _Outgoing):
            self.delegate.resume_writing()

    def eof_received(self) -> bool:
        self.conn.receive_data(b"")
        if isinstance(self.delegate, _ServiceConn):
            self.delegate.feed()
            return True
        if isinstance(self.delegate, _Outgoing):
            return False
        return False

    def data_received(self, data: bytes) -> None:
        if isinstance(self.delegate, _Outgoing):
            return
        self.conn.receive_data(data)
        if isinstance(self.delegate, _ServiceConn):
            self.delegate.feed()
            return
        assert self.transport is not None
        try:
            ev = self.conn.next_event()
            if ev is tcpros.NEED_DATA:
                return
            if not isinstance(ev, ConnectionHeader):
                raise RemoteProtocolError("expected a connection header")
            if "service" in ev:
                self._service(ev)
            else:
                self._topic(ev)
        except (RemoteProtocolError, LocalProtocolError) as err:
            log.info("refusing TCPROS connection: %s", err)
            with contextlib.suppress(Exception):
                self.transport.write(tcpros.encode_header({"error": str(err)}))
            self.transport.close()

    def _refuse(self, reason: str) -> None:
        assert self.transport is not None
        self.transport.write(tcpros.encode_header({"error": reason}))
        self.transport.close()

    def _topic(self, header: ConnectionHeader) -> None:
        d = tcpros.check_subscriber_header(header)
        pub = self.node._publishers.get(d["topic"])
        if pub is None:
            return self._refuse(f"no topic {d['topic']!r} on {self.node.name}")
        if d["md5sum"] not in ("*", pub.md5sum) or d["type"] not in ("*", pub.type):
            return self._refuse(
                f"client [{d['callerid']}] wants topic {d['topic']} to have datatype/md5sum "
                f"[{d['type']}/{d['md5sum']}], but our version has [{pub.type}/{pub.md5sum}]. Dropping connection."
            )
        assert self.transport is not None
        if d.get("tcp_nodelay") == "1":
            sock = self.transport.get_extra_info("socket")
            if sock is not None:
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.transport.write(
            tcpros.encode_header(
                {
                    "callerid": self.node.name,
                    "latching": "1" if pub.latch else "0",
                    "md5sum": pub.md5sum,
                    "message_definition": pub.definition,
                    "topic": pub.topic,
                    "type": pub.type,
                }
            )
        )
        link = _Outgoing(pub, self.transport, d["callerid"])
        self.delegate = link
        pub.add_link(link)
        if pub.latch and pub.last_frame is not None:
            link.write(pub.last_frame)
        pub._connected()

    def _service(self, header: ConnectionHeader) -> None:
        d = header.as_dict()
        svc = self.node._services.get(d.get("service", ""))
        if svc is None:
            return self._refuse(f"no service {d.get('service')!r} on {self.node.name}")
        assert self.transport is not None
        reply = {"callerid": self.node.name, "md5sum": svc.type.md5sum, "request_type": svc.type.name + "Request",
                 "response_type": svc.type.name + "Response", "type": svc.type.name}
        if d.get("probe") == "1":
            self.transport.write(tcpros.encode_header(reply))
            self.transport.close()
            return
        d = tcpros.check_service_client_header(header)
        if d["md5sum"] not in ("*", svc.type.md5sum):
            return self._refuse(f"request from [{d['callerid']}]: md5sums do not match: [{d['md5sum']}] vs. [{svc.type.md5sum}]")
        self.transport.write(tcpros.encode_header(reply))
        self.conn.set_frame_kind(FrameKind.MESSAGE)
        self.delegate = _ServiceConn(svc, self.transport, self.conn)
        self.delegate.feed()


# ================================================================= publisher


class Publisher:
    """A topic we publish. :meth:`publish` never blocks."""

    def __init__(self, node: Node, topic: str, typename: str, *, latch: bool, max_buffer: int) -> None:
        self.node = node
        self.topic = topic
        self.type = msgs.ros1_name(typename)
        self.md5sum = msgs.md5sum(typename, node.store)
        self.definition = msgs.message_definition(typename, node.store)
        msgs.warm(typename, node.store)
        self._store_type = msgs.store_name(typename)
        # flat types (strings, fixed-size fields): one generated struct call makes the frame
        self._frame = msgs.frame_serializer(typename, node.store) if msgs.is_flat(typename, node.store) else None
        self.latch = latch
        self.max_buffer = max_buffer
        self._links: set[_Outgoing] = set()
        self._last: bytes | None = None
        self._waiters: list[asyncio.Future] = []

    @property
    def num_connections(self) -> int:
        return len(self._links)

    @property
    def links(self) -> frozenset[_Outgoing]:
        """The subscribers' connections, as they are now."""
        return frozenset(self._links)

    @property
    def last_frame(self) -> bytes | None:
        """The last message sent (a latched topic's, for a subscriber that connects later)."""
        return self._last

    def add_link(self, link: _Outgoing) -> None:
        self._links.add(link)

    def remove_link(self, link: _Outgoing) -> None:
        self._links.discard(link)

    def _connected(self) -> None:
        for f in self._waiters:
            if not f.done():
                f.set_result(None)
        self._waiters.clear()

    async def wait_for_subscribers(self, n: int = 1, timeout: float = 10.0) -> None:
        async def wait() -> None:
            while len(self._links) < n:
                f = asyncio.get_running_loop().create_future()
                self._waiters.append(f)
                await f

        await asyncio.wait_for(wait(), timeout)

    def publish(self, msg: Any) -> None:
        make = self._frame
        if make is not None:
            try:
                frame = make(msg)
            except Exception as err:
                raise LocalProtocolError(f"cannot serialize {self.type}: {err!r}") from err
            if len(frame) < 65536:
                if self.latch:
                    self._last = frame
                for link in self._links:
                    link.write(frame)
                return
            self.publish_raw(memoryview(frame)[4:])
            return
        try:
            data = self.node.store.serialize_ros1(msg, self._store_type)
        except Exception as err:
            raise LocalProtocolError(f"cannot serialize {self.type}: {err!r}") from err
        self.publish_raw(data)

    def publish_raw(self, data: bytes | bytearray | memoryview) -> None:
        """Publish already serialized bytes."""
        if len(data) >= 65536:
            head = _U32.pack(len(data))
            if self.latch:
                self._last = head + bytes(data)
            for link in self._links:
                link.write_large(head, data)
            return
        frame = _U32.pack(len(data)) + bytes(data)
        if self.latch:
            self._last = frame
        for link in self._links:
            link.write(frame)

    async def wait_writable(self) -> None:
        """Wait until every subscriber connection accepts writes again (backpressure)."""
        for link in list(self._links):
            if link.paused:
                await link.wait_writable()

    async def publish_wait(self, msg: Any, *, raw: bool = False) -> None:
        """Publish, first waiting until no subscriber's buffer is over its limit."""
        await self.wait_writable()
        if raw:
            self.publish_raw(msg)
        else:
            self.publish(msg)

    @property
    def dropped(self) -> int:
        return sum(link.dropped for link in self._links)

    async def close(self) -> None:
        await self.node.unadvertise(self.topic)


# ================================================================= subscriber


class _Incoming(asyncio.BufferedProtocol):
    """Our connection to one publisher of a subscribed topic.

    A ``BufferedProtocol``: the event loop reads straight into a reused 64 KiB
    buffer, frames are parsed in place, and a frame too large for it (an image, a
    point cloud) is read straight into a buffer of its exact size, which is handed to
    the deserializer without another copy. Same limits as :class:`TCPROSConnection`
    (``max_header_size``, ``max_frame_size``), checked before a byte is buffered.
    """

    BUFFER = 65536

    def __init__(self, sub: Subscriber, uri: str) -> None:
        self.sub = sub
        self.uri = uri
        self.max_header_size = sub.node.max_header_size
        self.max_frame_size = sub.node.max_frame_size
        self.header_walker = tcpros.FrameWalker(max_size=self.max_header_size, what="header")
        self.walker = tcpros.FrameWalker(max_size=self.max_frame_size)
        self.transport: asyncio.Transport | None = None
        self.header: dict[str, str] | None = None
        self.ready: asyncio.Future = asyncio.get_running_loop().create_future()
        self.closed = asyncio.get_running_loop().create_future()
        self.buf = bytearray(self.BUFFER)
        self.view = memoryview(self.buf)
        self.start = 0  # first unparsed byte
        self.end = 0  # end of received data
        self.big: bytearray | None = None  # a large unit, read straight into its own buffer
        self.big_view: memoryview | None = None
        self.big_pos = 0
        self.failed = False

    def connection_made(self, transport) -> None:  # type: ignore[override]
        self.transport = transport
        sock = transport.get_extra_info("socket")
        if sock is not None and self.sub.tcp_nodelay:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        s = self.sub
        transport.write(
            tcpros.encode_header(
                {
                    "callerid": s.node.name,
                    "md5sum": s.md5sum,
                    "message_definition": s.definition,
                    "tcp_nodelay": "1" if s.tcp_nodelay else "0",
                    "topic": s.topic,
                    "type": s.type,
                }
            )
        )

    def get_buffer(self, sizehint: int) -> memoryview:
        if self.big is not None:
            assert self.big_view is not None
            return self.big_view[self.big_pos :]
        if self.end == len(self.buf):  # a partial unit at the end: move it to the front
            self._compact()
        return self.view[self.end :]

    def _compact(self) -> None:
        n = self.end - self.start
        if self.start:
            self.view[:n] = bytes(self.view[self.start : self.end])
        self.start, self.end = 0, n

    def buffer_updated(self, nbytes: int) -> None:
        if self.failed:
            self.start = self.end = 0
            return
        big = self.big
        if big is None:
            self.end += nbytes
            self._parse()
            return
        self.big_pos += nbytes
        if self.big_pos < len(big):
            return
        self.big = self.big_view = None  # type: ignore[assignment]
        if self.header is None:
            try:
                self._on_header(big)
            except RemoteProtocolError as err:
                self._fail(err)
        else:
            self.sub._deliver([big], self)

    def _on_header(self, body: bytes | bytearray | memoryview) -> None:
        header = tcpros.check_publisher_header(tcpros.decode_header(body))
        if header["md5sum"] not in ("*", self.sub.md5sum) and self.sub.md5sum != "*":
            raise RemoteProtocolError(f"publisher md5sum {header['md5sum']} != {self.sub.md5sum}")
        self.header = header
        self.sub.connection_headers.append(header)
        if not self.ready.done():
            self.ready.set_result(None)

    def _fail(self, err: Exception) -> None:
        log.info("dropping publisher %s of %s: %s", self.uri, self.sub.topic, err)
        self.failed = True
        self.start = self.end = 0
        if not self.ready.done():
            self.ready.set_exception(err)
        assert self.transport is not None
        self.transport.close()

    def _parse(self) -> None:
        view = self.view
        start, end = self.start, self.end
        if self.header is None:
            spans, stop, pending, error = self.header_walker.split(self.buf, start, end, count=1)
            if error is not None:
                return self._fail(error)
            if not spans:
                if pending is not None:
                    self._partial(start, end, pending)
                return
            try:
                self._on_header(bytes(view[spans[0][0] : spans[0][1]]))
            except RemoteProtocolError as err:
                return self._fail(err)
            start = spans[0][1]
        spans, start, pending, error = self.walker.split(self.buf, start, end)
        frames = [bytes(view[a:b]) for a, b in spans]
        if error is not None:  # the frames before it are still delivered
            self._fail(error)
        elif pending is not None:
            self._partial(start, end, pending)
        else:
            if start == end:
                start = end = 0
            self.start, self.end = start, end
        if frames:
            self.sub._deliver(frames, self)

    def _partial(self, start: int, end: int, size: int) -> None:
        """An incomplete unit of ``size`` body bytes begins at ``start``."""
        if 4 + size > len(self.buf):  # larger than the buffer: read the rest into its own
            big = bytearray(size)
            have = end - start - 4
            big[:have] = self.view[start + 4 : end]
            self.big, self.big_view, self.big_pos = big, memoryview(big), have
            self.start = self.end = 0
            return
        self.start, self.end = start, end
        if start + 4 + size > len(self.buf):
            self._compact()

    def eof_received(self) -> bool:
        return False

    def connection_lost(self, exc) -> None:
        if not self.ready.done():
            self.ready.set_exception(ConnectionResetError("publisher closed before its header"))
        if not self.closed.done():
            self.closed.set_result(None)
        self.sub._lost(self)


class Subscriber:
    """A subscription: a callback per message, or ``async for msg in sub``."""

    def __init__(
        self,
        node: Node,
        topic: str,
        typename: str,
        *,
        callback: Callable[[Any], Any] | None,
        raw: bool,
        tcp_nodelay: bool,
        queue_size: int,
        with_publisher: bool = False,
    ) -> None:
        self.node = node
        self.topic = topic
        #: the callback is called as ``callback(msg, publisher_header)`` (who sent it)
        self.with_publisher = with_publisher
        self.type = "*" if typename == "*" else msgs.ros1_name(typename)
        self.md5sum = "*" if typename == "*" else msgs.md5sum(typename, node.store)
        self.definition = "" if typename == "*" else msgs.message_definition(typename, node.store)
        self.callback = callback
        self.raw = raw or typename == "*"
        self._des = None if self.raw else msgs.deserializer(typename, node.store)
        self.tcp_nodelay = tcp_nodelay
        self.queue: collections.deque = collections.deque(maxlen=queue_size if queue_size > 0 else None)
        self._waiter: asyncio.Future | None = None
        self._links: dict[str, _Incoming] = {}
        self._connecting: dict[str, asyncio.Task] = {}
        self._closed = False
        self.connection_headers: list[dict[str, str]] = []  # every publisher header accepted
        self.received = 0
        self.errors = 0

    @property
    def num_connections(self) -> int:
        return sum(1 for c in self._links.values() if c.header is not None)

    @property
    def links(self) -> dict[str, _Incoming]:
        """The connections to publishers by their URI, as they are now (a copy)."""
        return dict(self._links)

    @property
    def publishers(self) -> list[str]:
        return sorted(self._links)

    def _deliver(self, frames: list[Any], link: _Incoming) -> None:
        self.received += len(frames)
        des = self._des
        if des is None:  # raw: bytes, as before (a large frame arrives in a bytearray)
            items = [f if type(f) is bytes else bytes(f) for f in frames]
        else:
            items = []
            for f in frames:
                try:
                    items.append(des(f))
                except RemoteProtocolError as err:
                    self.errors += 1
                    log.info("bad message on %s from %s: %s", self.topic, link.uri, err)
        cb = self.callback
        if cb is not None:
            header = link.header
            for item in items:
                try:
                    r = cb(item, header) if self.with_publisher else cb(item)
                    if asyncio.iscoroutine(r):
                        self.node._spawn(r)
                except Exception:
                    log.exception("subscriber callback failed on %s", self.topic)
            return
        self.queue.extend(items)
        w = self._waiter
        if w is not None and not w.done():
            w.set_result(None)

    def _lost(self, link: _Incoming) -> None:
        if self._links.get(link.uri) is link:
            del self._links[link.uri]

    async def wait_for_publishers(self, n: int = 1, timeout: float = 10.0) -> None:
        async def wait() -> None:
            while self.num_connections < n:
                await asyncio.sleep(0.01)

        await asyncio.wait_for(wait(), timeout)

    def __aiter__(self) -> AsyncIterator[Any]:
        return self._iter()

    async def _iter(self) -> AsyncIterator[Any]:
        while True:
            while self.queue:
                yield self.queue.popleft()
            if self._closed:
                return
            self._waiter = asyncio.get_running_loop().create_future()
            await self._waiter

    async def get(self, timeout: float | None = None) -> Any:
        """The next message (waits up to ``timeout`` seconds)."""

        async def one() -> Any:
            while not self.queue:
                if self._closed:
                    raise EOFError("subscriber closed")
                self._waiter = asyncio.get_running_loop().create_future()
                await self._waiter
            return self.queue.popleft()

        return await asyncio.wait_for(one(), timeout)

    async def _update(self, uris: list[str]) -> None:
        if self._closed:
            return
        wanted = set(uris)
        for uri in list(self._links):
            if uri not in wanted:
                link = self._links.pop(uri)
                if link.transport is not None:
                    link.transport.close()
        for uri in wanted:
            if uri not in self._links and uri not in self._connecting:
                self._connecting[uri] = self.node._spawn(self._connect(uri))

    async def _connect(self, uri: str) -> None:
        try:
            for attempt in range(3):
                try:
                    proto = await self.node.call_api(uri, "requestTopic", self.node.name, self.topic, [["TCPROS"]])
                    if not (isinstance(proto, list) and len(proto) == 3 and proto[0] == "TCPROS"):
                        raise RemoteProtocolError(f"requestTopic reply {proto!r}")
                    loop = asyncio.get_running_loop()
                    link = _Incoming(self, uri)
                    self._links[uri] = link
                    await asyncio.wait_for(loop.create_connection(lambda: link, proto[1], int(proto[2])), 5)
                    await asyncio.wait_for(link.ready, 5)
                    return
                except (OSError, asyncio.TimeoutError, RosApiError, RemoteProtocolError) as err:
                    self._links.pop(uri, None)
                    log.info("cannot connect to publisher %s of %s: %s", uri, self.topic, err)
                    if self._closed or isinstance(err, RemoteProtocolError):
                        return
                    await asyncio.sleep(0.1 * (attempt + 1))
        finally:
            self._connecting.pop(uri, None)

    async def close(self) -> None:
        await self.node.unsubscribe(self.topic, self)

    def _shutdown(self) -> None:
        self._closed = True
        for task in self._connecting.values():
            task.cancel()
        for link in self._links.values():
            if link.transport is not None:
                link.transport.close()
        self._links.clear()
        if self._waiter is not None and not self._waiter.done():
            self._waiter.set_result(None)
