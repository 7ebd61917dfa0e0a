"""The token issuer daemon: an aiohttp application behind mutual TLS.

Why one long module: the endpoints share the service's caches, the feed's long-polls
and heartbeats and the audit writer; the pure parts live in :mod:`authz_server.learning`,
:mod:`cryptoros.tokens` and :mod:`authz_server.registry`.

Endpoints (all behind the same mutual TLS; a client without a certificate from the
CA never gets past the handshake):

- ``POST /token``: OAuth 2 client credentials grant (RFC 6749 section 4.4), the
  client authenticated by its TLS certificate (RFC 8705). The certificate's SHA-256
  fingerprint names the manager; the answer is an RS256 JWT bound to that certificate
  (``cnf.x5t#S256``) carrying the manager's grants. With ``resource`` (RFC 8707,
  ``urn:cryptoros:peer:<x5t#S256 of a peer's certificate>``) the token's audience is
  that peer alone and it carries only the grants on topics and services the peer's
  manager is granted too (``invalid_target`` for an unknown or disabled peer).
- ``GET /.well-known/jwks.json``: the active key and every retired key a still-valid
  token may have been signed with.
- ``GET /revocations``: revoked token ids (unexpired), disabled managers and the
  managers in learning mode (until when), with a monotonic serial and an ``ETag`` so
  polls are cheap.
- ``POST /observations``: what an interceptor saw its own manager's nodes do (learning
  mode, unused grants; :mod:`authz_server.learning`), filed under the manager of the
  certificate that sends it.
- ``GET /healthz`` and ``GET /metrics`` (Prometheus text format).

Database calls run in a small thread pool, never on the event loop; the JWKS and the
feed are cached for ``cache_seconds`` (one lookup in flight per key); a manager's
grants are kept until the registry's version moves (:meth:`AuthzService.manager_for`),
so a token costs no database read but its audit row. Audit rows are written by group
commit: each request waits until its row is stored, and all rows that arrive
meanwhile share one transaction.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import hashlib
import heapq
import json
import logging
import math
import time
from collections.abc import Awaitable, Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, TypeVar

from aiohttp import HttpVersion11, web
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.exposition import CONTENT_TYPE_LATEST
from sqlalchemy.exc import SQLAlchemyError

from authz_server import keys as keymod
from authz_server.config import ServeConfig
from authz_server.learning import checked_observations, granted
from authz_server.registry import MAX_OBSERVATIONS, AuditEntry, ManagerInfo, Registry, RevocationFeed, new_jti
from cryptoros.files import PEM_LIMIT, read_bounded
from cryptoros.identity import identity_mismatch, named_holders
from cryptoros.lru import remember
from cryptoros.errors import ConfigError, CryptorosError, PKIError, RegistryError, TokenError
from cryptoros.ratelimit import OncePer, TokenBuckets
from cryptoros import pemfiles
from cryptoros.pemfiles import cert_fingerprint_sha256
from cryptoros.tls import peer_cert_der
from cryptoros.grants import Grant, Grants
from cryptoros.tokens import (
    FEED_STREAM_HEADER,
    build_claims,
    fingerprint_of_thumbprint,
    public_jwk,
    sign_token,
    thumbprint_of_audience,
)

log = logging.getLogger("cryptoros.authz")
T = TypeVar("T")

MAX_BODY = 16 * 1024
#: ``POST /observations`` per certificate: a rate a second and a burst
OBSERVE_RATE, OBSERVE_BURST = 2.0, 30
#: how often each replica reads the feed from the registry (long-polls wake on a change)
FEED_WATCH_INTERVAL = 0.25
#: a token whose grants changed in the registry while it was issued is built again, at
#: most this many times in all (then 503: the client retries)
ISSUE_ATTEMPTS = 3
#: the longest ``?wait=`` a client may ask for; it is held at most ``max_feed_wait`` (config)
MAX_FEED_WAIT = 3600.0
#: a streamed long-poll's heartbeat interval bounds (``?heartbeat=``, seconds)
MIN_HEARTBEAT = 0.2
MAX_HEARTBEAT = 300.0
#: a heartbeat on a streamed long-poll: one HTTP/1.1 chunk of one space
HEARTBEAT_CHUNK = b"1\r\n \r\n"
#: heartbeats fall due on this grid (seconds; half the interval if that is shorter), so one
#: wake-up writes every stream due at that instant
HEARTBEAT_GRID = 1.0
#: unsent bytes a stream's transport may hold before its heartbeats stop and it is cut
MAX_HEARTBEAT_BACKLOG = 4096
_dropped_log = OncePer(60.0, max_keys=1)
#: long-polls held at once, per client certificate and per replica (more are answered at once)
MAX_HELD_PER_CLIENT = 4
MAX_HELD = 10_000


class _Cache:
    """Values by key for ``ttl`` seconds, with one computation in flight per key.

    :meth:`clear` drops every value, and every computation in flight as well: one that
    started before the clear may have read what the clear is about, so its result goes
    to the callers already waiting on it and is not stored, and a caller that comes
    after the clear starts its own."""

    def __init__(self, ttl: float) -> None:
        self.ttl = ttl
        self._values: dict[Any, tuple[float, Any]] = {}
        self._inflight: dict[Any, asyncio.Future] = {}
        self._generation = 0

    async def get(self, key: Any, compute: Callable[[], Awaitable[T]]) -> T:
        now = time.monotonic()
        hit = self._values.get(key)
        if hit is not None and hit[0] > now:
            return hit[1]
        pending = self._inflight.get(key)
        if pending is not None:
            return await asyncio.shield(pending)
        fut: asyncio.Future = asyncio.get_running_loop().create_future()
        self._inflight[key] = fut
        generation = self._generation
        try:
            value = await compute()
        except BaseException as exc:
            fut.set_exception(exc)
            fut.exception()  # mark retrieved: waiters re-raise it, nobody else must
            raise
        else:
            fut.set_result(value)
            if self.ttl > 0 and generation == self._generation:
                self._values[key] = (time.monotonic() + self.ttl, value)
                if len(self._values) > 100_000:
                    self._values.clear()
            return value
        finally:
            if self._inflight.get(key) is fut:
                del self._inflight[key]

    def clear(self) -> None:
        self._values.clear()
        self._inflight.clear()
        self._generation += 1


class _Heartbeats:
    """The heartbeats of every held streamed long-poll, written by one timer callback as
    they fall due: a heartbeat costs one small write to its stream's transport, not a
    wake-up of the request that holds the stream nor one of its own. Due times are
    aligned on a grid (``HEARTBEAT_GRID``, or half the interval if that is shorter), so
    the streams due at one instant are written in one wake-up: each is late by less
    than one grid step and its spacing stays its interval. A heartbeat is one HTTP/1.1
    chunk holding a space (:data:`HEARTBEAT_CHUNK`), written straight to the transport
    without waiting for it to drain; the request's response must be chunked and
    uncompressed and have written its headers already (``_streamed_poll``). Written only
    while ``healthy()`` (the replica reads its registry). A stream whose transport is
    closing, or holds more than ``MAX_HEARTBEAT_BACKLOG`` bytes unsent (its client stopped
    reading), is dropped and its connection aborted: spaces never pile up in the replica."""

    def __init__(self, healthy: Callable[[], bool], counted: Callable[[int], None]) -> None:
        self._healthy, self._counted = healthy, counted
        self._due: list[tuple[float, int, asyncio.Transport, float]] = []
        self._live: set[int] = set()
        self._next_key = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._timer_at = 0.0
        self.dropped = 0

    @staticmethod
    def _aligned(at: float, interval: float) -> float:
        grid = min(HEARTBEAT_GRID, interval / 2)
        return math.ceil(at / grid - 1e-6) * grid

    def add(self, transport: asyncio.Transport, interval: float) -> int:
        self._loop = asyncio.get_running_loop()
        self._next_key += 1
        key = self._next_key
        heapq.heappush(self._due, (self._aligned(self._loop.time() + interval, interval), key, transport, interval))
        self._live.add(key)
        self._schedule()
        return key

    def remove(self, key: int) -> None:
        """Stop a stream's heartbeats. Its heap entry goes when the heap holds twice as
        many entries as live streams (so streams that come and go at a high rate, each
        removed long before its next beat, cannot grow the heap past that)."""
        self._live.discard(key)
        if len(self._due) > 2 * len(self._live) + 64:
            self._due = [entry for entry in self._due if entry[1] in self._live]
            heapq.heapify(self._due)

    def close(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _schedule(self) -> None:
        due, live = self._due, self._live
        while due and due[0][1] not in live:
            heapq.heappop(due)
        if not due:
            return
        at = due[0][0]
        if self._timer is not None:
            if self._timer_at <= at:
                return
            self._timer.cancel()
        assert self._loop is not None
        self._timer, self._timer_at = self._loop.call_at(at, self._tick), at

    def _tick(self) -> None:
        self._timer = None
        assert self._loop is not None
        now = self._loop.time()
        healthy = self._healthy()
        written = 0
        try:
            while self._due and self._due[0][0] <= now + 0.001:  # a timer may fire up to a clock tick early
                at, key, transport, interval = self._due[0]
                if key not in self._live:
                    heapq.heappop(self._due)
                    continue
                after = at + interval
                if after <= now:  # the loop was held up past a whole interval: no burst of beats
                    after = now + interval
                heapq.heapreplace(self._due, (self._aligned(after, interval), key, transport, interval))
                try:
                    if transport.is_closing() or transport.get_write_buffer_size() > MAX_HEARTBEAT_BACKLOG:
                        self._drop(key, transport)
                    elif healthy:
                        transport.write(HEARTBEAT_CHUNK)
                        written += 1
                except Exception as exc:  # gone under us: that stream alone stops
                    log.debug("a heartbeat could not be written: %s", exc)
                    self._drop(key, transport)
        finally:
            if written:
                self._counted(written)
            self._schedule()

    def _drop(self, key: int, transport: asyncio.Transport) -> None:
        self._live.discard(key)
        self.dropped += 1
        if not transport.is_closing():
            if _dropped_log("backlog"):
                log.warning("a streamed feed poll is cut: its client does not read its heartbeats "
                            "(over %d bytes unsent; logged once a minute)", MAX_HEARTBEAT_BACKLOG)
            transport.abort()  # its request is cancelled (handler_cancellation) and its hold ends


class _AuditWriter:
    """Group commit of audit rows: ``await write(entry)`` returns once it is stored (True),
    or once the registry refused it (False: an issued token whose grants changed since
    they were read, :meth:`~authz_server.registry.Registry.record`)."""

    def __init__(self, service: AuthzService) -> None:
        self.service = service
        self._pending: list[tuple[AuditEntry, asyncio.Future]] = []
        self._wake = asyncio.Event()
        self._task: asyncio.Task | None = None
        self._closing = False

    def start(self) -> None:
        self._task = asyncio.create_task(self._run(), name="audit-writer")

    async def write(self, entry: AuditEntry) -> bool:
        if self._closing:
            raise ConfigError("shutting down")
        fut = asyncio.get_running_loop().create_future()
        self._pending.append((entry, fut))
        self._wake.set()
        return await fut

    async def _run(self) -> None:
        while True:
            await self._wake.wait()
            self._wake.clear()
            batch, self._pending = self._pending, []
            if not batch:
                if self._closing:
                    return
                continue
            try:
                stored = await self.service.db(self.service.registry.record, [e for e, _ in batch])
            except Exception as exc:  # the DB is down: every waiter fails closed
                log.error("audit write failed for %d rows: %s", len(batch), exc)
                for _e, fut in batch:
                    if not fut.done():
                        fut.set_exception(exc)
            else:
                for (_e, fut), ok in zip(batch, stored):
                    if not fut.done():
                        fut.set_result(ok)
            if self._closing and not self._pending:
                return

    async def close(self) -> None:
        self._closing = True
        self._wake.set()
        if self._task is not None:
            await self._task


def _crl_number(crl: x509.CertificateRevocationList) -> int | None:
    try:
        return crl.extensions.get_extension_for_class(x509.CRLNumber).value.crl_number
    except x509.ExtensionNotFound:
        return None


def _crl_order(crl: x509.CertificateRevocationList) -> tuple[int, float]:
    """Which of two CRLs of one CA is the later: its CRL number, then when it was issued."""
    return (_crl_number(crl) or 0, crl.last_update_utc.timestamp())


class CRLWatcher:
    """Serials revoked by the CA's CRL, re-read when the file changes.

    The TLS context loads the CRL once, at start; this re-reads it (at most once per
    ``interval``) so a certificate revoked while the daemon runs is refused by the
    application within seconds. A CRL that does not parse or is not signed by the CA
    is ignored with an error in the log, keeping the last good one; so is one older than
    the one in use (a lower CRL number, or issued earlier): a copy of an old CRL would
    un-revoke the certificates revoked after it. An out-of-date CRL is still applied
    (revocations never lapse), with a warning. At start there is no good one to keep: a
    CRL that cannot be used then is a ConfigError (a server started on an empty or
    truncated copy had issued tokens to revoked certificates).
    """

    def __init__(self, crl_path, ca_path, interval: float = 1.0, *, registry: Any = None) -> None:
        #: the highest number of this CA's CRLs a server of ``registry`` applied (kept there,
        #: each higher one told): a server (re)started on an older copy would otherwise
        #: un-revoke what came after it (CLI re-audit)
        self.path, self.interval = crl_path, interval
        self._ca = pemfiles.load_certificate(ca_path)
        self._ca_id = cert_fingerprint_sha256(self._ca.public_bytes(serialization.Encoding.DER))
        self._registry = registry
        self.floor = registry.crl_number(self._ca_id) if registry is not None else 0
        self._stamp: tuple[int, int] | None = None
        self._bad: tuple[int, int] | None = None
        self._checked = 0.0
        self._crl: x509.CertificateRevocationList | None = None
        self.revoked: frozenset[int] = frozenset()
        self.refresh(first=True)

    def refresh(self, *, force: bool = False, first: bool = False) -> None:
        import os

        now = time.monotonic()
        if not force and now - self._checked < self.interval and self._stamp is not None:
            return
        self._checked = now
        try:
            st = os.stat(self.path)
            stamp = (st.st_mtime_ns, st.st_size)
            if stamp in (self._stamp, self._bad):
                return
            data = read_bounded(self.path, PEM_LIMIT)
            crl = pemfiles.parse_crl(data, self.path)
            if crl.issuer != self._ca.subject or not crl.is_signature_valid(self._ca.public_key()):
                raise ValueError("not issued by the CA")
            number = _crl_number(crl) or 0
            if self._crl is None and number < self.floor:
                raise ValueError(f"older than the CRLs this registry's servers applied (number {number}, against "
                                 f"{self.floor}): use the CA's current CRL")
            if self._crl is not None and _crl_order(crl) < _crl_order(self._crl):
                # a copy of an older CRL (still signed, still in date) would un-revoke what came after it
                raise ValueError(f"older than the CRL in use (number {_crl_number(crl)}, issued "
                                 f"{crl.last_update_utc:%Y-%m-%d %H:%M}, against {_crl_number(self._crl)}, "
                                 f"{self._crl.last_update_utc:%Y-%m-%d %H:%M})")
        except (OSError, ValueError, PKIError) as exc:
            if first:
                raise ConfigError(f"cannot use the CRL {self.path}: {exc} (revocations would not be checked: give "
                                  f"the CA's CRL, cryptoros-certs crl)") from None
            log.error("cannot reload the CRL %s, keeping the previous one: %s", self.path, exc)
            self._bad = locals().get("stamp")
            return
        self._stamp = stamp
        self._crl = crl
        if number > self.floor and self._registry is not None:
            try:
                self._registry.note_crl_number(self._ca_id, number)
                self.floor = number
            except Exception as exc:  # the registry down: the CRL is applied all the same
                log.warning("cannot record CRL number %d in the registry: %s", number, exc)
        if crl.next_update_utc is not None and crl.next_update_utc.timestamp() < time.time():
            log.warning("the CRL %s is out of date (a newer one was due %s UTC): still applied (revocations never "
                        "lapse); re-sign it (cryptoros-certs crl)", self.path, f"{crl.next_update_utc:%Y-%m-%d %H:%M}")
        revoked = frozenset(r.serial_number for r in crl)
        if revoked != self.revoked:
            log.info("CRL %s: %d revoked certificate(s)", self.path, len(revoked))
        self.revoked = revoked

    def is_revoked(self, der: bytes) -> bool:
        self.refresh()
        return bool(self.revoked) and pemfiles.cert_serial(der) in self.revoked


@dataclass
class _Signer:
    kid: str
    private_key: Any


class Metrics:
    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.issued = Counter("cryptoros_authz_tokens_issued", "Access tokens issued", registry=self.registry)
        self.denied = Counter("cryptoros_authz_token_denials", "Token requests refused, by reason",
                              ["reason"], registry=self.registry)
        self.latency = Histogram(
            "cryptoros_authz_request_duration_seconds", "Request handling time by endpoint", ["endpoint"],
            buckets=(0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5),
            registry=self.registry,
        )
        self.revocation_serial = Gauge("cryptoros_authz_revocation_serial", "Serial of the revocation feed",
                                       registry=self.registry)
        self.signing_key_age = Gauge("cryptoros_authz_signing_key_created_timestamp_seconds",
                                     "Creation time of the active signing key", registry=self.registry)
        self.feed_heartbeats = Counter("cryptoros_authz_feed_heartbeats", "Heartbeats written on streamed "
                                       "long-polls of the feed", registry=self.registry)
        self.feed_polls_held = Gauge("cryptoros_authz_feed_polls_held", "Long-polls of the feed held open now",
                                     registry=self.registry)
        self.tls_handshakes_refused = Counter("cryptoros_authz_tls_handshakes_refused", "TLS handshakes that "
                                              "failed or timed out at the public port", registry=self.registry)


class _Denied(CryptorosError):
    """A refused /token request; answered once, in the handler, as an OAuth error."""

    def __init__(self, status: int, error: str, reason: str, manager: str | None = None) -> None:
        super().__init__(reason=reason)
        self.status, self.error, self.manager = status, error, manager


#: seconds a failed registry request keeps /healthz unavailable (unless a token is issued meanwhile)
REGISTRY_FAILURE_SECONDS = 60.0
#: days before its certificate expires that the server warns (start, SIGHUP, /healthz)
CERT_WARN_DAYS = 14
#: client certificates whose named holders are kept (parsed once per certificate)
HOLDERS_CACHED = 4096


class AuthzService:
    """State of one daemon: registry, signing key, caches, metrics."""

    def __init__(self, cfg: ServeConfig, registry: Registry) -> None:
        self.cfg = cfg
        self.registry = registry
        self.executor = ThreadPoolExecutor(max_workers=cfg.db_threads, thread_name_prefix="authz-db")
        # the feed watcher's own thread: its read, which keeps the caches valid, never
        # queues behind the requests' (a flood would otherwise age it past cache_seconds)
        self._watch_executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="authz-watch")
        self.metrics = Metrics()
        # a manager's grants by certificate fingerprint, kept while the registry's version
        # is unchanged (manager_for); the version is read by the feed watcher
        self.heartbeats = _Heartbeats(lambda: self._latest is not None, self.metrics.feed_heartbeats.inc)
        self._managers = _Cache(float("inf"))
        self._holders: dict[str, list[tuple[str, str]]] = {}  # fingerprint -> whom its URI SANs name
        self._managers_version: int | None = None
        self._version: tuple[int, float] | None = None  # (registry version, monotonic time its read began)
        self._feed_serial: int | None = None
        self._shared = _Cache(cfg.cache_seconds)
        self._signer: _Signer | None = None
        self.audit = _AuditWriter(self)
        self._token_bucket = TokenBuckets(cfg.token_rate, cfg.token_burst)
        #: reports of observations per certificate (an interceptor sends one every few seconds)
        self._observe_bucket = TokenBuckets(OBSERVE_RATE, OBSERVE_BURST)
        self._rate_log = OncePer(60.0)
        self._pruner: asyncio.Task | None = None
        self._watcher: asyncio.Task | None = None
        self._latest: tuple[dict, str] | None = None
        self._feed_changed = asyncio.Event()
        self._closing = False
        self._held: dict[str, int] = {}  # long-polls held, per client certificate
        self._held_total = 0
        self.metrics.feed_polls_held.set_function(lambda: self._held_total)
        self.crl = CRLWatcher(cfg.tls.crl_file, cfg.tls.ca_file, registry=registry) if cfg.tls.crl_file else None
        #: (monotonic time, why) of the last request the registry failed, until a token is
        #: issued again: /healthz says so (a registry that reads but cannot write, a full
        #: disk, answered every token 503 while /healthz said ok)
        self.registry_failure: tuple[float, str] | None = None
        #: when this server's certificate expires (set by serve; /healthz says so ahead)
        self.cert_until: float | None = None

    async def db(self, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """Run a blocking registry call in the DB thread pool."""
        call = functools.partial(fn, *args, **kwargs)
        return await asyncio.get_running_loop().run_in_executor(self.executor, call)

    # ------------------------------------------------------------------ lifecycle
    async def start(self) -> None:
        active = await self.db(self.registry.active_key)
        if active is None:
            kid = await self.db(self.registry.rotate_key, self.cfg.keys)
            log.info("no signing key in the registry: created %s", kid)
            active = await self.db(self.registry.active_key)
            assert active is not None
        self._signer = await self._load_signer(active.kid, active.private_pem, active.encrypted)
        self.audit.start()
        self._pruner = asyncio.create_task(self._prune_audit_forever(), name="audit-pruner")
        self._watcher = asyncio.create_task(self._watch_feed(), name="feed-watcher")

    async def _prune_audit_forever(self, every: float = 3600.0) -> None:
        """Keep the audit log bounded (audit_keep_days, audit_max_rows), at start and hourly."""
        while True:
            try:
                n = await self.db(self.registry.prune_audit, keep_days=self.cfg.audit_keep_days,
                                  max_rows=self.cfg.audit_max_rows)
                if n:
                    log.info("audit log pruned: %d old rows deleted", n)
            except Exception as exc:  # the database is down: try again next time
                log.error("audit log pruning failed: %s", exc)
            await asyncio.sleep(every)

    async def close(self) -> None:
        for task in (self._pruner, self._watcher):
            if task is not None:
                task.cancel()
        await self.audit.close()
        self.heartbeats.close()
        self.executor.shutdown(wait=True)
        self._watch_executor.shutdown(wait=True)

    async def _load_signer(self, kid: str, pem: bytes, encrypted: bool) -> _Signer:
        key = await self.db(keymod.load_private, pem, encrypted, self.cfg.keys, kid)
        return _Signer(kid, key)

    @property
    def signing_kid(self) -> str | None:
        """The ``kid`` of the key signing now (None before :meth:`start`), without a
        database read (health checks, the start-up log)."""
        return self._signer.kid if self._signer is not None else None

    async def signer(self) -> _Signer:
        """The active signing key, following rotations made by the admin CLI."""
        async def fetch():
            return await self.db(self.registry.active_key)

        active = await self._shared.get("active_key", fetch)
        assert self._signer is not None
        if active is not None and active.kid != self._signer.kid:
            try:
                self._signer = await self._load_signer(active.kid, active.private_pem, active.encrypted)
                # the JWKS this replica serves lists the key before a token it signs names it
                self._shared.clear()
                log.info("signing key rotated: now signing with %s", active.kid)
            except ConfigError as exc:
                log.error("cannot load the new signing key %s, still signing with %s: %s",
                          active.kid, self._signer.kid, exc)
        return self._signer

    # ------------------------------------------------------------------ cached reads
    async def manager_for(self, fingerprint: str) -> tuple[ManagerInfo | None, Grants]:
        """The manager of a certificate and its grants: from the database once, then
        from memory for as long as the registry's version (a counter every change to a
        manager, certificate or grant bumps, in the same transaction) is the one the
        feed watcher read less than ``cache_seconds`` ago. A change is thus seen within
        one watcher interval (``FEED_WATCH_INTERVAL``), never later than
        ``cache_seconds`` after its commit; while the watcher cannot read the registry,
        nothing is served from memory."""
        version = self._fresh_version()
        if version is None or version != self._managers_version:
            self._managers.clear()
            self._managers_version = version

        async def fetch():
            info = await self.db(self.registry.lookup_fingerprint, fingerprint, now=time.time())
            grants = Grants(Grant(node=g.node, action=g.action, name=g.name, type=g.type)
                            for g in (info.grants if info else ()))
            return info, grants

        info, grants = await self._managers.get(fingerprint, fetch)
        if info is not None and info.fingerprint != fingerprint and (info.previous_until or 0) <= time.time():
            return None, Grants(())  # a renewed certificate's overlap ended (no registry change marks it)
        return info, grants

    def holder_mismatch(self, fingerprint: str, der: bytes, manager: str) -> str | None:
        """Why the client certificate ``der`` may not act as ``manager``, the one its
        fingerprint is bound to (:func:`cryptoros.identity.identity_mismatch`), or None.
        The CLI checks this where it sees the file; a fingerprint bound without it
        (``import``, ``set-cert --fingerprint``) to another robot's manager is refused here,
        not served that robot's grants."""
        holders = self._holders.get(fingerprint)
        if holders is None:
            holders = named_holders(x509.load_der_x509_certificate(der))
            remember(self._holders, fingerprint, holders, HOLDERS_CACHED)
        return identity_mismatch(holders, manager)

    def _fresh_version(self) -> int | None:
        if self._version is None or self.cfg.cache_seconds <= 0:
            return None
        version, read_at = self._version
        return version if time.monotonic() - read_at < self.cfg.cache_seconds else None

    async def jwks(self) -> dict:
        async def fetch():
            rows = await self.db(self.registry.published_keys, now=time.time(),
                                 max_lifetime=self.cfg.token_lifetime + 60)
            return {"keys": [public_jwk(keymod.load_public(r.public_pem), r.kid) for r in rows]}

        return await self._shared.get("jwks", fetch)

    async def current_feed(self) -> tuple[dict, str]:
        """The feed as served (registry part and, with a CRL, the revoked serials) and
        its ETag: the watcher's latest (at most ``FEED_WATCH_INTERVAL`` old), else read."""
        if self._latest is not None:
            return self._latest
        return self._stable(await self.feed())

    def _stable(self, feed: RevocationFeed) -> tuple[dict, str]:
        stable: dict[str, Any] = {"serial": feed.serial, "revoked_jtis": list(feed.revoked_jtis),
                                  "disabled_managers": list(feed.disabled_managers),
                                  "learning": dict(feed.learning)}
        if self.crl is not None:  # certificates the CA revoked reach interceptors with no SIGHUP
            self.crl.refresh()
            stable["revoked_serials"] = sorted(format(n, "x") for n in self.crl.revoked)
        return stable, _etag(json.dumps(stable, sort_keys=True).encode())

    def feed_event(self) -> asyncio.Event:
        """The event the next change of the feed sets (take it before reading the feed:
        a change between the read and the wait is then not missed)."""
        return self._feed_changed

    async def wait_feed_change(self, timeout: float, event: asyncio.Event | None = None) -> None:
        """Until the feed changes (a long-poll), ``timeout``, or the daemon stops."""
        if self._closing:
            return
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for((event or self._feed_changed).wait(), timeout)

    @contextlib.asynccontextmanager
    async def held_poll(self, client: str):
        """Whether a long-poll of ``client`` may be held: at most MAX_HELD_PER_CLIENT per
        client certificate and MAX_HELD in all, so connections held open stay bounded."""
        held = self._held.get(client, 0)
        ok = held < MAX_HELD_PER_CLIENT and self._held_total < MAX_HELD
        if ok:
            self._held[client] = held + 1
            self._held_total += 1
        try:
            yield ok
        finally:
            if ok:
                self._held_total -= 1
                left = self._held[client] - 1
                if left:
                    self._held[client] = left
                else:
                    del self._held[client]

    @property
    def closing(self) -> bool:
        return self._closing

    def release_waiters(self) -> None:
        """Stopping: every long-poll answers now (shutdown does not wait for them)."""
        self._closing = True
        self._feed_changed.set()

    async def _watch_feed(self) -> None:
        """One read of the registry's feed per FEED_WATCH_INTERVAL for this replica (not one
        per interceptor poll); a change wakes every long-poll waiting on this replica."""
        failing = False
        while True:
            try:
                began = time.monotonic()
                feed = await asyncio.get_running_loop().run_in_executor(
                    self._watch_executor, functools.partial(self.registry.revocation_feed, now=time.time()))
                self._version = (feed.registry_version, began)
                self._note_serial(feed.serial)
                latest = self._stable(feed)
                changed = self._latest is not None and latest[1] != self._latest[1]
                self._latest = latest
                if changed:
                    event, self._feed_changed = self._feed_changed, asyncio.Event()
                    event.set()
                if failing:
                    log.warning("the registry answers again: the feed is watched")
                failing = False
            except Exception as exc:  # the database is down: the feed is read per request (and fails)
                self._version = None
                if not failing:
                    log.error("cannot read the revocation feed from the registry: %s", exc)
                failing = True
                self._latest = None
                # held long-polls answer now (503 unless the registry answers them), not
                # after their wait: their clients try another replica meanwhile
                event, self._feed_changed = self._feed_changed, asyncio.Event()
                event.set()
            await asyncio.sleep(FEED_WATCH_INTERVAL)

    def _note_serial(self, serial: int) -> None:
        if serial != self._feed_serial:
            # the registry changed (a grant, a revocation): the next token of any
            # manager is built from the database, not from grants cached before
            self._feed_serial = serial
            self._managers.clear()
        self.metrics.revocation_serial.set(serial)

    async def feed(self) -> RevocationFeed:
        async def fetch():
            return await self.db(self.registry.revocation_feed, now=time.time())

        feed = await self._shared.get("feed", fetch)
        self._note_serial(feed.serial)
        return feed

    # ------------------------------------------------------------------ token issuing
    async def issue(self, request: web.Request) -> web.Response:
        remote = request.remote
        der = peer_cert_der(request.transport.get_extra_info("ssl_object") if request.transport else None)
        fp = cert_fingerprint_sha256(der)
        manager: str | None = None
        try:
            form = await _read_form(request)
            grant_type = form.get("grant_type")
            if grant_type is None:
                raise _Denied(400, "invalid_request", "grant_type missing")
            if grant_type != "client_credentials":
                raise _Denied(400, "unsupported_grant_type", f"grant_type {grant_type[:40]!r}")
            if self.crl is not None and self.crl.is_revoked(der):
                raise _Denied(401, "invalid_client", "certificate_revoked")
            if not self._token_bucket.allow(fp):  # before any audit row: a flood writes none
                self.metrics.denied.labels("rate_limited").inc()
                if self._rate_log(fp):
                    log.warning("token requests from certificate %s (%s) over %.0f/s: answered 429 (logged once a "
                                "minute)", fp[:16], remote, self.cfg.token_rate)
                return _oauth_error(429, "slow_down")
            for _attempt in range(ISSUE_ATTEMPTS):
                info, grants = await self.manager_for(fp)
                if info is None:
                    raise _Denied(401, "invalid_client", "unknown_certificate")
                manager = info.name
                mismatch = self.holder_mismatch(fp, der, manager)
                if mismatch is not None:
                    raise _Denied(401, "invalid_client", f"certificate_identity {mismatch}", manager)
                client_id = form.get("client_id")
                if client_id is not None and client_id != info.name:
                    raise _Denied(401, "invalid_client", f"client_id {client_id[:64]!r} does not match the certificate",
                                  manager)
                if not info.enabled:
                    raise _Denied(403, "access_denied", "manager_disabled", manager)
                audience, note, version = self.cfg.audience, "", info.version or 0
                resource = form.get("resource")
                if resource is not None:  # RFC 8707: a token for one peer interceptor only
                    audience, grants, note, peer_version = await self._narrowed(resource, grants, manager)
                    version = min(version, peer_version)
                signer = await self.signer()
                claims = build_claims(issuer=self.cfg.issuer, audience=audience, subject=info.name,
                                      grants=grants, cert_der=der, now=int(time.time()),
                                      lifetime=self.cfg.token_lifetime, jti=new_jti())
                token = sign_token(claims, signer.private_key, signer.kid)
                if await self.audit.write(AuditEntry("issued", info.name, fp, remote, note, claims["jti"], signer.kid,
                                                     claims["exp"], version=version)):
                    break
                # the registry changed since these grants were read (this replica's cache is
                # up to FEED_WATCH_INTERVAL behind): the token is dropped, never handed out,
                # and built again from the registry as it is now
                log.debug("grants of %s changed while its token was issued: issued again", manager)
                self._managers.clear()
            else:
                log.warning("token for %s not issued: the registry changed under each of %d attempts (answered 503)",
                            manager, ISSUE_ATTEMPTS)
                return _oauth_error(503, "temporarily_unavailable")
        except _Denied as d:
            self.metrics.denied.labels(d.reason.split(" ")[0]).inc()
            # a robot asking for a token for a peer the operator disabled is expected: info
            log.log(logging.INFO if d.reason.startswith("peer_disabled") else logging.WARNING,
                    "token denied: manager=%s fingerprint=%s remote=%s reason=%s", d.manager or "-", fp[:16], remote,
                    d.reason)
            try:
                await self.audit.write(AuditEntry("denied", d.manager, fp, remote, d.reason))
            except Exception:
                return _oauth_error(503, "temporarily_unavailable")
            return _oauth_error(d.status, d.error)
        self.metrics.issued.inc()
        return web.json_response(
            {"access_token": token, "token_type": "Bearer", "expires_in": self.cfg.token_lifetime},
            headers={"Cache-Control": "no-store", "Pragma": "no-cache"},
        )


    async def observe(self, request: web.Request) -> web.Response:
        """``POST /observations``: what the caller's interceptor saw its own nodes do
        (:mod:`authz_server.learning`), filed under the manager its certificate belongs
        to and no other. Learned requests are taken only while that manager learns;
        nothing here can start learning mode (only ``cryptoros-authz learn start``)."""
        der = peer_cert_der(request.transport.get_extra_info("ssl_object") if request.transport else None)
        fp = cert_fingerprint_sha256(der)
        if not self._observe_bucket.allow(fp):
            return _oauth_error(429, "slow_down")
        info, grants = await self.manager_for(fp)
        if info is None or self.holder_mismatch(fp, der, info.name) is not None:
            return _oauth_error(401, "invalid_client")
        if not info.enabled:
            return _oauth_error(403, "access_denied")
        if request.content_type != "application/json":
            return _oauth_error(400, "invalid_request")
        try:
            rows = checked_observations(await request.json(), now=time.time())
        except (ValueError, RegistryError) as exc:
            return web.json_response({"error": "invalid_request", "error_description": str(exc)[:200]}, status=400)
        # a request a grant allowed names a grant the manager holds: nothing else is kept as "used"
        kept = [r for r in rows if not r["allowed"] or granted(grants, r)]
        accepted, refused = await self.db(self.registry.record_observations, info.name, kept)
        refused += len(rows) - len(kept)
        if refused:
            log.info("observations from %s: %d refused (not learning, or over its %d rows)", info.name, refused,
                     MAX_OBSERVATIONS)
        return web.json_response({"accepted": accepted, "refused": refused})

    async def _narrowed(self, resource: str, grants: Grants, manager: str) -> tuple[str, Grants, str, int]:
        """Audience, grants, audit note and registry version (the peer's grants were read at)
        of a token for the peer ``resource`` names
        (``urn:cryptoros:peer:<x5t#S256>``): only the grants on topics and services the
        peer's manager holds a grant on too, so the peer learns nothing of the others
        (:meth:`~cryptoros.grants.Grants.narrowed_to`)."""
        try:
            thumbprint = thumbprint_of_audience(resource)
        except TokenError:
            raise _Denied(400, "invalid_target", "resource_malformed", manager) from None
        target, target_grants = await self.manager_for(fingerprint_of_thumbprint(thumbprint))
        if target is None:
            raise _Denied(400, "invalid_target", "resource_unknown", manager)
        if not target.enabled:  # what the manager's own robot asks for a disabled peer (a day-2 audit
            # read "manager=robot_a ... resource_unknown" as robot A refused): named as the peer's
            raise _Denied(400, "invalid_target", f"peer_disabled (a token for {target.name}, which is disabled)",
                          manager)
        return resource, grants.narrowed_to(target_grants), f"for {target.name}", target.version or 0


