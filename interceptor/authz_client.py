"""The interceptor's side of the authorization server.

- :class:`AuthzClient` speaks HTTPS with mutual TLS to ``cryptoros-authz``: ``POST
  /token`` (OAuth 2 client credentials, RFC 6749 4.4, client authenticated by its
  certificate, RFC 8705), the JWKS and the revocation feed.
- :class:`TokenKeeper` holds this interceptor's own access token: fetched at start,
  refreshed ``refresh_margin`` seconds before expiry, kept while the server is down
  and still valid, and refused (``TokenError("no_token")``) once it has expired:
  nothing new is allowed without one.
- :class:`PeerVerifier` verifies the tokens other interceptors present, with the
  JWKS and the revocation feed it polls every ``revocation_poll_interval`` seconds.
  Open streams register with :meth:`PeerVerifier.watch`; when the feed revokes their
  token or disables their manager, their ``on_revoked`` callback closes them.

Every wait is bounded by ``request_timeout``; failures are logged and retried, never
raised into the event loop.
"""

from __future__ import annotations

import asyncio
import logging
import ssl
import time
from collections.abc import Callable
from dataclasses import dataclass

import aiohttp

from cryptoros.errors import TokenError
from cryptoros.tokens import AccessToken, KeySet, Revocations, verify_access_token
from interceptor.config import AuthzSettings

log = logging.getLogger("cryptoros.interceptor.authz")

Clock = Callable[[], float]


class AuthzUnavailable(TokenError):
    """The authorization server could not be asked (down, refused us, bad answer)."""

    def __init__(self, detail: str) -> None:
        super().__init__("authz_unavailable", detail)


@dataclass(frozen=True, kw_only=True)
class OwnToken:
    token: str
    expires_at: float


class AuthzClient:
    """Mutual-TLS HTTPS client of the authorization server."""

    def __init__(self, settings: AuthzSettings, ssl_context: ssl.SSLContext) -> None:
        self.settings = settings
        self._ssl = ssl_context
        self._session: aiohttp.ClientSession | None = None
        self._feed_etag: str | None = None

    def _http(self) -> aiohttp.ClientSession:
        if self._session is None or self._session.closed:
            self._session = aiohttp.ClientSession(
                connector=aiohttp.TCPConnector(ssl=self._ssl, limit=4),
                timeout=aiohttp.ClientTimeout(total=self.settings.request_timeout),
            )
        return self._session

    async def close(self) -> None:
        if self._session is not None:
            await self._session.close()

    async def _json(self, method: str, path: str, **kw) -> tuple[int, dict | None, aiohttp.typedefs.LooseHeaders]:
        url = self.settings.url + path
        try:
            async with self._http().request(method, url, **kw) as resp:
                if resp.status == 304:
                    return resp.status, None, resp.headers
                body = await resp.json(content_type=None)
                if not isinstance(body, dict):
                    raise AuthzUnavailable(f"{path}: answer is not a JSON object")
                return resp.status, body, resp.headers
        except (aiohttp.ClientError, asyncio.TimeoutError, ValueError, ssl.SSLError, OSError) as exc:
            raise AuthzUnavailable(f"{method} {url}: {type(exc).__name__}: {exc}") from exc

    async def fetch_token(self, *, clock: Clock = time.time) -> OwnToken:
        asked_at = clock()
        status, body, _ = await self._json("POST", "/token", data={"grant_type": "client_credentials"})
        if status != 200 or body is None:
            raise AuthzUnavailable(f"token refused: HTTP {status} {body.get('error') if body else ''}".strip())
        token, lifetime = body.get("access_token"), body.get("expires_in")
        if not isinstance(token, str) or not isinstance(lifetime, int) or lifetime <= 0:
            raise AuthzUnavailable("token answer lacks access_token or expires_in")
        return OwnToken(token=token, expires_at=asked_at + lifetime)

    async def fetch_jwks(self) -> KeySet:
        status, body, _ = await self._json("GET", "/.well-known/jwks.json")
        if status != 200 or body is None:
            raise AuthzUnavailable(f"JWKS: HTTP {status}")
        keys = KeySet.from_jwks(body)
        if not len(keys):
            raise AuthzUnavailable("JWKS holds no RS256 key")
        return keys

    async def fetch_revocations(self) -> Revocations | None:
        """The feed, or None when it has not changed since the last poll."""
        headers = {"If-None-Match": self._feed_etag} if self._feed_etag else {}
        status, body, resp_headers = await self._json("GET", "/revocations", headers=headers)
        if status == 304:
            return None
        if status != 200 or body is None:
            raise AuthzUnavailable(f"revocation feed: HTTP {status}")
        jtis, managers = body.get("revoked_jtis"), body.get("disabled_managers")
        if not (isinstance(jtis, list) and isinstance(managers, list)):
            raise AuthzUnavailable("revocation feed lacks revoked_jtis or disabled_managers")
        self._feed_etag = resp_headers.get("ETag")
        return Revocations(
            revoked_jtis=frozenset(str(j) for j in jtis), disabled_subjects=frozenset(str(m) for m in managers)
        )


