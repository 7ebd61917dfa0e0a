"""The interceptor's side of the authorization server.

- :class:`AuthzClient` speaks HTTPS with mutual TLS to ``cryptoros-authz``: ``POST
  /token`` (OAuth 2 client credentials, RFC 6749 4.4, client authenticated by its
  certificate, RFC 8705), the JWKS, the revocation feed and ``POST /observations``.
- :class:`TokenKeeper` holds this interceptor's own access token: fetched at start,
  refreshed ``refresh_margin`` seconds before expiry, kept while the server is down
  and still valid, and refused (``TokenError("no_token")``) once it has expired:
  nothing new is allowed without one. A token issued for another manager than the
  configured one (the registry binds this certificate to it) is refused as a failed
  fetch would be, with none held after it (``TokenError("wrong_manager")``, which
  health and status show): the interceptor never runs on another manager's grants.

Peers' tokens are verified by :class:`interceptor.verifier.PeerVerifier`. Every wait is
bounded by ``request_timeout``; failures are logged and retried, never raised into the
event loop.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import errno
import json
import logging
import random
import socket
import ssl
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

import aiohttp
from cryptoros.errors import TokenError
from cryptoros.lru import remember
from cryptoros.tokens import (FEED_STREAM_HEADER, KeySet, Revocations, peer_audience)
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


class ReportRefused(TokenError):
    """The authorization server refused a report of observations as sent (HTTP 400, 413:
    a malformed row, too large): sending it again as it is cannot succeed."""

    def __init__(self, detail: str) -> None:
        super().__init__("report_refused", detail)


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
            error = body.get("error") if isinstance(body, dict) else None
            hint = (": the registry binds no enabled manager to this certificate (a renewed one needs "
                    "cryptoros-authz set-cert MANAGER --cert FILE; a disabled manager, enable-manager)"
                    if error == "invalid_client" else "")
            raise AuthzUnavailable(f"token refused: HTTP {status} {error or ''}".strip() + hint)
        token, lifetime = body.get("access_token"), body.get("expires_in")
        if not isinstance(token, str) or not isinstance(lifetime, int) or lifetime <= 0:
            raise AuthzUnavailable("token answer lacks access_token or expires_in")
        return OwnToken(token=token, expires_at=asked_at + lifetime)

    async def post_observations(self, rows: list[dict]) -> dict:
        """Report requests seen (:mod:`interceptor.learning`); the server's answer
        (``accepted``, ``refused``). :class:`ReportRefused` when the server refuses the
        report as sent, :class:`AuthzUnavailable` when it cannot take it now."""
        status, body, _headers = await self._json("POST", "/observations", json={"observations": rows})
        if status in (400, 413):
            raise ReportRefused(f"observations: HTTP {status}: {(body or {}).get('error_description', '')}")
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


def refresh_delay(lifetime: float, margin: float) -> float:
    """Seconds until a token valid ``lifetime`` more seconds is refreshed: half-way
    through its life, or ``margin`` seconds before it expires if that comes first (an
    outage of the authorization server then leaves the most of its life to retry in);
    a lifetime under the margin (30 s under the default 60 s) half-way, not every
    second; at least 1 s after it was fetched."""
    before_expiry = lifetime - margin
    return max(1.0, min(before_expiry, lifetime / 2) if before_expiry >= 1.0 else lifetime / 2)


class RetryLog:
    """Which failures of an operation retried until it works are logged (sans-IO: the
    caller passes the clock and logs the lines): the first at once, then at most one per
    ``interval`` seconds with the count, and one line when it works again. A robot whose
    certificate was revoked asks for a token every second or so, for as long as it runs."""

    def __init__(self, interval: float = 60.0) -> None:
        self.interval = interval
        self._since: float | None = None  # the first failure of this run of them
        self._tries = 0
        self._logged_at = 0.0

    def failed(self, now: float) -> str | None:
        """One more failure at ``now``: None (not logged this time), ``""`` (the first,
        logged as it is) or ``"still refused: N tries since HH:MM:SS"`` to log with it."""
        self._tries += 1
        if self._since is None:
            self._since = self._logged_at = now
            return ""
        if now - self._logged_at < self.interval:
            return None
        self._logged_at = now
        return f"still refused: {self._tries} tries since {self._started()}"

    def succeeded(self) -> str | None:
        """It worked: ``"after N failed tries since HH:MM:SS"`` once after failures, else None."""
        if self._since is None:
            return None
        line = f"after {self._tries} failed {'try' if self._tries == 1 else 'tries'} since {self._started()}"
        self._since, self._tries = None, 0
        return line

    def _started(self) -> str:
        return time.strftime("%H:%M:%S", time.localtime(self._since))


def _unverified_subject(token: str) -> str | None:
    """The ``sub`` claim of a token, read without verifying it: only ever to refuse a
    token (our own, just issued to us over mutual TLS), never to accept one."""
    try:
        payload = token.split(".")[1]
        claims = json.loads(base64.urlsafe_b64decode(payload + "=" * (-len(payload) % 4)))
    except (IndexError, ValueError):  # binascii.Error and UnicodeDecodeError are ValueErrors
        return None
    subject = claims.get("sub") if isinstance(claims, dict) else None
    return subject if isinstance(subject, str) else None


#: seconds a peer's stream waits for our own token while a refresh is under way (for_peer)
PEER_TOKEN_WAIT = 2.0


class TokenKeeper:
    """This interceptor's own access token, always fresh or refused, and the tokens it
    shows each peer: bound to that peer's certificate (audience) and narrowed to the
    grants the peer's manager shares names with (:meth:`for_peer`)."""

    #: A token this close to expiry is not handed out: the peer would see it expired.
    MIN_REMAINING = 2.0
    #: Peers whose narrowed tokens are kept (the least recently used one goes first).
    MAX_PEERS = 1024

    def __init__(self, client: AuthzClient, *, refresh_margin: float, clock: Clock = time.time,
                 manager: str | None = None) -> None:
        self._client = client
        #: the manager this interceptor is configured as: a token for any other is refused (None: not checked)
        self.manager = manager
        #: why the last token issued to us was refused (wrong_manager), until one is taken
        self._refusal: TokenError | None = None
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
        #: Whether a new token's signing key is known (the gateway: JWKS fetched again if
        #: not). While it is not, the token held is kept as long as it is valid and the
        #: refresh is tried again: after ``rotate-key`` a robot verified its own new token
        #: with the keys it had, refused itself and every stock tool for up to 60 s.
        self.key_known: Callable[[str], Awaitable[bool]] | None = None
        #: since when refreshes fail, and why (None: the last one worked): status says it
        #: while the token held still verifies (an expired server certificate, replicas down)
        self.failing: tuple[float, str] | None = None
        self._failures = RetryLog()
        #: when (our clock) :meth:`invalidate` dropped the token held, until the next
        #: refresh attempt ends (None: no successor awaited)
        self._dropped_at: float | None = None
        self._taken_at = float("-inf")  # when (our clock) the token held was taken

    def current(self) -> str:
        token = self._token
        if token is None or self._clock() >= token.expires_at - self.MIN_REMAINING:
            refusal = self._refusal
            if refusal is not None:
                raise TokenError(refusal.reason, refusal.detail)
            raise TokenError("no_token", "this interceptor holds no valid access token")
        return token.token

    def check(self, token: OwnToken) -> None:
        """Raise TokenError("wrong_manager") if ``token`` is not for our ``manager``: the
        registry binds our certificate to another manager (a policy imported with two
        certificates swapped), whose grants we must not use."""
        if self.manager is None:
            return
        subject = _unverified_subject(token.token)
        if subject != self.manager:
            bound = f"to manager {subject!r}" if subject is not None else "to no manager (a token without sub)"
            raise TokenError("wrong_manager", f"the registry binds this certificate {bound}, not {self.manager!r}")

    def _refuse(self, refusal: TokenError) -> None:
        """A token was issued for another manager: hold none (not the one before it either:
        the registry no longer binds our certificate to us), and say why."""
        self._token = None
        self._peer_tokens.clear()
        self._refusal = refusal
        log.error("access token refused, none held: %s (fix the certificate's manager in the registry, or "
                  "manager in this interceptor's configuration)", refusal.detail)

    def replacing(self, within: float) -> bool:
        """Whether the token held was dropped (revoked by the feed: a grant of ours
        changed) less than ``within`` seconds ago and its successor's first request is
        still under way. What was decided on the old token may stand that long instead
        of being torn down and set up again a moment later: a ROS 2 robot withdrew every
        offer and closed every inbound stream in the 40-100 ms of each refresh that one
        of its periodic checks fell into (a CI run). A refusal or a failed attempt ends
        it at once."""
        dropped = self._dropped_at
        return dropped is not None and self._clock() - dropped < within

    def taken_within(self, seconds: float) -> bool:
        """Whether the token held was taken (refreshed or installed) less than ``seconds``
        ago: a peer's token narrowed to the grants we held before may predate it."""
        return self._clock() - self._taken_at < seconds

    @property
    def expires_at(self) -> float | None:
        return self._token.expires_at if self._token else None

    def expired_within(self, grace: float) -> bool:
        """Whether the token held expired (as :meth:`current` counts it) less than
        ``grace`` seconds ago: it ran out with the authorization server out of reach,
        not refused (none is held then)."""
        token = self._token
        return token is not None and self._clock() < token.expires_at + grace

    async def for_peer(self, thumbprint: str) -> str:
        """The token to show the peer whose certificate has ``thumbprint``: fetched on
        first use, again with every refresh of our own token (:meth:`refresh`) and
        whenever the cached one is within the refresh margin of expiry; one fetch per
        peer in flight. While the authorization server cannot be reached the cached one is
        used until it expires, then TokenError (fail closed: never the full token).

        Our own token just dropped (the feed revoked it: a grant of ours changed) waits
        for the refresh asked for at once, at most :data:`PEER_TOKEN_WAIT` seconds: a
        peer's stream opened meanwhile was refused ``no_token`` after every grant change
        (ROS 2 audit). No own token, no peer token either."""
        try:
            self.current()
        except TokenError as exc:
            if exc.reason != "no_token":
                raise
            await self.ensure(PEER_TOKEN_WAIT)
            self.current()
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
        self.check(token)
        remember(self._peer_tokens, thumbprint, token, self.MAX_PEERS)
        return token

    async def refresh(self) -> None:
        token = await self._client.fetch_token(clock=self._clock)
        try:
            self.check(token)
        except TokenError as exc:
            self._refuse(exc)
            raise
        held = self._token
        if self.key_known is not None and held is not None and \
                self._clock() < held.expires_at - max(self.MIN_REMAINING, self.refresh_margin / 2) and \
                not await self.key_known(token.token):
            raise TokenError("unknown_kid", "the new token's signing key is not published yet: keeping the one held")
        self._token, self._refusal, self._taken_at = token, None, self._clock()
        # Grants may have changed: the peers' tokens are fetched anew (kept if that fails).
        for thumbprint in list(self._peer_tokens):
            try:
                await self._fetch_for_peer(thumbprint)
            except TokenError as exc:
                log.info("cannot refresh a peer's token (%s); keeping the cached one", exc.detail)
        if self._token is not token:  # revoked meanwhile (the feed, a grant changed again): run() asks again
            log.info("access token refreshed and revoked again while the peers' tokens were fetched: asking again")
            return
        self.refreshed.set()
        log.info("access token refreshed, valid for %.0f s", token.expires_at - self._clock())
        for listener in self.listeners:
            listener()

    def install(self, token: OwnToken) -> None:
        """Adopt a token fetched elsewhere (a reload's, bound to a renewed certificate):
        the peers' tokens, bound to the old one, are fetched anew on next use. A token
        for another manager raises TokenError (:meth:`check`) and changes nothing."""
        self.check(token)
        self._token, self._refusal, self._taken_at = token, None, self._clock()
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
        self._dropped_at = self._clock()
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
                self.failing = None
                again = self._failures.succeeded()
                if again is not None:
                    log.info("access token held again, %s", again)
                held = self._token
                delay = 0.0 if held is None else refresh_delay(held.expires_at - self._clock(), self.refresh_margin)
            except TokenError as exc:
                self.failing = (self.failing[0] if self.failing else self._clock(), exc.detail)
                remaining = (self._token.expires_at - self._clock()) if self._token else 0
                note = self._failures.failed(self._clock())
                if exc.reason != "wrong_manager" and note is not None:  # wrong_manager: an error where it is found
                    log.warning("cannot refresh access token (%s); cached token valid %.0f s more%s", exc.detail,
                                max(0, remaining), f"; {note}" if note else "")
                delay = backoff
                backoff = min(backoff * 2, 8.0)
            except Exception:  # a bug here must not end the keeper: the robot would hold no token, silently
                log.exception("refreshing the access token failed")
                delay = backoff
                backoff = min(backoff * 2, 8.0)
            self._dropped_at = None  # succeeded or failed: no successor is on its way any more
            self._attempted.set()
            self._attempted = asyncio.Event()
            try:
                await asyncio.wait_for(self._wake.wait(), delay)
            except asyncio.TimeoutError:
                pass



__all__ = ["AuthzClient", "AuthzRefused", "AuthzUnavailable", "OwnToken", "ReportRefused", "RetryLog", "TokenKeeper",
           "refresh_delay"]
