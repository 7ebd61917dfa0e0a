"""An asyncio ROS 1 node: publish, subscribe, serve and call services, node API.

Usage::

    async with Node("/talker", "http://127.0.0.1:11311") as node:
        pub = await node.advertise("/chatter", "std_msgs/String", latch=True)
        pub.publish(node.msg("std_msgs/String", data="hi"))
        sub = await node.subscribe("/chatter", "std_msgs/String")
        async for msg in sub: ...

The node is a facade over :mod:`cryptoros.ros1.rpc` (XML-RPC server and client of
the node API), :mod:`cryptoros.ros1.topics` (TCPROS server, publisher, subscriber)
and :mod:`cryptoros.ros1.services` (service server and client); every name it
exported before the split is still importable from here.

I/O is ``asyncio.Protocol`` over the sans-IO codecs in :mod:`cryptoros.ros1.tcpros`
and :mod:`cryptoros.ros1.xmlrpc`. The data path writes frames without awaiting,
coalescing the frames published within one loop iteration into one write; every
subscriber connection has a bounded outgoing buffer (frames past it are dropped, as
rospy does with a ``queue_size``; :meth:`Publisher.publish_wait` awaits room instead).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
from collections.abc import Callable
from typing import Any

from cryptoros.errors import LocalProtocolError, RemoteProtocolError
from cryptoros.ros1 import msgs, tcpros
from cryptoros.ros1.rpc import RosApiError, XmlRpcClient, XmlRpcServer, call
from cryptoros.ros1.services import ServiceServer, _ServiceClientProtocol
from cryptoros.ros1.uri import make_uri, split_uri
from cryptoros.ros1.topics import Publisher, Subscriber, _TcprosServerProtocol
from cryptoros.ros1.xmlrpc import Fault, Request, Response

log = logging.getLogger(__name__)

__all__ = [
    "Node",
    "Publisher",
    "Subscriber",
    "ServiceServer",
    "XmlRpcServer",
    "XmlRpcClient",
    "RosApiError",
    "call",
    "install_uvloop",
]


def install_uvloop() -> bool:
    """Use uvloop for new event loops if it is installed."""
    try:
        import uvloop
    except ImportError:
        return False
    asyncio.set_event_loop_policy(uvloop.EventLoopPolicy())
    return True


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
        tcpros_endpoint: tuple[str, int] | None = None,
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
        #: what requestTopic names instead of (host, TCPROS port): a relay in front of
        #: this node, e.g. a stunnel client whose far end connects to the TCPROS port
        self.tcpros_endpoint = tcpros_endpoint
        self._tcpros_server: asyncio.base_events.Server | None = None
        self._tcpros_conns: set = set()  # the TCPROS server's accepted connections (track_tcpros)
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

    def track_tcpros(self, transport) -> None:
        """A connection accepted on the TCPROS port (closed with the node)."""
        self._tcpros_conns.add(transport)

    def untrack_tcpros(self, transport) -> None:
        self._tcpros_conns.discard(transport)

    async def unadvertise(self, topic: str) -> None:
        pub = self._publishers.pop(topic, None)
        if pub is None:
            return
        for link in pub.links:
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
        with_publisher: bool = False,
    ) -> Subscriber:
        """Subscribe; ``typename='*'`` takes any type (raw bytes). ``queue_size`` bounds
        the iterator's queue (0: unbounded; oldest dropped first). ``with_publisher``:
        the callback also gets the sending publisher's connection header."""
        topic = _global(topic)
        if topic in self._subscribers:
            raise LocalProtocolError(f"{topic} is already subscribed by this node")
        sub = Subscriber(self, topic, typename, callback=callback, raw=raw, tcp_nodelay=tcp_nodelay, queue_size=queue_size,
                         with_publisher=with_publisher)
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
        return make_uri(self.host, self._tcpros_port, "rosrpc", "")

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
        u = split_uri(uri, ("rosrpc",))
        header = {"callerid": self.name, "md5sum": srv.md5sum, "persistent": "0", "service": name}
        proto = _ServiceClientProtocol(header)
        loop = asyncio.get_running_loop()
        transport, _ = await asyncio.wait_for(loop.create_connection(lambda: proto, u.host, u.port), timeout)
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
                for link in pb.links:
                    n += 1
                    info.append([n, link.peer, "o", "TCPROS", t, True, ""])
            for t, s in self._subscribers.items():
                for uri, link in s.links.items():
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
            host, port = self.tcpros_endpoint or (self.host, self._tcpros_port)
            return ok(["TCPROS", host, port], f"ready on {host}:{port}")
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
