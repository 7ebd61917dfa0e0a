"""The ROS 1 interceptor: the asyncio edge over the sans-IO codecs and the policy.

One process per host. Its listeners:

- **public** (mutual TLS): every stream from another interceptor opens with a
  :class:`~cryptoros.tunnel.Preamble` (token, purpose, target). The token is
  verified and bound to the TLS certificate, then, by purpose:
  ``master``  XML-RPC for the master this interceptor fronts (master role);
  ``node``    XML-RPC for one exported local node API;
  ``topic``/``service``  TCPROS for one exported local TCPROS server: the
  connection header is checked, then bytes are pumped.
- **local master** (plain HTTP on loopback, node role): the ``ROS_MASTER_URI`` of
  this host's unmodified nodes. Calls are checked against this interceptor's own
  grants, their URIs exported, and forwarded over a tunnel to the master's
  interceptor.
- **relays** (plain, loopback, created on demand): one per remote endpoint a local
  process was handed; each tunnels to the endpoint's owner.

Everything fails closed: a call or stream that cannot be decided is refused, the
log gets who, what and why, the peer gets an opaque denial.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
import logging
import os
import socket
import ssl
import time
import urllib.parse
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

from aiohttp import web
from cryptography import x509
from cryptography.hazmat.primitives.serialization import Encoding

from cryptoros.errors import CryptorosError, PolicyDenied, RemoteProtocolError, TokenError
from cryptoros.policy.ros1 import (
    NAME_BINDING,
    PARAM_READ,
    PARAM_WRITE,
    check_master_call,
    check_param_call,
    filter_param_reply,
    check_node_call,
    check_publisher_header,
    check_service_client_header,
    check_service_server_header,
    check_subscriber_header,
    ros_error,
)
from cryptoros.ratelimit import TokenBuckets
from cryptoros.ros1 import msgs
from cryptoros.ros1.node import tune_malloc
from cryptoros.ros1.rewrite import redact_node_reply, rewrite_call, rewrite_response, tcpros_only
from cryptoros.ros1.tcpros import NEED_DATA as TCPROS_NEED_DATA
from cryptoros.ros1.tcpros import ConnectionHeader, TCPROSConnection, canonical_header, encode_header
from cryptoros.ros1.xmlrpc import (
    MULTICALL,
    ConnectionClosed,
    Fault,
    Request,
    Response,
    Role,
    XmlRpcConnection,
    assemble_multicall,
    expand_multicall,
    make_multicall,
    request_path,
    split_multicall_response,
)
from cryptoros.ros1.xmlrpc import NEED_DATA as XMLRPC_NEED_DATA
from cryptoros.tls import cert_thumbprint_s256, client_context, peer_cert_der, server_context
from cryptoros.tokens import AccessToken, peer_audience
from cryptoros.tunnel import Preamble, PreambleReader, PreambleReply, encode
from interceptor.authz_client import AuthzClient, PeerVerifier, TokenKeeper
from interceptor.config import InterceptorConfig
from interceptor.metrics import Metrics
from interceptor.pump import FrameCounter, MessageBudget, splice
from interceptor.translate import KIND_TCPROS, KIND_XMLRPC, MASTER, Canonical, Translator

log = logging.getLogger("cryptoros.interceptor")

OPAQUE = "denied by cryptoros"
#: What a caller is told when its call was allowed but nobody answered (the ROS master
#: or the peer's interceptor down): not a denial, so not worded as one.
UNANSWERED = "cryptoros: no answer from the ROS master or the peer (not a denial)"
_UNANSWERED_REASONS = frozenset({"peer_unreachable", "tunnel_failed"})
CALL_TIMEOUT = 30.0
IDLE_TIMEOUT = 600.0
READ_SIZE = 65536
PARAM_CALLER_API_INDEX = {"subscribeParam": 1, "unsubscribeParam": 1}
#: Master calls that release a registration: their URIs must already have a relay.
_RELEASING_CALLS = frozenset({"unregisterPublisher", "unregisterSubscriber", "unregisterService", "unsubscribeParam"})


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


def cert_hosts(der: bytes) -> frozenset[str]:
    """IP and DNS names in a certificate's SAN: where its owner's endpoints may live."""
    try:
        san = x509.load_der_x509_certificate(der).extensions.get_extension_for_class(x509.SubjectAlternativeName)
    except (ValueError, x509.ExtensionNotFound):
        return frozenset()
    ips = {str(ip) for ip in san.value.get_values_for_type(x509.IPAddress)}
    return frozenset(ips | set(san.value.get_values_for_type(x509.DNSName)))


def _take_stream_buffer(reader: asyncio.StreamReader) -> bytes:
    """Bytes a StreamReader buffered but nobody read yet (handed to the pump)."""
    buffer = getattr(reader, "_buffer", None)  # CPython's StreamReader keeps a bytearray here
    if not buffer:
        return b""
    data = bytes(buffer)
    buffer.clear()
    return data


async def _read_into(reader: asyncio.StreamReader, feed: Callable[[bytes], None], timeout: float) -> None:
    data = await asyncio.wait_for(reader.read(READ_SIZE), timeout)
    feed(data)


async def read_xmlrpc(reader: asyncio.StreamReader, conn: XmlRpcConnection, timeout: float):
    """The next XML-RPC event of ``conn``, reading from ``reader`` as needed."""
    while True:
        event = conn.next_event()
        if event is not XMLRPC_NEED_DATA:
            return event
        await _read_into(reader, conn.receive_data, timeout)


async def read_tcpros_header(
    reader: asyncio.StreamReader, timeout: float, max_size: int, max_fields: int = 32
) -> tuple[ConnectionHeader, bytes]:
    """One TCPROS connection header and whatever bytes followed it (within
    ``timeout`` overall; at most ``max_size`` bytes and ``max_fields`` fields)."""
    conn = TCPROSConnection(max_header_size=max_size, max_header_fields=max_fields)
    deadline = time.monotonic() + timeout
    while True:
        event = conn.next_event()
        if isinstance(event, ConnectionHeader):
            rest, _eof = conn.trailing_data
            return event, rest
        if event is not TCPROS_NEED_DATA:
            raise RemoteProtocolError("connection closed before its header")
        await _read_into(reader, conn.receive_data, max(0.01, deadline - time.monotonic()))


def _ros_ok(response: Response | Fault) -> bool:
    return isinstance(response, Response) and isinstance(response.value, list) and response.value[:1] == [1]


class XmlRpcTunnel:
    """XML-RPC calls over one tunnel stream to a peer interceptor (opened lazily,
    reopened once if the peer closed an idle keep-alive stream)."""

    def __init__(self, owner: Interceptor, host: str, port: int, purpose: str, target: str) -> None:
        self._owner = owner
        self._address = (host, port)
        self._purpose = purpose
        self._target = target
        self._stream: tuple[asyncio.StreamReader, asyncio.StreamWriter, Peer] | None = None
        self._conn: XmlRpcConnection | None = None
        self._lock = asyncio.Lock()

    async def call(self, request: Request) -> Response | Fault:
        async with self._lock:
            for attempt in (0, 1):
                fresh = self._stream is None
                if fresh:
                    # The first request rides with the preamble: no extra round trip.
                    self._conn = XmlRpcConnection(Role.CLIENT, max_body_size=self._owner.cfg.limits.max_xmlrpc_body)
                    self._stream = await self._owner.open_tunnel(
                        *self._address, self._purpose, self._target, first=self._conn.send(request)
                    )
                reader, writer, _peer = self._stream
                try:
                    if not fresh:
                        writer.write(self._conn.send(request))
                        await asyncio.wait_for(writer.drain(), CALL_TIMEOUT)
                    event = await read_xmlrpc(reader, self._conn, CALL_TIMEOUT)
                    if isinstance(event, ConnectionClosed):
                        raise ConnectionResetError("tunnel closed")
                    return event
                except (ConnectionError, RemoteProtocolError) as exc:
                    await self.close_locked()
                    if fresh or attempt:
                        raise PolicyDenied("tunnel_failed", f"{self._purpose} tunnel: {exc}") from exc
            raise AssertionError("unreachable")

    async def close_locked(self) -> None:
        if self._stream is not None:
            self._stream[1].close()
            self._stream = None

    async def close(self) -> None:
        async with self._lock:
            await self.close_locked()


class TunnelPool:
    """Reusable XML-RPC tunnels to one peer endpoint: rospy opens a new connection for
    every node-API call, and a TLS handshake per call would cost about 8 KB and
    10 ms; idle tunnels are kept (up to ``max_idle``) and reused."""

    def __init__(self, owner: Interceptor, host: str, port: int, purpose: str, target: str, max_idle: int = 4):
        self._args = (owner, host, port, purpose, target)
        self._idle: list[XmlRpcTunnel] = []
        self._max_idle = max_idle

    async def call(self, request: Request) -> Response | Fault:
        tunnel = self._idle.pop() if self._idle else XmlRpcTunnel(*self._args)
        try:
            response = await tunnel.call(request)
        except BaseException:
            await tunnel.close()
            raise
        if len(self._idle) < self._max_idle:
            self._idle.append(tunnel)
        else:
            await tunnel.close()
        return response

    async def close(self) -> None:
        while self._idle:
            await self._idle.pop().close()


class Interceptor:
    """One host's interceptor. ``await start()``, then ``await stop()``."""

    def __init__(self, cfg: InterceptorConfig) -> None:
        self.cfg = cfg
        self.metrics = Metrics()
        self._server_ctx = server_context(cfg.tls)
        self._client_ctx = client_context(cfg.tls, check_hostname=True)
        self.authz = AuthzClient(cfg.authz, client_context(cfg.tls, check_hostname=True))
        self.keeper = TokenKeeper(self.authz, refresh_margin=cfg.authz.refresh_margin)
        self.verifier = PeerVerifier(
            self.authz,
            issuer=cfg.authz.issuer,
            audience=cfg.authz.audience,
            poll_interval=cfg.authz.revocation_poll_interval,
            grace=cfg.authz.token_grace,
            revocation_grace=cfg.authz.revocation_grace,
            feed_wait=cfg.authz.feed_wait,
        )
        #: Peer interceptors we opened streams to, by (manager, certificate thumbprint):
        #: where to show them our new token and fetch theirs.
        self._peer_endpoints: dict[tuple[str, str], tuple[str, int]] = {}
        #: the last token each peer endpoint we connected to showed us (need to know: ROS 2)
        self._peer_tokens: dict[tuple[str, int], AccessToken] = {}
        self._exchanges: set[tuple[str, int]] = set()
        local_master = (
            f"http://{cfg.local_master.host}:{cfg.local_master.port}/" if cfg.local_master is not None else None
        )
        self.translator = Translator(
            public_host=cfg.public.host,
            public_port=cfg.public.port,
            local_master_uri=local_master,
            open_relay=self._open_relay,
            max_relays_per_host=cfg.limits.max_relays_per_peer,
            on_change=self._save_state,
        )
        if local_master:
            self.translator.add_master_uri(local_master)
        if "master" in cfg.roles and cfg.master.upstream:
            self.translator.add_master_uri(cfg.master.upstream)
        self._own_cert_der = _read_cert_der(cfg.tls.cert_file)
        self.verifier.own_audience = peer_audience(cert_thumbprint_s256(self._own_cert_der))
        #: per peer endpoint, which of our tokens it has seen: whole (master streams) or
        #: narrowed for it (everything else); a token exchange refreshes each
        self._views: dict[tuple[str, int], set[bool]] = {}
        self._own_access: AccessToken | None = None
        self._own_token: str | None = None
        self.topic_types: dict[str, str] = {}  # topics published by this host's nodes
        self._owners: dict[str, list] = {}  # master role: node -> [manager, registrations]
        self._open_per_peer: dict[str, int] = {}
        self._pending: dict[tuple[str, str], int] = {}  # unauthenticated streams per source / certificate
        self._budgets: dict[str, MessageBudget] = {}
        self._pools: dict[tuple[str, int, str, str], TunnelPool] = {}
        rate = cfg.limits.max_new_connections_per_second
        self._new_conn_limiter = TokenBuckets(rate, 2 * rate)  # per peer manager
        self._servers: list[asyncio.AbstractServer] = []
        self._public_server: asyncio.AbstractServer | None = None
        self._tasks: list[asyncio.Task] = []
        self._streams: set[asyncio.Future] = set()
        self._metrics_runner: web.AppRunner | None = None
        self._relay_sockets: list[socket.socket] = []
        self._relay_socket_of: dict[tuple[str, int], socket.socket] = {}
        self._relay_servers: dict[tuple[str, int], asyncio.AbstractServer] = {}
        self._relay_refs: dict[tuple[str, int], int] = {}  # master role: registrations behind each relay
        self._started = False
        self._state_loaded = False
        self._save_pending = False
        self._local_subscribers: dict[str, dict[str, str]] = {}  # topic -> {node: local node API}
        self._resubscribing: set[str] = set()

    # ================================================================ life cycle
    async def start(self, *, token_wait: float = 10.0) -> None:
        # Large reads are copied out of the pump's buffer: keep glibc from mmap-ing
        # (and page-faulting) each one (perf-baselines.md: +30 to 100 % on 1 MB frames).
        tune_malloc()
        self._load_state()
        try:
            await asyncio.wait_for(self._first_token(), token_wait)
        except (asyncio.TimeoutError, TokenError) as exc:
            log.error("no access token yet (%s): everything is refused until one arrives", exc)
        self.verifier.listeners.append(self._on_feed)
        self.verifier.stale_listeners.append(self._on_stale_peer_token)
        self.keeper.listeners.append(self._on_own_token)
        self._tasks.append(asyncio.create_task(self.keeper.run(), name="token-keeper"))
        self._tasks.append(asyncio.create_task(self.verifier.run(), name="revocation-feed"))
        self._public_server = await self._listen_public(self._server_ctx)
        if "node" in self.cfg.roles:
            lm = self.cfg.local_master
            self._servers.append(await asyncio.start_server(self._on_local_master, lm.host, lm.port))
        if self.cfg.metrics is not None:
            await self._start_metrics()
        self._started = True
        for topic in list(self._local_subscribers):  # restarted: local subscribers lost their streams
            self._resubscribe_soon(topic, delay=0.5)
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

    async def _listen_public(self, ctx) -> asyncio.AbstractServer:
        ctx.sslobject_class = self._counting_sslobject_class()
        return await asyncio.start_server(
            self._on_public, self.cfg.public.host, self.cfg.public.port, ssl=ctx, reuse_address=True,
            ssl_handshake_timeout=self.cfg.limits.handshake_timeout, limit=READ_SIZE,
        )

    async def stop(self, grace: float = 5.0) -> None:
        """Stop listening, let open streams finish for ``grace`` seconds, then cut them."""
        servers = [s for s in (self._public_server, *self._servers) if s is not None]
        for server in servers:
            server.close()
        if self._streams:
            await asyncio.wait(list(self._streams), timeout=grace)
        for task in self._tasks:
            task.cancel()
        for stream in list(self._streams):
            stream.cancel()
        for server in servers:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(server.wait_closed(), 1)
        for pool in self._pools.values():
            await pool.close()
        for sock in self._relay_sockets:
            sock.close()
        self._relay_sockets.clear()
        if self._metrics_runner is not None:
            await self._metrics_runner.cleanup()
        await self.authz.close()

    async def reload(self, cfg: InterceptorConfig) -> None:
        """SIGHUP: new certificates, CRL and policy; open streams stay up. All or
        nothing: the new TLS material is loaded and a token bound to the new
        certificate fetched and verified before anything is swapped, so a failure (a
        renewed certificate the registry does not know yet, the authorization server
        down) keeps the old state everywhere (the caller catches and logs)."""
        server_ctx = server_context(cfg.tls)
        client_ctx = client_context(cfg.tls, check_hostname=True)
        authz_ctx = client_context(cfg.tls, check_hostname=True)
        own_der = _read_cert_der(cfg.tls.cert_file)
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
            self._public_server = await self._listen_public(server_ctx)
        except OSError:
            self._public_server = await self._listen_public(self._server_ctx)
            raise
        self._server_ctx, self._client_ctx = server_ctx, client_ctx
        self.cfg = cfg
        # every holder of the certificate reads the new one: the authorization server
        # binds the next token to it, and our own token is checked against it
        self._own_cert_der = own_der
        self.verifier.own_audience = peer_audience(cert_thumbprint_s256(own_der))
        await self.authz.use_ssl_context(authz_ctx)
        self.keeper.install(token)  # new grants, bound to the new certificate; peers' tokens anew
        self._own_access = None
        self.own_access()
        log.info("reloaded certificates, CRL and policy")

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
            self._check_feed_age()
        except (TokenError, PolicyDenied) as exc:
            health = f"{exc.reason}: {exc.detail}"
        cert = x509.load_der_x509_certificate(self._own_cert_der)
        crl = self.cfg.tls.crl_file
        last = self.verifier.last_feed_at
        return {
            "manager": self.cfg.manager, "roles": list(self.cfg.roles), "public": str(self.cfg.public),
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
                self._check_feed_age()
                self.own_access()  # our own token verifies now: not revoked, manager not disabled
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

    # ================================================================ helpers
    def _counting_sslobject_class(self) -> type[ssl.SSLObject]:
        """An SSLObject whose failed handshakes are counted and logged like every other
        denial (asyncio itself only logs them in debug mode)."""
        metrics = self.metrics

        class CountingSSLObject(ssl.SSLObject):
            def do_handshake(self) -> None:
                try:
                    super().do_handshake()
                except (ssl.SSLWantReadError, ssl.SSLWantWriteError):
                    raise
                except ssl.SSLError as exc:
                    reason = (exc.reason or type(exc).__name__).lower()
                    metrics.denied.labels("tls", reason).inc()
                    log.warning("DENY tls handshake: %s", exc)
                    raise

        return CountingSSLObject

    def _on_feed(self, revocations) -> None:
        """When the feed revokes our own token or disables our manager, drop the token
        (nothing is allowed on it any more) and ask for a new one at once."""
        own = self._own_access
        serial = x509.load_der_x509_certificate(self._own_cert_der).serial_number
        if serial in revocations.revoked_serials:
            log.error("our own certificate (serial %x) was revoked by the CA: no token is issued to it any more; "
                      "renew it (cryptoros-certs renew, set-cert, SIGHUP)", serial)
            self._own_access = None
            self.keeper.invalidate()
        elif own is not None and (own.jti in revocations.revoked_jtis or own.subject in revocations.disabled_subjects):
            log.warning("our own access token was revoked; asking for a new one")
            self._own_access = None
            self.keeper.invalidate()
        elif self._started:
            self.keeper.wake()  # the registry changed: our grants may have (grants live)

    # ---------------------------------------------------------------- token exchange
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
        if endpoint in self._exchanges or not self._started:
            return
        self._exchanges.add(endpoint)

        async def exchange() -> None:
            try:
                for whole in sorted(self._views.get(endpoint, {False})):
                    _reader, writer, _peer = await self.open_tunnel(*endpoint, "refresh", "", whole=whole)
                    writer.close()
            except (CryptorosError, OSError, asyncio.TimeoutError) as exc:
                log.info("token exchange with %s:%d failed: %s", *endpoint, exc)
            finally:
                self._exchanges.discard(endpoint)

        self._tasks.append(asyncio.ensure_future(exchange()))
        self._tasks = [t for t in self._tasks if not t.done()]

    def own_access(self) -> AccessToken:
        """Our own token, verified like a peer's (it carries our grants)."""
        token = self.keeper.current()
        if self._own_access is None or self._own_token != token:
            self._own_access = self.verifier.verify(token, self._own_cert_der)
            self._own_token = token
        return self._own_access

    def _deny(self, kind: str, exc: CryptorosError, who: str) -> None:
        reason = getattr(exc, "reason", type(exc).__name__)
        self.metrics.denied.labels(kind, reason).inc()
        log.warning("DENY %s from %s: %s", kind, who, exc)

    def _track(self, coro: Awaitable) -> asyncio.Future:
        future = asyncio.ensure_future(coro)
        self._streams.add(future)
        future.add_done_callback(self._streams.discard)
        return future

    def _open_relay(self, target: Canonical, port: int = 0) -> tuple[str, int]:
        """Bind a loopback listener for ``target`` now (so its URI exists at once), on
        ``port`` if given and free (a relay kept across a restart); it starts
        accepting on the next turn of the loop."""
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(("127.0.0.1", port))
        except OSError:
            if not port:
                sock.close()
                raise
            sock.bind(("127.0.0.1", 0))
        sock.listen(128)
        sock.setblocking(False)
        self._relay_sockets.append(sock)
        handler = self._on_xmlrpc_relay if target.kind == KIND_XMLRPC else self._on_tcpros_relay

        host, port = sock.getsockname()[:2]

        async def serve() -> None:
            server = await asyncio.start_server(lambda r, w: handler(r, w, target), sock=sock, limit=READ_SIZE)
            self._servers.append(server)
            if sock.fileno() < 0:  # released before it started
                server.close()
            else:
                self._relay_servers[(host, port)] = server

        self._relay_socket_of[(host, port)] = sock
        asyncio.get_running_loop().create_task(serve())
        log.debug("relay %s:%d -> %s", host, port, target)
        return host, port

    # ---------------------------------------------------------------- state across restarts
    def _state_path(self):
        return None if self.cfg.state_dir is None else self.cfg.state_dir / f"{self.cfg.manager}.state.json"

    def _save_state(self) -> None:
        """Keep the tables a restart would otherwise lose (written atomically)."""
        path = self._state_path()
        if path is None or not self._state_loaded:
            return
        data = {"version": 1, "translator": self.translator.snapshot(), "topic_types": self.topic_types,
                "owners": self._owners, "local_subscribers": self._local_subscribers}
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(".tmp")
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            with os.fdopen(fd, "w") as f:
                json.dump(data, f)
            os.replace(tmp, path)
        except OSError as exc:
            log.error("cannot keep state in %s: %s", path, exc)

    def _save_state_soon(self) -> None:
        """Save once after this turn of the loop (a multicall changes many owners)."""
        if self._state_path() is not None and not self._save_pending:
            self._save_pending = True

            def save() -> None:
                self._save_pending = False
                self._save_state()

            asyncio.get_running_loop().call_soon(save)

    def _load_state(self) -> None:
        path = self._state_path()
        self._state_loaded = True
        if path is None or not path.exists():
            return
        try:
            data = json.loads(path.read_text())
            if data.get("version") != 1:
                raise ValueError(f"unknown state version {data.get('version')!r}")
            problems = self.translator.restore(data["translator"])
            self.topic_types.update({str(k): str(v) for k, v in data.get("topic_types", {}).items()})
            self._owners.update({str(k): [str(v[0]), int(v[1])] for k, v in data.get("owners", {}).items()})
            for topic, subscribers in data.get("local_subscribers", {}).items():
                self._local_subscribers[str(topic)] = {str(n): str(api) for n, api in subscribers.items()}
        except (OSError, ValueError, KeyError, TypeError) as exc:
            log.error("state in %s not used (%s): nodes of this host may need a restart", path, exc)
            return
        for problem in problems:
            log.warning("state: %s", problem)
        log.info("state restored from %s: %d exports, %d relays, %d published topics", path,
                 len(data["translator"].get("exports", {})), self.translator.relay_count, len(self.topic_types))
        self._save_state()

    def pool(self, host: str, port: int, purpose: str, target: str) -> TunnelPool:
        key = (host, port, purpose, target)
        pool = self._pools.get(key)
        if pool is None:
            pool = self._pools[key] = TunnelPool(self, host, port, purpose, target)
        return pool

    async def open_tunnel(
        self, host: str, port: int, purpose: str, target: str, *, first: bytes = b"", whole: bool | None = None,
    ) -> tuple[asyncio.StreamReader, asyncio.StreamWriter, Peer]:
        """Mutual TLS to a peer interceptor, our token in the preamble, its token in
        the reply (verified and bound to its certificate). ``first`` (a connection
        header, an XML-RPC request) is sent right behind the preamble, saving a round
        trip; the peer reads it only once our token passed.

        The token shown is narrowed for the peer (its certificate the audience, only
        the grants on names its manager holds too), except on master streams
        (``whole``, by default for purpose ``master``): the master's interceptor judges
        every registration, so it sees every grant."""
        self.keeper.current()  # no token of our own: nothing is opened
        whole = purpose == "master" if whole is None else whole
        try:
            reader, writer = await asyncio.wait_for(
                asyncio.open_connection(
                    host, port, ssl=self._client_ctx, server_hostname=host,
                    local_addr=(self.cfg.public.host, 0), limit=READ_SIZE,
                ),
                self.cfg.limits.handshake_timeout,
            )
        except (OSError, asyncio.TimeoutError) as exc:
            raise PolicyDenied("peer_unreachable", f"{host}:{port}: {exc}") from exc
        try:
            der = peer_cert_der(writer.get_extra_info("ssl_object"))
            token = self.keeper.current() if whole else await self.keeper.for_peer(cert_thumbprint_s256(der))
            self._views.setdefault((host, port), set()).add(whole)
            writer.write(encode(Preamble(token=token, purpose=purpose, target=target)) + first)
            preamble_reader = PreambleReader(PreambleReply)
            reply = None
            while reply is None:
                await _read_into(reader, preamble_reader.receive_data, self.cfg.limits.handshake_timeout)
                event = preamble_reader.next_event()
                reply = event if isinstance(event, PreambleReply) else None
            if not reply.ok:
                raise PolicyDenied("peer_refused", f"{host}:{port} refused the {purpose} stream")
            access = await self.verifier.verify_fresh(reply.token, der)
            self.verifier.note(access)
            self._peer_endpoints[(access.subject, access.thumbprint)] = (host, port)
            self._peer_tokens[(host, port)] = access
            leftover = preamble_reader.trailing_data()
            if leftover:
                reader._buffer[:0] = leftover  # type: ignore[attr-defined]  # give back bytes read past the reply
        except BaseException:
            writer.close()
            raise
        self.metrics.connections.labels(purpose, "out").inc()
        return reader, writer, Peer(access=access, hosts=cert_hosts(der))

    # ================================================================ public side
    async def _on_public(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._streams.add(task)
            task.add_done_callback(self._streams.discard)
        peername = writer.get_extra_info("peername")
        who = f"{peername[0]}:{peername[1]}" if peername else "?"
        limits = self.cfg.limits
        pending: list[tuple[str, str]] = []
        try:
            der = peer_cert_der(writer.get_extra_info("ssl_object"))
            # Before the token is verified a stream is bounded per source address and
            # per certificate, and its preamble has one deadline from accept.
            for key, cap in (
                (("source", peername[0] if peername else "?"), limits.max_pending_per_source),
                (("certificate", hashlib.sha256(der).hexdigest()), limits.max_pending_per_certificate),
            ):
                if self._pending.get(key, 0) >= cap:
                    raise PolicyDenied("pending_limit", f"{cap} unauthenticated streams from this {key[0]} already")
                self._pending[key] = self._pending.get(key, 0) + 1
                pending.append(key)
            preamble_reader = PreambleReader(Preamble)
            preamble = None
            async with asyncio.timeout(limits.preamble_timeout):
                while preamble is None:
                    await _read_into(reader, preamble_reader.receive_data, limits.preamble_timeout)
                    event = preamble_reader.next_event()
                    preamble = event if isinstance(event, Preamble) else None
            access = await self.verifier.verify_fresh(preamble.token, der)
            self.verifier.note(access)
            who = f"{access.subject}@{who}"
            self._check_feed_age()
            if preamble.purpose != "refresh":
                self._check_purpose(preamble)
            if not self._new_conn_limiter.allow(access.subject):
                raise PolicyDenied("rate_limited", f"more than {self.cfg.limits.max_new_connections_per_second}/s new streams")
            if self._open_per_peer.get(access.subject, 0) >= self.cfg.limits.max_connections_per_peer:
                raise PolicyDenied("connection_limit", f"{self.cfg.limits.max_connections_per_peer} streams open")
            own_token = await self.keeper.for_peer(cert_thumbprint_s256(der))  # what this peer needs, no more
        except (CryptorosError, asyncio.TimeoutError, ConnectionError) as exc:
            if isinstance(exc, CryptorosError):
                self._deny("stream", exc, who)
            else:
                reason = "preamble_timeout" if isinstance(exc, asyncio.TimeoutError) else type(exc).__name__
                self.metrics.denied.labels("stream", reason).inc()
                log.warning("DENY stream from %s: %s", who, reason)
            with contextlib.suppress(Exception):
                writer.write(encode(PreambleReply(ok=False, error="denied")))
                await asyncio.wait_for(writer.drain(), 1)
            if isinstance(exc, asyncio.TimeoutError) or getattr(exc, "reason", "") == "pending_limit":
                writer.transport.abort()  # no graceful TLS close for a peer that dribbles
            else:
                writer.close()
            return
        finally:
            for key in pending:
                left = self._pending[key] - 1
                if left:
                    self._pending[key] = left
                else:
                    del self._pending[key]
        writer.write(encode(PreambleReply(ok=True, token=own_token)))
        if preamble.purpose == "refresh":  # tokens shown both ways: nothing more to do
            self.metrics.connections.labels("refresh", "in").inc()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(writer.drain(), limits.handshake_timeout)
            writer.close()
            return
        leftover = preamble_reader.trailing_data()
        if leftover:
            reader._buffer[:0] = leftover  # type: ignore[attr-defined]
        purpose = preamble.purpose
        self.metrics.connections.labels(purpose, "in").inc()
        self.metrics.open_streams.labels(purpose).inc()
        self._open_per_peer[access.subject] = self._open_per_peer.get(access.subject, 0) + 1

        cut_by: dict[str, str] = {}

        def cut(reason: str) -> None:
            cut_by.setdefault("reason", reason)
            self.metrics.cutoffs.inc()
            writer.transport.abort()

        unwatch = self.verifier.watch(access, cut)
        peer = Peer(access=access, hosts=cert_hosts(der), watch=unwatch, cut=cut_by)
        try:
            if purpose == "master":
                await self._serve_master_stream(reader, writer, peer)
            elif purpose == "node":
                await self._serve_node_stream(reader, writer, peer, preamble.target)
            else:
                await self._serve_tcpros_stream(reader, writer, peer, preamble.target, purpose)
        except (CryptorosError, asyncio.TimeoutError, ConnectionError) as exc:
            if isinstance(exc, CryptorosError):
                self._deny(purpose, exc, who)
        except asyncio.CancelledError:
            pass  # stop(): the grace period is over
        finally:
            unwatch()
            self.metrics.open_streams.labels(purpose).dec()
            self._open_per_peer[access.subject] -= 1
            writer.close()

    def _check_feed_age(self) -> None:
        """Fail closed when the revocation feed is stale (a revoked peer could be let in)
        or the authorization server refuses our certificate (revoked by the CA)."""
        if self.verifier.refused:
            raise PolicyDenied("authz_refused", "the authorization server refuses this interceptor's certificate "
                                                "(HTTP 401: revoked by the CA?)")
        last = self.verifier.last_feed_at
        age = None if last is None else time.time() - last
        if age is None or age > self.cfg.limits.max_feed_age:
            raise PolicyDenied("feed_stale", f"revocation feed {'never read' if age is None else f'{age:.0f} s old'}"
                                             f" (max_feed_age {self.cfg.limits.max_feed_age:.0f} s)")

    def _check_purpose(self, preamble: Preamble) -> None:
        if preamble.purpose == "master":
            if "master" not in self.cfg.roles:
                raise PolicyDenied("no_master_here", "this interceptor does not front a master")
        elif preamble.purpose == "node":
            self.translator.resolve(KIND_XMLRPC, preamble.target)
        elif preamble.purpose in ("topic", "service"):
            self.translator.resolve(KIND_TCPROS, preamble.target)
        else:
            raise PolicyDenied("bad_purpose", f"purpose {preamble.purpose} is not served by the ROS 1 role")

    async def _serve_xmlrpc(
        self,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        handle: Callable[[Request], Awaitable[Response | Fault]],
    ) -> None:
        """Answer XML-RPC requests on a stream until it closes. A request that does not
        parse (bad head, oversized declared body, bad XML) is answered with one ROS
        error triple and the connection is cut without reading the rest."""
        limits = self.cfg.limits
        conn = XmlRpcConnection(Role.SERVER, max_body_size=limits.max_xmlrpc_body, gzip_threshold=1400)
        while True:
            try:
                event = await read_xmlrpc(reader, conn, IDLE_TIMEOUT)
            except RemoteProtocolError:
                writer.transport.pause_reading()
                with contextlib.suppress(Exception):
                    writer.write(conn.send(Response(value=ros_error(OPAQUE), keep_alive=False)))
                    await asyncio.wait_for(writer.drain(), 1)
                writer.transport.abort()
                raise
            if isinstance(event, ConnectionClosed):
                return
            response = await handle(event)
            if not event.keep_alive:
                response = type(response)(**{**response.__dict__, "keep_alive": False})
            writer.write(conn.send(response))
            await asyncio.wait_for(writer.drain(), CALL_TIMEOUT)
            if not event.keep_alive:
                return

    async def _decide_calls(
        self,
        request: Request,
        decide: Callable[[Request], Request],
        forward: Callable[[Request], Awaitable[Response | Fault]],
        after: Callable[[Request, Response | Fault], Response | Fault],
        kind: str,
        who: str,
    ) -> Response | Fault:
        """Decide each call of a request (a multicall call by call), forward the
        allowed ones in one request, and answer refused ones with a ROS error."""
        try:
            calls = expand_multicall(request, max_calls=self.cfg.limits.max_multicall)
        except RemoteProtocolError as exc:
            self._deny(kind, exc, who)
            return Fault(code=-1, string=OPAQUE)
        results: list[Response | Fault | None] = [None] * len(calls)
        allowed: list[tuple[int, Request]] = []
        for i, call in enumerate(calls):
            try:
                allowed.append((i, decide(call)))
                self.metrics.allowed.labels(kind).inc()
            except CryptorosError as exc:  # a policy denial, a malformed call, no token of ours
                self._deny(kind, exc, f"{who} {call.method}")
                results[i] = Response(value=ros_error(OPAQUE))
        if allowed:
            multicall = request.method == MULTICALL
            outgoing = make_multicall([c for _, c in allowed], like=request) if multicall else allowed[0][1]
            try:
                reply = await forward(outgoing)
                parts = split_multicall_response(reply, len(allowed)) if multicall else [reply]
                for (i, call), part in zip(allowed, parts, strict=True):
                    results[i] = after(call, part)
            except (CryptorosError, ConnectionError, OSError, asyncio.TimeoutError) as exc:
                unanswered = getattr(exc, "reason", None) in _UNANSWERED_REASONS or not isinstance(exc, CryptorosError)
                if unanswered:
                    log.warning("%s call from %s got no answer: %s", kind, who, exc or type(exc).__name__)
                else:
                    self._deny(kind, exc, who)
                for i, _ in allowed:
                    results[i] = Response(value=ros_error(UNANSWERED if unanswered else OPAQUE))
        if request.method == MULTICALL:
            return assemble_multicall(results)  # type: ignore[arg-type]
        return results[0]  # type: ignore[return-value]

    # ---------------------------------------------------------------- master role
    def _owner_of(self, node: str) -> str | None:
        entry = self._owners.get(node)
        return entry[0] if entry else None

    def _check_node_limit(self, call: Request, manager: str) -> None:
        """A peer registers at most ``max_nodes_per_peer`` node names at the master."""
        if call.method not in NAME_BINDING or not call.params or call.params[0] in self._owners:
            return
        cap = self.cfg.limits.max_nodes_per_peer
        if sum(1 for owner, _count in self._owners.values() if owner == manager) >= cap:
            raise PolicyDenied("node_limit", f"{manager} has {cap} nodes registered already (max_nodes_per_peer)")

    def _note_registration(self, call: Request, response: Response | Fault, manager: str) -> None:
        if not _ros_ok(response) or not call.params:
            return
        node = call.params[0]
        if call.method.startswith("register") or call.method == "subscribeParam":
            entry = self._owners.setdefault(node, [manager, 0])
            entry[1] += 1
            self._count_relay_refs(call, +1)
            self._save_state_soon()
        elif (call.method.startswith("unregister") or call.method == "unsubscribeParam") and \
                isinstance(response.value[2], int) and response.value[2] > 0:
            entry = self._owners.get(node)
            if entry is not None:
                entry[1] -= 1
                if entry[1] <= 0:
                    del self._owners[node]
                self._save_state_soon()
            self._count_relay_refs(call, -1)

    def _count_relay_refs(self, call: Request, delta: int) -> None:
        """Relays the master holds URIs of: one count per registration behind each;
        a relay whose last registration was released is closed (its fd freed)."""
        for index in _RELAY_URI_INDEX.get(call.method, ()):
            uri = call.params[index] if len(call.params) > index else None
            endpoint = _local_endpoint(uri)
            if endpoint is None or self.translator.relay_target(*endpoint) is None:
                continue
            count = self._relay_refs.get(endpoint, 0) + delta
            if count > 0:
                self._relay_refs[endpoint] = count
                continue
            self._relay_refs.pop(endpoint, None)
            if delta < 0:
                self._release_relay(endpoint)

    def _release_relay(self, endpoint: tuple[str, int]) -> None:
        self.translator.forget_relay(*endpoint)
        server = self._relay_servers.pop(endpoint, None)
        if server is not None:
            server.close()
        sock = self._relay_socket_of.pop(endpoint, None)
        if sock is not None:
            sock.close()
        log.debug("relay %s:%d released (no registration behind it)", *endpoint)

    async def _serve_master_stream(self, reader, writer, peer: Peer) -> None:
        def to_local_from_peer(uri: str) -> str:
            target = Canonical.parse(uri)
            if target is None or target.host not in peer.hosts:
                raise PolicyDenied("endpoint_not_peer", f"{uri!r:.80} is not an endpoint of {peer.manager}")
            return self.translator.to_local(uri)

        def existing_from_peer(uri: str) -> str:
            # unregister*/unsubscribeParam never open a relay: an endpoint no relay was
            # opened for was never registered, so the call could match nothing.
            target = Canonical.parse(uri)
            if target is None or target.host not in peer.hosts:
                raise PolicyDenied("endpoint_not_peer", f"{uri!r:.80} is not an endpoint of {peer.manager}")
            local = self.translator.existing_local(uri)
            if local is None:
                raise PolicyDenied("unknown_endpoint", f"{uri!r:.80} was never registered through this interceptor")
            return local

        def decide(call: Request) -> Request:
            grants = self.verifier.freshest(peer.access).grants  # decisions use the peer's freshest token
            check_master_call(call.method, call.params, manager=peer.manager, grants=grants, owner_of=self._owner_of)
            call = _resolved_param_call(call, grants)
            self._check_node_limit(call, peer.manager)
            uri_map = existing_from_peer if call.method in _RELEASING_CALLS else to_local_from_peer
            call = rewrite_call(call, caller_api=uri_map, service_api=uri_map)
            return _rewrite_param_api(call, uri_map)

        def after(call: Request, response: Response | Fault) -> Response | Fault:
            self._note_registration(call, response, peer.manager)
            response = _filtered_param_reply(call, response, self.verifier.freshest(peer.access).grants)
            return rewrite_response(call, response, uri=self.translator.to_canonical)

        async def handle(request: Request) -> Response | Fault:
            return await self._decide_calls(request, decide, self._call_upstream_master, after, "master", peer.manager)

        await self._serve_xmlrpc(reader, writer, handle)

    async def _call_upstream_master(self, request: Request) -> Response | Fault:
        return await self._call_plain(self.cfg.master.upstream, request)

    async def _call_plain(self, uri: str, request: Request) -> Response | Fault:
        """One XML-RPC call to a local process (one connection per call)."""
        host, port = _host_port(uri)
        reader, writer = await asyncio.wait_for(asyncio.open_connection(host, port, limit=READ_SIZE), CALL_TIMEOUT)
        try:
            conn = XmlRpcConnection(Role.CLIENT, host=f"{host}:{port}", max_body_size=self.cfg.limits.max_xmlrpc_body)
            # The path is the one the node advertised, never one a peer wrote.
            outgoing = Request(method=request.method, params=request.params,
                               path=request_path(urllib.parse.urlsplit(uri).path), keep_alive=False, accept_gzip=True)
            writer.write(conn.send(outgoing))
            await asyncio.wait_for(writer.drain(), CALL_TIMEOUT)
            event = await read_xmlrpc(reader, conn, CALL_TIMEOUT)
            if isinstance(event, ConnectionClosed):
                raise RemoteProtocolError(f"{uri} closed without answering")
            return type(event)(**{**event.__dict__, "keep_alive": True})
        finally:
            writer.close()

    # ---------------------------------------------------------------- node side
    async def _serve_node_stream(self, reader, writer, peer: Peer, target: str) -> None:
        endpoint = self.translator.resolve(KIND_XMLRPC, target)

        def decide(call: Request) -> Request:
            check_node_call(
                call.method,
                call.params,
                grants=self.verifier.freshest(peer.access).grants,
                peer_is_master=peer.manager == self.cfg.master.manager,
                topic_types=self.topic_types,
            )
            return tcpros_only(rewrite_call(call, publisher_uri=self.translator.to_local))

        def after(call: Request, response: Response | Fault) -> Response | Fault:
            response = redact_node_reply(call, response, MASTER)
            return rewrite_response(call, response, tcpros=self.translator.tcpros_to_canonical)

        async def handle(request: Request) -> Response | Fault:
            return await self._decide_calls(
                request, decide, lambda r: self._call_plain(endpoint.uri, r), after, "node", peer.manager
            )

        await self._serve_xmlrpc(reader, writer, handle)

    async def _serve_tcpros_stream(self, reader, writer, peer: Peer, target: str, purpose: str) -> None:
        endpoint = self.translator.resolve(KIND_TCPROS, target)
        limits = self.cfg.limits
        header, rest = await read_tcpros_header(
            reader, limits.handshake_timeout, limits.max_header_size, limits.max_header_fields
        )
        fields = header.as_dict()

        def judge(grants) -> frozenset[str] | None:
            """The peer's side of this stream against its grants (again whenever it shows
            a fresher token: a removed grant cuts exactly the streams it covered)."""
            if purpose == "topic":
                if "topic" not in fields:
                    raise PolicyDenied("malformed", "topic stream without a topic header")
                published = self.topic_types.get(fields["topic"])
                check_subscriber_header(
                    fields, grants=grants, published_type=published, published_md5=_md5_or_none(published)
                )
                return None
            if "service" not in fields:
                raise PolicyDenied("malformed", "service stream without a service header")
            return check_service_client_header(fields, grants=grants)

        try:
            client_types = judge(self.verifier.freshest(peer.access).grants)
            if peer.watch is not None:
                peer.watch.set_recheck(lambda fresh: judge(fresh.grants))
        except PolicyDenied:
            writer.write(encode_header({"error": OPAQUE}))
            with contextlib.suppress(Exception):
                await asyncio.wait_for(writer.drain(), 1)
            raise
        local_reader, local_writer = await asyncio.wait_for(
            asyncio.open_connection(endpoint.host, endpoint.port, limit=READ_SIZE), limits.handshake_timeout
        )
        try:
            # Only the known fields, rebuilt from the parsed values, reach the node; what
            # followed the header (a service request) goes through the frame check below.
            local_writer.write(encode_header(canonical_header(header)))
            reply, reply_rest = await read_tcpros_header(local_reader, CALL_TIMEOUT, limits.max_header_size)
            reply_fields = reply.as_dict()
            own = self.own_access()
            if purpose == "topic":
                check_publisher_header(reply_fields, grants=own.grants, topic=fields["topic"])
            else:
                check_service_server_header(
                    reply_fields, service=fields["service"], server_grants=own.grants, client_types=client_types
                )
        except BaseException as exc:
            local_writer.close()
            if isinstance(exc, PolicyDenied):
                writer.write(encode_header({"error": OPAQUE}))
            raise
        self.metrics.allowed.labels(purpose).inc()
        writer.write(encode_header(canonical_header(reply)))
        if purpose == "topic":
            # A subscriber sends nothing after its header: whatever it sends is dropped.
            await self._pump(reader, writer, local_reader, local_writer, left_pending=b"", right_pending=reply_rest,
                             left_discard=True)
        else:
            # Service requests from the peer: size-checked, and counted against its budget.
            name = fields["service"]
            frames = FrameCounter(max_size=limits.message_size_for(name), what=f"{peer.manager} {name}")
            await self._pump(reader, writer, local_reader, local_writer, left_pending=rest, right_pending=reply_rest,
                             left_budget=self._budget(peer), left_frames=frames,
                             on_deny=lambda exc: self._deny(purpose, exc, peer.manager))

    def _budget(self, peer: Peer) -> MessageBudget | None:
        """The message budget of one peer (shared by all its streams), if limited."""
        rate = self.cfg.limits.max_messages_per_second
        if rate is None:
            return None
        budget = self._budgets.get(peer.manager)
        if budget is None or budget.rate != rate:
            budget = self._budgets[peer.manager] = MessageBudget(rate)
        return budget

    async def _pump(
        self, left_reader, left_writer, right_reader, right_writer, *,
        left_pending: bytes, right_pending: bytes,
        left_budget: MessageBudget | None = None, left_frames: FrameCounter | None = None,
        left_discard: bool = False, on_deny: Callable[[PolicyDenied], None] | None = None,
    ) -> None:
        """Hand both streams to the byte pump and wait until both sides closed. The
        left side is toward the peer (bytes read there count as rx); ``*_pending`` are
        bytes read past the header on each side, which go through the same checks."""
        tx = self.metrics.bytes.labels("tx")
        rx = self.metrics.bytes.labels("rx")
        done = splice(
            left_writer.transport,
            right_writer.transport,
            left_pending=left_pending + _take_stream_buffer(left_reader),
            right_pending=right_pending + _take_stream_buffer(right_reader),
            on_left_bytes=rx.inc,
            on_right_bytes=tx.inc,
            left_budget=left_budget,
            left_frames=left_frames,
            left_discard=left_discard,
            on_deny=on_deny,
        )
        for transport in (left_writer.transport, right_writer.transport):
            if not transport.is_closing() and not transport.is_reading():
                transport.resume_reading()
        await done

    # ---------------------------------------------------------------- local master
    async def _on_local_master(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        master = self.cfg.master.interceptor or self.cfg.public
        tunnel = self.pool(master.host, master.port, "master", "")

        def decide(call: Request) -> Request:
            own = self.own_access()
            check_master_call(
                call.method, call.params, manager=own.subject, grants=own.grants, owner_of=lambda _node: None
            )
            call = _resolved_param_call(call, own.grants)
            call = rewrite_call(call, caller_api=self.translator.to_canonical, service_api=self.translator.to_canonical)
            return _rewrite_param_api(call, self.translator.to_canonical)

        def after(call: Request, response: Response | Fault) -> Response | Fault:
            if call.method == "registerPublisher" and _ros_ok(response):
                if self.topic_types.get(call.params[1]) != call.params[2]:
                    self.topic_types[call.params[1]] = call.params[2]
                    self._save_state()
            elif call.method in ("registerSubscriber", "unregisterSubscriber") and _ros_ok(response):
                self._note_local_subscriber(call)
            response = _filtered_param_reply(call, response, self.own_access().grants)
            return rewrite_response(call, response, uri=self.translator.to_local)

        async def handle(request: Request) -> Response | Fault:
            return await self._decide_calls(request, decide, tunnel.call, after, "local-master", "local node")

        try:
            await self._serve_xmlrpc(reader, writer, handle)
        except (RemoteProtocolError, asyncio.TimeoutError, ConnectionError) as exc:
            log.warning("local master connection dropped: %s", exc)
        finally:
            writer.close()

    # ---------------------------------------------------------------- subscribers reconnect
    def _note_local_subscriber(self, call: Request) -> None:
        """Which local nodes subscribe what, and their node APIs (to nudge them)."""
        node, topic = call.params[0], call.params[1]
        api = call.params[3] if call.method == "registerSubscriber" else call.params[2]
        subscribers = self._local_subscribers.setdefault(topic, {})
        if call.method == "registerSubscriber":
            subscribers[node] = self.translator.to_local(api)
        else:
            subscribers.pop(node, None)
            if not subscribers:
                del self._local_subscribers[topic]
        self._save_state()

    def _resubscribe_soon(self, topic: str, delay: float = 0.5, via: tuple[str, int] | None = None) -> None:
        """A topic stream into this host ended: tell the topic's local subscribers the
        current publishers (``publisherUpdate``, as the master would), so rospy and
        roscpp connect again once the publisher's side is back (they retry a failed
        connect by themselves, but not a connection the other side closed). ``via``
        is the publisher's interceptor: waited for (a token exchange, backing off up
        to a minute) before the subscribers are told."""
        if topic not in self._local_subscribers or topic in self._resubscribing or not self._started:
            return
        self._resubscribing.add(topic)

        async def nudge() -> None:
            try:
                await asyncio.sleep(delay)
                if via is not None:
                    await self._wait_reachable(via)
                uris = await self._publishers_of(topic)
                for node, api in list(self._local_subscribers.get(topic, {}).items()):
                    try:
                        await self._call_plain(api, Request(method="publisherUpdate", params=("/master", topic, uris)))
                    except (CryptorosError, OSError, asyncio.TimeoutError) as exc:
                        log.info("publisherUpdate of %s to %s failed: %s", topic, node, exc)
            except (CryptorosError, OSError, asyncio.TimeoutError) as exc:
                log.info("cannot list the publishers of %s: %s", topic, exc)
            finally:
                self._resubscribing.discard(topic)

        self._tasks.append(asyncio.ensure_future(nudge()))
        self._tasks = [t for t in self._tasks if not t.done()]

    async def _wait_reachable(self, endpoint: tuple[str, int], patience: float = 60.0) -> None:
        """Until a token exchange with a peer interceptor succeeds (or ``patience`` ends)."""
        deadline = time.monotonic() + patience
        backoff = 0.25
        while True:
            try:
                _reader, writer, _peer = await self.open_tunnel(*endpoint, "refresh", "")
                writer.close()
                return
            except (CryptorosError, OSError, asyncio.TimeoutError):
                if time.monotonic() + backoff > deadline:
                    raise
                await asyncio.sleep(backoff)
                backoff = min(backoff * 2, 4.0)

    async def _publishers_of(self, topic: str) -> list[str]:
        """The topic's publishers as the master knows them, as URIs local nodes can call."""
        master = self.cfg.master.interceptor or self.cfg.public
        tunnel = self.pool(master.host, master.port, "master", "")
        state = await tunnel.call(Request(method="getSystemState", params=("/cryptoros",)))
        if not _ros_ok(state):
            raise PolicyDenied("master_refused", f"getSystemState: {state!r:.80}")
        nodes = next((names for name, names in state.value[2][0] if name == topic), [])
        uris = []
        for node in nodes:
            reply = await tunnel.call(Request(method="lookupNode", params=("/cryptoros", node)))
            if _ros_ok(reply) and isinstance(reply.value[2], str):
                uris.append(self.translator.to_local(reply.value[2]))
        return uris

    # ---------------------------------------------------------------- relays
    async def _on_xmlrpc_relay(self, reader, writer, target: Canonical) -> None:
        """A local process calls a remote node's API (or the master calls a node's)."""
        tunnel = self.pool(target.host, target.port, "node", target.id)

        def decide(call: Request) -> Request:
            if call.method == "shutdown":
                raise PolicyDenied("shutdown_dropped", "node shutdown is never forwarded")
            return tcpros_only(rewrite_call(call, publisher_uri=self.translator.to_canonical))

        def after(call: Request, response: Response | Fault) -> Response | Fault:
            return rewrite_response(call, response, tcpros=self.translator.tcpros_to_local)

        async def handle(request: Request) -> Response | Fault:
            return await self._decide_calls(request, decide, tunnel.call, after, "relay", str(target))

        try:
            await self._serve_xmlrpc(reader, writer, handle)
        except (RemoteProtocolError, asyncio.TimeoutError, ConnectionError) as exc:
            log.warning("relay %s dropped: %s", target, exc)
        finally:
            writer.close()

    async def _on_tcpros_relay(self, reader, writer, target: Canonical) -> None:
        """A local subscriber or service client connects to a remote TCPROS server."""
        self._track(self._tcpros_relay(reader, writer, target))

    async def _tcpros_relay(self, reader, writer, target: Canonical) -> None:
        limits = self.cfg.limits
        tunnel_writer = None
        try:
            header, rest = await read_tcpros_header(
                reader, limits.handshake_timeout, limits.max_header_size, limits.max_header_fields
            )
            fields = header.as_dict()
            own = self.own_access()
            if "topic" in fields:
                purpose = "topic"
                if not own.grants.allows("subscribe", fields.get("callerid", ""), fields["topic"], fields.get("type", "")):
                    raise PolicyDenied("not_granted", f"{fields.get('callerid')} may not subscribe {fields['topic']}")
            elif "service" in fields:
                purpose = "service"
                client_types = check_service_client_header(fields, grants=own.grants)
            else:
                raise PolicyDenied("malformed", "TCPROS header with neither topic nor service")
            tunnel_reader, tunnel_writer, peer = await self.open_tunnel(
                target.host, target.port, purpose, target.id, first=encode_header(canonical_header(header)) + rest
            )
            unwatch = self.verifier.watch(peer.access, lambda _r: tunnel_writer.transport.abort())
            reply, reply_rest = await read_tcpros_header(
                tunnel_reader, CALL_TIMEOUT, limits.max_header_size, limits.max_header_fields
            )
            reply_fields = reply.as_dict()

            def judge(grants) -> None:
                """The publisher's (server's) side against its grants, again on each fresher token."""
                if purpose == "topic":
                    check_publisher_header(reply_fields, grants=grants, topic=fields["topic"])
                else:
                    check_service_server_header(
                        reply_fields, service=fields["service"], server_grants=grants, client_types=client_types
                    )

            judge(self.verifier.freshest(peer.access).grants)
            unwatch.set_recheck(lambda fresh: judge(fresh.grants))
            writer.write(encode_header(canonical_header(reply)))
            self.metrics.open_streams.labels(purpose).inc()
            try:
                # What the peer sends into this host (messages it publishes, replies of
                # its service) is size-checked frame by frame before a byte is relayed;
                # published messages count against its budget.
                name = fields.get("topic") or fields["service"]
                frames = FrameCounter(
                    max_size=limits.message_size_for(name), service_response=purpose == "service",
                    what=f"{peer.manager} {name}",
                )
                budget = self._budget(peer) if purpose == "topic" else None
                await self._pump(tunnel_reader, tunnel_writer, reader, writer, left_pending=reply_rest,
                                 right_pending=b"", left_budget=budget, left_frames=frames,
                                 on_deny=lambda exc: self._deny("relay", exc, str(target)))
            finally:
                unwatch()
                self.metrics.open_streams.labels(purpose).dec()
                if purpose == "topic":
                    self._resubscribe_soon(fields["topic"], via=(target.host, target.port))
        except (CryptorosError, asyncio.TimeoutError, ConnectionError, OSError) as exc:
            if isinstance(exc, CryptorosError):
                self._deny("relay", exc, str(target))
                with contextlib.suppress(Exception):
                    writer.write(encode_header({"error": OPAQUE}))
            if tunnel_writer is not None:
                tunnel_writer.close()
            writer.close()


#: Where the URIs of a master call sit that are relays at the master's interceptor.
_RELAY_URI_INDEX = {
    "registerPublisher": (3,), "registerSubscriber": (3,), "registerService": (2, 3), "subscribeParam": (1,),
    "unregisterPublisher": (2,), "unregisterSubscriber": (2,), "unregisterService": (2,), "unsubscribeParam": (1,),
}


def _local_endpoint(uri) -> tuple[str, int] | None:
    if not isinstance(uri, str):
        return None
    try:
        u = urllib.parse.urlsplit(uri)
        return (u.hostname, u.port) if u.hostname and u.port else None
    except ValueError:
        return None


def _resolved_param_call(call: Request, grants) -> Request:
    """A parameter call sent on with its key resolved as rosmaster would (checked)."""
    if call.method not in PARAM_READ and call.method not in PARAM_WRITE:
        return call
    params = check_param_call(call.method, call.params, grants=grants)
    return Request(method=call.method, params=params, path=call.path, keep_alive=call.keep_alive,
                   accept_gzip=call.accept_gzip)


def _filtered_param_reply(call: Request, response: Response | Fault, grants) -> Response | Fault:
    """Parameter replies narrowed to what the caller may read."""
    if not isinstance(response, Response) or (call.method not in PARAM_READ and call.method != "getParamNames"):
        return response
    value = filter_param_reply(call.method, call.params, response.value, grants=grants)
    return response if value is response.value else Response(value=value, keep_alive=response.keep_alive)


def _rewrite_param_api(call: Request, fn: Callable[[str], str]) -> Request:
    index = PARAM_CALLER_API_INDEX.get(call.method)
    if index is None or len(call.params) <= index or not isinstance(call.params[index], str):
        return call
    params = call.params[:index] + (fn(call.params[index]),) + call.params[index + 1 :]
    return Request(method=call.method, params=params, path=call.path, keep_alive=call.keep_alive,
                   accept_gzip=call.accept_gzip)


def _host_port(uri: str) -> tuple[str, int]:
    rest = uri.split("://", 1)[-1].split("/", 1)[0]
    host, _, port = rest.rpartition(":")
    return host, int(port)


def _md5_or_none(type_name: str | None) -> str | None:
    if type_name is None:
        return None
    try:
        return msgs.md5sum(type_name)
    except Exception:  # a type outside the known typestore: the publisher itself checks md5
        return None


def _read_cert_der(path) -> bytes:
    with open(path, "rb") as f:
        return x509.load_pem_x509_certificate(f.read()).public_bytes(Encoding.DER)


__all__ = ["Interceptor", "Peer", "XmlRpcTunnel", "cert_hosts", "read_tcpros_header", "read_xmlrpc"]
