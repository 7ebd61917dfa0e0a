"""The gateway: what every role of an interceptor shares (the asyncio edge).

One per process. It owns:

- the **public listener** (mutual TLS, handshake deadline, failed handshakes counted),
  and for every stream the sans-IO :class:`~interceptor.gate.StreamGate`: preamble
  with its deadline, the peer's token verified and bound to its certificate, limits
  (unauthenticated streams per source and certificate, new streams per second, open
  streams per peer), the opaque reply; then the stream goes to the role registered for
  its purpose, with the bytes that followed the preamble handed on explicitly;
- **tokens**: our own (:class:`~interceptor.authz_client.TokenKeeper`), peers'
  (:class:`~interceptor.authz_client.PeerVerifier`, which also keeps the registry of
  live streams: which peer, which token, which grant covers each, and cuts them on
  revocation, a removed grant or expiry plus grace), token exchange with peers;
- **outbound tunnels** to peer interceptors (:meth:`Gateway.open_tunnel`);
- the byte **pump** hand-off, per-peer message budgets, metrics, ``/healthz`` and
  ``/status``;
- **reload** through one certificate source: both TLS contexts, the authorization
  client's context and the own-certificate binding are rebuilt from the same files,
  all or nothing.

Roles (:mod:`interceptor.ros1`, :mod:`interceptor.ros2`) are composed with it: each
registers the purposes it serves (:meth:`Gateway.serve`) and the life-cycle hooks of
:class:`Role`. Neither role knows the other.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import hashlib
import logging
import os
import socket
import ssl
import time
from collections.abc import Awaitable, Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

from aiohttp import web
from cryptography import x509

from cryptoros.errors import ConfigError, CryptorosError, PolicyDenied, RemoteProtocolError, TokenError
from cryptoros.monitor.model import MonitorModel
from cryptoros.pemfiles import cert_der, cert_serial
from cryptoros.ratelimit import TokenBuckets
from cryptoros.tls import (
    FullHandshakes,
    PeerCertificateCheck,
    SessionCache,
    cert_thumbprint_s256,
    client_context,
    offering,
    peer_cert_der,
    server_context,
)
from cryptoros.tokens import AccessToken, peer_audience
from cryptoros.tunnel import NEED_DATA, Preamble, PreambleReader, PreambleReply, encode
from interceptor.authz_client import AuthzClient, PeerVerifier, TokenKeeper
from interceptor.config import InterceptorConfig, check_reload
from interceptor.denials import DenialTable
from interceptor.gate import REFRESH, PendingStreams, StreamGate, TargetCheck, feed_problem, held_feed_wait
from interceptor.metrics import Metrics
from interceptor.monitor import Monitor, quarantine_path
from interceptor.pump import FrameCounter, MessageBudget, splice

log = logging.getLogger("cryptoros.interceptor")

READ_SIZE = 65536
#: a spare connection to a peer (TLS done, no preamble yet) is used within this share of
#: the preamble timeout or turned into a token exchange: the peer's preamble deadline
#: counts from its accept (and refuses a stream that waits longer)
SPARE_AGE = 0.4
#: spare connections kept ready per peer endpoint (a subscription's TCPROS stream and a
#: service call, or a few nodes starting together, each find one)
SPARES_PER_PEER = 2
#: a spare is connected only once no stream was opened to its endpoint for this long
#: (seconds): its handshake then takes no CPU from the streams of a burst
SPARE_QUIET = 0.01
#: peer endpoints remembered (tokens they showed, views of ours they saw): the least recently
#: used go first (a peer may name endpoints on many ports of its address over time)
MAX_PEER_ENDPOINTS = 4096


@contextlib.contextmanager
def listening(what: str, endpoint: object) -> Iterator[None]:
    """A listener that cannot bind is a ConfigError naming it and its address:
    ``cannot listen on 127.0.0.2:11400 (public): Address already in use``."""
    try:
        yield
    except OSError as exc:
        detail = os.strerror(exc.errno) if exc.errno else str(exc)
        raise ConfigError(f"cannot listen on {endpoint} ({what}): {detail}") from None


def _remember(table: dict, key, value, cap: int = MAX_PEER_ENDPOINTS) -> None:
    """``table[key] = value`` as the most recent entry, keeping at most ``cap``."""
    table.pop(key, None)
    table[key] = value
    while len(table) > cap:
        del table[next(iter(table))]


@dataclass(frozen=True, slots=True)
class Peer:
    """A verified peer interceptor: the token it opened the stream with, the addresses
    its certificate names, and the stream's registration with the verifier (which
    re-judges it when the peer shows a fresher token)."""

    access: AccessToken
    hosts: frozenset[str]
    watch: Any = field(default=None, compare=False)
    #: why the gateway cut the stream ("reason" key), if it did (revoked, grant removed, expired)
    cut: dict = field(default_factory=dict, compare=False)

    @property
    def manager(self) -> str:
        return self.access.subject


@dataclass(frozen=True, slots=True)
class Tunnel:
    """A stream we opened to a peer interceptor, past its reply: ``pending`` holds the
    bytes it sent behind the reply (the role reads them first)."""

    reader: asyncio.StreamReader
    writer: asyncio.StreamWriter
    peer: Peer
    pending: bytes = b""
    #: completed by :meth:`settle` (see :meth:`Gateway.open_tunnel`, ``settles``)
    settled: asyncio.Future | None = field(default=None, compare=False)

    def settle(self) -> None:
        """This stream's set-up is over (its first reply relayed, or it failed): the
        spare connection for the next stream to this peer may be made now."""
        if self.settled is not None and not self.settled.done():
            self.settled.set_result(None)


@dataclass(frozen=True, slots=True)
class _Connected:
    """A TLS connection to a peer interceptor, before its preamble: the session it
    offered (if any) and, for a spare, the future its user completes once the peer's
    reply is verified (the spare's opening slot is held until then)."""

    reader: asyncio.StreamReader
    writer: asyncio.StreamWriter
    ssl_object: Any
    offer: Any
    used: asyncio.Future | None = None
    #: the task that made the spare (and holds its opening slot until it is used)
    maker: Any = None


@dataclass(frozen=True, slots=True)
class InboundStream:
    """A stream the gate admitted, handed to the role serving its purpose: ``pending``
    holds the bytes the peer sent behind its preamble."""

    reader: asyncio.StreamReader
    writer: asyncio.StreamWriter
    peer: Peer
    purpose: str
    target: str
    pending: bytes = b""
    #: what the role's target check resolved the target to (checked before the reply)
    resolved: Any = None


class Role:
    """A role composed with a :class:`Gateway`: what it does at each step of the
    gateway's life (each hook may do nothing), and the gateway's configuration,
    metrics and verifier as they are now (a reload swaps them in the gateway)."""

    def __init__(self, gateway: Gateway) -> None:
        self.gw = gateway

    @property
    def cfg(self) -> InterceptorConfig:
        return self.gw.cfg

    @property
    def metrics(self) -> Metrics:
        return self.gw.metrics

    @property
    def verifier(self) -> PeerVerifier:
        return self.gw.verifier

    async def prepare(self) -> None:
        """Before the first token and the public listener (restore state, start a child)."""

    async def start(self) -> None:
        """Once the gateway is up (open the role's own listeners, start its tasks)."""

    async def stopping(self) -> None:
        """Stop taking new work; the gateway then drains and cuts open streams."""

    async def stopped(self) -> None:
        """Release what is left (pools, listeners, children)."""

    def status(self) -> dict:
        """What the role adds to ``/status`` (top-level keys of its own)."""
        return {}

    def problem(self) -> PolicyDenied | None:
        """Why the role does not serve now (a deployment check failing), or None: makes
        ``/healthz`` 503 and ``cryptoros status`` exit 1 with that reason."""
        return None

    def check_reload(self, cfg: InterceptorConfig) -> None:
        """Raise CryptorosError if the role cannot take ``cfg`` without a restart."""

    def reloaded(self) -> None:
        """The gateway swapped to the new configuration."""


@functools.lru_cache(maxsize=256)
def cert_hosts(der: bytes) -> frozenset[str]:
    """IP and DNS names in a certificate's SAN: where its owner's endpoints may live
    (each certificate parsed once: a peer shows the same one on every stream)."""
    try:
        san = x509.load_der_x509_certificate(der).extensions.get_extension_for_class(x509.SubjectAlternativeName)
    except (ValueError, x509.ExtensionNotFound):
        return frozenset()
    ips = {str(ip) for ip in san.value.get_values_for_type(x509.IPAddress)}
    return frozenset(ips | set(san.value.get_values_for_type(x509.DNSName)))


def take_buffered(reader: asyncio.StreamReader) -> bytes:
    """Bytes a StreamReader received but nobody read yet, when a stream leaves the
    StreamReader for the pump (which takes the transport). The one place the edge reads
    CPython's StreamReader internals: asyncio has no public "take what is buffered"."""
    buffer = getattr(reader, "_buffer", None)
    if not buffer:
        return b""
    data = bytes(buffer)
    buffer.clear()
    return data


async def read_into(reader: asyncio.StreamReader, feed: Callable[[bytes], None], timeout: float) -> None:
    """One read (within ``timeout``) handed to a sans-IO codec's ``receive_data``."""
    data = await asyncio.wait_for(reader.read(READ_SIZE), timeout)
    feed(data)


async def read_chunks(reader: asyncio.StreamReader, size: int, first: bytes = b""):
    """``first`` (bytes already read from the stream), then every read until EOF."""
    if first:
        yield first
    while data := await reader.read(size):
        yield data


class PublicListener:
    """The public port's listening socket, accepting by hand: each accepted socket goes
    to ``on_accept(sock)`` in a task of its own before any byte of it is read (the
    gateway counts it against its caps, then starts TLS on it). ``close`` and
    ``wait_closed`` as an ``asyncio.Server``'s."""

    def __init__(self, listener: socket.socket, on_accept: Callable[[socket.socket], Awaitable[None]]) -> None:
        self._listener = listener
        self._on_accept = on_accept
        self._loop = asyncio.get_running_loop()
        self._closed = self._loop.create_future()
        self._loop.add_reader(listener.fileno(), self._accept)

    @classmethod
    async def start(cls, host: str, port: int, on_accept: Callable[[socket.socket], Awaitable[None]],
                    backlog: int = 100) -> PublicListener:
        infos = await asyncio.get_running_loop().getaddrinfo(host, port, type=socket.SOCK_STREAM,
                                                             flags=socket.AI_PASSIVE)
        family, _type, _proto, _name, address = infos[0]
        listener = socket.socket(family, socket.SOCK_STREAM)
        try:
            listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            listener.bind(address)
            listener.listen(backlog)
            listener.setblocking(False)
        except BaseException:
            listener.close()
            raise
        return cls(listener, on_accept)

    def _accept(self) -> None:
        for _ in range(64):  # a burst: take it, but let the loop run between bursts
            try:
                sock, _addr = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # out of descriptors and the like: the rest wait in the backlog
                log.warning("accept on the public port failed: %s", exc)
                self._loop.remove_reader(self._listener.fileno())
                self._loop.call_later(0.1, self._resume)
                return
            sock.setblocking(False)
            asyncio.ensure_future(self._on_accept(sock))

    def _resume(self) -> None:
        if not self._closed.done():
            self._loop.add_reader(self._listener.fileno(), self._accept)

    def close(self) -> None:
        if self._closed.done():
            return
        self._loop.remove_reader(self._listener.fileno())
        self._listener.close()
        self._closed.set_result(None)

    async def wait_closed(self) -> None:
        await self._closed


class Gateway:
    """One host's interceptor: ``serve()`` purposes and ``add_role()`` roles, then
    ``await start()``, then ``await stop()``."""

    def __init__(self, cfg: InterceptorConfig) -> None:
        self.cfg = cfg
        self.metrics = Metrics()
        self.denials = DenialTable()  # refusals, aggregated for the log and /status
        #: the runtime monitor ([monitor]); roles tap the streams it watches
        self.monitor = Monitor(cfg.monitor, self.metrics.registry, deny=self.deny,
                               state_path=quarantine_path(cfg.state_dir, cfg.manager) if cfg.state_dir else None
                               ) if cfg.monitor is not None else None
        self._server_ctx, self._client_ctx, self._sessions, self._full_handshakes, self._cert_check = (
            self._tls_state(cfg))
        self.authz = AuthzClient(cfg.authz, client_context(cfg.tls, check_hostname=True))
        self.keeper = TokenKeeper(self.authz, refresh_margin=cfg.authz.refresh_margin)
        self.verifier = PeerVerifier(
            self.authz,
            issuer=cfg.authz.issuer,
            audience=cfg.authz.audience,
            poll_interval=cfg.authz.revocation_poll_interval,
            grace=cfg.authz.token_grace,
            revocation_grace=cfg.authz.revocation_grace,
            feed_wait=self._held_feed_wait(cfg),
            feed_heartbeat=cfg.authz.feed_heartbeat,
        )
        self._own_cert_der = cert_der(cfg.tls.cert_file)
        self._own_serial = cert_serial(self._own_cert_der)  # parsed once, not per feed
        self.verifier.own_audience = peer_audience(cert_thumbprint_s256(self._own_cert_der))
        self._own_access: AccessToken | None = None
        self._own_token: str | None = None
        #: Peer interceptors we opened streams to, by (manager, certificate thumbprint):
        #: where to show them our new token and fetch theirs.
        self._peer_endpoints: dict[tuple[str, str], tuple[str, int]] = {}
        #: the last token each peer endpoint we connected to showed us
        self._peer_tokens: dict[tuple[str, int], AccessToken] = {}
        #: per peer endpoint, which of our tokens it has seen: whole (master streams) or
        #: narrowed for it (everything else); a token exchange refreshes each
        self._views: dict[tuple[str, int], set[bool]] = {}
        self._exchanges: set[tuple[str, int]] = set()
        #: streams being opened per peer endpoint (see _opening_slot); entries live while in use
        self._opening: dict[tuple[str, int], list] = {}
        #: up to SPARES_PER_PEER ready spare connections per peer endpoint, oldest first,
        #: made after a stream to it (see _want_spare)
        self._spares: dict[tuple[str, int], list[_Connected]] = {}
        #: per endpoint, the tasks making (or holding, until taken) its spares
        self._spare_makers: dict[tuple[str, int], set[asyncio.Future]] = {}
        #: per endpoint, spares being connected now (each done once ready or failed)
        self._spare_connecting: dict[tuple[str, int], set[asyncio.Future]] = {}
        #: when the last few streams to each peer endpoint were opened, newest last (how
        #: many spares it gets; they wait for a quiet moment)
        self._recent_streams: dict[tuple[str, int], list[float]] = {}
        #: incremented by :meth:`_drop_spares` (a reload, a stop): a spare whose connect
        #: began before is not listed (made with the old client context; see _keep_spare)
        self._spare_generation = 0
        self._purposes: dict[str, tuple[TargetCheck, Callable[[InboundStream], Awaitable[None]]]] = {}
        self._checks: dict[str, TargetCheck] = {}  # what the gate of every stream is given
        self._roles: list[Role] = []
        self._open_per_peer: dict[str, int] = {}
        self._pending = PendingStreams()
        self._budgets: dict[str, MessageBudget] = {}
        self._new_stream_limiter = self._stream_limiter(cfg)
        self._public_server: PublicListener | None = None
        self._tasks: list[asyncio.Task] = []
        self._streams: set[asyncio.Future] = set()
        self._cuttable: set[asyncio.Future] = set()  # streams with nothing in flight (see cuttable)
        self._metrics_runner: web.AppRunner | None = None
        self.started = False

    # ================================================================ composition
    def serve(self, purpose: str, check: TargetCheck, handler: Callable[[InboundStream], Awaitable[None]]) -> None:
        """Streams of ``purpose`` go to ``handler`` once the gate admitted them;
        ``check`` refuses a target the role does not serve before the reply."""
        if purpose in self._purposes or purpose == REFRESH:
            raise CryptorosError(f"purpose {purpose} is served twice")
        self._purposes[purpose] = (check, handler)
        self._checks[purpose] = check

    def add_role(self, role: Role) -> None:
        self._roles.append(role)

    def spawn(self, coro: Awaitable, name: str | None = None) -> asyncio.Future:
        """A background task of the gateway or a role, cancelled by :meth:`stop`."""
        task = asyncio.ensure_future(coro)
        if name and isinstance(task, asyncio.Task):
            task.set_name(name)
        self._tasks = [t for t in self._tasks if not t.done()]
        self._tasks.append(task)
        return task

    def track(self, coro: Awaitable) -> asyncio.Future:
        """A stream's task: waited for (``grace``) and then cut by :meth:`stop`."""
        future = asyncio.ensure_future(coro)
        self._streams.add(future)
        future.add_done_callback(self._streams.discard)
        return future

    async def start_local_server(self, what: str, endpoint: object,
                                 handler: Callable[[asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]],
                                 **kw: Any) -> asyncio.Server:
        """``asyncio.start_server`` for a role's listener (the local master, a relay):
        one that cannot bind is a ConfigError naming it (:func:`listening`), and a
        connection's handler that :meth:`stop` cuts ends quietly, its connection aborted
        (Python 3.11's ``start_server`` logs a traceback for a handler that ends
        cancelled). ``kw``: ``host``/``port`` or ``sock``, ``limit``."""
        async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            try:
                await handler(reader, writer)
            except asyncio.CancelledError:  # only stop() cancels a handler: nobody waits on it
                writer.transport.abort()

        with listening(what, endpoint):
            return await asyncio.start_server(handle, **kw)

    @contextlib.contextmanager
    def cuttable(self) -> Iterator[None]:
        """While inside, the current stream has nothing in flight that a stop could
        break (an XML-RPC stream waiting for its next request, a topic stream, which
        never ends by itself): :meth:`stop` cuts it at once instead of giving it the
        grace period meant for requests under way."""
        task = asyncio.current_task()
        if task is None:
            yield
            return
        self._cuttable.add(task)
        try:
            yield
        finally:
            self._cuttable.discard(task)

    # ================================================================ life cycle
    async def start(self, *, token_wait: float = 10.0) -> None:
        for role in self._roles:
            await role.prepare()
        try:
            await asyncio.wait_for(self._first_token(), token_wait)
        except (asyncio.TimeoutError, TokenError) as exc:
            log.error("no access token yet (%s): everything is refused until one arrives", exc)
        self.verifier.listeners.append(self._on_feed)
        self.verifier.stale_listeners.append(self._on_stale_peer_token)
        self.verifier.cut_listeners.append(lambda reason: self.metrics.cutoffs.labels(reason).inc())
        self.verifier.own_expiry = lambda: self.keeper.expires_at
        self.keeper.listeners.append(self._on_own_token)
        self.spawn(self.keeper.run(), "token-keeper")
        self.spawn(self.verifier.run(), "revocation-feed")
        with listening("public", self.cfg.public):
            self._public_server = await self._listen_public(self._server_ctx, self.cfg)
        if self.cfg.metrics is not None:
            with listening("metrics", self.cfg.metrics):
                await self._start_metrics()
        self.started = True
        for role in self._roles:
            await role.start()
        log.info(
            "interceptor for manager %s up: roles %s, public %s%s",
            self.cfg.manager,
            ",".join(self.cfg.roles),
            self.cfg.public,
            f", local master {self.cfg.local_master}" if self.cfg.local_master else "",
        )

    async def _first_token(self) -> None:
        while True:
            try:
                await self.keeper.refresh()
                await self.verifier.refresh_jwks()
                feed = await self.authz.fetch_revocations()
                if feed is not None:
                    self.verifier.apply(feed)
                self.verifier.last_feed_at = time.time()
                self.own_access()
                return
            except TokenError as exc:
                log.warning("waiting for the authorization server: %s", exc)
                await asyncio.sleep(0.5)

    async def _listen_public(self, ctx: ssl.SSLContext, cfg: InterceptorConfig) -> PublicListener:
        """The public listener of ``cfg`` (a reload's new one, before ``self.cfg`` is
        swapped). It accepts TCP, counted against the unauthenticated-stream caps from
        its accept, and only then makes the TLS handshake (:meth:`_on_public`): a
        connection that never sends a ClientHello holds a slot, not an unbounded
        descriptor."""
        ctx.sslobject_class = self._counting_sslobject_class()
        return await PublicListener.start(cfg.public.host, cfg.public.port, lambda sock: self._on_public(sock, ctx))

    async def _accept_tls(self, sock: socket.socket, ctx: ssl.SSLContext,
                          who: str) -> tuple[asyncio.StreamReader, asyncio.StreamWriter] | None:
        """The server side of the mutual TLS handshake on an accepted socket, within
        ``handshake_timeout``: a stream pair, or None for a failed or late handshake
        (counted and logged like every other denial, the socket closed)."""
        loop = asyncio.get_running_loop()
        reader = asyncio.StreamReader(limit=READ_SIZE)
        protocol = asyncio.StreamReaderProtocol(reader)
        try:
            with self.cuttable():  # nothing in flight yet: a stop need not wait for it
                transport, _ = await loop.connect_accepted_socket(
                    lambda: protocol, sock, ssl=ctx, ssl_handshake_timeout=self.cfg.limits.handshake_timeout)
        except asyncio.CancelledError:
            sock.close()
            raise
        except OSError as exc:  # an SSLError, a reset, the handshake deadline (TimeoutError)
            sock.close()
            if isinstance(exc, ssl.SSLError):
                return None  # counted and logged as it happened (_counting_sslobject_class)
            if isinstance(exc, TimeoutError) or "longer than" in str(exc):
                self.metrics.denied.labels("tls", "handshake_timeout").inc()
                log.warning("DENY tls handshake from %s: %s", who, str(exc) or "handshake_timeout")
            else:  # closed before or during the handshake (a port probe, a peer gone): no denial
                log.debug("connection from %s closed in its TLS handshake: %s", who, exc)
            return None
        return reader, asyncio.StreamWriter(transport, protocol, reader, loop)

    def _counting_sslobject_class(self) -> type[ssl.SSLObject]:
        """An SSLObject whose failed handshakes are counted and logged like every other
        denial (asyncio itself only logs them in debug mode), and whose handshake fails
        for a client certificate :class:`~cryptoros.tls.PeerCertificateCheck` refuses:
        one the CA revoked after the CRL was loaded (the feed's serials), one out of its
        validity period or on the CRL on a resumed handshake (which OpenSSL does not
        verify again). The client's connection then closes before any stream begins."""
        gateway = self

        class CountingSSLObject(ssl.SSLObject):
            def do_handshake(self) -> None:
                try:
                    super().do_handshake()
                except (ssl.SSLWantReadError, ssl.SSLWantWriteError):
                    raise
                except ssl.SSLError as exc:
                    reason = (exc.reason or type(exc).__name__).lower()
                    gateway.metrics.denied.labels("tls", reason).inc()
                    log.warning("DENY tls handshake: %s", exc)
                    raise
                if self.server_side:
                    try:
                        gateway._cert_check.check(peer_cert_der(self))
                    except TokenError as exc:
                        gateway.metrics.denied.labels("tls", exc.reason).inc()
                        log.warning("DENY tls handshake: %s", exc)
                        raise ssl.SSLError(ssl.SSL_ERROR_SSL, f"{exc.reason}: {exc.detail}") from None

        return CountingSSLObject

    async def stop(self, grace: float = 5.0) -> None:
        """Stop listening, cut the streams with nothing in flight (:meth:`cuttable`), let
        the others (a call, a service request under way) finish for ``grace`` seconds,
        then cut them."""
        for role in self._roles:
            await role.stopping()
        server = self._public_server
        if server is not None:
            server.close()
        for stream in list(self._cuttable):  # nothing in flight: no grace to wait for
            stream.cancel()
        waiting = [s for s in self._streams if s not in self._cuttable]
        if waiting:
            await asyncio.wait(waiting, timeout=grace)
        self._drop_spares()
        for task in self._tasks:
            task.cancel()
        for stream in list(self._streams):
            stream.cancel()
        if server is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(server.wait_closed(), 1)
        for role in self._roles:
            await role.stopped()
        if self._metrics_runner is not None:
            await self._metrics_runner.cleanup()
        await self.authz.close()

    def _tls_state(self, cfg: InterceptorConfig):
        """Everything TLS between interceptors, built from one configuration: both
        contexts, the client's kept sessions (for that client context only), the
        server's record of full handshakes and the per-handshake certificate check (the
        CRL as loaded with the contexts, and the serials the revocation feed lists now).
        A new server context draws new ticket keys, so a reload makes every earlier
        session worthless."""
        lifetime = cfg.limits.tls_session_lifetime
        client_ctx = client_context(cfg.tls, check_hostname=True, resumable=lifetime > 0)
        return (server_context(cfg.tls, tickets=1 if lifetime > 0 else 0), client_ctx,
                SessionCache(client_ctx, lifetime=lifetime), FullHandshakes(lifetime),
                PeerCertificateCheck(cfg.tls.crl_file,
                                     revoked_serials=lambda: self.verifier.revocations.revoked_serials))

    @staticmethod
    def _held_feed_wait(cfg: InterceptorConfig) -> float:
        """How long the feed's long-polls are held under ``cfg`` (:func:`held_feed_wait`)."""
        wait = held_feed_wait(cfg.authz.feed_wait, request_timeout=cfg.authz.request_timeout,
                              max_feed_age=cfg.limits.max_feed_age, heartbeat=cfg.authz.feed_heartbeat)
        if wait < cfg.authz.feed_wait:
            log.warning("[authz] feed_wait %g s is over [limits] max_feed_age %g s less request_timeout %g s "
                        "and 1 s: the feed's long-polls are held %g s", cfg.authz.feed_wait,
                        cfg.limits.max_feed_age, cfg.authz.request_timeout, wait)
        return wait

    @staticmethod
    def _stream_limiter(cfg: InterceptorConfig) -> TokenBuckets:
        """New streams per peer manager: ``max_new_connections_per_second``, twice that at once."""
        rate = cfg.limits.max_new_connections_per_second
        return TokenBuckets(rate, 2 * rate)

    def _check_peer_certificate(self, ssl_object, direction: str) -> bytes:
        """The peer's certificate, checked on every stream (resumed or not): validity
        period, CRL and the CA's revocations in the feed (for a stream in, inside the
        handshake: :meth:`_counting_sslobject_class`), then its token. Returns its DER."""
        der = peer_cert_der(ssl_object)
        resumed = bool(ssl_object.session_reused)
        self.metrics.handshakes.labels(direction, "resumed" if resumed else "full").inc()
        self.metrics.stream_checks.labels("certificate").inc()
        if direction == "in":
            self._full_handshakes.admit(der, resumed=resumed, version=ssl_object.version())
        else:
            self._cert_check.check(der)
        return der

    async def reload(self, cfg: InterceptorConfig) -> None:
        """SIGHUP: new certificates, CRL, policy and settings; open streams stay up.

        Every key of the file is either applied or refused (the table:
        :data:`interceptor.config.RELOAD`). A key that needs a restart ([authz] url,
        [listen] public, manager, roles...) refuses the whole reload with a ConfigError
        naming it, before anything is read or swapped. Otherwise all or nothing: the new
        TLS material is loaded, the public listener re-bound with the new context and
        limits, and a token bound to the new certificate fetched and verified before
        anything is swapped, so a failure (a renewed certificate the registry does not
        know yet, the authorization server down) keeps the old state everywhere (the
        caller catches and logs). Then the new configuration is swapped in and handed to
        the holders that keep a copy (authorization client, token keeper, verifier, the
        new-stream rate, the roles)."""
        check_reload(self.cfg, cfg)
        for role in self._roles:
            role.check_reload(cfg)
        monitor_model = MonitorModel.load(cfg.monitor.model) if cfg.monitor is not None else None
        # one certificate source: every holder below is built from cfg.tls
        tls_state = self._tls_state(cfg)
        server_ctx = tls_state[0]
        authz_ctx = client_context(cfg.tls, check_hostname=True)
        own_der = cert_der(cfg.tls.cert_file)
        probe = AuthzClient(cfg.authz, authz_ctx)
        try:
            token = await probe.fetch_token()
        finally:
            await probe.close()
        self.verifier.verify(token.token, own_der)  # bound to the new certificate, not revoked
        old = self._public_server
        if old is not None:
            old.close()
        try:
            self._public_server = await self._listen_public(server_ctx, cfg)
        except OSError:
            self._public_server = await self._listen_public(self._server_ctx, self.cfg)
            raise
        self._server_ctx, self._client_ctx, self._sessions, self._full_handshakes, self._cert_check = tls_state
        self._drop_spares()  # made with the old certificate: a token bound to the new one fails on them
        if cfg.limits.max_new_connections_per_second != self.cfg.limits.max_new_connections_per_second:
            self._new_stream_limiter = self._stream_limiter(cfg)
        self.cfg = cfg  # what is read per use (most [limits]) applies from here
        # every holder of the certificate reads the new one: the authorization server
        # binds the next token to it, and our own token is checked against it
        self._own_cert_der = own_der
        self._own_serial = cert_serial(own_der)
        self.verifier.own_audience = peer_audience(cert_thumbprint_s256(own_der))
        self.verifier.reconfigure(poll_interval=cfg.authz.revocation_poll_interval, grace=cfg.authz.token_grace,
                                  revocation_grace=cfg.authz.revocation_grace, feed_wait=self._held_feed_wait(cfg),
                                  feed_heartbeat=cfg.authz.feed_heartbeat)
        self.keeper.refresh_margin = cfg.authz.refresh_margin
        self.authz.settings = cfg.authz  # same servers (check_reload): request_timeout from the new session on
        await self.authz.use_ssl_context(authz_ctx)
        self.keeper.install(token)  # new grants, bound to the new certificate; peers' tokens anew
        self._own_access = None
        self.own_access()
        if self.monitor is not None and cfg.monitor is not None and monitor_model is not None:
            self.monitor.reconfigure(cfg.monitor, monitor_model)  # a retrained model: scored with from now on
        for role in self._roles:
            role.reloaded()
        log.info("reloaded certificates, CRL, policy, settings%s", " and the monitor's model" if self.monitor else "")

    # ================================================================ health
    def feed_problem(self) -> PolicyDenied | None:
        return feed_problem(refused=self.verifier.refused, last_feed_at=self.verifier.last_feed_at,
                            now=time.time(), max_age=self.cfg.limits.max_feed_age)

    def check_feed_age(self) -> None:
        problem = self.feed_problem()
        if problem is not None:
            raise problem

    def check_roles(self) -> None:
        """Raise the first role's problem (a deployment check failing), if any."""
        for role in self._roles:
            problem = role.problem()
            if problem is not None:
                raise problem

    def status(self) -> dict:
        """What ``cryptoros status`` shows: who this interceptor is to the registry now
        (token subject, grants, expiry), how fresh its view of revocations is
        (feed, CRL), how long its certificate lasts, and its peers with open streams."""
        now = time.time()
        health, token = "ok", None
        try:
            access = self.own_access()
            token = {"subject": access.subject, "jti": access.jti, "expires_in": round(access.expires_at - now),
                     "grants": [[g.node, g.action, g.name, g.type] for g in access.grants]}
            self.check_feed_age()
            self.check_roles()
        except (TokenError, PolicyDenied) as exc:
            health = f"{exc.reason}: {exc.detail}"
        cert = x509.load_der_x509_certificate(self._own_cert_der)
        crl = self.cfg.tls.crl_file
        last = self.verifier.last_feed_at
        return {
            "manager": self.cfg.manager, "pid": os.getpid(), "roles": list(self.cfg.roles), "public": str(self.cfg.public),
            "health": health, "token": token,
            "certificate": {"subject": cert.subject.rfc4514_string(), "serial": format(cert.serial_number, "x"),
                            "not_after": cert.not_valid_after_utc.isoformat(),
                            "days_left": round((cert.not_valid_after_utc.timestamp() - now) / 86400, 1)},
            "feed": {"age": None if last is None else round(now - last, 1),
                     "revoked_tokens": len(self.verifier.revocations.revoked_jtis),
                     "disabled_managers": sorted(self.verifier.revocations.disabled_subjects)},
            "crl": None if crl is None else {"file": str(crl), "age": round(now - os.stat(crl).st_mtime, 1)
                                             if os.path.exists(crl) else None},
            "peers": self.verifier.streams_by_peer(),
            "open_streams": len(self._streams),
            "message_rate": self.cfg.limits.max_messages_per_second,
            "throttled": {manager: budget.throttled for manager, budget in sorted(self._budgets.items())
                          if budget.throttled},
            "monitor": self.monitor.status() if self.monitor is not None else None,
            "denials": self.denials.table(time.monotonic()),
            **{key: value for role in self._roles for key, value in role.status().items()},
        }

    async def _start_metrics(self) -> None:
        app = web.Application()

        async def metrics(_request: web.Request) -> web.Response:
            if self.keeper.expires_at:
                self.metrics.token_expires.set(self.keeper.expires_at)
            return web.Response(body=self.metrics.render(), content_type="text/plain", charset="utf-8")

        async def healthz(_request: web.Request) -> web.Response:
            try:
                self.keeper.current()
                self.check_feed_age()
                self.own_access()  # our own token verifies now: not revoked, manager not disabled
                self.check_roles()
            except (TokenError, PolicyDenied) as exc:
                return web.json_response({"status": exc.reason, "detail": exc.detail}, status=503)
            last = self.verifier.last_feed_at
            return web.json_response({"status": "ok", "open_streams": len(self._streams),
                                      "feed_age": None if last is None else round(time.time() - last, 1)})

        async def status(_request: web.Request) -> web.Response:
            return web.json_response(self.status())

        app.router.add_get("/metrics", metrics)
        app.router.add_get("/healthz", healthz)
        app.router.add_get("/status", status)
        self._metrics_runner = web.AppRunner(app, access_log=None, handle_signals=False)
        await self._metrics_runner.setup()
        await web.TCPSite(self._metrics_runner, self.cfg.metrics.host, self.cfg.metrics.port).start()

    # ================================================================ tokens
    def _on_feed(self, revocations) -> None:
        """When the feed revokes our own token or disables our manager, drop the token
        (nothing is allowed on it any more) and ask for a new one at once."""
        own = self._own_access
        serial = self._own_serial
        if serial in revocations.revoked_serials:
            log.error("our own certificate (serial %x) was revoked by the CA: no token is issued to it any more; "
                      "renew it (cryptoros-certs renew, set-cert, SIGHUP)", serial)
            self._own_access = None
            self.keeper.invalidate()
        elif own is not None and (own.jti in revocations.revoked_jtis or own.subject in revocations.disabled_subjects):
            log.warning("our own access token was revoked; asking for a new one")
            self._own_access = None
            self.keeper.invalidate()
        elif self.started:
            self.keeper.wake()  # the registry changed: our grants may have (grants live)

    def _on_own_token(self) -> None:
        """Show every peer we have streams to our new token (and take theirs)."""
        for endpoint in set(self._peer_endpoints.values()):
            self._exchange_soon(endpoint)

    def _on_stale_peer_token(self, access: AccessToken) -> None:
        """The feed revoked a peer's token: fetch its fresh one if we know where it is
        (a peer that opened streams to us shows us its own)."""
        endpoint = self._peer_endpoints.get((access.subject, access.thumbprint))
        if endpoint is not None:
            self._exchange_soon(endpoint)

    def _exchange_soon(self, endpoint: tuple[str, int]) -> None:
        if endpoint in self._exchanges or not self.started:
            return
        self._exchanges.add(endpoint)

        async def exchange() -> None:
            try:
                for whole in sorted(self._views.get(endpoint, {False})):
                    tunnel = await self.open_tunnel(*endpoint, REFRESH, "", whole=whole)
                    tunnel.writer.close()
            except (CryptorosError, OSError, asyncio.TimeoutError) as exc:
                log.info("token exchange with %s:%d failed: %s", *endpoint, exc)
            finally:
                self._exchanges.discard(endpoint)

        self.spawn(exchange())

    def own_access(self) -> AccessToken:
        """Our own token, verified like a peer's (it carries our grants)."""
        token = self.keeper.current()
        if self._own_access is None or self._own_token != token:
            self._own_access = self.verifier.verify(token, self._own_cert_der)
            self._own_token = token
        return self._own_access

    def peer_token(self, host: str, port: int) -> AccessToken | None:
        """The last token the peer interceptor at ``host:port`` showed us, if any."""
        return self._peer_tokens.get((host, port))

    async def exchange_tokens(self, host: str, port: int) -> AccessToken:
        """Show a peer interceptor our token and take its own (no stream kept)."""
        tunnel = await self.open_tunnel(host, port, REFRESH, "")
        tunnel.writer.close()
        return tunnel.peer.access

    def deny(self, kind: str, exc: CryptorosError, who: str, *, logged: bool = True, hint: str | None = None) -> None:
        """Count a refusal by reason; log it, aggregated (:mod:`interceptor.denials`: the
        first of a kind, peer, reason and target at once, then a count per interval).
        ``logged``: False for a flood the caller logs once in a while itself; ``hint``:
        the ``cryptoros-authz grant ...`` that would allow it (``cryptoros denials``)."""
        reason = getattr(exc, "reason", type(exc).__name__)
        self.metrics.denied.labels(kind, reason).inc()
        for line in self.denials.record(kind, who, reason, str(exc), time.monotonic(), hint=hint):
            if logged:
                log.warning("%s", line)

    # ================================================================ outbound
    async def open_tunnel(
        self, host: str, port: int, purpose: str, target: str, *, first: bytes = b"", whole: bool | None = None,
        settles: bool = False,
    ) -> Tunnel:
        """Mutual TLS to a peer interceptor, our token in the preamble, its token in
        the reply (verified and bound to its certificate). ``first`` (a connection
        header, an XML-RPC request) is sent right behind the preamble, saving a round
        trip; the peer reads it only once our token passed.

        The token shown is narrowed for the peer (its certificate the audience, only
        the grants on names its manager holds too), except on master streams
        (``whole``, by default for purpose ``master``): the master's interceptor judges
        every registration, so it sees every grant.

        ``settles``: the caller calls :meth:`Tunnel.settle` once the stream's set-up is
        over; the spare connection for the next stream (``spare_connections``) is made
        only then, so its handshake does not take the CPU from this stream's set-up on
        both interceptors (otherwise it is made at once)."""
        self.keeper.current()  # no token of our own: nothing is opened
        whole = purpose == "master" if whole is None else whole
        endpoint = (host, port)
        if purpose != REFRESH:
            self._note_stream(endpoint)
        # a token exchange also tells whether the peer is reachable now (_wait_reachable):
        # it never goes over a spare, which may have been connected before the peer stopped
        spare = self._take_spare(endpoint) if purpose != REFRESH else None
        connecting = ([f for f in self._spare_connecting.get(endpoint, ()) if not f.done()]
                      if spare is None and purpose != REFRESH else [])
        if connecting:
            # a spare is being connected: it is ready sooner than a connection of our own
            await asyncio.wait(connecting, timeout=self.cfg.limits.handshake_timeout,
                               return_when=asyncio.FIRST_COMPLETED)
            spare = self._take_spare(endpoint)
        settled = asyncio.get_running_loop().create_future() if settles else None
        if spare is not None:
            log.debug("%s stream to %s:%d over a spare connection", purpose, host, port)
            try:
                tunnel = await self._tunnel_over(spare, host, port, purpose, target, first=first, whole=whole)
            except (ConnectionError, RemoteProtocolError, ssl.SSLError) as exc:
                log.info("spare connection to %s:%d was gone (%s): opening a fresh one", host, port, exc)
                tunnel = None  # the peer closed it before a byte of this stream was read
            finally:
                if not spare.used.done():
                    spare.used.set_result(None)
            if tunnel is not None:
                self.metrics.spares.labels("used").inc()
                return self._with_spare_after(tunnel, endpoint, purpose, settled)
        async with self._opening_slot(host, port):
            tunnel = await self._tunnel_over(await self._connect(host, port), host, port, purpose, target,
                                             first=first, whole=whole)
        return self._with_spare_after(tunnel, endpoint, purpose, settled)

    # ---------------------------------------------------------------- spare connections
    def _with_spare_after(self, tunnel: Tunnel, endpoint: tuple[str, int], purpose: str,
                          settled: asyncio.Future | None) -> Tunnel:
        """``tunnel``, and a spare for the next stream to ``endpoint`` made once it settles."""
        self._want_spare(endpoint, purpose, settled)
        if settled is None:
            return tunnel
        return Tunnel(tunnel.reader, tunnel.writer, tunnel.peer, tunnel.pending, settled)

    def _take_spare(self, endpoint: tuple[str, int]) -> _Connected | None:
        """The oldest ready spare to ``endpoint`` still open, if any (its maker stops
        counting toward the endpoint's spares: the next stream may want another)."""
        spares = self._spares.get(endpoint)
        while spares:
            spare = spares.pop(0)
            if not spares:
                del self._spares[endpoint]
            self._discard_maker(endpoint, spare.maker)
            if spare.writer.is_closing() or spare.reader.at_eof():
                spare.writer.close()
                spare.used.set_result(None)
                continue
            return spare
        return None

    def _discard_maker(self, endpoint: tuple[str, int], maker: Any) -> None:
        makers = self._spare_makers.get(endpoint)
        if makers is not None:
            makers.discard(maker)
            if not makers:
                del self._spare_makers[endpoint]

    def _note_stream(self, endpoint: tuple[str, int]) -> None:
        now = time.monotonic()
        recent = [t for t in self._recent_streams.get(endpoint, ()) if now - t < self._spare_window()]
        _remember(self._recent_streams, endpoint, [*recent[-SPARES_PER_PEER:], now])

    def _spare_window(self) -> float:
        return SPARE_AGE * self.cfg.limits.preamble_timeout

    def _spares_wanted(self, endpoint: tuple[str, int]) -> int:
        """As many spares as streams to ``endpoint`` were opened within a spare's life
        before the last one (at most ``SPARES_PER_PEER``): a peer that gets a stream now
        and then gets none (no handshake and token exchange for nothing), one that got
        a few in a row gets them."""
        recent = self._recent_streams.get(endpoint, [])
        if not recent:
            return 0
        now = time.monotonic()
        return min(SPARES_PER_PEER, sum(1 for t in recent[:-1] if now - t < self._spare_window()))

    def _want_spare(self, endpoint: tuple[str, int], purpose: str, after: asyncio.Future | None = None) -> None:
        """After a stream to ``endpoint``, have up to ``SPARES_PER_PEER`` connections to
        it ready (TLS done, no preamble; how many: :meth:`_spares_wanted`): the next
        streams skip the handshake's wait.
        Their preamble, token check and every other per-stream check run when one is
        used; unused for ``SPARE_AGE`` x the preamble timeout, a spare carries a token
        exchange and closes, so a burst costs a few extra connections and an idle peer
        none. A spare is connected once the stream ``after`` belongs to settled (bounded
        by the handshake timeout) and no stream was opened to ``endpoint`` for
        ``SPARE_QUIET`` seconds: its handshake runs between bursts, not during one."""
        if purpose == REFRESH or not self.started or not self.cfg.limits.spare_connections:
            return
        wanted = self._spares_wanted(endpoint)
        if wanted <= len(self._spare_makers.get(endpoint, ())):
            return
        makers = self._spare_makers.setdefault(endpoint, set())
        while len(makers) < wanted:
            makers.add(self.spawn(self._keep_spare(endpoint, after)))

    async def _keep_spare(self, endpoint: tuple[str, int], after: asyncio.Future | None = None) -> None:
        host, port = endpoint
        me = asyncio.current_task()
        spare: _Connected | None = None
        connecting: asyncio.Future | None = None
        try:
            if after is not None:
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(asyncio.shield(after), self.cfg.limits.handshake_timeout)
            while (quiet := self._recent_streams.get(endpoint, [0.0])[-1] + SPARE_QUIET - time.monotonic()) > 0:
                await asyncio.sleep(quiet)
            async with self._opening_slot(host, port):  # a spare counts as an opening stream at the peer
                connecting = asyncio.get_running_loop().create_future()
                self._spare_connecting.setdefault(endpoint, set()).add(connecting)
                generation = self._spare_generation
                connected = await self._connect(host, port)
                if generation != self._spare_generation:
                    # spares were dropped meanwhile (a reload): this one has the old client
                    # context, and a token bound to the new certificate is refused over it
                    connected.writer.close()
                    self.metrics.spares.labels("stale").inc()
                    log.debug("spare connection to %s:%d made before a reload: closed", host, port)
                    return
                spare = _Connected(connected.reader, connected.writer, connected.ssl_object, connected.offer,
                                   asyncio.get_running_loop().create_future(), me)
                self._spares.setdefault(endpoint, []).append(spare)
                self.metrics.spares.labels("made").inc()
                connecting.set_result(None)
                log.debug("spare connection to %s:%d ready", host, port)
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(asyncio.shield(spare.used), SPARE_AGE * self.cfg.limits.preamble_timeout)
                if self._unlist_spare(endpoint, spare):  # unused: show the peer our token and close
                    log.debug("spare connection to %s:%d unused: a token exchange", host, port)
                    self._discard_maker(endpoint, me)
                    self.metrics.spares.labels("expired").inc()
                    tunnel = await self._tunnel_over(spare, host, port, REFRESH, "", first=b"", whole=False)
                    tunnel.writer.close()
                else:  # taken: its user holds the slot until the peer's reply is verified
                    await asyncio.wait_for(asyncio.shield(spare.used), self.cfg.limits.handshake_timeout)
        except (CryptorosError, OSError, asyncio.TimeoutError) as exc:
            log.info("spare connection to %s:%d: %s", host, port, exc)
        except Exception:
            log.exception("spare connection to %s:%d", host, port)
        finally:
            if connecting is not None:
                if not connecting.done():
                    connecting.set_result(None)
                waiting = self._spare_connecting.get(endpoint)
                if waiting is not None:
                    waiting.discard(connecting)
                    if not waiting:
                        del self._spare_connecting[endpoint]
            self._discard_maker(endpoint, me)
            if spare is not None and self._unlist_spare(endpoint, spare):
                spare.writer.close()

    def _unlist_spare(self, endpoint: tuple[str, int], spare: _Connected) -> bool:
        """Take ``spare`` off the ready list of ``endpoint``; False if it was not there (taken)."""
        spares = self._spares.get(endpoint, [])
        for i, ready in enumerate(spares):
            if ready is spare:
                del spares[i]
                if not spares:
                    del self._spares[endpoint]
                return True
        return False

    def _drop_spares(self) -> None:
        """Close every ready spare; one still connecting is closed once connected (generation)."""
        self._spare_generation += 1
        for spares in self._spares.values():
            for spare in spares:
                spare.writer.close()
                if not spare.used.done():
                    spare.used.set_result(None)
        self._spares.clear()

    @contextlib.asynccontextmanager
    async def _opening_slot(self, host: str, port: int):
        """At most ``max_pending_per_certificate`` streams to one peer endpoint between
        connect and its verified reply: the peer refuses more unauthenticated streams
        from one certificate than that (``pending_limit``), so a burst (a robot's
        bring-up: dozens of nodes subscribing at once) waits its turn here instead of
        being refused there. The wait is bounded by the handshake timeout."""
        endpoint = (host, port)
        slot = self._opening.get(endpoint)
        if slot is None:
            slot = self._opening[endpoint] = [asyncio.Semaphore(self.cfg.limits.max_pending_per_certificate), 0]
        slot[1] += 1
        try:
            try:
                await asyncio.wait_for(slot[0].acquire(), self.cfg.limits.handshake_timeout)
            except asyncio.TimeoutError:
                raise PolicyDenied("peer_busy", f"{host}:{port}: no free slot to open a stream within "
                                                f"{self.cfg.limits.handshake_timeout:g} s") from None
            try:
                yield
            finally:
                slot[0].release()
        finally:
            slot[1] -= 1
            if slot[1] == 0 and self._opening.get(endpoint) is slot:
                del self._opening[endpoint]

    async def _connect(self, host: str, port: int) -> _Connected:
        """Mutual TLS to a peer interceptor, resuming the session kept for it if any."""
        sessions = self._sessions
        offer = sessions.get((host, port))
        try:
            with offering(self._client_ctx, offer):
                reader, writer = await asyncio.wait_for(
                    asyncio.open_connection(
                        host, port, ssl=self._client_ctx, server_hostname=host,
                        local_addr=(self.cfg.public.host, 0), limit=READ_SIZE,
                    ),
                    self.cfg.limits.handshake_timeout,
                )
        except (OSError, asyncio.TimeoutError) as exc:
            if offer is not None:
                sessions.forget((host, port))
            raise PolicyDenied("peer_unreachable", f"{host}:{port}: {exc}") from exc
        return _Connected(reader, writer, writer.get_extra_info("ssl_object"), offer)

    async def _tunnel_over(
        self, connected: _Connected, host: str, port: int, purpose: str, target: str, *, first: bytes, whole: bool,
    ) -> Tunnel:
        """Our token in the preamble (``first`` right behind it), the peer's reply and
        its token verified and bound to its certificate, checked again on this stream."""
        reader, writer, ssl_object, offer = connected.reader, connected.writer, connected.ssl_object, connected.offer
        sessions = self._sessions
        try:
            der = self._check_peer_certificate(ssl_object, "out")
            token = self.keeper.current() if whole else await self.keeper.for_peer(cert_thumbprint_s256(der))
            _remember(self._views, (host, port), self._views.get((host, port), set()) | {whole})
            writer.write(encode(Preamble(token=token, purpose=purpose, target=target)) + first)
            preamble_reader = PreambleReader(PreambleReply)
            reply = None
            async with asyncio.timeout(self.cfg.limits.handshake_timeout):  # the whole reply, not each read
                while reply is None:
                    await read_into(reader, preamble_reader.receive_data, self.cfg.limits.handshake_timeout)
                    event = preamble_reader.next_event()
                    reply = event if isinstance(event, PreambleReply) else None
            if not reply.ok:
                if ssl_object.session_reused:  # e.g. too old for the peer: the next one in full
                    sessions.forget((host, port))
                raise PolicyDenied("peer_refused", f"{host}:{port} refused the {purpose} stream")
            self.metrics.stream_checks.labels("token").inc()
            access = await self.verifier.verify_fresh(reply.token, der)
            self.verifier.note(access)
            sessions.put((host, port), ssl_object, offer)  # the ticket came before the reply
            _remember(self._peer_endpoints, (access.subject, access.thumbprint), (host, port))
            _remember(self._peer_tokens, (host, port), access)
            pending = preamble_reader.trailing_data()
        except BaseException:
            writer.close()
            raise
        self.metrics.connections.labels(purpose, "out").inc()
        return Tunnel(reader, writer, Peer(access=access, hosts=cert_hosts(der)), pending)

    # ================================================================ public side
    async def _on_public(self, sock: socket.socket, ctx: ssl.SSLContext) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._streams.add(task)
            task.add_done_callback(self._streams.discard)
        try:
            peername = sock.getpeername()
        except OSError:  # gone already
            sock.close()
            return
        who = f"{peername[0]}:{peername[1]}" if peername else "?"
        limits = self.cfg.limits
        entered: list[tuple[str, ...]] = []
        gate = StreamGate(self._checks)
        try:
            # Until its token is verified a stream is bounded per source address and in
            # all from its accept (through the TLS handshake), then per certificate too.
            for key, cap in ((("source", peername[0] if peername else "?"), limits.max_pending_per_source),
                             (("all",), limits.max_pending_streams)):
                self._pending.enter(key, cap, "interceptor" if key == ("all",) else key[0])
                entered.append(key)
        except PolicyDenied as exc:
            for key in entered:
                self._pending.leave(key)
            self.metrics.denied.labels("tls", exc.reason).inc()
            log.warning("DENY connection from %s: %s", who, exc)
            sock.close()
            return
        writer: asyncio.StreamWriter | None = None
        try:
            streams = await self._accept_tls(sock, ctx, who)
            if streams is None:
                return
            reader, writer = streams
            der = self._check_peer_certificate(writer.get_extra_info("ssl_object"), "in")
            key = ("certificate", hashlib.sha256(der).hexdigest())
            self._pending.enter(key, limits.max_pending_per_certificate, "certificate")
            entered.append(key)
            # nothing in flight until the preamble (a peer's spare connection waits here):
            # a stop cuts it at once instead of waiting out its grace period
            async with asyncio.timeout(limits.preamble_timeout):
                with self.cuttable():
                    while (event := gate.next_event()) is NEED_DATA:
                        await read_into(reader, gate.receive_data, limits.preamble_timeout)
            self.metrics.stream_checks.labels("token").inc()
            access = await self.verifier.verify_fresh(event.preamble.token, der)
            self.verifier.note(access)
            who = f"{access.subject}@{who}"
            admitted = gate.admit(
                access, feed=self.feed_problem(), allow_new_stream=self._new_stream_limiter.allow,
                open_streams=self._open_per_peer.get(access.subject, 0), max_streams=limits.max_connections_per_peer,
            )
            own_token = await self.keeper.for_peer(cert_thumbprint_s256(der))  # what this peer needs, no more
        except asyncio.CancelledError:
            if writer is not None:
                writer.transport.abort()  # stop(): no preamble yet, nothing to finish
            raise
        except (CryptorosError, asyncio.TimeoutError, ConnectionError) as exc:
            if isinstance(exc, CryptorosError):
                self.deny("stream", exc, who)
            else:
                reason = "preamble_timeout" if isinstance(exc, asyncio.TimeoutError) else type(exc).__name__
                self.metrics.denied.labels("stream", reason).inc()
                log.warning("DENY stream from %s: %s", who, reason)
            with contextlib.suppress(Exception):
                writer.write(gate.refuse())
                await asyncio.wait_for(writer.drain(), 1)
            if isinstance(exc, asyncio.TimeoutError) or getattr(exc, "reason", "") == "pending_limit":
                writer.transport.abort()  # no graceful TLS close for a peer that dribbles
            else:
                writer.close()
            return
        finally:
            for key in entered:
                self._pending.leave(key)
        writer.write(gate.accept(own_token))
        purpose = admitted.purpose
        if purpose == REFRESH:  # tokens shown both ways: nothing more to do
            self.metrics.connections.labels(REFRESH, "in").inc()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(writer.drain(), limits.handshake_timeout)
            writer.close()
            return
        self.metrics.connections.labels(purpose, "in").inc()
        self.metrics.open_streams.labels(purpose).inc()
        self._open_per_peer[access.subject] = self._open_per_peer.get(access.subject, 0) + 1

        cut_by: dict[str, str] = {}

        def cut(reason: str) -> None:
            cut_by.setdefault("reason", reason)
            writer.transport.abort()

        unwatch = self.verifier.watch(access, cut)
        peer = Peer(access=access, hosts=cert_hosts(der), watch=unwatch, cut=cut_by)
        _check, serve = self._purposes[purpose]
        try:
            await serve(InboundStream(reader, writer, peer, purpose, admitted.target, gate.trailing_data,
                                      admitted.resolved))
        except (CryptorosError, asyncio.TimeoutError, ConnectionError) as exc:
            if isinstance(exc, CryptorosError):
                self.deny(purpose, exc, who)
        except asyncio.CancelledError:
            pass  # stop(): the grace period is over
        finally:
            unwatch()
            self.metrics.open_streams.labels(purpose).dec()
            left = self._open_per_peer[access.subject] - 1
            if left > 0:
                self._open_per_peer[access.subject] = left
            else:
                del self._open_per_peer[access.subject]
            writer.close()

    # ================================================================ the pump
    def budget(self, peer: Peer) -> MessageBudget | None:
        """The message budget of one peer (shared by all its streams), if limited."""
        rate = self.cfg.limits.max_messages_per_second
        if rate is None:
            return None
        budget = self._budgets.get(peer.manager)
        if budget is None or budget.rate != rate:
            budget = self._budgets[peer.manager] = MessageBudget(rate)
        return budget

    async def pump(
        self, left_reader, left_writer, right_reader, right_writer, *,
        left_pending: bytes, right_pending: bytes,
        left_budget: MessageBudget | None = None, left_frames: FrameCounter | None = None,
        left_discard: bool = False, on_deny: Callable[[PolicyDenied], None] | None = None,
        endless: bool = False, left_tap: Callable[[bytes], None] | None = None,
        right_tap: Callable[[bytes], None] | None = None, left_gate: Callable[[bytes], bool] | None = None,
    ) -> None:
        """Hand both streams to the byte pump and wait until both sides closed. The
        left side is toward the peer (bytes read there count as rx); ``*_pending`` are
        bytes read past the header on each side, which go through the same checks.
        ``endless``: a topic stream, cut at once by :meth:`stop` (see :meth:`cuttable`)."""
        tx = self.metrics.bytes.labels("tx")
        rx = self.metrics.bytes.labels("rx")
        done = splice(
            left_writer.transport,
            right_writer.transport,
            left_pending=left_pending + take_buffered(left_reader),
            right_pending=right_pending + take_buffered(right_reader),
            on_left_bytes=rx.inc,
            on_right_bytes=tx.inc,
            left_budget=left_budget,
            left_frames=left_frames,
            left_discard=left_discard,
            on_deny=on_deny,
            left_tap=left_tap,
            right_tap=right_tap,
            left_gate=left_gate,
        )
        for transport in (left_writer.transport, right_writer.transport):
            if not transport.is_closing() and not transport.is_reading():
                transport.resume_reading()
        if endless:
            with self.cuttable():
                await done
        else:
            await done


__all__ = ["READ_SIZE", "Gateway", "InboundStream", "Peer", "Role", "Tunnel", "cert_hosts", "listening",
           "read_chunks", "read_into", "take_buffered"]
