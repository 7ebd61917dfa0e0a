"""An asyncio ROS 1 node: publish, subscribe, serve and call services, node API.

Usage::

    async with Node("/talker", "http://127.0.0.1:11311") as node:
        pub = await node.advertise("/chatter", "std_msgs/String", latch=True)
        pub.publish(node.msg("std_msgs/String", data="hi"))
        sub = await node.subscribe("/chatter", "std_msgs/String")
        async for msg in sub: ...

I/O is ``asyncio.Protocol`` over the sans-IO codecs in :mod:`cryptoros.ros1.tcpros`
and :mod:`cryptoros.ros1.xmlrpc`. The data path writes frames without awaiting,
coalescing the frames published within one loop iteration into one write; every
subscriber connection has a bounded outgoing buffer (frames past it are dropped, as
rospy does with a ``queue_size``; :meth:`Publisher.publish_wait` awaits room instead).
"""

from __future__ import annotations

import asyncio
import collections
import struct
import contextlib
import logging
import os
import socket
import urllib.parse
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any

from cryptoros.errors import CryptorosError, LocalProtocolError, RemoteProtocolError
from cryptoros.ros1 import msgs, tcpros
from cryptoros.ros1.tcpros import ConnectionHeader, FrameKind, TCPROSConnection
from cryptoros.ros1.xmlrpc import (
    MULTICALL,
    NEED_DATA,
    ConnectionClosed,
    Fault,
    Request,
    Response,
    Role,
    XmlRpcConnection,
    assemble_multicall,
    expand_multicall,
    request_path,
)

log = logging.getLogger(__name__)
_U32 = struct.Struct("<I")

__all__ = ["Node", "Publisher", "Subscriber", "ServiceServer", "XmlRpcServer", "XmlRpcClient", "RosApiError", "call"]

Handler = Callable[[Request], Awaitable[Response | Fault]]


class RosApiError(CryptorosError):
    """A ROS API call answered with a failure code or a fault."""


def tune_malloc(threshold: int = 16 << 20) -> bool:
    """Keep glibc from mmap-ing (and page-faulting) every buffer of 128 KiB or more:
    large messages then reuse heap memory (perf-baselines.md: +30 to 100 % on 1 MB)."""
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        m_mmap_threshold, m_trim_threshold = -3, -1
        return bool(libc.mallopt(m_mmap_threshold, threshold)) and bool(libc.mallopt(m_trim_threshold, 4 * threshold))
    except (OSError, AttributeError):
        return False


def install_uvloop() -> bool:
    """Use uvloop for new event loops if it is installed."""
    try:
        import uvloop
    except ImportError:
        return False
    asyncio.set_event_loop_policy(uvloop.EventLoopPolicy())
    return True


# ================================================================= XML-RPC server


class _XmlRpcServerProtocol(asyncio.Protocol):
    def __init__(self, handler: Handler, conns: set) -> None:
        self.handler = handler
        self.conns = conns
        self.conn = XmlRpcConnection(Role.SERVER, gzip_threshold=1400)
        self.transport: asyncio.Transport | None = None
        self.queue: asyncio.Queue[Request | None] = asyncio.Queue()
        self.task: asyncio.Task | None = None

    def connection_made(self, transport) -> None:  # type: ignore[override]
        self.transport = transport
        self.conns.add(self)
        self.task = asyncio.get_running_loop().create_task(self._serve())

    def data_received(self, data: bytes) -> None:
        self.conn.receive_data(data)
        self._pump()

    def eof_received(self) -> bool:
        self.conn.receive_data(b"")
        self._pump()
        return True

    def connection_lost(self, exc) -> None:
        self.conns.discard(self)
        self.queue.put_nowait(None)

    def _pump(self) -> None:
        while True:
            try:
                ev = self.conn.next_event()
            except RemoteProtocolError as err:
                log.info("dropping XML-RPC client: %s", err)
                self.queue.put_nowait(None)
                return
            if ev is NEED_DATA:
                return
            if isinstance(ev, ConnectionClosed):
                self.queue.put_nowait(None)
                return
            self.queue.put_nowait(ev)

    async def _serve(self) -> None:
        try:
            while True:
                req = await self.queue.get()
                if req is None:
                    break
                if req.method == MULTICALL:
                    try:
                        calls = expand_multicall(req)
                        results = [await self._one(c) for c in calls]
                        resp: Response | Fault = assemble_multicall(results, keep_alive=req.keep_alive)
                    except RemoteProtocolError as err:
                        resp = Fault(code=1, string=str(err))
                else:
                    resp = await self._one(req)
                if not req.keep_alive:
                    resp = type(resp)(**{**resp.__dict__, "keep_alive": False})
                assert self.transport is not None
                if self.transport.is_closing():
                    break
                self.transport.write(self.conn.send(resp))
                if not req.keep_alive:
                    break
        finally:
            if self.transport is not None:
                self.transport.close()

    async def _one(self, req: Request) -> Response | Fault:
        try:
            return await self.handler(req)
        except RemoteProtocolError as err:
            return Fault(code=1, string=f"bad call: {err}")
        except Exception as err:  # a handler bug must not kill the server
            log.exception("XML-RPC handler failed for %s", req.method)
            return Fault(code=1, string=f"{type(err).__name__}: {err}")


