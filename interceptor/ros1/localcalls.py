"""XML-RPC calls to local processes (the ROS master, a local node's API) over
kept-alive connections: a burst of peers' calls (a robot's nodes registering and
subscribing at once) reuses a few connections instead of a TCP connection and a server
thread each."""

from __future__ import annotations

import asyncio
import logging

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
from interceptor.idle import IdleKeeper
from interceptor.ros1.wire import CALL_TIMEOUT, read_xmlrpc
from interceptor.streams import READ_SIZE, drain_within

#: connections kept open to one server between calls (each may hold a thread there)
MAX_IDLE = 8
#: a connection unused this long (seconds) is closed rather than reused
IDLE_SECONDS = 10.0
#: seconds between finding a node exposed and asking it to shut down (:func:`ask_to_shut_down`)
EXPOSED_SHUTDOWN_DELAY = 1.0
#: the same for a node name found exposed before (exposure.NodeGuard.REPEAT_WINDOW)
REPEAT_SHUTDOWN_DELAY = 0.05

log = logging.getLogger("cryptoros.interceptor")


class _Kept:
    __slots__ = ("reader", "writer", "conn")

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, conn: XmlRpcConnection) -> None:
        self.reader, self.writer, self.conn = reader, writer, conn


class LocalXmlRpc:
    """Calls to one plain ``http://`` XML-RPC server on this host. A call takes the
    connection used last (or opens one); a kept connection the server closed meanwhile
    fails before any byte of an answer, and the call is made once more on a new one
    (the server never read it: a restarted master or node, an idle connection closed)."""

    def __init__(self, uri: str, *, max_body: int, max_idle: int = MAX_IDLE, idle_seconds: float = IDLE_SECONDS):
        where = split_uri(uri, ("http",))
        self._host, self._port, self._path = where.host, where.port, request_path(where.path)
        self._max_body = max_body
        self._idle: IdleKeeper[_Kept] = IdleKeeper(lambda kept: kept.writer.close(), max_idle=max_idle,
                                                   idle_seconds=idle_seconds)
        self.opened = 0  # connections opened (tests, status)

    @property
    def idle_count(self) -> int:
        """Connections kept open for the next call."""
        return len(self._idle)

    async def call(self, request: Request) -> Response | Fault:
        # The path is the one the server was configured or registered with, never one a peer wrote.
        outgoing = Request(method=request.method, params=request.params, path=self._path, keep_alive=True,
                           accept_gzip=True)
        while True:
            kept = self._idle.take(lambda kept: not kept.reader.at_eof())
            reused = kept is not None
            if kept is None:
                kept = await self._open()
            try:
                kept.writer.write(kept.conn.send(outgoing))
                await drain_within(kept.writer, CALL_TIMEOUT)
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
            if event.keep_alive and not kept.conn.trailing_data.data:  # nothing unasked-for behind it
                self._idle.park(kept)
            else:
                kept.writer.close()
            return type(event)(**{**event.__dict__, "keep_alive": True})

    async def _open(self) -> _Kept:
        reader, writer = await asyncio.wait_for(
            asyncio.open_connection(self._host, self._port, limit=READ_SIZE), CALL_TIMEOUT)
        self.opened += 1
        return _Kept(reader, writer, XmlRpcConnection(Role.CLIENT, host=f"{self._host}:{self._port}",
                                                      max_body_size=self._max_body))

    def close(self) -> None:
        self._idle.close()


