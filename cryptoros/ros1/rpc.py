"""The ROS 1 node API over XML-RPC, on asyncio: server and client.

:class:`XmlRpcServer` answers calls through a ``handler(Request)`` (the node's slave
API, the master); :class:`XmlRpcClient` is a keep-alive client for one URI;
:func:`call` is a one-shot call. Both are ``asyncio`` I/O over the sans-IO
:class:`~cryptoros.ros1.xmlrpc.XmlRpcConnection`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
from collections.abc import Awaitable, Callable
from typing import Any

from cryptoros.errors import CryptorosError, RemoteProtocolError
from cryptoros.ros1.uri import make_uri, split_uri
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

log = logging.getLogger("cryptoros.ros1.node")  # one logger for every part of the node

__all__ = ["Handler", "RosApiError", "XmlRpcClient", "XmlRpcServer", "call"]

Handler = Callable[[Request], Awaitable[Response | Fault]]


class RosApiError(CryptorosError):
    """A ROS API call answered with a failure code or a fault."""


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
        return make_uri(self.host, self.port)

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
    u = split_uri(uri, scheme)
    return u.host, u.port, request_path(u.path)


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