class XmlRpcServer:
    """An asyncio HTTP/1.1 XML-RPC server; ``handler(Request)`` returns the answer."""

    def __init__(self, handler: Handler, host: str = "127.0.0.1", port: int = 0) -> None:
        self.handler = handler
        self.host = host
        self.port = port
        self.server: asyncio.base_events.Server | None = None
        self.conns: set[_XmlRpcServerProtocol] = set()

    async def start(self) -> None:
        loop = asyncio.get_running_loop()
        self.server = await loop.create_server(
            lambda: _XmlRpcServerProtocol(self.handler, self.conns), self.host, self.port, reuse_address=True
        )
        self.port = self.server.sockets[0].getsockname()[1]

    @property
    def uri(self) -> str:
        return f"http://{self.host}:{self.port}/"

    async def close(self) -> None:
        if self.server is not None:
            self.server.close()
            for c in list(self.conns):
                if c.transport is not None:
                    c.transport.close()
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self.server.wait_closed(), 2)
            self.server = None


# ================================================================= XML-RPC client


def _split_uri(uri: str, scheme: tuple[str, ...] = ("http",)) -> tuple[str, int, str]:
    u = urllib.parse.urlsplit(uri)
    if u.scheme not in scheme or not u.hostname or not u.port:
        raise RemoteProtocolError(f"bad URI {uri!r}")
    return u.hostname, u.port, request_path(u.path)


class XmlRpcClient:
    """A keep-alive XML-RPC client for one URI; calls are serialized."""

    def __init__(self, uri: str, *, timeout: float = 10.0) -> None:
        self.uri = uri
        self.host, self.port, self.path = _split_uri(uri)
        self.timeout = timeout
        self._lock = asyncio.Lock()
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._conn: XmlRpcConnection | None = None

    async def _connect(self) -> None:
        self._reader, self._writer = await asyncio.open_connection(self.host, self.port)
        sock = self._writer.get_extra_info("socket")
        if sock is not None:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._conn = XmlRpcConnection(Role.CLIENT, host=f"{self.host}:{self.port}")

    async def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            with contextlib.suppress(Exception):
                await self._writer.wait_closed()
        self._writer = self._reader = self._conn = None

    async def call_raw(self, method: str, *params: Any) -> Response | Fault:
        async with self._lock:
            return await asyncio.wait_for(self._call(method, params), self.timeout)

    async def _call(self, method: str, params: tuple) -> Response | Fault:
        for attempt in (0, 1):
            fresh = self._writer is None
            if fresh:
                await self._connect()
            assert self._writer and self._reader and self._conn
            try:
                self._writer.write(self._conn.send(Request(method=method, params=params, path=self.path)))
                await self._writer.drain()
                while True:
                    ev = self._conn.next_event()
                    if ev is NEED_DATA:
                        data = await self._reader.read(65536)
                        self._conn.receive_data(data)
                        continue
                    if isinstance(ev, ConnectionClosed):
                        raise ConnectionResetError("server closed the connection")
                    if not ev.keep_alive:
                        await self.close()
                    return ev
            except (ConnectionError, RemoteProtocolError) as err:
                await self.close()
                # a kept-alive connection the server dropped: retry once on a new one
                if fresh or attempt or isinstance(err, RemoteProtocolError):
                    raise
        raise AssertionError("unreachable")

    async def call(self, method: str, *params: Any) -> Any:
        """Call a ROS API method: returns the value of ``[code, msg, value]`` when
        ``code == 1``, raises :class:`RosApiError` otherwise."""
        resp = await self.call_raw(method, *params)
        if isinstance(resp, Fault):
            raise RosApiError(f"{method}: fault {resp.code}: {resp.string}")
        v = resp.value
        if not isinstance(v, list) or len(v) != 3:
            raise RemoteProtocolError(f"{method}: reply is not [code, msg, value]: {v!r}")
        if v[0] != 1:
            raise RosApiError(f"{method}: {v[1]} (code {v[0]})")
        return v[2]