async def _read_form(request: web.Request) -> dict[str, str]:
    if request.content_length is not None and request.content_length > MAX_BODY:
        raise _Denied(400, "invalid_request", "body too large")
    ctype = request.content_type
    if ctype not in ("application/x-www-form-urlencoded", ""):
        raise _Denied(400, "invalid_request", f"content type {ctype[:60]!r}")
    try:
        post = await request.post()
    except Exception as exc:  # bad encoding, oversized...
        raise _Denied(400, "invalid_request", f"unreadable body: {type(exc).__name__}") from None
    form: dict[str, str] = {}
    for key in post:
        values = post.getall(key)
        if len(values) != 1 or not isinstance(values[0], str):
            raise _Denied(400, "invalid_request", f"parameter {key[:30]!r} repeated or not text")
        form[key] = values[0]
    return form


def _oauth_error(status: int, error: str) -> web.Response:
    return web.json_response({"error": error}, status=status,
                             headers={"Cache-Control": "no-store", "Pragma": "no-cache"})


_revoked_log = OncePer(60.0, max_keys=1024)


def _log_revoked_client(der: bytes, request: web.Request) -> None:
    """One line per revoked certificate per minute, naming it (a robot retrying every
    second would otherwise fill the log without saying who it is)."""
    from cryptography import x509

    cert = pemfiles.parse_certificate(der)
    if not _revoked_log(cert.serial_number):
        return
    names = cert.subject.get_attributes_for_oid(x509.NameOID.COMMON_NAME)
    log.warning("refused %s %s from %s: its client certificate (CN %s, serial %x) was revoked since start-up "
                "(logged once a minute)", request.method, request.path, request.remote,
                names[0].value if names else "?", cert.serial_number)


