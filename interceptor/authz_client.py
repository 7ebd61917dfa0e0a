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

Every wait is bounded by ``request_timeout``; failures are logged and retried, never
raised into the event loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import json
import logging
import random
import socket
import ssl
import time
from collections.abc import Callable
import dataclasses
from dataclasses import dataclass

import aiohttp
from cryptoros import pemfiles
from cryptoros.errors import PKIError, PolicyDenied, TokenError
from cryptoros.learning import LearningState
from cryptoros.lru import remember
from cryptoros.tokens import (FEED_STREAM_HEADER, AccessToken, Grants, KeySet, Revocations, VerifiedTokenCache,
                              peer_audience)
from interceptor.config import AuthzSettings

log = logging.getLogger("cryptoros.interceptor.authz")

Clock = Callable[[], float]


#: the most a feed answer may weigh (a feed of many revoked tokens is still far under)
MAX_FEED_BYTES = 16 << 20


async def _drop(session: aiohttp.ClientSession | None) -> None:
    """Close a session now, requests under way on it included (they fail at once and are
    asked again on the new one): its TLS connections are aborted, not shut down
    gracefully, which would wait on a replica streaming a held answer."""
    if session is None:
        return
    if session.connector is not None:
        await session.connector.close(abort_ssl=True)
    await session.close()


async def _streamed_feed(resp: aiohttp.ClientResponse, alive: Callable[[], None], path: str,
                         replaced: asyncio.Event) -> tuple[int, dict | None, dict[str, str]]:
    """Read a streamed long-poll: spaces (heartbeats: ``alive``), then one JSON object,
    the feed with its ``etag`` (200) or ``{"unchanged": true, "etag": ...}`` (304). When
    the session is ``replaced`` (a reload, another replica) the read stops at once, as
    a lost connection: closing a TLS connection does not wake a read waiting on it."""
    data = bytearray()
    stop = asyncio.ensure_future(replaced.wait())
    read: asyncio.Future | None = None
    try:
        while True:
            read = asyncio.ensure_future(resp.content.readany())
            await asyncio.wait((read, stop), return_when=asyncio.FIRST_COMPLETED)
            if not read.done():
                resp.close()
                raise aiohttp.ServerDisconnectedError("the session was replaced")
            chunk = read.result()
            if not chunk:
                break
            if not data and not chunk.strip():
                alive()
                continue
            data += chunk
            if len(data) > MAX_FEED_BYTES:
                raise AuthzUnavailable(f"{path}: a streamed answer over {MAX_FEED_BYTES} bytes")
    finally:
        stop.cancel()
        if read is not None and not read.done():
            read.cancel()
    try:
        body = json.loads(data)
    except ValueError as exc:
        raise AuthzUnavailable(f"{path}: a streamed answer that is not JSON: {exc}") from None
    if not isinstance(body, dict) or not isinstance(body.get("etag"), str):
        raise AuthzUnavailable(f"{path}: a streamed answer without its etag")
    etag = body.pop("etag")
    if body.get("unchanged") is True:
        return 304, None, {"ETag": etag}
    return 200, body, {"ETag": etag}