async def call(uri: str, method: str, *params: Any, timeout: float = 10.0) -> Any:
    """One-shot ROS API call on a fresh connection."""
    client = XmlRpcClient(uri, timeout=timeout)
    try:
        return await client.call(method, *params)
    finally:
        await client.close()


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
        self.pub._links.discard(self)
        self.resume_writing()


class _ServiceConn:
    """One service client connected to one of our services (after the header)."""

    def __init__(self, service: ServiceServer, transport: asyncio.Transport, conn: TCPROSConnection) -> None:
        self.service = service
        self.transport = transport
        self.conn = conn
        self.queue: asyncio.Queue[bytes | None] = asyncio.Queue()
        self.task = asyncio.get_running_loop().create_task(self._serve())

    def feed(self) -> None:
        try:
            while True:
                ev = self.conn.next_event()
                if ev is tcpros.NEED_DATA:
                    return
                if isinstance(ev, tcpros.ConnectionClosed):
                    self.queue.put_nowait(None)
                    return
                if isinstance(ev, tcpros.Message):
                    self.queue.put_nowait(ev.data)
        except RemoteProtocolError as err:
            log.info("service %s: bad request stream: %s", self.service.name, err)
            self.queue.put_nowait(None)

    async def _serve(self) -> None:
        try:
            while (data := await self.queue.get()) is not None:
                ok, out = await self.service._handle(data)
                if self.transport.is_closing():
                    return
                self.transport.write(tcpros.encode_service_response(ok, out))
        finally:
            self.transport.close()


class _TcprosServerProtocol(asyncio.Protocol):
    """Accepts connections on the node's TCPROS port and demultiplexes on the header."""

    def __init__(self, node: Node) -> None:
        self.node = node
        self.conn = TCPROSConnection(max_header_size=node.max_header_size, max_frame_size=node.max_frame_size)
        self.transport: asyncio.Transport | None = None
        self.delegate: _Outgoing | _ServiceConn | None = None

    def connection_made(self, transport) -> None:  # type: ignore[override]
        self.transport = transport
        self.node._tcpros_conns.add(transport)

    def connection_lost(self, exc) -> None:
        self.node._tcpros_conns.discard(self.transport)
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
        pub._links.add(link)
        if pub.latch and pub._last is not None:
            link.write(pub._last)
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
    ) -> None:
        self.node = node
        self.topic = topic
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
            for item in items:
                try:
                    r = cb(item)
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


# ================================================================= services


class ServiceServer:
    def __init__(self, node: Node, name: str, srv: msgs.ServiceType, handler: Callable[[Any], Any]) -> None:
        self.node = node
        self.name = name
        self.type = srv
        self.handler = handler

    async def _handle(self, data: bytes) -> tuple[bool, bytes]:
        try:
            req = msgs.deserialize(data, self.type.request, self.type.store)
            resp = self.handler(req)
            if asyncio.iscoroutine(resp):
                resp = await resp
            return True, msgs.serialize(resp, self.type.response, self.type.store)
        except Exception as err:
            log.info("service %s failed: %r", self.name, err)
            return False, f"service cannot process request: {err}".encode()

    async def close(self) -> None:
        await self.node.unadvertise_service(self.name)