class TokenKeeper:
    """This interceptor's own access token, always fresh or refused."""

    #: A token this close to expiry is not handed out: the peer would see it expired.
    MIN_REMAINING = 2.0

    def __init__(self, client: AuthzClient, *, refresh_margin: float, clock: Clock = time.time) -> None:
        self._client = client
        self._margin = refresh_margin
        self._clock = clock
        self._token: OwnToken | None = None
        self.refreshed = asyncio.Event()
        self._wake = asyncio.Event()

    def current(self) -> str:
        token = self._token
        if token is None or self._clock() >= token.expires_at - self.MIN_REMAINING:
            raise TokenError("no_token", "this interceptor holds no valid access token")
        return token.token

    @property
    def expires_at(self) -> float | None:
        return self._token.expires_at if self._token else None

    async def refresh(self) -> None:
        self._token = await self._client.fetch_token(clock=self._clock)
        self.refreshed.set()
        log.info("access token refreshed, valid for %.0f s", self._token.expires_at - self._clock())

    def invalidate(self) -> None:
        """Our token was revoked (or our manager disabled): drop it and ask again now."""
        self._token = None
        self._wake.set()

    async def run(self) -> None:
        """Refresh before expiry forever; back off (1 s doubling to 30 s) on failure;
        wake early when :meth:`invalidate` is called."""
        backoff = 1.0
        while True:
            try:
                await self.refresh()
                backoff = 1.0
                lifetime = self._token.expires_at - self._clock()
                delay = max(1.0, min(lifetime - self._margin, lifetime / 2))
            except TokenError as exc:
                remaining = (self._token.expires_at - self._clock()) if self._token else 0
                log.warning("cannot refresh access token (%s); cached token valid %.0f s more", exc.detail, max(0, remaining))
                delay = backoff
                backoff = min(backoff * 2, 8.0)
            self._wake.clear()
            try:
                await asyncio.wait_for(self._wake.wait(), delay)
            except asyncio.TimeoutError:
                pass


@dataclass(eq=False)
class _Watch:
    access: AccessToken
    on_revoked: Callable[[str], None]


class PeerVerifier:
    """Verifies peer tokens; cuts off open streams on revocation."""

    JWKS_REFRESH_INTERVAL = 60.0
    UNKNOWN_KID_COOLDOWN = 5.0

    def __init__(
        self,
        client: AuthzClient,
        *,
        issuer: str,
        audience: str,
        poll_interval: float,
        clock: Clock = time.time,
    ) -> None:
        self._client = client
        self.issuer = issuer
        self.audience = audience
        self._poll = poll_interval
        self._clock = clock
        self.keys = KeySet({})
        self.revocations = Revocations()
        self._watches: set[_Watch] = set()
        self._last_jwks = 0.0
        self.ready = asyncio.Event()
        self.last_feed_at: float | None = None
        #: Called with each new feed (after open streams were cut).
        self.listeners: list[Callable[[Revocations], None]] = []

    def verify(self, token: str, peer_cert_der: bytes | None) -> AccessToken:
        """Verify with the keys and revocations known now; TokenError on any failure."""
        return verify_access_token(
            token,
            keys=self.keys,
            issuer=self.issuer,
            audience=self.audience,
            peer_cert_der=peer_cert_der,
            now=self._clock(),
            revocations=self.revocations,
        )

    async def verify_fresh(self, token: str, peer_cert_der: bytes | None) -> AccessToken:
        """Like :meth:`verify`, but an unknown ``kid`` triggers one JWKS refresh first
        (key rotation), at most once per cooldown so garbage cannot hammer the server."""
        try:
            return self.verify(token, peer_cert_der)
        except TokenError as exc:
            if exc.reason != "unknown_kid" or self._clock() - self._last_jwks < self.UNKNOWN_KID_COOLDOWN:
                raise
        await self._refresh_jwks()
        return self.verify(token, peer_cert_der)

    def watch(self, access: AccessToken, on_revoked: Callable[[str], None]) -> Callable[[], None]:
        """Register an open stream; returns the function to call when it closes."""
        entry = _Watch(access, on_revoked)
        self._watches.add(entry)
        return lambda: self._watches.discard(entry)

    @property
    def open_streams(self) -> int:
        return len(self._watches)

    async def _refresh_jwks(self) -> None:
        self._last_jwks = self._clock()
        try:
            self.keys = await self._client.fetch_jwks()
        except TokenError as exc:
            log.warning("cannot refresh JWKS (%s); keeping %d known keys", exc.detail, len(self.keys))

    def apply(self, revocations: Revocations) -> int:
        """Adopt a new feed and cut off every watched stream it revokes; returns how many."""
        self.revocations = revocations
        cut = 0
        for entry in list(self._watches):
            access = entry.access
            if access.jti in revocations.revoked_jtis:
                reason = "revoked"
            elif access.subject in revocations.disabled_subjects:
                reason = "subject_disabled"
            else:
                continue
            self._watches.discard(entry)
            cut += 1
            log.warning("cutting off stream of manager=%s jti=%s: %s", access.subject, access.jti, reason)
            try:
                entry.on_revoked(reason)
            except Exception:  # a broken stream must not stop the others from being cut
                log.exception("closing a revoked stream failed")
        for listener in self.listeners:
            listener(revocations)
        return cut

    async def run(self) -> None:
        """Poll the revocation feed every interval and the JWKS every minute, forever."""
        while True:
            if self._clock() - self._last_jwks >= self.JWKS_REFRESH_INTERVAL or not len(self.keys):
                await self._refresh_jwks()
            try:
                feed = await self._client.fetch_revocations()
                self.last_feed_at = self._clock()
                if feed is not None:
                    self.apply(feed)
                if len(self.keys):
                    self.ready.set()
            except TokenError as exc:
                log.warning("cannot poll the revocation feed (%s); keeping the last one", exc.detail)
            await asyncio.sleep(self._poll)


__all__ = ["AuthzClient", "AuthzUnavailable", "OwnToken", "PeerVerifier", "TokenKeeper"]