#: times one request is asked again because this client replaced its session under it
MAX_SWAP_RETRIES = 3


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
        #: set when the session is replaced: a streamed answer being read on the old one stops
        self._replaced = asyncio.Event()
        self._feed_etag: str | None = None
        self._current = 0  # the replica in use (settings.urls)
        self._spread = random.randrange(1 << 16)  # which address of a name this client tries first

    def _http(self) -> aiohttp.ClientSession:
        if self._session is None or self._session.closed:
            self._session = aiohttp.ClientSession(
                connector=aiohttp.TCPConnector(ssl=self._ssl, limit=4, resolver=_SpreadResolver(self._spread),
                                               use_dns_cache=False, socket_factory=_keepalive_socket),
                timeout=aiohttp.ClientTimeout(total=self.settings.request_timeout),
            )
        return self._session

    async def close(self) -> None:
        if self._session is not None:
            await self._session.close()

    async def use_ssl_context(self, ssl_context: ssl.SSLContext) -> None:
        """Present a new client certificate from the next request on (reload): the
        pooled connections, made with the old one, are closed."""
        old, self._session, self._ssl = self._session, None, ssl_context
        self._replaced.set()
        self._replaced = asyncio.Event()
        await _drop(old)

    async def _json(self, method: str, path: str, *, alive: Callable[[], None] | None = None,
                    **kw) -> tuple[int, dict | None, aiohttp.typedefs.LooseHeaders]:
        """One request to the replica in use; one that does not answer (connection
        refused, reset, TLS failure, timeout, a streamed answer cut or gone quiet) or
        answers 5xx (it cannot serve now) hands the request to the next, which is then
        used from now on. Any other HTTP answer is an answer: no failover on a 4xx. A
        streamed long-poll of the feed (:data:`FEED_STREAM_HEADER`) calls ``alive`` on
        each heartbeat and comes back as 304 (unchanged) or 200 with the feed."""
        bases = self.settings.urls or (self.settings.url,)
        failures = []
        tries = [(self._current + k) % len(bases) for k in range(len(bases))]
        retried = set()
        fresh = False
        swaps = 0
        while tries:
            if fresh:
                await self._next_address()
                fresh = False
            index = tries.pop(0)
            url = bases[index] + path
            replaced = self._replaced  # this request's session's: set when that session is replaced
            try:
                async with self._http().request(method, url, **kw) as resp:
                    if resp.status >= 500 and (tries or index not in retried):
                        # this replica cannot serve now (its database?): the next url; with
                        # none left, once more on new connections to the next address of the
                        # url's name (one name, an address per replica)
                        failures.append(f"{method} {url}: HTTP {resp.status}")
                        if not tries:
                            retried.add(index)
                            tries.insert(0, index)
                            fresh = True
                        continue
                    if resp.status == 304:
                        answer = resp.status, None, resp.headers
                    elif resp.status == 200 and resp.headers.get(FEED_STREAM_HEADER):
                        answer = await _streamed_feed(resp, alive or (lambda: None), path, replaced)
                    else:
                        body = await resp.json(content_type=None)
                        if not isinstance(body, dict):
                            raise AuthzUnavailable(f"{path}: answer is not a JSON object")
                        answer = resp.status, body, resp.headers
            except (aiohttp.ClientConnectionError, aiohttp.ClientPayloadError, asyncio.TimeoutError, ssl.SSLError,
                    OSError) as exc:
                if replaced.is_set() and swaps < MAX_SWAP_RETRIES:
                    # this client closed the session under the request (a reload's new
                    # certificate, another address): not the replica's failure, the same
                    # url again on the new session ("Connector is closed" was logged as one)
                    swaps += 1
                    tries.insert(0, index)
                    continue
                failures.append(f"{method} {url}: {type(exc).__name__}: {exc}{_hint(exc)}")
                if _lost_connection(exc) and index not in retried:
                    # a kept connection died under the request (its replica went away): once
                    # more on a new one, which tries every address the url's name has
                    retried.add(index)
                    tries.insert(0, index)
                elif isinstance(exc, (asyncio.TimeoutError, aiohttp.ClientPayloadError)) and not tries \
                        and index not in retried:
                    # the last url's replica went quiet (hung) or cut its answer: once more on
                    # new connections, starting with the next address of its name
                    retried.add(index)
                    tries.insert(0, index)
                    fresh = True
                continue
            except (aiohttp.ClientError, ValueError) as exc:
                raise AuthzUnavailable(f"{method} {url}: {type(exc).__name__}: {exc}{_hint(exc)}") from exc
            if index != self._current:
                log.warning("authorization server %s does not answer; using %s", bases[self._current], bases[index])
                self._current = index
            return answer
        raise AuthzUnavailable("; ".join(failures) if len(failures) == 1 else
                               f"no authorization server answers ({len(failures)} tried): " + "; ".join(failures))

    async def _next_address(self) -> None:
        """New connections from now on, starting with the next address of each url's
        name: the kept ones (to a replica that answered 5xx) are closed, requests held
        on them included (their callers ask again)."""
        self._spread += 1
        old, self._session = self._session, None
        self._replaced.set()
        self._replaced = asyncio.Event()
        await _drop(old)

    async def fetch_token(self, *, clock: Clock = time.time, resource: str | None = None) -> OwnToken:
        """Our token; with ``resource`` (RFC 8707) one for that peer only, narrowed to
        what it needs to judge our streams."""
        asked_at = clock()
        form = {"grant_type": "client_credentials", **({"resource": resource} if resource else {})}
        status, body, _ = await self._json("POST", "/token", data=form)
        if status != 200 or body is None:
            raise AuthzUnavailable(f"token refused: HTTP {status} {body.get('error') if body else ''}".strip())
        token, lifetime = body.get("access_token"), body.get("expires_in")
        if not isinstance(token, str) or not isinstance(lifetime, int) or lifetime <= 0:
            raise AuthzUnavailable("token answer lacks access_token or expires_in")
        return OwnToken(token=token, expires_at=asked_at + lifetime)

    async def post_observations(self, rows: list[dict]) -> dict:
        """Report requests seen (:mod:`interceptor.learning`); the server's answer
        (``accepted``, ``refused``)."""
        status, body, _headers = await self._json("POST", "/observations", json={"observations": rows})
        if status != 200 or body is None:
            raise AuthzUnavailable(f"observations: HTTP {status}: {(body or {}).get('error_description', '')}")
        return body

    async def fetch_jwks(self) -> KeySet:
        status, body, _ = await self._json("GET", "/.well-known/jwks.json")
        if status != 200 or body is None:
            raise AuthzUnavailable(f"JWKS: HTTP {status}")
        keys = KeySet.from_jwks(body)
        if not len(keys):
            raise AuthzUnavailable("JWKS holds no RS256 key")
        return keys

    async def fetch_revocations(self, *, wait: float = 0.0, heartbeat: float = 0.0,
                                alive: Callable[[], None] | None = None) -> Revocations | None:
        """The feed, or None when it has not changed since the last poll. With ``wait``
        (and a feed already known) a long-poll: the server answers when the feed
        changes, or with 304 after ``wait`` seconds. With ``heartbeat`` too, the server
        shows every ``heartbeat`` seconds that it is alive and the feed unchanged
        (``alive`` is called): a replica quiet for two heartbeats is left for the next."""
        headers = {"If-None-Match": self._feed_etag} if self._feed_etag else {}
        extra = {}
        timeout = self.settings.request_timeout
        if wait and self._feed_etag and heartbeat:
            extra = {"params": {"wait": f"{wait:g}", "heartbeat": f"{heartbeat:g}"}, "alive": alive,
                     "timeout": aiohttp.ClientTimeout(total=wait + heartbeat + timeout,
                                                      sock_read=2 * heartbeat + timeout)}
        elif wait and self._feed_etag:
            extra = {"params": {"wait": f"{wait:g}"}, "timeout": aiohttp.ClientTimeout(total=wait + timeout)}
        status, body, resp_headers = await self._json("GET", "/revocations", headers=headers, **extra)
        if status == 304:
            return None
        if status == 401:
            raise AuthzRefused("revocation feed: HTTP 401 (our certificate is refused: revoked by the CA?)")
        if status != 200 or body is None:
            raise AuthzUnavailable(f"revocation feed: HTTP {status}")
        jtis, managers = body.get("revoked_jtis"), body.get("disabled_managers")
        if not (isinstance(jtis, list) and isinstance(managers, list)):
            raise AuthzUnavailable("revocation feed lacks revoked_jtis or disabled_managers")
        serials = body.get("revoked_serials", [])
        try:
            revoked_serials = frozenset(int(str(n), 16) for n in serials)
        except (TypeError, ValueError):
            raise AuthzUnavailable("revocation feed: revoked_serials are not hex serials") from None
        serial = body.get("serial")
        if serial is not None and (not isinstance(serial, int) or isinstance(serial, bool)):
            raise AuthzUnavailable("revocation feed: serial is not an integer")
        learning = body.get("learning", {})
        if not (isinstance(learning, dict) and all(isinstance(m, str) and isinstance(u, (int, float))
                                                   and not isinstance(u, bool) for m, u in learning.items())):
            raise AuthzUnavailable("revocation feed: learning is not a map of manager to end time")
        self._feed_etag = resp_headers.get("ETag")
        return Revocations(
            revoked_jtis=frozenset(str(j) for j in jtis), disabled_subjects=frozenset(str(m) for m in managers),
            revoked_serials=revoked_serials, serial=serial,
            learning=tuple(sorted((m, float(u)) for m, u in learning.items())),
        )


