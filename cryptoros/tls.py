"""The one TLS context factory every cryptoros program uses.

Policy, in the spirit of the CryptoROS paper's cipher string
``TLSv1.2:!LOW:!EXPORT:!MD5:!aNULL:!ADH:!AECDH:!DES:!eNULL:!RC2:!RC4`` but tightened to
forward-secret AEAD suites only:

- minimum TLS 1.2 (optionally pinned to exactly 1.2 with ``pin_tls12``);
- TLS 1.2 suites: ECDHE key exchange with AES-GCM or ChaCha20-Poly1305, nothing else
  (no static RSA key exchange, no CBC, no SHA-1 MACs, no DHE);
- TLS 1.3 suites are OpenSSL's defaults, which are all AEAD and forward secret
  (Python's ``ssl`` cannot narrow them further);
- mutual authentication: a server context *requires* a client certificate chaining to
  the configured CA; a client context verifies the server the same way;
- when a CRL file is configured, the peer's leaf certificate is checked against it,
  and a CA with no CRL then fails verification (fail closed);
- TLS 1.3 session resumption is opt-in (``server_context(tickets=1)``, a
  :class:`ResumingContext` client and a :class:`SessionCache`). A resumed handshake
  does not verify the peer's chain, CRL or validity period again, so whoever resumes
  must run :class:`PeerCertificateCheck` on every stream, resumed or not.

``python -m cryptoros.tls`` prints the suites that result on this machine.
"""

from __future__ import annotations

import contextlib
import contextvars
import hashlib
import ssl
import stat
import time
from collections.abc import Callable, Collection, Iterator
from dataclasses import dataclass
from pathlib import Path

from cryptography.hazmat.primitives import serialization

from cryptoros.errors import ConfigError, CryptorosError, TokenError
from cryptoros import pemfiles
from cryptoros.files import PEM_LIMIT
from cryptoros.lru import remember

#: The paper's cipher configuration string (seed 003, Eq. 5), kept for reference.
PAPER_CIPHER_STRING = "TLSv1.2:!LOW:!EXPORT:!MD5:!aNULL:!ADH:!AECDH:!DES:!eNULL:!RC2:!RC4"

#: What cryptoros uses for TLS 1.2: the paper's exclusions, tightened to ECDHE + AEAD.
STRICT_TLS12_CIPHERS = (
    "ECDHE+AESGCM:ECDHE+CHACHA20:"
    "!LOW:!EXPORT:!MD5:!aNULL:!ADH:!AECDH:!DES:!eNULL:!RC2:!RC4:!3DES:!SHA1:!PSK:!SRP:!DSS"
)


@dataclass(frozen=True, kw_only=True)
class TLSConfig:
    """Where a program's TLS material lives. Validated on construction."""

    ca_file: Path
    cert_file: Path
    key_file: Path
    key_passphrase: bytes | None = None
    crl_file: Path | None = None
    pin_tls12: bool = False
    #: the file ``key_passphrase`` was read from (None: none, or the environment), for
    #: :meth:`secret_files`
    key_passphrase_file: Path | None = None

    def __post_init__(self) -> None:
        for label in ("ca_file", "cert_file", "key_file", "crl_file"):
            value = getattr(self, label)
            if value is None:
                continue
            path = Path(value)
            object.__setattr__(self, label, path)
            what = f"TLS {label.replace('_', ' ')}"
            try:
                st = path.stat()
            except OSError:
                raise ConfigError(f"{what} not found: {path}") from None
            # OpenSSL reads these itself: what read_bounded refuses is refused here.
            if not stat.S_ISREG(st.st_mode):
                raise ConfigError(f"{what} {path} is not a regular file (a device, FIFO or directory)")
            if st.st_size > PEM_LIMIT:
                raise ConfigError(f"{what} {path} is larger than {PEM_LIMIT >> 20} MiB: not a certificate, key or CRL")

    def secret_files(self) -> list[tuple[str, Path | None]]:
        """(what it holds, path or None) of the files named here that hold a secret, for
        :func:`cryptoros.files.open_to_others`."""
        return [("the TLS key", self.key_file), ("the TLS key's passphrase file", self.key_passphrase_file)]


