"""The daemon's public socket: accepts connections and caps the ones still in their TLS
handshake, per source address and in all, before handing each finished one to aiohttp.

A stranger needs no certificate to open connections that never finish a ClientHello.
Listening through aiohttp's own site, 20,000 of them from one host held the daemon at its
descriptor limit: every robot's token request failed, its memory grew to 4.5 GB (each
handshake holds asyncio's 256 KiB buffer) and nothing was logged. Here a connection
counts against :data:`PER_SOURCE` and :data:`IN_ALL` from its accept until its
handshake ends (``handshake_timeout`` at most). Over its source's cap it is closed at
once, before any TLS work, with one log line per source and minute. With :data:`IN_ALL`
reached, a new connection from a source not known takes the place of the oldest
connection in its handshake of the unknown source holding the most (closed): a stranger
holds up to :data:`PER_SOURCE` on each of its addresses, a robot one or two, so a robot
never seen before (or every robot, after a restart) still gets in while strangers hold
every slot, however fast they open new ones (a stranger's audit: 640 idle connections
from 10 addresses kept a new robot out; a re-audit: evicting the oldest of all, a flood
evicted every robot in its handshake). A source a client with a verified certificate
connected from is not counted in all (only against its own address's cap); loopback is
not capped per source (the host's own processes: a fleet of clients on one machine).

A connection past its handshake counts against its client certificate's cap
(``per_client``) and the cap in all (``established``) until it closes: a certificate
holder that opened 20,000 connections and left each request head unfinished held the
daemon at its descriptor limit with 2.8 GB of memory, and every robot's token request
timed out (insider audit). Over its certificate's cap a new connection is closed at
once; with the cap in all reached, the oldest connection of the certificate holding
the most is closed to make room, unless the newcomer's own certificate holds as many
(then the newcomer is). How long a connection may sit without a request is aiohttp's
``keepalive_timeout`` (server.py: ``idle_timeout``), counted from the connection's start
and from each answer, an unfinished request head included.

A handshake that fails (no client certificate, one the CA did not issue, bytes that are
not TLS, a timeout) is counted, and the count said in one WARNING line at most every
:data:`FAILED_SUMMARY_SECONDS` with the latest source and reason (logged per handshake
at debug only, a stranger's 20,000 handshakes left nothing in the log).
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import ipaddress
import logging
import socket
import ssl
from collections.abc import Callable

from cryptoros.lru import remember
from cryptoros.ratelimit import OncePer

log = logging.getLogger("cryptoros.authz")

#: connections in their TLS handshake from one source address at most
PER_SOURCE = 64
#: ... and in all, sources that completed a handshake before not counted
IN_ALL = 512
#: seconds a connection may take to finish its TLS handshake
HANDSHAKE_TIMEOUT = 10.0
#: source addresses remembered as a verified client's
KNOWN_SOURCES = 4096
#: failed handshakes are summed up in one log line at most this often (seconds)
FAILED_SUMMARY_SECONDS = 10.0
#: connections past their handshake of one client certificate, and in all, at most
PER_CLIENT = 256
ESTABLISHED = 2048


class _Counted(asyncio.Protocol):
    """The protocol of one connection as the listener sees it: aiohttp's handler behind
    it, started only once the connection is admitted against its certificate's cap."""

    def __init__(self, inner: asyncio.Protocol, listener: TLSListener) -> None:
        self._inner: asyncio.Protocol | None = inner
        self._listener = listener
        self._client: str | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._client = self._listener._admit(self, transport)
        if self._client is None:
            self._inner = None
            transport.abort()
            return
        assert self._inner is not None
        self._inner.connection_made(transport)

    def data_received(self, data: bytes) -> None:
        if self._inner is not None:
            self._inner.data_received(data)

    def eof_received(self) -> bool | None:
        return self._inner.eof_received() if self._inner is not None else None

    def pause_writing(self) -> None:
        if self._inner is not None:
            self._inner.pause_writing()

    def resume_writing(self) -> None:
        if self._inner is not None:
            self._inner.resume_writing()

    def connection_lost(self, exc: Exception | None) -> None:
        if self._client is not None:
            self._listener._closed(self, self._client)
        if self._inner is not None:
            self._inner.connection_lost(exc)


def _loopback(address: str) -> bool:
    try:
        return ipaddress.ip_address(address.split("%", 1)[0]).is_loopback
    except ValueError:
        return False