def _lost_connection(exc: BaseException) -> bool:
    """The request failed on a connection that was open (not in connecting to it)."""
    return isinstance(exc, (aiohttp.ServerDisconnectedError, aiohttp.ClientOSError)) and \
        not isinstance(exc, aiohttp.ClientConnectorError)


class _SpreadResolver(aiohttp.ThreadedResolver):
    """Every address the system resolver (getaddrinfo: /etc/hosts, DNS) gives for a name;
    the connector tries them in turn until one connects, so one name with an address
    per replica fails over on a new connection. The list is rotated by this client's
    own offset: a fleet given one name spreads over its addresses, as round-robin DNS
    would, even where the resolver returns them in one order."""

    def __init__(self, offset: int) -> None:
        super().__init__()
        self._offset = offset

    async def resolve(self, host: str, port: int = 0, family: socket.AddressFamily = socket.AF_INET):
        hosts = await super().resolve(host, port, family)
        if len(hosts) > 1:
            k = self._offset % len(hosts)
            hosts = hosts[k:] + hosts[:k]
        return hosts


def _keepalive_socket(addr_info) -> socket.socket:
    """A TCP socket with keepalive probes after 10 s idle, every 5 s, 3 unanswered:
    a replica whose host is gone is noticed about 25 s into a held long-poll, not at
    its end."""
    family, type_, proto, _name, _addr = addr_info
    sock = socket.socket(family=family, type=type_, proto=proto)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
    for option, value in (("TCP_KEEPIDLE", 10), ("TCP_KEEPINTVL", 5), ("TCP_KEEPCNT", 3)):
        if hasattr(socket, option):
            sock.setsockopt(socket.IPPROTO_TCP, getattr(socket, option), value)
    return sock