def _base_context(protocol: int, cfg: TLSConfig, cls: type[ssl.SSLContext] = ssl.SSLContext) -> ssl.SSLContext:
    ctx = cls(protocol)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    if cfg.pin_tls12:
        ctx.maximum_version = ssl.TLSVersion.TLSv1_2
    ctx.set_ciphers(STRICT_TLS12_CIPHERS)
    ctx.options |= ssl.OP_NO_COMPRESSION | ssl.OP_NO_RENEGOTIATION | ssl.OP_CIPHER_SERVER_PREFERENCE
    ctx.verify_mode = ssl.CERT_REQUIRED
    try:
        ctx.load_verify_locations(cafile=str(cfg.ca_file))
        # The CRL is not OpenSSL's to check (no VERIFY_CRL_CHECK_LEAF): OpenSSL refuses
        # every peer once the CRL's next-update time passes, and a fleet whose CRL was not
        # re-signed within its 7 days stopped whole. Revocation is checked on every
        # handshake by the application instead (PeerCertificateCheck, the authorization
        # server's CRLWatcher): the CRL's serials, out of date or not (a revocation never
        # lapses), and the authorization server's live revocation feed.
        ctx.load_cert_chain(str(cfg.cert_file), str(cfg.key_file),
                            password=cfg.key_passphrase or (lambda: _no_password(cfg.key_file)))
    except ssl.SSLError as exc:
        _explain_material(cfg)
        raise ConfigError(f"cannot load TLS material ({cfg.cert_file}, {cfg.key_file}): {exc.reason or exc}") from exc
    return ctx


def _explain_material(cfg: TLSConfig) -> None:
    """OpenSSL says only ``PEM lib``, ``NO_CERTIFICATE_OR_CRL_FOUND`` or
    ``KEY_VALUES_MISMATCH``: read the files ourselves to say which one and why
    (:mod:`cryptoros.pemfiles` names the file; an operator audit could not tell which of
    three files was empty, or that the CA's certificate had been given as the robot's)."""
    try:
        pemfiles.load_certificates(cfg.ca_file)
    except CryptorosError as exc:
        raise ConfigError(f"TLS CA: {exc}") from None
    try:
        cert = pemfiles.load_certificate(cfg.cert_file)
    except CryptorosError as exc:
        raise ConfigError(f"TLS certificate: {exc}") from None
    try:
        key = pemfiles.load_private_key(cfg.key_file, cfg.key_passphrase)
    except pemfiles.WrongPassphrase:
        raise ConfigError(f"TLS key {cfg.key_file}: the passphrase given does not open it (a wrong passphrase, "
                          "or the passphrase of another key?)") from None
    except CryptorosError as exc:
        raise ConfigError(f"TLS key: {exc}") from None
    spki = (serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo)
    if key.public_key().public_bytes(*spki) != cert.public_key().public_bytes(*spki):
        raise ConfigError(f"TLS key {cfg.key_file} does not belong to the certificate {cfg.cert_file} (the CA's "
                          "certificate given as this host's, or another host's key?)")


def _no_password(key_file: Path) -> bytes:
    # Called by OpenSSL only if the key file is encrypted and no passphrase was given.
    raise ConfigError(f"TLS key {key_file} is encrypted and no passphrase was given")


def server_context(cfg: TLSConfig, *, tickets: int = 0) -> ssl.SSLContext:
    """A server context that requires and verifies a client certificate.

    By default it sends no TLS 1.3 session tickets: most clients (aiohttp, asyncio's
    ``open_connection``) cannot use them, and each carries the client certificate
    (about 1.7 KB per connection, measured). ``tickets=1`` is for peers that resume
    (interceptors): the ticket is encrypted with a key this context drew at random, so
    a new context (a reload) makes every earlier ticket worthless. OpenSSL accepts a
    ticket for 7,200 s; a shorter lifetime is the caller's to enforce on every resumed
    stream (:class:`FullHandshakes`)."""
    ctx = _base_context(ssl.PROTOCOL_TLS_SERVER, cfg)
    ctx.num_tickets = tickets
    return ctx


