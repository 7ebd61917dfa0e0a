"""ROS 1 services on asyncio: :class:`ServiceServer` and the client side of a call.

A service client connected to the node's TCPROS port is served by
:class:`_ServiceConn` (handed over by the TCPROS server of
:mod:`cryptoros.ros1.topics` after the header); :class:`_ServiceClientProtocol` is
one call of :meth:`cryptoros.ros1.node.Node.call_service`.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import Any

from cryptoros.errors import RemoteProtocolError
from cryptoros.ros1 import msgs, tcpros
from cryptoros.ros1.tcpros import FrameKind, TCPROSConnection

#: The owning :class:`cryptoros.ros1.node.Node` (not imported: the node imports this module).
Node = Any

log = logging.getLogger("cryptoros.ros1.node")  # one logger for every part of the node

__all__ = ["ServiceServer"]


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
