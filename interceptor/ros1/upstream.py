"""XML-RPC calls to the local ROS master (rosmaster, ``cryptoros master``) over
kept-alive connections: a burst of peers' master calls (a robot's nodes registering at
once) reuses a few connections instead of a TCP connection and a server thread each."""

from __future__ import annotations

import asyncio

from cryptoros.errors import RemoteProtocolError
from cryptoros.ros1.uri import split_uri
from cryptoros.ros1.xmlrpc import (
    ConnectionClosed,
    Fault,
    Request,
    Response,
    Role,
    XmlRpcConnection,
    request_path,
)
from interceptor.ros1.wire import CALL_TIMEOUT, read_xmlrpc
from interceptor.streams import READ_SIZE

#: connections kept open to the master between calls (each holds a thread of rosmaster)
MAX_IDLE = 8
#: a connection unused this long (seconds) is closed rather than reused
IDLE_SECONDS = 10.0


class _Kept:
    __slots__ = ("reader", "writer", "conn", "since")

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, conn: XmlRpcConnection) -> None:
        self.reader, self.writer, self.conn = reader, writer, conn
        self.since = 0.0


class UpstreamMaster:
    """Calls to one plain ``http://`` XML-RPC server on this host. A call takes the
    connection used last (or opens one); a kept connection the server closed meanwhile
    fails before any byte of an answer, and the call is made once more on a new one
    (a master call repeated is harmless: a registration made twice is one)."""

    def __init__(self, uri: str, *, max_body: int, max_idle: int = MAX_IDLE, idle_seconds: float = IDLE_SECONDS):
        where = split_uri(uri, ("http",))
        self._host, self._port, self._path = where.host, where.port, request_path(where.path)
        self._max_body = max_body
        self._max_idle = max_idle
        self._idle_seconds = idle_seconds
        self._idle: list[_Kept] = []
        self.opened = 0  # connections opened (tests, status)

    async def call(self, request: Request) -> Response | Fault:
        # The path is the one the master was configured with, never one a peer wrote.
        outgoing = Request(method=request.method, params=request.params, path=self._path, keep_alive=True,
                           accept_gzip=True)
        while True:
            kept = self._take()
            reused = kept is not None
            if kept is None:
                kept = await self._open()
            try:
                kept.writer.write(kept.conn.send(outgoing))
                await asyncio.wait_for(kept.writer.drain(), CALL_TIMEOUT)
                event = await read_xmlrpc(kept.reader, kept.conn, CALL_TIMEOUT)
                if isinstance(event, ConnectionClosed):
                    raise ConnectionResetError("closed without answering")
            except (ConnectionError, RemoteProtocolError) as exc:
                kept.writer.close()
                if reused and not kept.conn.trailing_data.data:  # closed while idle: nothing was answered
                    continue
                raise RemoteProtocolError(f"http://{self._host}:{self._port}/: {exc}") from exc
            except BaseException:
                kept.writer.close()
                raise
            if event.keep_alive:
                self._park(kept)
            else:
                kept.writer.close()
            return type(event)(**{**event.__dict__, "keep_alive": True})

    def _take(self) -> _Kept | None:
        now = asyncio.get_running_loop().time()
        while self._idle:
            kept = self._idle.pop()
            if now - kept.since < self._idle_seconds and not kept.reader.at_eof():
                return kept
            kept.writer.close()
        return None

    def _park(self, kept: _Kept) -> None:
        if len(self._idle) >= self._max_idle:
            kept.writer.close()
            return
        kept.since = asyncio.get_running_loop().time()
        self._idle.append(kept)

    async def _open(self) -> _Kept:
        reader, writer = await asyncio.wait_for(
            asyncio.open_connection(self._host, self._port, limit=READ_SIZE), CALL_TIMEOUT)
        self.opened += 1
        return _Kept(reader, writer, XmlRpcConnection(Role.CLIENT, host=f"{self._host}:{self._port}",
                                                      max_body_size=self._max_body))

    def close(self) -> None:
        while self._idle:
            self._idle.pop().writer.close()


__all__ = ["IDLE_SECONDS", "MAX_IDLE", "UpstreamMaster"]