class _ServiceClientProtocol(asyncio.Protocol):
    def __init__(self, header: dict[str, str]) -> None:
        self.header = header
        self.conn = TCPROSConnection(frame_kind=FrameKind.SERVICE_RESPONSE)
        self.events: asyncio.Queue = asyncio.Queue()
        self.transport: asyncio.Transport | None = None

    def connection_made(self, transport) -> None:  # type: ignore[override]
        self.transport = transport
        transport.write(tcpros.encode_header(self.header))

    def data_received(self, data: bytes) -> None:
        self.conn.receive_data(data)
        self._pump()

    def eof_received(self) -> bool:
        self.conn.receive_data(b"")
        self._pump()
        return False

    def connection_lost(self, exc) -> None:
        self.events.put_nowait(ConnectionResetError("service connection lost"))

    def _pump(self) -> None:
        try:
            while (ev := self.conn.next_event()) is not tcpros.NEED_DATA:
                self.events.put_nowait(ev)
                if isinstance(ev, tcpros.ConnectionClosed):
                    return
        except RemoteProtocolError as err:
            self.events.put_nowait(err)

    async def next(self, timeout: float) -> Any:
        ev = await asyncio.wait_for(self.events.get(), timeout)
        if isinstance(ev, BaseException):
            raise ev
        if isinstance(ev, tcpros.ConnectionClosed):
            raise RemoteProtocolError("service closed the connection")
        return ev


# ================================================================= node


def _global(name: str, namespace: str = "/") -> str:
    if not name:
        raise LocalProtocolError("empty ROS name")
    return name if name.startswith("/") else namespace.rstrip("/") + "/" + name