class TLSListener:
    """Mutual TLS on ``host:port`` for ``protocol_factory`` (aiohttp's ``runner.server``);
    ``ssl_ctx`` may be replaced while it runs (a reload: new connections use it)."""

    def __init__(self, host: str, port: int, ssl_ctx: ssl.SSLContext, protocol_factory: Callable[[], asyncio.Protocol],
                 *, per_source: int = PER_SOURCE, in_all: int = IN_ALL,
                 handshake_timeout: float = HANDSHAKE_TIMEOUT, backlog: int = 1024,
                 uncapped_source: Callable[[str], bool] = _loopback,
                 failed_summary_seconds: float = FAILED_SUMMARY_SECONDS,
                 on_failed_handshake: Callable[[], None] = lambda: None,
                 per_client: int = PER_CLIENT, established: int = ESTABLISHED) -> None:
        self.host, self.port, self.ssl_ctx = host, port, ssl_ctx
        self._factory = protocol_factory
        self._uncapped_source = uncapped_source
        self.per_source, self.in_all, self.handshake_timeout, self._backlog = per_source, in_all, handshake_timeout, backlog
        self._pending: dict[str, int] = {}
        self._pending_in_all = 0
        self._known: dict[str, bool] = {}
        #: handshakes not ended, oldest first: (source, counted in all, socket)
        self._live: dict[asyncio.Task, tuple[str, bool, socket.socket]] = {}
        self._evicting: dict[asyncio.Task, socket.socket] = {}  # gave their places, not ended yet
        self.per_client, self.established = per_client, established
        #: connections past their handshake, per client certificate fingerprint, oldest first
        self._clients: dict[str, dict[_Counted, asyncio.BaseTransport]] = {}
        self._established = 0
        self.refused_clients = 0  # connections closed after their handshake, over a cap
        #: the handshakes counted in all, per source, oldest first (the ones to give a place)
        self._counted: dict[str, dict[asyncio.Task, None]] = {}
        self._sock: socket.socket | None = None
        self._task: asyncio.Task | None = None
        self._log_once = OncePer(60.0)
        self.refused = 0  # connections closed at accept, over a cap
        self.evicted = 0  # connections closed in their handshake to make room in all
        self.failed = 0  # handshakes that failed or timed out
        self._on_failed = on_failed_handshake
        self._summary_seconds = failed_summary_seconds
        #: the failures since the last summary: how many, the latest (source, error), and
        #: the summary due (None: none since the last one)
        self._failed_since = 0
        self._latest_failure: tuple[str, BaseException] | None = None
        self._summary: asyncio.TimerHandle | None = None
        self._summary_from = 0.0

    def start(self) -> None:
        """Bind and listen now (an OSError, EADDRINUSE included, is the caller's); accept
        from the next turn of the loop."""
        family = socket.AF_INET6 if ":" in self.host else socket.AF_INET
        self._sock = socket.create_server((self.host, self.port), family=family, backlog=self._backlog)
        self._sock.setblocking(False)
        self._task = asyncio.get_running_loop().create_task(self._accept())

    def pending(self) -> int:
        return sum(self._pending.values())

    async def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        for task in list(self._live):
            task.cancel()
        if self._sock is not None:
            self._sock.close()
        if self._summary is not None:
            self._summary.cancel()
            self._summarize()

    def _over_cap(self, source: str) -> str | None:
        if not self._uncapped_source(source) and self._pending.get(source, 0) >= self.per_source:
            return f"{self.per_source} connections from it in their TLS handshake already"
        return None

    def _make_room(self) -> None:
        """:data:`IN_ALL` reached: the oldest handshake counted in all of the source
        holding the most gives its place."""
        while self._pending_in_all >= self.in_all and self._counted:
            source = max(self._counted, key=lambda s: len(self._counted[s]))
            oldest = next(iter(self._counted[source]))
            self._evicting[oldest] = self._live[oldest][2]  # closed once the task ends (see _ended)
            self._release(oldest)
            oldest.cancel()
            self.evicted += 1
            if self._log_once(("evicted",)):
                log.warning("%d connections from unknown sources in their TLS handshake: the oldest of the source "
                            "holding the most closed to make room (%d so far; logged once a minute)",
                            self.in_all, self.evicted)

    def _release(self, task: asyncio.Task) -> None:
        """A handshake ended (or gave its place): it counts no more."""
        entry = self._live.pop(task, None)
        if entry is None:
            return
        source, counted, _conn = entry
        if counted:
            tasks = self._counted.get(source)
            if tasks is not None:
                tasks.pop(task, None)
                if not tasks:
                    del self._counted[source]
        left = self._pending.get(source, 0) - 1
        if left > 0:
            self._pending[source] = left
        else:
            self._pending.pop(source, None)
        self._pending_in_all -= counted

    async def _accept(self) -> None:
        loop = asyncio.get_running_loop()
        assert self._sock is not None
        while True:
            try:
                conn, address = await loop.sock_accept(self._sock)
            except asyncio.CancelledError:
                raise
            except Exception as exc:  # EMFILE and the like: the caps bind first; never spin, never stop accepting
                if self._log_once(("accept", type(exc).__name__, getattr(exc, "errno", None))):
                    log.error("cannot accept connections on %s:%d: %s", self.host, self.port,
                              getattr(exc, "strerror", None) or exc)
                await asyncio.sleep(0.1)
                continue
            source = str(address[0])
            why = self._over_cap(source)
            if why is not None:
                self.refused += 1
                conn.close()
                if self._log_once(("refused", source)):
                    log.warning("connections from %s closed at accept: %s (%d refused so far; logged once a minute "
                                "per source)", source, why, self.refused)
                continue
            counted = source not in self._known
            if counted:
                self._make_room()
            self._pending[source] = self._pending.get(source, 0) + 1
            self._pending_in_all += counted
            task = loop.create_task(self._handshake(conn, source))
            self._live[task] = (source, counted, conn)
            if counted:
                self._counted.setdefault(source, {})[task] = None
            task.add_done_callback(self._ended)

    def open_connections(self) -> int:
        """Connections past their handshake, open now."""
        return self._established

    def _admit(self, conn: _Counted, transport: asyncio.BaseTransport) -> str | None:
        """A connection's handshake is done: its certificate's fingerprint if it is
        admitted (counted until :meth:`_closed`), None if it is over a cap."""
        ssl_object = transport.get_extra_info("ssl_object")
        der = ssl_object.getpeercert(binary_form=True) if ssl_object is not None else None
        if not der:
            return None
        client = hashlib.sha256(der).hexdigest()
        held = self._clients.get(client, {})
        if len(held) >= self.per_client:
            return self._refuse(client, f"{self.per_client} connections of its certificate open already")
        if self._established >= self.established:
            most = max(self._clients, key=lambda c: len(self._clients[c]))
            if len(self._clients[most]) <= len(held) + 1:
                return self._refuse(client, f"{self.established} connections open in all, its certificate "
                                            "holding as many as any")
            oldest, victim = next(iter(self._clients[most].items()))
            self._closed(oldest, most)  # counted no more; its connection_lost finds it gone
            victim.abort()
            if self._log_once(("evicted-client", most[:16])):
                log.warning("%d connections open in all: the oldest of certificate %s, which holds the most, "
                            "closed to make room (logged once a minute per certificate)", self.established, most[:16])
        self._clients.setdefault(client, {})[conn] = transport
        self._established += 1
        return client

    def _refuse(self, client: str, why: str) -> None:
        self.refused_clients += 1
        if self._log_once(("refused-client", client[:16])):
            log.warning("connections of certificate %s closed after their handshake: %s (%d refused so far; logged "
                        "once a minute per certificate)", client[:16], why, self.refused_clients)
        return None

    def _closed(self, conn: _Counted, client: str) -> None:
        held = self._clients.get(client)
        if held is None or held.pop(conn, None) is None:
            return
        self._established -= 1
        if not held:
            del self._clients[client]

    async def _handshake(self, conn: socket.socket, source: str) -> None:
        try:
            await asyncio.get_running_loop().connect_accepted_socket(
                lambda: _Counted(self._factory(), self), conn, ssl=self.ssl_ctx,
                ssl_handshake_timeout=self.handshake_timeout)
            remember(self._known, source, True, KNOWN_SOURCES)  # a verified client certificate
        except (OSError, asyncio.TimeoutError) as exc:  # a failed or late handshake, a reset
            log.debug("TLS handshake from %s failed: %s", source, exc)
            conn.close()
            self._failed(source, exc)

    def _failed(self, source: str, exc: BaseException) -> None:
        """Counted; said by the summary due (one scheduled with the first failure after
        the last one), so a flood costs a count and a tuple per handshake."""
        self.failed += 1
        self._failed_since += 1
        self._latest_failure = (source, exc)
        self._on_failed()
        if self._summary is None:
            loop = asyncio.get_running_loop()
            self._summary_from = loop.time()
            self._summary = loop.call_later(self._summary_seconds, self._summarize)

    def _summarize(self) -> None:
        self._summary = None
        if self._latest_failure is None:
            return
        source, exc = self._latest_failure
        log.warning("%d TLS handshakes refused in the last %.0f s, latest from %s: %s (%d since start; each "
                    "one is logged at debug)", self._failed_since,
                    max(asyncio.get_running_loop().time() - self._summary_from, 1.0), source,
                    str(exc) or type(exc).__name__, self.failed)
        self._failed_since, self._latest_failure = 0, None

    def _ended(self, task: asyncio.Task) -> None:
        """A handshake task is done. A cancelled one (closed to make room, or the listener
        closing) may never have started: its socket is closed here, after asyncio closed
        the transport of one that had (closing it earlier could free its descriptor for
        the next accept while the transport still had it registered)."""
        entry = self._live.get(task)
        conn = entry[2] if entry is not None else self._evicting.pop(task, None)
        if conn is not None and task.cancelled():
            conn.close()
        self._release(task)

__all__ = ["ESTABLISHED", "FAILED_SUMMARY_SECONDS", "HANDSHAKE_TIMEOUT", "IN_ALL", "PER_CLIENT", "PER_SOURCE",
           "TLSListener"]