def make_app(service: AuthzService, *, probe: bool = False) -> web.Application:
    """The daemon's application; ``probe``: only ``/healthz`` and ``/metrics``, for the
    plain-HTTP loopback endpoint health checkers use (no client certificate)."""
    metrics = service.metrics

    @web.middleware
    async def guard(request: web.Request, handler):
        started = time.perf_counter()
        endpoint = request.match_info.route.resource.canonical if request.match_info.route.resource else "other"
        try:
            # Belt and braces: the TLS context already requires a verified certificate.
            ssl_object = request.transport.get_extra_info("ssl_object") if request.transport else None
            der = peer_cert_der(ssl_object)
            if service.crl is not None and request.path != "/token" and service.crl.is_revoked(der):
                _log_revoked_client(der, request)
                return _oauth_error(401, "invalid_client")
            response = await handler(request)
            if request.path == "/token" and response.status == 200:
                service.registry_failure = None
            return response
        except TokenError:
            return _oauth_error(401, "invalid_client")
        except web.HTTPException:
            raise
        except ConnectionError as exc:  # the client left while its answer was written (a stop, a cut)
            log.info("%s %s: the client left before its answer (%s)", request.method, request.path,
                     type(exc).__name__)
            raise
        except (CryptorosError, SQLAlchemyError) as exc:  # the registry cannot be read: try another replica
            why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            log.error("%s %s failed: %s", request.method, request.path, why)
            service.registry_failure = (time.monotonic(), f"{request.method} {request.path}: {why}"[:300])
            return _oauth_error(503, "temporarily_unavailable")
        except Exception:
            log.exception("%s %s failed", request.method, request.path)
            return _oauth_error(500, "server_error")
        finally:
            metrics.latency.labels(endpoint).observe(time.perf_counter() - started)

    async def token(request: web.Request) -> web.Response:
        return await service.issue(request)

    async def observations(request: web.Request) -> web.Response:
        return await service.observe(request)

    async def jwks(request: web.Request) -> web.Response:
        body = json.dumps(await service.jwks(), sort_keys=True).encode()
        return _etagged(request, body, "public, max-age=5")

    async def revocations(request: web.Request) -> web.Response:
        """The feed; ``?wait=S`` (at most MAX_FEED_WAIT) with a current ``If-None-Match``
        is a long-poll: the answer comes when the feed changes, when this replica can no
        longer read the registry (503), or 304 after S seconds, held at most
        ``max_feed_wait`` (a client asking longer simply asks again sooner)."""
        try:
            wait = float(request.query.get("wait", "0"))
            heartbeat = float(request.query.get("heartbeat", "0"))
        except ValueError:
            return _oauth_error(400, "invalid_request")
        if not (0 <= wait <= MAX_FEED_WAIT and (heartbeat == 0 or MIN_HEARTBEAT <= heartbeat <= MAX_HEARTBEAT)):
            return _oauth_error(400, "invalid_request")
        wait = min(wait, service.cfg.max_feed_wait)
        event = service.feed_event()
        stable, etag = await service.current_feed()
        if wait and etag in _if_none_match(request):
            der = peer_cert_der(request.transport.get_extra_info("ssl_object") if request.transport else None)
            async with service.held_poll(cert_fingerprint_sha256(der)) as held:
                if held and heartbeat and request.version >= HttpVersion11:  # its spaces are chunks
                    return await _streamed_poll(request, wait, heartbeat)
                if held:  # else over the client's or the replica's bound: answered at once, it polls
                    await service.wait_feed_change(wait, event)
            stable, etag = await service.current_feed()
        if etag in _if_none_match(request):
            return web.Response(status=304, headers={"ETag": etag, "Cache-Control": "no-cache"})
        body = dict(stable, generated_at=int(time.time()))
        return web.json_response(body, headers={"ETag": etag, "Cache-Control": "no-cache"})

    async def _streamed_poll(request: web.Request, wait: float, heartbeat: float) -> web.StreamResponse:
        """A long-poll that shows it is alive: a 200 and a space at once, then a space every
        ``heartbeat`` seconds (:class:`_Heartbeats`) while the feed stays as the client
        knows it and this replica reads its registry, then one JSON object: the feed (with
        its ``etag``) when it changed, or ``{"unchanged": true, "etag": ...}`` after
        ``wait``. JSON allows the
        leading spaces. A replica that can no longer read its registry cuts the
        connection (the client then tries another); one that hangs stops the spaces,
        which its client notices within two heartbeats."""
        known = _if_none_match(request)
        loop = asyncio.get_running_loop()
        deadline = loop.time() + wait
        response = web.StreamResponse(status=200, headers={"Content-Type": "application/json",
                                                           "Cache-Control": "no-cache", FEED_STREAM_HEADER: "1"})
        response.enable_chunked_encoding()
        await response.prepare(request)
        await response.write(b" ")  # the headers and a first space through aiohttp; the next ones are raw chunks
        if request.transport is None:  # gone already
            return response
        beats = service.heartbeats.add(request.transport, heartbeat)  # written by one timer, when due
        try:
            while True:
                event = service.feed_event()
                stable, etag = await service.current_feed()
                left = deadline - loop.time()
                if etag not in known or left <= 0 or service.closing:
                    break
                await service.wait_feed_change(left, event)
            service.heartbeats.remove(beats)
            answer = dict(stable, generated_at=int(time.time()), etag=etag) if etag not in known \
                else {"unchanged": True, "etag": etag}
            await response.write(json.dumps(answer).encode())
            await response.write_eof()
        except (CryptorosError, SQLAlchemyError) as exc:  # the registry cannot be read: cut, the client moves on
            log.error("a streamed feed poll is cut: %s", str(exc).splitlines()[0] if str(exc) else exc)
            if request.transport is not None:
                request.transport.abort()
        finally:
            service.heartbeats.remove(beats)
        return response

    async def healthz(request: web.Request) -> web.Response:
        async def ping():
            await service.db(service.registry.ping)
            return True

        try:
            await service._shared.get("ping", ping)
        except Exception as exc:
            log.error("health check: database unreachable: %s", exc)
            return web.json_response({"status": "unavailable", "database": "unreachable"}, status=503)
        failure = service.registry_failure
        if failure is not None and time.monotonic() - failure[0] < REGISTRY_FAILURE_SECONDS:
            return web.json_response({"status": "unavailable", "database": "failing", "last_failure": failure[1]},
                                     status=503)
        left = None if service.cert_until is None else service.cert_until - time.time()
        if left is not None and left <= 0:
            return web.json_response({"status": "unavailable", "database": "ok", "certificate": "expired"},
                                     status=503)
        certificate = "ok" if left is None or left >= CERT_WARN_DAYS * 86400 else f"expires in {left / 86400:.1f} days"
        return web.json_response({"status": "ok", "database": "ok", "kid": service.signing_kid,
                                  "certificate": certificate})

    async def prometheus(request: web.Request) -> web.Response:
        return web.Response(body=generate_latest(metrics.registry), headers={"Content-Type": CONTENT_TYPE_LATEST})

    if probe:
        app = web.Application(client_max_size=1024)
        app.router.add_get("/healthz", healthz)
        app.router.add_get("/metrics", prometheus)
        return app
    app = web.Application(middlewares=[guard], client_max_size=MAX_BODY)
    app.router.add_post("/token", token)
    app.router.add_post("/observations", observations)
    app.router.add_get("/.well-known/jwks.json", jwks)
    app.router.add_get("/revocations", revocations)
    app.router.add_get("/healthz", healthz)
    app.router.add_get("/metrics", prometheus)
    return app


def _etag(body: bytes) -> str:
    return '"' + hashlib.sha256(body).hexdigest()[:32] + '"'


def _if_none_match(request: web.Request) -> set[str]:
    raw = request.headers.get("If-None-Match", "")
    return {part.strip() for part in raw.split(",") if part.strip()}


def _etagged(request: web.Request, body: bytes, cache_control: str) -> web.Response:
    etag = _etag(body)
    if etag in _if_none_match(request):
        return web.Response(status=304, headers={"ETag": etag, "Cache-Control": cache_control})
    return web.Response(body=body, content_type="application/json",
                        headers={"ETag": etag, "Cache-Control": cache_control})