def client_context(cfg: TLSConfig, *, check_hostname: bool = True, resumable: bool = False) -> ssl.SSLContext:
    """A client context that presents our certificate and verifies the server's.

    ``check_hostname=False`` is for peers addressed by an identity other than their
    host name (interceptors check the peer's identity URI themselves); the chain is
    verified against the CA either way. ``resumable=True`` gives a
    :class:`ResumingContext` (offer a session with :func:`offering`).
    """
    ctx = _base_context(ssl.PROTOCOL_TLS_CLIENT, cfg, ResumingContext if resumable else ssl.SSLContext)
    ctx.check_hostname = check_hostname
    return ctx


# ---------------------------------------------------------------- session resumption

#: (context, session) the next connect of this task offers, see :func:`offering`
_OFFERED: contextvars.ContextVar[tuple[ssl.SSLContext, ssl.SSLSession] | None] = contextvars.ContextVar(
    "cryptoros_tls_session", default=None)


class ResumingContext(ssl.SSLContext):
    """A client context that offers the session set by :func:`offering` around a connect.

    asyncio's ``open_connection``/``create_connection`` take no ``session=``, but both
    asyncio's and uvloop's SSL transport build their ``SSLObject`` with
    ``context.wrap_bio(...)`` inside the connecting task (its context variables
    visible), so the session travels in a context variable to this ``wrap_bio``. A
    session is offered only to the context it was kept for (OpenSSL refuses others)."""

    def wrap_bio(self, incoming, outgoing, server_side=False, server_hostname=None, session=None):
        offered = _OFFERED.get()
        if session is None and not server_side and offered is not None and offered[0] is self:
            session = offered[1]
        return super().wrap_bio(incoming, outgoing, server_side=server_side, server_hostname=server_hostname,
                                session=session)


@contextlib.contextmanager
def offering(ctx: ssl.SSLContext, offer: Offer | ssl.SSLSession | None) -> Iterator[None]:
    """Connects this task makes with ``ctx`` inside the block offer ``offer``'s session."""
    session = offer.session if isinstance(offer, Offer) else offer
    token = _OFFERED.set(None if session is None else (ctx, session))
    try:
        yield
    finally:
        _OFFERED.reset(token)


#: the most seconds OpenSSL accepts a ticket (its default session timeout for TLS)
MAX_SESSION_LIFETIME = 7200.0
#: what the server allows past ``lifetime`` (the client's chain starts before the
#: server notes the full handshake; both measure on their own monotonic clocks)
LIFETIME_SLACK = 5.0


@dataclass(frozen=True, slots=True)
class Offer:
    """A session kept for a peer endpoint and when the full handshake it descends from
    was made (monotonic seconds)."""

    session: ssl.SSLSession
    origin: float


