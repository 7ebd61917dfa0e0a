"""XML-RPC calls to a peer interceptor over tunnel streams, and the pool that shares
them per peer endpoint (given the function that opens a tunnel)."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable

from cryptoros.errors import PolicyDenied, RemoteProtocolError
from cryptoros.ros1.xmlrpc import (
    ConnectionClosed,
    Fault,
    Request,
    Response,
    Role,
    XmlRpcConnection,
)
from interceptor.idle import IdleKeeper
from interceptor.streams import Tunnel, drain_within

#: ``Gateway.open_tunnel``: a stream to a peer interceptor, the first request behind its preamble
OpenTunnel = Callable[..., Awaitable[Tunnel]]

from interceptor.ros1.wire import (
    CALL_TIMEOUT,
    POOL_BUSY,
    POOL_WAIT,
    read_xmlrpc,
)


class XmlRpcTunnel:
    """XML-RPC calls over one tunnel stream to a peer interceptor (opened lazily,
    reopened once if the peer closed an idle keep-alive stream)."""

    def __init__(self, open_tunnel: OpenTunnel, host: str, port: int, purpose: str, target: str, *,
                 max_body: int) -> None:
        self._open_tunnel = open_tunnel
        self._max_body = max_body
        self._address = (host, port)
        self._purpose = purpose
        self._target = target
        self._stream: Tunnel | None = None
        self._conn: XmlRpcConnection | None = None
        self._lock = asyncio.Lock()

    async def call(self, request: Request) -> Response | Fault:
        async with self._lock:
            for attempt in (0, 1):
                fresh = self._stream is None
                if fresh:
                    # The first request rides with the preamble: no extra round trip.
                    self._conn = XmlRpcConnection(Role.CLIENT, max_body_size=self._max_body)
                    self._stream = await self._open_tunnel(
                        *self._address, self._purpose, self._target, first=self._conn.send(request), settles=True
                    )
                    if self._stream.pending:
                        self._conn.receive_data(self._stream.pending)
                reader, writer = self._stream.reader, self._stream.writer
                try:
                    if not fresh:
                        writer.write(self._conn.send(request))
                        await drain_within(writer, CALL_TIMEOUT)
                    try:
                        event = await read_xmlrpc(reader, self._conn, CALL_TIMEOUT)
                    finally:
                        if fresh:
                            self._stream.settle()
                    if isinstance(event, ConnectionClosed):
                        raise ConnectionResetError("tunnel closed")
                    return event
                except (ConnectionError, RemoteProtocolError) as exc:
                    await self.close_locked()
                    if fresh or attempt:
                        raise PolicyDenied("tunnel_failed", f"{self._purpose} tunnel: {exc}") from exc
            raise AssertionError("unreachable")

    async def close_locked(self) -> None:
        self.close_now()

    def close_now(self) -> None:
        """Close the stream of a tunnel not in use (idle in its pool)."""
        if self._stream is not None:
            self._stream.writer.close()
            self._stream = None

    async def close(self) -> None:
        async with self._lock:
            await self.close_locked()


class TunnelPool:
    """Reusable XML-RPC tunnels to one peer endpoint: rospy opens a new connection for
    every node-API call, and a TLS handshake per call would cost about 8 KB and
    10 ms; idle tunnels are kept (up to ``max_idle``) and reused. With ``max_busy``
    calls in flight, the next one waits up to :data:`POOL_WAIT` for a tunnel to come
    back before it opens one of its own: a burst of calls (a robot's nodes registering
    at once) shares a few tunnels instead of paying a handshake each.

    A tunnel unused for ``idle_timeout`` seconds is closed (a peer closes an idle stream
    after :data:`IDLE_TIMEOUT`: this side closes first). A closed pool (:meth:`close`:
    its relay released, or evicted) keeps no tunnel: a call still under way, or made
    later through a connection that holds the pool, closes its own."""

    def __init__(self, make_tunnel: Callable[[], XmlRpcTunnel], max_idle: int = 4, max_busy: int = POOL_BUSY,
                 idle_timeout: float = 60.0, wait: float = POOL_WAIT,
                 on_idle_close: Callable[[], None] = lambda: None):
        self._make_tunnel = make_tunnel
        self._wait = wait
        self._idle: IdleKeeper[XmlRpcTunnel] = IdleKeeper(
            lambda tunnel: tunnel.close_now(), max_idle=max_idle, idle_seconds=idle_timeout, on_expired=on_idle_close)
        self._max_busy = max_busy
        self._busy = 0
        self.closed = False
        #: calls waiting for a tunnel: each gets one handed back, or None (open your own)
        self._waiters: list[asyncio.Future] = []

    @property
    def idle_count(self) -> int:
        return len(self._idle)

    async def _acquire(self) -> XmlRpcTunnel:
        if (tunnel := self._idle.take()) is not None:
            return tunnel
        if self._busy >= self._max_busy:
            waiter = asyncio.get_running_loop().create_future()
            self._waiters.append(waiter)
            try:
                tunnel = await asyncio.wait_for(waiter, self._wait)
            except asyncio.TimeoutError:
                tunnel = None
            finally:
                if waiter in self._waiters:
                    self._waiters.remove(waiter)
            if tunnel is not None:
                return tunnel
        return self._make_tunnel()

    def _hand_over(self, tunnel: XmlRpcTunnel | None) -> bool:
        """Give ``tunnel`` (None: leave to open one) to the first call still waiting."""
        while self._waiters:
            waiter = self._waiters.pop(0)
            if not waiter.done():
                waiter.set_result(tunnel)
                return True
        return False

    async def call(self, request: Request) -> Response | Fault:
        tunnel = await self._acquire()
        self._busy += 1
        try:
            response = await tunnel.call(request)
        except BaseException:
            self._busy -= 1
            self._hand_over(None)
            await tunnel.close()
            raise
        self._busy -= 1
        if self._hand_over(tunnel):
            return response
        self._park(tunnel)
        return response

    def _park(self, tunnel: XmlRpcTunnel) -> None:
        """Keep an unused tunnel for the next call (closed after ``idle_timeout``)."""
        if self.closed:
            tunnel.close_now()
            return
        self._idle.park(tunnel)

    def close(self) -> None:
        """Close the idle tunnels now, and every tunnel that comes back from then on."""
        self.closed = True
        self._idle.close()


__all__ = ["OpenTunnel", "TunnelPool", "XmlRpcTunnel"]
