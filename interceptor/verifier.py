"""Peers' tokens and the streams they open.

- :class:`PeerVerifier` verifies the tokens other interceptors present, with the
  JWKS and the revocation feed it polls every ``revocation_poll_interval`` seconds.
  A token seen before is not decoded again (a bounded cache by the token's SHA-256,
  emptied when the keys or the feed change); its expiry, its binding to the stream's
  certificate and the feed are checked on every stream.
  Open streams register with :meth:`PeerVerifier.watch`; when the feed revokes their
  token or disables their manager, their ``on_revoked`` callback closes them.

A stream never outlives its authority. The verifier keeps the *freshest* verified
token of every peer (its manager and certificate, :meth:`PeerVerifier.note`): a peer
presents a new one on any stream, or on a ``refresh`` exchange its interceptor makes
when its token changes. Every open stream is judged by its peer's freshest token:

- it is cut once that token has expired for more than ``grace`` seconds, and so is
  every stream once our own token has (both ends' authority must hold; the check runs
  on its own timer, never behind a request to the authorization server);
- when a fresher token arrives, the stream's ``recheck`` runs the policy again with
  the new grants and cuts the stream if it is no longer covered (a removed grant cuts
  exactly the streams it covered);
- when the feed revokes the token a stream was judged by, the stream is not cut at
  once if the peer can show a fresh, unrevoked token within ``revocation_grace``
  seconds (its interceptor fetches one as soon as it sees the revocation): then it
  is rechecked with that token. A peer that shows none (down, or compromised and
  unwilling) is cut when the grace ends. A disabled manager is cut at once.

The feed and the JWKS come through :class:`~interceptor.authz_client.AuthzClient`.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import time
from collections.abc import Callable, Iterator
import dataclasses
from dataclasses import dataclass

from cryptoros import pemfiles
from cryptoros.errors import PKIError, PolicyDenied, TokenError
from cryptoros.learning import LearningState
from cryptoros.lru import remember
from cryptoros.grants import Grants
from cryptoros.tokens import AccessToken, KeySet, Revocations, VerifiedTokenCache

from interceptor.authz_client import AuthzClient, AuthzRefused

log = logging.getLogger("cryptoros.interceptor.authz")

Clock = Callable[[], float]


@dataclass(eq=False)
class _Watch:
    access: AccessToken
    on_revoked: Callable[[str], None]
    #: Raises PolicyDenied when the stream is not covered by a (fresher) token.
    recheck: Callable[[AccessToken], None] | None = None
    #: When the token it was judged by was revoked: cut at this time unless a fresh one comes.
    revoked_deadline: float | None = None
    #: why the verifier cut it, once it did
    reason: str | None = None


class StreamWatch:
    """One open stream as the verifier watches it (:meth:`PeerVerifier.watch`): its judge
    declared, its end told, and why it was cut, if it was."""

    __slots__ = ("_entry", "_watches")

    def __init__(self, entry: _Watch, watches: set[_Watch]) -> None:
        self._entry, self._watches = entry, watches

    def judge_by(self, judge: Callable[[Grants], None]) -> None:
        """Re-judge the stream with ``judge`` (raises PolicyDenied when the grants no
        longer cover it) on every fresher token its peer shows."""
        self._entry.recheck = lambda access: judge(access.grants)

    def close(self) -> None:
        """The stream ended: no more watching."""
        self._watches.discard(self._entry)

    @property
    def reason(self) -> str | None:
        """Why the verifier cut the stream (``revoked``, ``grant_removed: ...``), or None."""
        return self._entry.reason


def _cuts_logged_together(method: Callable) -> Callable:
    """A :class:`PeerVerifier` method whose cuts are logged together at its end
    (:meth:`PeerVerifier._cuts_together`)."""
    @functools.wraps(method)
    def logged_together(self, *args, **kwargs):
        with self._cuts_together():
            return method(self, *args, **kwargs)
    return logged_together


def _log_cut(key: tuple[str, str, str], streams: int) -> None:
    manager, jti, reason = key
    log.warning("cutting off stream of manager=%s jti=%s: %s%s", manager, jti, reason,
                f" ({streams} streams)" if streams > 1 else "")


def _peer_key(access: AccessToken) -> tuple[str, str, str]:
    """A peer as we know it: its manager, the certificate its tokens are bound to and
    their audience (the master's interceptor sees a peer's whole token on master
    streams and the token narrowed for it on node streams: two views, never mixed)."""
    aud = access.claims.get("aud")
    return access.subject, access.thumbprint, aud if isinstance(aud, str) else repr(aud)


class PeerVerifier:
    """Verifies peer tokens; cuts off open streams on revocation."""

    JWKS_REFRESH_INTERVAL = 60.0
    #: tokens whose decode is kept (:class:`~cryptoros.tokens.VerifiedTokenCache`)
    TOKEN_CACHE_SIZE = 4096
    #: certificates whose serials are remembered (for CA revocations in the feed)
    MAX_CERTIFICATES = 4096
    #: an unknown ``kid`` fetches the JWKS again at most this often: after a rotation the
    #: first fetch can come before the key is published (a replica's 1 s cache), and at
    #: 5 s a peer's new token stayed refused that long
    UNKNOWN_KID_COOLDOWN = 1.0

    def __init__(
        self,
        client: AuthzClient,
        *,
        issuer: str,
        audience: str,
        poll_interval: float,
        grace: float = 30.0,
        revocation_grace: float = 3.0,
        clock: Clock = time.time,
        feed_wait: float = 0.0,
        feed_heartbeat: float = 0.0,
        token_cache_size: int = TOKEN_CACHE_SIZE,
    ) -> None:
        self._client = client
        #: decoded tokens by their SHA-256; emptied when the keys, the audiences or the feed change
        self.token_cache = VerifiedTokenCache(token_cache_size)
        self.issuer = issuer
        self.audience = audience
        #: seconds a feed request may be held by the server (long-poll); 0: plain polling
        self.feed_wait = feed_wait
        #: seconds between the server's signs of life on a held feed request (0: none);
        #: each one also keeps the feed fresh (:attr:`last_feed_at`)
        self.feed_heartbeat = feed_heartbeat
        #: ``urn:cryptoros:peer:<our certificate's thumbprint>``: tokens peers narrowed for us.
        self.own_audience: str | None = None
        self._poll = poll_interval
        self.grace = grace
        self.revocation_grace = revocation_grace
        self._freshest: dict[tuple[str, str], AccessToken] = {}
        self._serials: dict[str, int] = {}  # certificate thumbprint -> serial, of peers verified
        self._clock = clock
        self.keys = KeySet({})
        self.revocations = Revocations()
        self._watches: set[_Watch] = set()
        self._last_jwks = 0.0
        self.ready = asyncio.Event()
        self.last_feed_at: float | None = None
        #: The last feed poll was refused (401): our certificate is not accepted any more.
        self.refused = False
        #: Called with each new feed (after open streams were cut).
        self.listeners: list[Callable[[Revocations], None]] = []
        #: Called with a peer token the feed just revoked (its holder may have a new one).
        self.stale_listeners: list[Callable[[AccessToken], None]] = []
        #: Called with the reason label of every stream cut (``token_expired``, ``revoked``...).
        self.cut_listeners: list[Callable[[str], None]] = []
        #: cuts made together (a feed, a sweep, a fresher token), logged at its end: (manager, jti, reason) -> streams
        self._cut_batch: dict[tuple[str, str, str], int] | None = None
        #: called with each fresher token a peer shows (after its streams are judged again on it)
        self.fresh_listeners: list[Callable[[AccessToken], None]] = []
        #: When this interceptor's own token expires (None: it holds none): once that is
        #: ``grace`` ago, every open stream is cut, whatever the peers' tokens say.
        self.own_expiry: Callable[[], float | None] = lambda: None
        self._down_since: float | None = None  # the feed has not answered since then
        #: learning mode (:mod:`cryptoros.learning`): every verified token's grants are
        #: seen through it; None: grants as they are
        self.learning: LearningState | None = None
        self._widened: frozenset[str] = frozenset()  # managers widened at the last look

    def reconfigure(self, *, poll_interval: float, grace: float, revocation_grace: float, feed_wait: float,
                    feed_heartbeat: float) -> None:
        """A reload's settings: the poll interval and the feed's long-poll from the next
        request (one held now ends as it was asked), the graces from the next sweep and feed."""
        self._poll = poll_interval
        self.grace = grace
        self.revocation_grace = revocation_grace
        self.feed_wait = feed_wait
        self.feed_heartbeat = feed_heartbeat

    def verify(self, token: str, peer_cert_der: bytes | None) -> AccessToken:
        """Verify with the keys and revocations known now; TokenError on any failure.
        The audience is the deployment's (a whole token) or :attr:`own_audience` (a
        token narrowed for this interceptor); one narrowed for another peer is refused.

        A token verified before is not decoded again (:attr:`token_cache`: signature
        and claims); its time, its binding to ``peer_cert_der`` and the feed are
        checked on every call."""
        access = self.token_cache.verify(
            token,
            keys=self.keys,
            issuer=self.issuer,
            audience=(self.audience, self.own_audience) if self.own_audience else self.audience,
            peer_cert_der=peer_cert_der,
            now=self._clock(),
            revocations=self.revocations,
        )
        if self.learning is not None:
            access = dataclasses.replace(access, grants=self.learning.grants(access.subject, access.grants))
        if access.thumbprint not in self._serials:  # so a CA revocation in the feed can cut its streams
            try:
                serial = pemfiles.cert_serial(peer_cert_der)
            except PKIError:  # not a certificate (the TLS layer hands us only real ones)
                return access
            remember(self._serials, access.thumbprint, serial, self.MAX_CERTIFICATES)
        return access

    async def verify_fresh(self, token: str, peer_cert_der: bytes | None) -> AccessToken:
        """Like :meth:`verify`, but an unknown ``kid`` triggers one JWKS refresh first
        (key rotation), at most once per cooldown so garbage cannot hammer the server."""
        try:
            return self.verify(token, peer_cert_der)
        except TokenError as exc:
            if exc.reason != "unknown_kid" or self._clock() - self._last_jwks < self.UNKNOWN_KID_COOLDOWN:
                raise
        await self.refresh_jwks()
        return self.verify(token, peer_cert_der)

    async def knows_key(self, token: str, cert_der: bytes | None) -> bool:
        """Whether ``token`` (this interceptor's own, from the authorization server) is
        signed with a key in the JWKS, fetched again if it is not (``rotate-key``).
        Other failures are not this check's: True."""
        for attempt in range(2):
            try:
                self.verify(token, cert_der)
                return True
            except TokenError as exc:
                if exc.reason != "unknown_kid":
                    return True
            if attempt == 0:
                await self.refresh_jwks()
        return False

    def watch(self, access: AccessToken, on_cut: Callable[[str], None],
              judge: Callable[[Grants], None] | None = None) -> StreamWatch:
        """Register an open stream judged by ``access``: ``on_cut`` is called with the
        reason when the verifier cuts it; ``judge`` (or one declared later on the
        returned watch) re-judges it on every fresher token of its peer."""
        entry = _Watch(self.freshest(access), on_cut)
        watch = StreamWatch(entry, self._watches)
        if judge is not None:
            watch.judge_by(judge)
        self._watches.add(entry)
        return watch

    # ------------------------------------------------------------ freshest tokens
    def note(self, access: AccessToken) -> AccessToken:
        """Remember a verified token of a peer; returns the peer's freshest. A fresher
        token re-judges the peer's open streams (:meth:`_rejudge`).

        Token times are whole seconds: of two tokens issued in the same second (a grant
        changed just after the peer fetched one), the one shown last wins. Only the
        holder of the peer's certificate can show tokens for it, and an interceptor
        always shows its newest."""
        key = _peer_key(access)
        current = self._freshest.get(key)
        if current is access or current is not None and current.jti == access.jti:
            return current
        if current is not None and (current.expires_at, current.issued_at) > (access.expires_at, access.issued_at) \
                and current.jti not in self.revocations.revoked_jtis:
            return current
        self._freshest[key] = access
        self._rejudge(key, access)
        for listener in self.fresh_listeners:
            listener(access)
        return access

    def freshest(self, access: AccessToken) -> AccessToken:
        """The freshest verified token of the peer that presented ``access``."""
        current = self._freshest.get(_peer_key(access))
        if current is None or current.expires_at < access.expires_at:
            return access
        return current

    def _cut(self, entry: _Watch, reason: str) -> None:
        self._watches.discard(entry)
        entry.reason = reason
        key = (entry.access.subject, entry.access.jti, reason)
        if self._cut_batch is not None:
            self._cut_batch[key] = self._cut_batch.get(key, 0) + 1
        else:
            _log_cut(key, 1)
        for listener in self.cut_listeners:
            listener(reason.split(":", 1)[0])
        try:
            entry.on_revoked(reason)
        except Exception:  # a broken stream must not stop the others from being cut
            log.exception("closing a stream failed")

    @contextlib.contextmanager
    def _cuts_together(self) -> Iterator[None]:
        """The cuts made inside are logged once per manager, token and reason, with how
        many streams (a disabled robot's 50 streams were 50 lines)."""
        if self._cut_batch is not None:
            yield
            return
        self._cut_batch = {}
        try:
            yield
        finally:
            batch, self._cut_batch = self._cut_batch, None
            for key, streams in batch.items():
                _log_cut(key, streams)

    @_cuts_logged_together
    def _rejudge(self, key: tuple[str, str], access: AccessToken) -> None:
        for entry in list(self._watches):
            if _peer_key(entry.access) != key:
                continue
            if entry.recheck is not None:
                try:
                    entry.recheck(access)
                except PolicyDenied as exc:
                    self._cut(entry, f"grant_removed: {exc.detail}")
                    continue
            entry.access = access
            entry.revoked_deadline = None

    @_cuts_logged_together
    def sweep(self) -> int:
        """Cut streams whose peer's freshest token expired more than ``grace`` ago, or
        whose revoked token was not replaced within ``revocation_grace``, and every
        stream once our own token expired more than ``grace`` ago (both ends' authority
        must hold); forget tokens no stream needs. Returns how many streams were cut."""
        now = self._clock()
        own = self.own_expiry()
        cut = self._rejudge_learning()
        for entry in list(self._watches):
            if entry.access.expires_at + self.grace < now:
                self._cut(entry, f"token_expired: no fresh token {now - entry.access.expires_at:.0f} s after expiry")
                cut += 1
            elif own is not None and own + self.grace < now:
                self._cut(entry, f"own_token_expired: this interceptor's own token expired {now - own:.0f} s ago")
                cut += 1
            elif entry.revoked_deadline is not None and entry.revoked_deadline <= now:
                self._cut(entry, "revoked")
                cut += 1
        live = {_peer_key(e.access) for e in self._watches}
        for key, access in list(self._freshest.items()):
            if key not in live and access.expires_at + self.grace < now:
                del self._freshest[key]
        return cut

    def _rejudge_learning(self) -> int:
        """Streams let through by learning mode are judged again once it ended for their
        peer's manager or for ours (a window ran out, or the feed dropped it); the ones
        no grant covers are cut (``learning_ended``). Returns how many were cut."""
        state = self.learning
        if state is None:
            return 0
        widened = frozenset(m for m, _until in state.windows.items() if state.widens(m))
        ended, self._widened = self._widened - widened, widened
        if not ended:
            return 0
        if state.own in ended:
            state.table.forget_learned()
        cut = 0
        for entry in list(self._watches):
            if entry.recheck is None or not (entry.access.subject in ended or state.own in ended):
                continue
            try:
                entry.recheck(entry.access)
            except PolicyDenied as exc:
                self._cut(entry, f"learning_ended: {exc.detail}")
                cut += 1
        return cut

    def streams_by_peer(self) -> dict[str, int]:
        """Open streams per peer manager."""
        counts: dict[str, int] = {}
        for entry in self._watches:
            counts[entry.access.subject] = counts.get(entry.access.subject, 0) + 1
        return dict(sorted(counts.items()))

    @property
    def open_streams(self) -> int:
        return len(self._watches)

    async def refresh_jwks(self) -> None:
        """Fetch the authorization server's signing keys now (kept as they were if it fails)."""
        self._last_jwks = self._clock()
        try:
            self.keys = await self._client.fetch_jwks()
        except TokenError as exc:
            log.warning("cannot refresh JWKS (%s); keeping %d known keys", exc.detail, len(self.keys))

    @_cuts_logged_together
    def apply(self, revocations: Revocations) -> int:
        """Adopt a new feed: cut every watched stream of a disabled manager or over a
        certificate the CA revoked (its serial in the feed's CRL list); a stream
        whose token is revoked gets ``revocation_grace`` seconds for its peer to show a
        fresh one (see the module docstring). Returns how many were cut now."""
        self.revocations = revocations
        if self.learning is not None:
            self.learning.windows = dict(revocations.learning)
        cut = self._rejudge_learning()
        stale: dict[tuple[str, str], AccessToken] = {}
        deadline = self._clock() + self.revocation_grace
        for entry in list(self._watches):
            access = entry.access
            if access.subject in revocations.disabled_subjects:
                self._cut(entry, "subject_disabled")
                cut += 1
            elif self._serials.get(access.thumbprint) in revocations.revoked_serials:
                self._cut(entry, "certificate_revoked")  # no fresh token helps: they are bound to it
                cut += 1
            elif access.jti in revocations.revoked_jtis:
                if entry.revoked_deadline is None:
                    entry.revoked_deadline = deadline
                stale[_peer_key(access)] = access
        for key, access in stale.items():
            if self._freshest.get(key) is access:
                del self._freshest[key]
            for listener in self.stale_listeners:
                listener(access)
        for listener in self.listeners:
            listener(revocations)
        return cut

    async def run(self) -> None:
        """Follow the revocation feed forever: long-polls of ``feed_wait`` seconds (the
        server answers at once when it changes), never more often than the poll
        interval (a server that does not hold the request is simply polled); the JWKS
        every minute; expired and revoked streams swept every poll interval. Three
        tasks: the sweep never waits on the network, so a server that is down or hangs
        cannot hold back a cut."""
        others = [asyncio.ensure_future(self._sweep_forever()), asyncio.ensure_future(self._refresh_jwks_forever())]
        try:
            await self._follow_feed()
        finally:
            for task in others:
                task.cancel()

    async def _sweep_forever(self) -> None:
        while True:
            await asyncio.sleep(self._poll)
            try:
                self.sweep()
            except Exception:  # a sweep that stopped for good would let every stream outlive its authority
                log.exception("sweeping the open streams failed")

    async def _refresh_jwks_forever(self) -> None:
        while True:
            await asyncio.sleep(self._poll)
            if self._clock() - self._last_jwks >= self.JWKS_REFRESH_INTERVAL:
                await self.refresh_jwks()

    def _feed_alive(self) -> None:
        """A sign of life of the feed (an answer, or a heartbeat of a held request: the
        server reads its registry and the feed is unchanged as of now): fresh from now,
        and one line if it had stopped answering."""
        self.last_feed_at = self._clock()
        self.refused = False
        if self._down_since is not None:
            log.warning("the revocation feed answers again (unreachable for %.0f s)", self.last_feed_at - self._down_since)
            self._down_since = None

    async def _follow_feed(self) -> None:
        while True:
            started = time.monotonic()
            if not len(self.keys):
                await self.refresh_jwks()
            try:
                feed = await self._client.fetch_revocations(wait=self.feed_wait if self.ready.is_set() else 0.0,
                                                            heartbeat=self.feed_heartbeat, alive=self._feed_alive)
                self._feed_alive()
                if feed is not None:
                    self.apply(feed)
                if len(self.keys):
                    self.ready.set()
            except TokenError as exc:
                self.refused = isinstance(exc, AuthzRefused)
                if self._down_since is None:  # one line when it goes, one when it comes back
                    self._down_since = self._clock()
                    log.warning("cannot poll the revocation feed (%s); keeping the last one, new streams are "
                                "refused once it is older than max_feed_age", exc.detail)
            await asyncio.sleep(max(0.0, self._poll - (time.monotonic() - started)))


__all__ = ["PeerVerifier", "StreamWatch"]