class SessionCache:
    """Client side: one TLS session per peer endpoint, for one client context; bounded
    in entries and in age. A session that resumes is offered again (its ticket is kept
    until it stops resuming or ages out); one from a full handshake replaces it. The age
    counts from the full handshake a session descends from (a ticket from a resumed
    handshake has a new ``time`` of its own), so the client makes a full handshake with
    every peer at least every ``lifetime`` seconds. Sans-IO: ``now`` is
    ``time.monotonic()`` unless given."""

    def __init__(self, ctx: ssl.SSLContext, *, lifetime: float, max_entries: int = 1024) -> None:
        self.ctx = ctx
        self.lifetime = lifetime
        self.max_entries = max_entries
        self._offers: dict[tuple[str, int], Offer] = {}

    def get(self, endpoint: tuple[str, int], now: float | None = None) -> Offer | None:
        """The session to offer ``endpoint``, if one is young enough."""
        offer = self._offers.get(endpoint)
        if offer is None:
            return None
        if (time.monotonic() if now is None else now) - offer.origin >= self.lifetime:
            del self._offers[endpoint]
            return None
        return offer

    def put(self, endpoint: tuple[str, int], ssl_object: ssl.SSLObject | ssl.SSLSocket | None,
            offered: Offer | None, now: float | None = None) -> None:
        """Keep the session of a connection to ``endpoint``, made after offering
        ``offered``. Call it after the first read (a TLS 1.3 ticket arrives after the
        handshake); a connection without a ticket keeps nothing."""
        if self.lifetime <= 0 or ssl_object is None or ssl_object.context is not self.ctx:
            return
        if offered is not None and ssl_object.session_reused and self._offers.get(endpoint) is offered:
            # The ticket offered still resumes: offer it again rather than read the new one
            # (Python copies a session on every read, ~0.14 ms of CPU). RFC 8446 C.4 asks
            # clients not to reuse a ticket so that a passive observer cannot link the
            # connections; between two interceptors the addresses link them anyway, and
            # every resumed handshake still makes a fresh (EC)DHE key exchange.
            return
        session = ssl_object.session
        if session is None or not session.has_ticket or ssl_object.version() != "TLSv1.3":
            return  # TLS 1.2 resumes without a fresh key exchange: never offered
        reused = offered is not None and ssl_object.session_reused
        origin = offered.origin if reused else (time.monotonic() if now is None else now)
        remember(self._offers, endpoint, Offer(session, origin), self.max_entries)

    def forget(self, endpoint: tuple[str, int]) -> None:
        self._offers.pop(endpoint, None)

    def __len__(self) -> int:
        return len(self._offers)


class FullHandshakes:
    """Server side: when each client certificate last made a full handshake (its chain
    and the CRL verified by OpenSSL), so a resumed stream whose certificate has not done
    so for ``lifetime`` (+ :data:`LIFETIME_SLACK`) seconds is refused
    (``session_too_old``): tickets live 7,200 s in OpenSSL, which Python cannot lower.
    Bounded; a certificate forgotten must handshake in full again. Sans-IO."""

    def __init__(self, lifetime: float, *, max_entries: int = 4096) -> None:
        self.lifetime = lifetime
        self.max_entries = max_entries
        self._last: dict[bytes, float] = {}

    def admit(self, der: bytes, *, resumed: bool, version: str | None = "TLSv1.3", now: float | None = None) -> None:
        """Note a full handshake; refuse a resumed one that is too old, or not TLS 1.3
        (a TLS 1.2 resumption has no fresh key exchange: no forward secrecy)."""
        current = time.monotonic() if now is None else now
        key = hashlib.sha256(der).digest()
        if not resumed:
            remember(self._last, key, current, self.max_entries)
            return
        if version != "TLSv1.3":
            raise TokenError("session_not_tls13", f"a resumed {version} session (only TLS 1.3 resumes)")
        last = self._last.get(key)
        if self.lifetime <= 0 or last is None or current - last >= self.lifetime + LIFETIME_SLACK:
            raise TokenError("session_too_old", "a resumed TLS session older than the session lifetime")