class LocalCalls:
    """One :class:`LocalXmlRpc` per local URI called, the least recently used closed
    past ``max_servers`` (each keeps at most ``max_idle`` connections, for at most
    ``IDLE_SECONDS``: a node that went away holds nothing for long)."""

    def __init__(self, *, max_body: int, max_servers: int = 256) -> None:
        self._max_body = max_body
        self._max_servers = max_servers
        self._servers: dict[str, LocalXmlRpc] = {}

    async def call(self, uri: str, request: Request, *, max_idle: int = 2, max_body: int | None = None
                   ) -> Response | Fault:
        """``max_idle``: connections kept to ``uri``; ``max_body``: the largest answer
        read from it (default: the one given at construction). Both set by its first call."""
        server = self._servers.pop(uri, None)
        if server is None:
            server = LocalXmlRpc(uri, max_body=max_body or self._max_body, max_idle=max_idle)
        self._servers[uri] = server  # the most recently used last
        while len(self._servers) > self._max_servers:
            self._servers.pop(next(iter(self._servers))).close()
        return await server.call(request)

    def close(self) -> None:
        while self._servers:
            self._servers.popitem()[1].close()


async def ask_to_shut_down(calls: LocalCalls, node: str, port: int, why: str,
                           hosts: tuple[str, ...] = ("127.0.0.1",), delay: float = EXPOSED_SHUTDOWN_DELAY) -> bool:
    """Ask a local node whose XML-RPC API other hosts reach to shut down (its own
    ``shutdown`` API, at the first of ``hosts`` that takes the connection: loopback, then
    the address of this host it announced, for a node bound to that address alone), as
    ``rosnode kill`` does. Refused registrations alone leave it running: rospy keeps a
    refused subscriber, and a stranger's ``publisherUpdate`` to its open port fed it
    messages around the interceptor (deployment audit). Whether it was asked.

    Asked ``delay`` seconds later, once the node is through its start: rospy shut down
    within its first milliseconds raced its TCPROS server thread into a traceback (1 run
    of 4). A node found exposed again and again (respawned by roslaunch) is asked with
    :data:`REPEAT_SHUTDOWN_DELAY`: a stranger reached such a node half of the time with
    the first time's delay (stranger audit)."""
    request = Request(method="shutdown", params=("/cryptoros", f"cryptoros: {why}"))
    await asyncio.sleep(delay)
    failure: BaseException | None = None
    for host in dict.fromkeys(hosts):
        where = f"[{host}]" if ":" in host else host
        try:
            reply = await calls.call(f"http://{where}:{port}/", request, max_idle=0)
            answer = "it agreed" if isinstance(reply, Response) else "it answered a fault"
        except RemoteProtocolError:  # rospy closes its API as it shuts down, before answering
            answer = "its API closed"
        except (OSError, asyncio.TimeoutError) as exc:
            failure = exc
            continue
        log.warning("node %s listens where other hosts reach it (port %d): asked to shut down (%s)", node, port,
                    answer)
        return True
    if isinstance(failure, ConnectionRefusedError):  # most likely it exited first (status names it if not)
        log.info("node %s (port %d) refused the connection when asked to shut down: exited already?", node, port)
        return False
    log.warning("node %s listens where other hosts reach it (port %d) and could not be asked to shut down: "
                "%s; stop it and start it with ROS_IP=127.0.0.1", node, port, failure)
    return False


async def shut_down_replaced(calls: LocalCalls, node: str, uri: str) -> None:
    """Tell the previous process of ``node``, at its XML-RPC API ``uri`` on this host, to
    shut down because a new process registered the name: what rosmaster does in plain ROS
    (its own call reaches the interceptors as a peer's ``shutdown``, never forwarded). Left
    running, the old process is deaf: rosmaster dropped its registrations (day-2 audit).
    A process already gone (a restart) refuses the connection: nothing to tell."""
    request = Request(method="shutdown", params=("/master", f"[{node}] Reason: new node registered with same name"))
    try:
        await calls.call(uri, request, max_idle=0)
    except RemoteProtocolError:  # rospy closes its API as it shuts down, before answering
        pass
    except (OSError, asyncio.TimeoutError):
        return
    log.info("node %s registered from a new process: its previous process (%s) asked to shut down", node, uri)


__all__ = ["EXPOSED_SHUTDOWN_DELAY", "IDLE_SECONDS", "MAX_IDLE", "REPEAT_SHUTDOWN_DELAY", "LocalCalls", "LocalXmlRpc",
           "ask_to_shut_down",
           "shut_down_replaced"]