class Node:
    """A ROS 1 node on asyncio. ``await start()`` (or ``async with``) binds its
    XML-RPC and TCPROS ports on ``host``; ``close()`` unregisters everything."""

    def __init__(
        self,
        name: str,
        master_uri: str | None = None,
        *,
        host: str | None = None,
        xmlrpc_port: int = 0,
        tcpros_port: int = 0,
        store: msgs.Typestore | None = None,
        max_header_size: int = tcpros.DEFAULT_MAX_HEADER_SIZE,
        max_frame_size: int = tcpros.DEFAULT_MAX_FRAME_SIZE,
        api_timeout: float = 10.0,
    ) -> None:
        self.name = _global(name)
        self.master_uri = master_uri or os.environ.get("ROS_MASTER_URI", "http://127.0.0.1:11311")
        self.host = host or os.environ.get("ROS_IP") or os.environ.get("ROS_HOSTNAME") or "127.0.0.1"
        self.store = store or msgs.typestore()
        self.max_header_size = max_header_size
        self.max_frame_size = max_frame_size
        self.api_timeout = api_timeout
        self.xmlrpc = XmlRpcServer(self._handle_api, self.host, xmlrpc_port)
        self._tcpros_port = tcpros_port
        self._tcpros_server: asyncio.base_events.Server | None = None
        self._tcpros_conns: set = set()
        self._publishers: dict[str, Publisher] = {}
        self._subscribers: dict[str, Subscriber] = {}
        self._services: dict[str, ServiceServer] = {}
        self._tasks: set[asyncio.Task] = set()
        self._master: XmlRpcClient | None = None
        self._started = False
        self._closed = False
        self.shutdown_requested = asyncio.Event()
        self.shutdown_reason = ""

    # -- lifecycle
    async def start(self) -> Node:
        loop = asyncio.get_running_loop()
        await self.xmlrpc.start()
        self._tcpros_server = await loop.create_server(
            lambda: _TcprosServerProtocol(self), self.host, self._tcpros_port, reuse_address=True
        )
        self._tcpros_port = self._tcpros_server.sockets[0].getsockname()[1]
        self._master = XmlRpcClient(self.master_uri, timeout=self.api_timeout)
        self._started = True
        return self

    async def __aenter__(self) -> Node:
        return await self.start()

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    @property
    def uri(self) -> str:
        return self.xmlrpc.uri

    @property
    def tcpros_port(self) -> int:
        return self._tcpros_port

    def _spawn(self, coro) -> asyncio.Task:
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    async def master(self, method: str, *params: Any) -> Any:
        if self._master is None:
            raise LocalProtocolError("node not started")
        return await self._master.call(method, self.name, *params)

    async def call_api(self, uri: str, method: str, *params: Any) -> Any:
        return await call(uri, method, *params, timeout=self.api_timeout)

    async def close(self) -> None:
        """Unregister everything (one ``system.multicall``-free sequence of calls),
        close connections and servers. Bounded: a dead master costs at most a few s."""
        if self._closed or not self._started:
            self._closed = True
            return
        self._closed = True
        with contextlib.suppress(Exception):
            async with asyncio.timeout(5):
                for topic in list(self._publishers):
                    await self.unadvertise(topic)
                for topic in list(self._subscribers):
                    await self.unsubscribe(topic)
                for name in list(self._services):
                    await self.unadvertise_service(name)
        for task in list(self._tasks):
            task.cancel()
        for t in list(self._tcpros_conns):
            t.close()
        if self._tcpros_server is not None:
            self._tcpros_server.close()
        await self.xmlrpc.close()
        if self._master is not None:
            await self._master.close()

    # -- messages
    def msg(self, typename: str, **fields: Any) -> Any:
        """Build a message of ``typename`` (fields by keyword)."""
        return msgs.msg_class(typename, self.store)(**fields)

    # -- publishing
    async def advertise(
        self, topic: str, typename: str, *, latch: bool = False, max_buffer: int = 8 << 20
    ) -> Publisher:
        topic = _global(topic)
        if topic in self._publishers:
            raise LocalProtocolError(f"{topic} is already advertised by this node")
        pub = Publisher(self, topic, typename, latch=latch, max_buffer=max_buffer)
        self._publishers[topic] = pub
        try:
            await self.master("registerPublisher", topic, pub.type, self.uri)
        except BaseException:
            del self._publishers[topic]
            raise
        return pub

    async def unadvertise(self, topic: str) -> None:
        pub = self._publishers.pop(topic, None)
        if pub is None:
            return
        for link in list(pub._links):
            link.flush()
            link.transport.close()
        await self.master("unregisterPublisher", topic, self.uri)

    # -- subscribing
    async def subscribe(
        self,
        topic: str,
        typename: str,
        callback: Callable[[Any], Any] | None = None,
        *,
        raw: bool = False,
        tcp_nodelay: bool = True,
        queue_size: int = 0,
    ) -> Subscriber:
        """Subscribe; ``typename='*'`` takes any type (raw bytes). ``queue_size`` bounds
        the iterator's queue (0: unbounded; oldest dropped first)."""
        topic = _global(topic)
        if topic in self._subscribers:
            raise LocalProtocolError(f"{topic} is already subscribed by this node")
        sub = Subscriber(self, topic, typename, callback=callback, raw=raw, tcp_nodelay=tcp_nodelay, queue_size=queue_size)
        self._subscribers[topic] = sub
        try:
            uris = await self.master("registerSubscriber", topic, sub.type, self.uri)
        except BaseException:
            del self._subscribers[topic]
            raise
        if not isinstance(uris, list):
            raise RemoteProtocolError("registerSubscriber reply is not a list")
        await sub._update([u for u in uris if isinstance(u, str)])
        return sub

    async def unsubscribe(self, topic: str, sub: Subscriber | None = None) -> None:
        current = self._subscribers.get(topic)
        if current is None or (sub is not None and current is not sub):
            return
        del self._subscribers[topic]
        current._shutdown()
        await self.master("unregisterSubscriber", topic, self.uri)

    # -- services
    @property
    def service_uri(self) -> str:
        return f"rosrpc://{self.host}:{self._tcpros_port}"

    async def advertise_service(self, name: str, srv_type: str, handler: Callable[[Any], Any]) -> ServiceServer:
        name = _global(name)
        if name in self._services:
            raise LocalProtocolError(f"{name} is already served by this node")
        svc = ServiceServer(self, name, msgs.service_type(srv_type, self.store), handler)
        self._services[name] = svc
        try:
            await self.master("registerService", name, self.service_uri, self.uri)
        except BaseException:
            del self._services[name]
            raise
        return svc

    async def unadvertise_service(self, name: str) -> None:
        if self._services.pop(name, None) is not None:
            await self.master("unregisterService", name, self.service_uri)

    async def call_service(self, name: str, srv_type: str, request: Any, *, timeout: float = 10.0) -> Any:
        """Look the service up on the master, call it once, return the response.
        A service that answers ``ok=0`` raises :class:`RosApiError` with its text."""
        name = _global(name)
        srv = msgs.service_type(srv_type, self.store)
        uri = await self.master("lookupService", name)
        u = urllib.parse.urlsplit(uri)
        if u.scheme != "rosrpc" or not u.hostname or not u.port:
            raise RemoteProtocolError(f"bad service URI {uri!r}")
        header = {"callerid": self.name, "md5sum": srv.md5sum, "persistent": "0", "service": name}
        proto = _ServiceClientProtocol(header)
        loop = asyncio.get_running_loop()
        transport, _ = await asyncio.wait_for(loop.create_connection(lambda: proto, u.hostname, u.port), timeout)
        try:
            tcpros.check_service_server_header(await proto.next(timeout))
            transport.write(tcpros.encode_frame(msgs.serialize(request, srv.request, srv.store)))
            resp = await proto.next(timeout)
            if not resp.ok:
                raise RosApiError(f"service {name} failed: {resp.error}")
            return msgs.deserialize(resp.data, srv.response, srv.store)
        finally:
            transport.close()

    # -- parameters
    async def get_param(self, key: str) -> Any:
        return await self.master("getParam", key)

    async def set_param(self, key: str, value: Any) -> None:
        await self.master("setParam", key, value)

    # -- node API (slave API)
    async def _handle_api(self, req: Request) -> Response | Fault:
        m = req.method
        p = req.params
        ok = lambda value, msg="": Response(value=[1, msg, value])  # noqa: E731
        if m == "getPid":
            return ok(os.getpid())
        if m == "getMasterUri":
            return ok(self.master_uri)
        if m == "getSubscriptions":
            return ok([[t, s.type] for t, s in self._subscribers.items()])
        if m == "getPublications":
            return ok([[t, pb.type] for t, pb in self._publishers.items()])
        if m == "getBusStats":
            return ok([[], [], []])
        if m == "getBusInfo":
            info = []
            n = 0
            for t, pb in self._publishers.items():
                for link in pb._links:
                    n += 1
                    info.append([n, link.peer, "o", "TCPROS", t, True, ""])
            for t, s in self._subscribers.items():
                for uri, link in s._links.items():
                    n += 1
                    info.append([n, uri, "i", "TCPROS", t, link.header is not None, ""])
            return ok(info)
        if m == "requestTopic":
            if len(p) != 3 or not isinstance(p[1], str) or not isinstance(p[2], list):
                return Response(value=[-1, "requestTopic(caller_id, topic, protocols)", 0])
            if p[1] not in self._publishers:
                return Response(value=[0, f"not a publisher of {p[1]}", []])
            if not any(isinstance(x, list) and x and x[0] == "TCPROS" for x in p[2]):
                return Response(value=[0, "no supported protocol", []])
            return ok(["TCPROS", self.host, self._tcpros_port], f"ready on {self.host}:{self._tcpros_port}")
        if m == "publisherUpdate":
            if len(p) != 3 or not isinstance(p[1], str) or not isinstance(p[2], list):
                return Response(value=[-1, "publisherUpdate(caller_id, topic, publishers)", 0])
            sub = self._subscribers.get(p[1])
            if sub is not None:
                await sub._update([u for u in p[2] if isinstance(u, str)])
            return ok(0)
        if m == "paramUpdate":
            return ok(0)
        if m == "shutdown":
            self.shutdown_reason = str(p[1]) if len(p) > 1 else ""
            log.warning("%s: shutdown requested: %s", self.name, self.shutdown_reason)
            self.shutdown_requested.set()
            return ok(0)
        return Fault(code=-1, string=f"method {m!r} is not supported")