class PeerCertificateCheck:
    """What a full handshake checked of the peer's certificate and a resumed one does
    not: its validity period and the configured CRL; and what neither checks: the
    serials the CA revoked since the CRL was loaded (``revoked_serials``, read at each
    check: the authorization server's revocation feed). Run on every handshake, resumed
    or not (the chain itself was verified by the full handshake the session descends
    from, with the same CA: a reload draws new ticket keys). Raises TokenError
    (``certificate_expired``, ``certificate_not_yet_valid``, ``certificate_revoked``).
    Each certificate is parsed once (bounded cache by SHA-256)."""

    MAX_CERTIFICATES = 4096

    def __init__(self, crl_file: Path | None, *,
                 revoked_serials: Callable[[], Collection[int]] = frozenset) -> None:
        self._feed_serials = revoked_serials
        #: (issuer name DER, serial) of every certificate the CRL file revokes (every CRL in
        #: it, as OpenSSL reads a bundle; a serial is unique only per issuer)
        self.revoked: frozenset[tuple[bytes, int]] = frozenset()
        #: when the file's earliest CRL says a newer one is due (epoch seconds; None: no
        #: CRL, or none names a date). Past it the CRL is still applied: a revocation never
        #: lapses, and what the CA revoked since reaches us through the feed.
        self.next_update: float | None = None
        if crl_file is not None:
            try:
                crls = pemfiles.load_crls(crl_file)
            except CryptorosError as exc:
                raise ConfigError(f"cannot load the CRL {crl_file}: {exc}") from exc
            self.revoked = frozenset((crl.issuer.public_bytes(), entry.serial_number)
                                     for crl in crls for entry in crl)
            due = [crl.next_update_utc.timestamp() for crl in crls if crl.next_update_utc is not None]
            self.next_update = min(due) if due else None
        self._seen: dict[bytes, tuple[int, float, float, bytes]] = {}

    def check(self, der: bytes, now: float | None = None) -> None:
        key = hashlib.sha256(der).digest()
        facts = self._seen.get(key)
        if facts is None:
            try:
                cert = pemfiles.parse_certificate(der)
            except CryptorosError as exc:
                raise TokenError("bad_peer_certificate", str(exc)) from exc
            facts = (cert.serial_number, cert.not_valid_before_utc.timestamp(), cert.not_valid_after_utc.timestamp(),
                     cert.issuer.public_bytes())
            remember(self._seen, key, facts, self.MAX_CERTIFICATES)
        serial, not_before, not_after, issuer = facts
        current = time.time() if now is None else now
        if current > not_after:
            raise TokenError("certificate_expired", f"the peer's certificate (serial {serial:x}) expired")
        if current < not_before:
            raise TokenError("certificate_not_yet_valid", f"the peer's certificate (serial {serial:x}) is not valid yet")
        if (issuer, serial) in self.revoked:
            raise TokenError("certificate_revoked", f"the peer's certificate (serial {serial:x}) is on the CRL")
        if serial in self._feed_serials():
            raise TokenError("certificate_revoked", f"the peer's certificate (serial {serial:x}) was revoked by the CA "
                                                    "(revocation feed)")


def checking_server(ctx: ssl.SSLContext, check: Callable[[bytes], None]) -> ssl.SSLContext:
    """``ctx`` (a client context) whose handshakes fail, as a TLS failure, for a server
    certificate ``check`` refuses (:meth:`PeerCertificateCheck.check`: the CRL and the
    feed's revoked serials, which OpenSSL does not check here). Only where connections
    are made through ``wrap_bio`` (asyncio, uvloop, aiohttp)."""

    class ServerCheckedSSLObject(ssl.SSLObject):
        def do_handshake(self) -> None:
            super().do_handshake()
            if not self.server_side:
                try:
                    check(peer_cert_der(self))
                except TokenError as exc:
                    raise ssl.SSLError(ssl.SSL_ERROR_SSL, f"the server's certificate: {exc.reason}: {exc.detail}") \
                        from None

    ctx.sslobject_class = ServerCheckedSSLObject
    return ctx


def peer_cert_der(ssl_object: ssl.SSLObject | ssl.SSLSocket | None) -> bytes:
    """The DER bytes of the verified peer certificate; no certificate is a denial."""
    der = ssl_object.getpeercert(binary_form=True) if ssl_object is not None else None
    if not der:
        raise TokenError("no_peer_certificate", "the TLS peer presented no certificate")
    return der


#: The fingerprints of a DER certificate live in :mod:`cryptoros.pemfiles`; kept here
#: for the callers that import them from this module.
cert_thumbprint_s256 = pemfiles.cert_thumbprint_s256
cert_fingerprint_sha256 = pemfiles.cert_fingerprint_sha256


def describe_suites(ctx: ssl.SSLContext) -> list[str]:
    """Names of the suites a context may negotiate, TLS 1.3 ones included."""
    return [c["name"] for c in ctx.get_ciphers()]


def _main() -> None:  # pragma: no cover - documentation helper
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    ctx.set_ciphers(STRICT_TLS12_CIPHERS)
    print(f"{ssl.OPENSSL_VERSION}")
    for c in ctx.get_ciphers():
        print(f"{c['protocol']:8s} {c['name']}")


if __name__ == "__main__":  # pragma: no cover
    _main()
