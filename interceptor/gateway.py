"""The gateway: what every role of an interceptor shares (the asyncio edge).

One per process. It owns:

- the **public listener** (mutual TLS, handshake deadline, failed handshakes counted),
  and for every stream the sans-IO :class:`~interceptor.gate.StreamGate`: preamble
  with its deadline, the peer's token verified and bound to its certificate, limits
  (unauthenticated streams per source and certificate, new streams per second, open
  streams per peer), the opaque reply; then the stream goes to the role registered for
  its purpose, with the bytes that followed the preamble handed on explicitly;
- **tokens**: our own (:class:`~interceptor.authz_client.TokenKeeper`), peers'
  (:class:`~interceptor.verifier.PeerVerifier`, which also keeps the registry of
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
import time
from collections.abc import Awaitable, Callable, Iterator
from typing import Any

from aiohttp import web

from cryptoros.errors import PEER_FAILURES, CryptorosError, PolicyDenied, TokenError
from cryptoros.lru import remember
from cryptoros.monitor.model import MonitorModel
from cryptoros.ratelimit import Shunned, TokenBuckets
from cryptoros.tokens import AccessToken
from interceptor.authz_client import AuthzClient, RetryLog, TokenKeeper
from interceptor.verifier import PeerVerifier
from interceptor.certsource import CertSource
from interceptor.config import InterceptorConfig, check_reload
from interceptor.denials import DenialTable
from interceptor.learning import Learner
from interceptor.gate import FEED_HINTS, REFRESH, PendingStreams, TargetCheck, held_feed_wait
from interceptor.metrics import Metrics
from interceptor.monitor import Monitor, quarantine_path
from interceptor.pump import FrameCounter, MessageBudget, splice
from interceptor.slots import KeyedSlots

from interceptor.admission import FAILED_HANDSHAKE_BURST, FAILED_HANDSHAKE_RATE, KNOWN_SOURCES, SHUN_SECONDS, Admission
from interceptor.health import Health
from interceptor.outbound import Outbound
from interceptor.streams import (
    READ_SIZE,
    InboundStream,
    Peer,
    PublicListener,
    Tunnel,
    _Connected,
    cert_hosts,
    listening,
    log,
    read_chunks,
    read_into,
    take_buffered,
)


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


#: reads of the revocation feed a reload makes, 0.5 s apart, while it still lists the
#: manager the new token was just issued to as disabled
RELOAD_FEED_TRIES = 5


class Gateway(Admission, Outbound, Health):
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
        #: every TLS context, session cache and certificate fact, from one [tls] (interceptor/certsource.py)
        self.certs = self._load_certs(cfg)
        self.authz = AuthzClient(cfg.authz, self.certs.authz_ctx)
        self.keeper = TokenKeeper(self.authz, refresh_margin=cfg.authz.refresh_margin, manager=cfg.manager)
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
        #: learning mode (interceptor/learning.py): the verifier sees every token's grants through it
        self.learner = Learner(cfg.manager, serves_everyone="master" in cfg.roles, authz=self.authz,
                               registry=self.metrics.registry)
        self.verifier.learning = self.learner.state
        self.verifier.own_audience = self.certs.own_audience
        self.keeper.key_known = self._key_known
        self._own_access: AccessToken | None = None
        self._own_token: str | None = None
        #: the certificate a reload is installing while it applies the feed it read with
        #: it: our own serial in that feed is the new certificate's (_on_feed)
        self._installing: CertSource | None = None
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
        self._opening = KeyedSlots()
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
        #: incremented by :meth:`drop_spares` (a reload, a stop): a spare whose connect
        #: began before is not listed (made with the old client context; see keep_spare)
        self._spare_generation = 0
        self._purposes: dict[str, tuple[TargetCheck, Callable[[InboundStream], Awaitable[None]]]] = {}
        self._checks: dict[str, TargetCheck] = {}  # what the gate of every stream is given
        self._roles: list[Role] = []
        self._open_per_peer: dict[str, int] = {}
        self._pending = PendingStreams()
        #: source addresses verified peers streamed from (admission.py: KNOWN_SOURCES)
        self._known_sources: dict[str, bool] = {}
        #: unknown sources whose handshakes failed too fast (admission.py: FAILED_HANDSHAKE_RATE)
        self._shunned = Shunned(FAILED_HANDSHAKE_RATE, FAILED_HANDSHAKE_BURST, SHUN_SECONDS, max_keys=KNOWN_SOURCES)
        #: called when a source joins them (before it is added)
        self.source_listeners: list[Callable[[], None]] = []
        #: streams counted in all of the pending ones (unknown sources), not verified yet:
        #: per source, oldest first, the keys each entered (admission.py: _make_room)
        self._unverified: dict[str, dict[asyncio.Task, list]] = {}
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
        if self.cfg.limits.max_messages_per_second is None:
            log.warning("[limits] max_messages_per_second = 0: no per-peer message rate; one peer's flood can "
                        "stall other peers' flows into this host, during it and for a minute or more after it "
                        "on ROS 2 (docs/interceptor.md, \"Message rate\"); only benchmarks should run so")
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
        self.learner.install_log_marker()
        self.spawn(self.learner.run(), "learning")
        with listening("public", self.cfg.public):
            self._public_server = await PublicListener.start(self.cfg.public.host, self.cfg.public.port,
                                                             self._on_public)
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
        waits = RetryLog()
        while True:
            try:
                await self.keeper.refresh()
                await self.verifier.refresh_jwks()
                feed = await self.authz.fetch_revocations()
                if feed is not None:
                    self.verifier.apply(feed)
                self.verifier.last_feed_at = time.time()
                self.own_access()
                again = waits.succeeded()
                if again is not None:
                    log.info("access token held, %s", again)
                return
            except TokenError as exc:
                note = waits.failed(time.time())
                if note is not None:
                    log.warning("waiting for the authorization server: %s%s", exc, f"; {note}" if note else "")
                await asyncio.sleep(0.5)

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
        self.drop_spares()
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
        with contextlib.suppress(Exception):  # what was learned last is not lost with the process
            await asyncio.wait_for(self.learner.report(), 2.0)
        self.learner.remove_log_marker()
        await self.authz.close()

    def _load_certs(self, cfg: InterceptorConfig) -> CertSource:
        """The certificate source of ``cfg``: its handshakes counted and checked here
        (:meth:`_counting_sslobject_class`), the CA's revocations from the feed."""
        return CertSource.load(cfg, revoked_serials=lambda: self.verifier.revocations.revoked_serials,
                               sslobject_class=self._counting_sslobject_class())

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

    async def reload(self, cfg: InterceptorConfig) -> None:
        """SIGHUP: new certificates, CRL, policy and settings; open streams stay up.

        Every key of the file is either applied or refused (the table:
        :data:`interceptor.config.RELOAD`). A key that needs a restart ([authz] url,
        [listen] public, manager, roles...) refuses the whole reload with a ConfigError
        naming it, before anything is read or swapped. Otherwise all or nothing: the new
        TLS material is loaded (a new :class:`~interceptor.certsource.CertSource`) and a
        token bound to the new certificate fetched and verified before anything is
        swapped, so a failure (a renewed certificate the registry does not
        know yet, the authorization server down) keeps the old state everywhere (the
        caller catches and logs). Then the new configuration is swapped in and handed to
        the holders that keep a copy (authorization client, token keeper, verifier, the
        new-stream rate, the roles)."""
        check_reload(self.cfg, cfg)
        for role in self._roles:
            role.check_reload(cfg)
        monitor_model = MonitorModel.load(cfg.monitor.model) if cfg.monitor is not None else None
        certs = self._load_certs(cfg)  # one certificate source: every holder reads it by reference
        probe = AuthzClient(cfg.authz, certs.authz_ctx)
        feed_applied = False
        try:
            token = await probe.fetch_token()
            # the feed as it is now, read with the new certificate: the one held may be stale
            # (a revoked certificate cannot poll it) and still list our manager as disabled,
            # which had refused every reload after a re-admission (ROS 2 audit)
            with contextlib.suppress(TokenError):
                for _ in range(RELOAD_FEED_TRIES):
                    feed = await probe.fetch_revocations()
                    if feed is None or cfg.manager not in feed.disabled_subjects:
                        break
                    # the server issued the token, so it has our manager enabled: its feed,
                    # read from the registry every 0.25 s, has yet to say so (seen under load)
                    await asyncio.sleep(0.5)
                if feed is not None:
                    self._installing = certs  # the old serial, revoked in it, is about to be replaced
                    try:
                        self.verifier.apply(feed)
                    finally:
                        self._installing = None
                    feed_applied = True
                    self.verifier.last_feed_at = time.time()
        finally:
            await probe.close()
        try:
            self.verifier.verify(token.token, certs.own_der)  # bound to the new certificate, not revoked
            self.keeper.check(token)  # for our manager: the registry may bind the renewed certificate to another
        except CryptorosError:
            if feed_applied:  # the old certificate stays: that feed is judged against it after all
                self._on_feed(self.verifier.revocations)
            raise
        self.certs = certs  # the next handshake, in or out, uses it; the public port stays as it is
        self.drop_spares()  # made with the old certificate: a token bound to the new one fails on them
        if cfg.limits.max_new_connections_per_second != self.cfg.limits.max_new_connections_per_second:
            self._new_stream_limiter = self._stream_limiter(cfg)
        self.cfg = cfg  # what is read per use (most [limits]) applies from here
        # the authorization server binds the next token to the new certificate, and our
        # own token is checked against it
        self.verifier.own_audience = certs.own_audience
        self.verifier.reconfigure(poll_interval=cfg.authz.revocation_poll_interval, grace=cfg.authz.token_grace,
                                  revocation_grace=cfg.authz.revocation_grace, feed_wait=self._held_feed_wait(cfg),
                                  feed_heartbeat=cfg.authz.feed_heartbeat)
        self.keeper.refresh_margin = cfg.authz.refresh_margin
        self.authz.settings = cfg.authz  # same servers (check_reload): request_timeout from the new session on
        await self.authz.use_ssl_context(certs.authz_ctx)
        self.keeper.install(token)  # new grants, bound to the new certificate; peers' tokens anew
        self._own_access = None
        self.own_access()
        if self.monitor is not None and cfg.monitor is not None and monitor_model is not None:
            self.monitor.reconfigure(cfg.monitor, monitor_model)  # a retrained model: scored with from now on
        for role in self._roles:
            role.reloaded()
        log.info("reloaded certificates, CRL, policy, settings%s", " and the monitor's model" if self.monitor else "")

    # ================================================================ tokens
    def _on_feed(self, revocations) -> None:
        """When the feed revokes our own token or disables our manager, drop the token
        (nothing is allowed on it any more) and ask for a new one at once."""
        own = self._own_access
        serial = (self._installing or self.certs).own_serial
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
            except PEER_FAILURES as exc:
                log.info("token exchange with %s:%d failed: %s", *endpoint, exc)
            finally:
                self._exchanges.discard(endpoint)

        self.spawn(exchange())

    def known_sources(self) -> list[str]:
        """Source addresses verified peers streamed from, oldest first (kept across a
        restart by the ROS 1 role's state: a restarted interceptor that knew none counted
        every robot against the strangers' cap, and a stranger's idle connections kept
        them out)."""
        return list(self._known_sources)

    def know_sources(self, sources: list[str]) -> None:
        for source in sources[-KNOWN_SOURCES:]:
            remember(self._known_sources, str(source), True, KNOWN_SOURCES)

    async def _key_known(self, token: str) -> bool:
        """Whether our new ``token``'s signing key is known (the keeper keeps the token
        it holds until it is)."""
        return await self.verifier.knows_key(token, self.certs.own_der)

    def own_access(self) -> AccessToken:
        """Our own token, verified like a peer's (it carries our grants)."""
        token = self.keeper.current()
        if self._own_access is None or self._own_token != token:
            self._own_access = self.verifier.verify(token, self.certs.own_der)
            self._own_token = token
        return self._own_access

    def own_access_in_grace(self) -> AccessToken:
        """:meth:`own_access`; once our token ran out with the authorization server out of
        reach, the last one for ``[authz] token_grace`` more: what a peer gives a stream
        of ours past its token's expiry, so that what we send and take ends when the
        peers' cut says, not before. A refused token (none held) raises at once."""
        try:
            return self.own_access()
        except TokenError as exc:
            if exc.reason != "no_token" or self._own_access is None or \
                    not self.keeper.expired_within(self.cfg.authz.token_grace):
                raise
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
        the ``cryptoros-authz grant ...`` that would allow it (``cryptoros denials``); a
        stale feed's refusal says what to do (:data:`~interceptor.gate.FEED_HINTS`)."""
        reason = exc.reason
        self.metrics.denied.labels(kind, reason).inc()
        for line in self.denials.record(kind, who, reason, str(exc), time.monotonic(),
                                        hint=hint or FEED_HINTS.get(reason)):
            if logged:
                log.warning("%s", line)

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
            stall_timeout=self.cfg.limits.stalled_stream_timeout,
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