def _hint(exc: BaseException) -> str:
    """What a bare TLS or connection failure most likely means, for the log line."""
    if isinstance(exc, aiohttp.ClientConnectorCertificateError):
        return " (the authorization server's certificate does not verify against [tls] ca, or its name/IP differs)"
    if "alert" in str(exc).lower():  # TLS refused us (TLS 1.3: after the client's side of the handshake)
        return (" (the authorization server refused the TLS connection: is this certificate issued by the CA it "
                "trusts, and not revoked?)")
    reset = isinstance(exc, ConnectionResetError) or getattr(exc, "errno", None) == errno.ECONNRESET
    if reset or isinstance(exc, aiohttp.ServerDisconnectedError):
        return (" (the authorization server closed the connection: it went away or restarted, or, on a new "
                "connection, it refused this certificate: issued by the CA it trusts, not revoked?)")
    if isinstance(exc, (aiohttp.ClientConnectorError, ConnectionRefusedError)):
        return " (nothing answers there: is cryptoros-authz running, and [authz] url right?)"
    return ""


class AuthzRefused(AuthzUnavailable):
    """The authorization server answered, and refused our certificate (401)."""


class TokenKeeper:
    """This interceptor's own access token, always fresh or refused, and the tokens it
    shows each peer: bound to that peer's certificate (audience) and narrowed to the
    grants the peer's manager shares names with (:meth:`for_peer`)."""

    #: A token this close to expiry is not handed out: the peer would see it expired.
    MIN_REMAINING = 2.0
    #: Peers whose narrowed tokens are kept (the least recently used one goes first).
    MAX_PEERS = 1024

    def __init__(self, client: AuthzClient, *, refresh_margin: float, clock: Clock = time.time) -> None:
        self._client = client
        #: seconds before expiry a token is refreshed (a reload may change it: from the next refresh on)
        self.refresh_margin = refresh_margin
        self._clock = clock
        self._token: OwnToken | None = None
        self._peer_tokens: dict[str, OwnToken] = {}  # by the peer certificate's thumbprint
        self._peer_fetches: dict[str, asyncio.Future] = {}
        self.refreshed = asyncio.Event()
        self._wake = asyncio.Event()
        self._attempted = asyncio.Event()  # set (and replaced) after every refresh attempt
        self._last_forced = float("-inf")
        #: Called after each new token (the interceptor shows it to its peers).
        self.listeners: list[Callable[[], None]] = []

    def current(self) -> str:
        token = self._token
        if token is None or self._clock() >= token.expires_at - self.MIN_REMAINING:
            raise TokenError("no_token", "this interceptor holds no valid access token")
        return token.token

    @property
    def expires_at(self) -> float | None:
        return self._token.expires_at if self._token else None

    async def for_peer(self, thumbprint: str) -> str:
        """The token to show the peer whose certificate has ``thumbprint``: fetched on
        first use, again with every refresh of our own token (:meth:`refresh`) and
        whenever the cached one is within the refresh margin of expiry; one fetch per
        peer in flight. While the authorization server cannot be reached the cached one is
        used until it expires, then TokenError (fail closed: never the full token)."""
        self.current()  # no own token, no peer token either
        cached = self._peer_tokens.get(thumbprint)
        now = self._clock()
        if cached is not None and now < cached.expires_at - max(self.MIN_REMAINING, self.refresh_margin):
            self._peer_tokens[thumbprint] = self._peer_tokens.pop(thumbprint)  # most recently used
            return cached.token
        fetch = self._peer_fetches.get(thumbprint)
        if fetch is None:
            fetch = self._peer_fetches[thumbprint] = asyncio.ensure_future(self._fetch_for_peer(thumbprint))
            fetch.add_done_callback(lambda _f: self._peer_fetches.pop(thumbprint, None))
        try:
            return (await asyncio.shield(fetch)).token
        except TokenError:
            if cached is not None and self._clock() < cached.expires_at - self.MIN_REMAINING:
                return cached.token
            raise

    async def _fetch_for_peer(self, thumbprint: str) -> OwnToken:
        token = await self._client.fetch_token(clock=self._clock, resource=peer_audience(thumbprint))
        remember(self._peer_tokens, thumbprint, token, self.MAX_PEERS)
        return token

    async def refresh(self) -> None:
        self._token = await self._client.fetch_token(clock=self._clock)
        # Grants may have changed: the peers' tokens are fetched anew (kept if that fails).
        for thumbprint in list(self._peer_tokens):
            try:
                await self._fetch_for_peer(thumbprint)
            except TokenError as exc:
                log.info("cannot refresh a peer's token (%s); keeping the cached one", exc.detail)
        self.refreshed.set()
        log.info("access token refreshed, valid for %.0f s", self._token.expires_at - self._clock())
        for listener in self.listeners:
            listener()

    def install(self, token: OwnToken) -> None:
        """Adopt a token fetched elsewhere (a reload's, bound to a renewed certificate):
        the peers' tokens, bound to the old one, are fetched anew on next use."""
        self._token = token
        self._peer_tokens.clear()
        self.refreshed.set()
        log.info("access token installed, valid for %.0f s", token.expires_at - self._clock())
        for listener in self.listeners:
            listener()

    def wake(self) -> None:
        """Refresh now (the registry changed: our grants may have)."""
        self._wake.set()

    async def ensure(self, timeout: float) -> None:
        """Hold a valid token if one can be had within ``timeout``: a local call made
        while none is held (our manager was re-enabled a moment ago, the feed just said
        so) waits for the next refresh attempt instead of being refused at once. The
        attempt is forced at most once a second (a flood of local calls must not become
        a flood of token requests); a refused attempt (manager still disabled) ends the
        wait at once, and the caller refuses with the reason."""
        try:
            self.current()
            return
        except TokenError:
            pass
        attempted = self._attempted
        now = time.monotonic()
        if now - self._last_forced >= 1.0:
            self._last_forced = now
            self._wake.set()
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(attempted.wait(), timeout)

    def invalidate(self) -> None:
        """Our token was revoked (or our manager disabled): drop it and ask again now."""
        self._token = None
        self._peer_tokens.clear()
        self._wake.set()

    async def run(self) -> None:
        """Refresh before expiry forever; back off (1 s doubling to 8 s) on failure;
        wake early when :meth:`wake` or :meth:`invalidate` is called (a wake that comes
        while a refresh is under way is not lost: that refresh may predate the change)."""
        backoff = 1.0
        while True:
            self._wake.clear()
            try:
                await self.refresh()
                backoff = 1.0
                lifetime = self._token.expires_at - self._clock()
                delay = max(1.0, min(lifetime - self.refresh_margin, lifetime / 2))
            except TokenError as exc:
                remaining = (self._token.expires_at - self._clock()) if self._token else 0
                log.warning("cannot refresh access token (%s); cached token valid %.0f s more", exc.detail, max(0, remaining))
                delay = backoff
                backoff = min(backoff * 2, 8.0)
            self._attempted.set()
            self._attempted = asyncio.Event()
            try:
                await asyncio.wait_for(self._wake.wait(), delay)
            except asyncio.TimeoutError:
                pass


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
    UNKNOWN_KID_COOLDOWN = 5.0

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
        log.warning("cutting off stream of manager=%s jti=%s: %s", entry.access.subject, entry.access.jti, reason)
        for listener in self.cut_listeners:
            listener(reason.split(":", 1)[0])
        try:
            entry.on_revoked(reason)
        except Exception:  # a broken stream must not stop the others from being cut
            log.exception("closing a stream failed")

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


__all__ = ["AuthzClient", "AuthzRefused", "AuthzUnavailable", "OwnToken", "PeerVerifier", "StreamWatch", "TokenKeeper"]
