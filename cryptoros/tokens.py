"""Access-token claims, signing and verification.

The token is an RS256 JWT (RFC 7519) shaped as an OAuth 2 access token (RFC 9068):

    header  {"alg": "RS256", "typ": "at+jwt", "kid": <signing key id>}
    claims  {"iss", "aud", "sub": <manager>, "iat", "nbf", "exp", "jti",
             "cnf": {"x5t#S256": <thumbprint of the manager's TLS certificate>},
             "grants": {<node>: {<action>: [[<topic or service>, <type>], ...]}}}

:func:`verify_access_token` verifies a token completely, in two halves:
:func:`decode_access_token` (the only caller of ``jwt.decode`` in cryptoros: it never
takes the algorithm from the token, requires every claim, checks audience, issuer and
the key by ``kid``) and :func:`check_decoded_token` (time with the clock passed in, the
binding of the token to the TLS certificate the peer presented, RFC 8705, and
revocations). :class:`VerifiedTokenCache` keeps the first half of tokens already
verified (the same token arrives on many streams) and runs the second on every
stream. Every refusal is a
:class:`~cryptoros.errors.TokenError` whose ``reason`` names what failed, for logs
and metrics; a peer is only ever told an opaque denial.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import time
import uuid
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import jwt
from cryptography.hazmat.primitives.asymmetric import rsa
from jwt.algorithms import RSAAlgorithm

from cryptoros.errors import TokenError
from cryptoros.grants import ACTIONS, Grant, Grants, node_matches, nodes_overlap
from cryptoros.lru import remember
from cryptoros.pemfiles import cert_serial, cert_thumbprint_s256

ALGORITHM = "RS256"
TOKEN_TYPE = "at+jwt"
REQUIRED_CLAIMS = ("iss", "aud", "sub", "iat", "nbf", "exp", "jti", "cnf", "grants")
MAX_TOKEN_BYTES = 64 * 1024


#: RFC 8707 resource indicator (and ``aud``) of a token meant for one peer interceptor,
#: named by the thumbprint of its TLS certificate.
PEER_AUDIENCE_PREFIX = "urn:cryptoros:peer:"
_THUMBPRINT_LENGTH = 43  # base64url of 32 bytes, unpadded


def peer_audience(thumbprint: str) -> str:
    """The audience of a token narrowed for the peer whose certificate has ``thumbprint``."""
    return PEER_AUDIENCE_PREFIX + thumbprint


def thumbprint_of_audience(resource: str) -> str:
    """The certificate thumbprint a peer audience names; TokenError if it names none."""
    thumb = resource[len(PEER_AUDIENCE_PREFIX):] if resource.startswith(PEER_AUDIENCE_PREFIX) else ""
    if len(thumb) != _THUMBPRINT_LENGTH or not all(c.isalnum() or c in "-_" for c in thumb):
        raise TokenError("invalid_target", f"resource {resource[:80]!r} is not {PEER_AUDIENCE_PREFIX}<x5t#S256>")
    return thumb


def fingerprint_of_thumbprint(thumbprint: str) -> str:
    """Registry fingerprint (hex SHA-256) of a certificate from its ``x5t#S256``."""
    import base64

    return base64.urlsafe_b64decode(thumbprint + "=").hex()


#: the response header that marks a streamed long-poll of the revocation feed (spaces as
#: heartbeats, then one JSON object); the authorization server sets it, clients read it
FEED_STREAM_HEADER = "X-Cryptoros-Feed-Stream"


@dataclass(frozen=True, kw_only=True)
class Revocations:
    """What the authorization server's revocation feed says right now."""

    revoked_jtis: frozenset[str] = frozenset()
    disabled_subjects: frozenset[str] = frozenset()
    #: serials the CA's CRL lists: a token is refused over such a certificate
    revoked_serials: frozenset[int] = frozenset()
    #: the registry's version (the feed's ``serial``): it moves with every change of
    #: the registry (a grant, a manager, a revocation); None when the feed has none
    serial: int | None = None
    #: managers in learning mode and when each window ends (Unix seconds):
    #: :mod:`cryptoros.learning`
    learning: tuple[tuple[str, float], ...] = ()


@dataclass(frozen=True, kw_only=True)
class AccessToken:
    """A verified token: only :func:`verify_access_token` makes these."""

    subject: str
    jti: str
    issued_at: int
    expires_at: int
    grants: Grants
    thumbprint: str
    claims: Mapping[str, Any] = field(repr=False)


def build_claims(
    *,
    issuer: str,
    audience: str,
    subject: str,
    grants: Grants,
    cert_der: bytes,
    now: int,
    lifetime: int,
    jti: str | None = None,
) -> dict[str, Any]:
    """The claims of a new access token bound to the certificate ``cert_der``."""
    if lifetime <= 0:
        raise ValueError("token lifetime must be positive")
    now = int(now)
    return {
        "iss": issuer,
        "aud": audience,
        "sub": subject,
        "iat": now,
        "nbf": now,
        "exp": now + int(lifetime),
        "jti": jti or uuid.uuid4().hex,
        "cnf": {"x5t#S256": cert_thumbprint_s256(cert_der)},
        "grants": grants.to_claim(),
    }


def sign_token(claims: Mapping[str, Any], private_key: rsa.RSAPrivateKey, kid: str) -> str:
    """Sign claims as an RS256 JWT with ``kid`` and ``typ: at+jwt`` in the header."""
    if not isinstance(private_key, rsa.RSAPrivateKey):
        raise TypeError("RS256 tokens need an RSA private key")
    return jwt.encode(dict(claims), private_key, algorithm=ALGORITHM, headers={"kid": kid, "typ": TOKEN_TYPE})


def public_jwk(public_key: rsa.RSAPublicKey, kid: str) -> dict[str, str]:
    """The public key as a JWK for the JWKS endpoint."""
    jwk = RSAAlgorithm.to_jwk(public_key, as_dict=True)
    jwk.update({"kid": kid, "use": "sig", "alg": ALGORITHM})
    return jwk


class KeySet:
    """Verification keys by ``kid``, as published in the JWKS. Immutable; swap on refresh."""

    __slots__ = ("_keys", "_numbers")

    def __init__(self, keys: Mapping[str, rsa.RSAPublicKey]) -> None:
        self._keys = dict(keys)
        #: kid -> (n, e): two key sets are equal when they hold the same keys by the same kids
        self._numbers = {kid: (k.public_numbers().n, k.public_numbers().e) for kid, k in self._keys.items()}

    def __eq__(self, other: object) -> bool:
        return isinstance(other, KeySet) and other._numbers == self._numbers

    def __hash__(self) -> int:
        return hash(frozenset(self._numbers.items()))

    @classmethod
    def from_jwks(cls, jwks: Mapping[str, Any]) -> KeySet:
        keys = {}
        for jwk in jwks.get("keys", []) if isinstance(jwks, Mapping) else []:
            if not isinstance(jwk, Mapping) or jwk.get("kty") != "RSA" or jwk.get("alg", ALGORITHM) != ALGORITHM:
                continue  # only RSA signing keys for RS256 are ever accepted
            kid = jwk.get("kid")
            if not isinstance(kid, str) or not kid:
                continue
            key = RSAAlgorithm.from_jwk(json.dumps(dict(jwk)))
            if isinstance(key, rsa.RSAPublicKey):
                keys[kid] = key
        return cls(keys)

    def get(self, kid: str) -> rsa.RSAPublicKey:
        try:
            return self._keys[kid]
        except (KeyError, TypeError):
            raise TokenError("unknown_kid", f"no verification key with kid {kid!r}") from None

    def kids(self) -> list[str]:
        return sorted(self._keys)

    def __len__(self) -> int:
        return len(self._keys)


_PYJWT_REASONS: tuple[tuple[type[Exception], str], ...] = (
    (jwt.InvalidSignatureError, "bad_signature"),
    (jwt.InvalidAudienceError, "bad_audience"),
    (jwt.InvalidIssuerError, "bad_issuer"),
    (jwt.MissingRequiredClaimError, "missing_claim"),
    (jwt.InvalidAlgorithmError, "bad_algorithm"),
    (jwt.ExpiredSignatureError, "expired"),
    (jwt.ImmatureSignatureError, "not_yet_valid"),
    (jwt.DecodeError, "malformed"),
    (jwt.InvalidTokenError, "malformed"),
)


def _serial_of(der: bytes) -> int:
    return cert_serial(der)


@dataclass(frozen=True, kw_only=True)
class DecodedToken:
    """A token whose signature, algorithm, key, issuer, audience and claim shapes were
    checked by :func:`decode_access_token`; nothing about the clock, the TLS certificate
    of a stream or the revocation feed is checked yet. Only :func:`check_decoded_token`
    turns it into an :class:`AccessToken`."""

    token: str = field(repr=False)
    not_before: int
    #: ``cnf`` ``x5t#S256``: the certificate the token is bound to
    bound: str
    #: what :func:`check_decoded_token` returns once every per-stream check passed
    unchecked: AccessToken = field(repr=False)


def decode_access_token(
    token: str, *, keys: KeySet, issuer: str, audience: str | tuple[str, ...],
) -> DecodedToken:
    """The half of :func:`verify_access_token` that depends on the token alone (and the
    keys, issuer and audience): signature (RS256, key by ``kid``), every required claim,
    ``iss``, ``aud``, the types of ``sub``, ``jti``, ``iat``, ``nbf``, ``exp``, ``cnf``
    and the grants claim. TokenError on any failure."""
    if not isinstance(token, str) or not token or len(token) > MAX_TOKEN_BYTES:
        raise TokenError("malformed", "token missing, not text, or oversized")
    try:
        header = jwt.get_unverified_header(token)
    except jwt.InvalidTokenError as exc:
        raise TokenError("malformed", f"unreadable header: {exc}") from exc
    if header.get("alg") != ALGORITHM:
        raise TokenError("bad_algorithm", f"alg {header.get('alg')!r} refused; only {ALGORITHM}")
    public_key = keys.get(header.get("kid"))
    try:
        claims = jwt.decode(
            token,
            key=public_key,
            algorithms=[ALGORITHM],
            audience=audience,
            issuer=issuer,
            options={
                "require": list(REQUIRED_CLAIMS),
                "verify_signature": True,
                "verify_aud": True,
                "verify_iss": True,
                # Time is checked by check_decoded_token against the clock passed in.
                "verify_exp": False,
                "verify_nbf": False,
                "verify_iat": False,
            },
        )
    except Exception as exc:
        for exc_type, reason in _PYJWT_REASONS:
            if isinstance(exc, exc_type):
                raise TokenError(reason, str(exc)) from exc
        raise TokenError("malformed", str(exc)) from exc

    subject, jti = claims["sub"], claims["jti"]
    times = {k: claims[k] for k in ("iat", "nbf", "exp")}
    if not (isinstance(subject, str) and subject and isinstance(jti, str) and jti):
        raise TokenError("malformed", "sub and jti must be non-empty strings")
    if not all(isinstance(v, int) and not isinstance(v, bool) for v in times.values()):
        raise TokenError("malformed", "iat, nbf and exp must be integers")
    cnf = claims["cnf"]
    bound = cnf.get("x5t#S256") if isinstance(cnf, Mapping) else None
    if not isinstance(bound, str):
        raise TokenError("malformed", "cnf claim has no x5t#S256")
    return DecodedToken(
        token=token,
        not_before=times["nbf"],
        bound=bound,
        unchecked=AccessToken(
            subject=subject,
            jti=jti,
            issued_at=times["iat"],
            expires_at=times["exp"],
            grants=Grants.from_claim(claims["grants"]),
            thumbprint=bound,
            claims=claims,
        ),
    )


def check_decoded_token(
    decoded: DecodedToken,
    *,
    peer_cert_der: bytes | None,
    now: float | None = None,
    leeway: float = 5.0,
    revocations: Revocations | None = None,
) -> AccessToken:
    """The half of :func:`verify_access_token` that depends on the stream: ``exp`` and
    ``nbf`` against the clock (with ``leeway``), the binding to the certificate the
    peer presented on this TLS connection (RFC 8705), and the revocation feed (the
    certificate's serial, the ``jti``, the manager). Runs on every stream, cached
    decode or not. TokenError on any failure."""
    access = decoded.unchecked
    current = time.time() if now is None else now
    if current >= access.expires_at + leeway:
        raise TokenError("expired", f"expired at {access.expires_at}, now {int(current)}")
    if current + leeway < decoded.not_before:
        raise TokenError("not_yet_valid", f"not valid before {decoded.not_before}, now {int(current)}")

    if not peer_cert_der:
        raise TokenError("no_peer_certificate", "no TLS certificate to check the token binding against")
    presented = cert_thumbprint_s256(peer_cert_der)
    if not hmac.compare_digest(decoded.bound.encode(), presented.encode()):
        raise TokenError("cnf_mismatch", "token is bound to another certificate")

    if revocations is not None:
        if revocations.revoked_serials and _serial_of(peer_cert_der) in revocations.revoked_serials:
            raise TokenError("certificate_revoked", "the certificate this token is bound to was revoked by the CA")
        if access.jti in revocations.revoked_jtis:
            raise TokenError("revoked", f"token {access.jti} was revoked")
        if access.subject in revocations.disabled_subjects:
            raise TokenError("subject_disabled", f"manager {access.subject} is disabled")
    return access


def verify_access_token(
    token: str,
    *,
    keys: KeySet,
    issuer: str,
    audience: str | tuple[str, ...],
    peer_cert_der: bytes | None,
    now: float | None = None,
    leeway: float = 5.0,
    revocations: Revocations | None = None,
) -> AccessToken:
    """Verify ``token`` completely or raise :class:`TokenError`:
    :func:`decode_access_token` then :func:`check_decoded_token`.

    ``peer_cert_der`` is the certificate the peer presented on this TLS connection:
    the token must be bound to it. ``audience`` may name several accepted audiences
    (the deployment's and this verifier's own :func:`peer_audience`). ``now`` defaults to the wall clock; pass the
    simulator's clock or a test's fixed time explicitly.
    """
    decoded = decode_access_token(token, keys=keys, issuer=issuer, audience=audience)
    return check_decoded_token(decoded, peer_cert_der=peer_cert_der, now=now, leeway=leeway, revocations=revocations)


class VerifiedTokenCache:
    """Tokens already verified, so that the same token shown on many streams is decoded
    (signature and claims) once: keyed by the SHA-256 of the token text, bounded (the
    least recently used entry goes first), and only ever filled with a token that
    passed the *whole* verification once.

    What is cached is the decode alone: every :meth:`verify`, hit or miss, runs
    :func:`check_decoded_token` on this stream's inputs (the clock with the same
    leeway, the peer's certificate, the revocation feed). An entry whose token has
    expired is dropped on its next hit. The cache empties itself whenever something the
    decode depends on differs from what it was filled with: the key set (a key added,
    removed or replaced: rotation), the issuer or the accepted audiences, or the
    revocation feed (any change of it, the registry's serial included: the feed does
    not say which tokens a grant change concerns, so nothing finer is possible)."""

    def __init__(self, max_entries: int = 4096) -> None:
        if max_entries < 1:
            raise ValueError("max_entries must be at least 1")
        self.max_entries = max_entries
        self._entries: OrderedDict[bytes, DecodedToken] = OrderedDict()
        self._inputs: tuple[Any, ...] | None = None
        self.hits = 0
        self.misses = 0

    def __len__(self) -> int:
        return len(self._entries)

    def clear(self) -> None:
        self._entries.clear()

    def _sync(self, keys: KeySet, issuer: str, audience: str | tuple[str, ...], revocations: Revocations | None) -> None:
        inputs = (keys, issuer, audience, revocations)
        last = self._inputs
        if last is not None and all(a is b for a, b in zip(inputs, last, strict=True)):
            return  # the same objects: nothing changed (the usual case, no comparison)
        if last is None or inputs != last:
            self._entries.clear()
        self._inputs = inputs

    def verify(
        self,
        token: str,
        *,
        keys: KeySet,
        issuer: str,
        audience: str | tuple[str, ...],
        peer_cert_der: bytes | None,
        now: float | None = None,
        leeway: float = 5.0,
        revocations: Revocations | None = None,
    ) -> AccessToken:
        """What :func:`verify_access_token` returns or raises, with the decode cached."""
        if not isinstance(token, str) or not token or len(token) > MAX_TOKEN_BYTES:
            raise TokenError("malformed", "token missing, not text, or oversized")
        self._sync(keys, issuer, audience, revocations)
        digest = hashlib.sha256(token.encode()).digest()
        decoded = self._entries.get(digest)
        checks = {"peer_cert_der": peer_cert_der, "now": now, "leeway": leeway, "revocations": revocations}
        if decoded is not None and decoded.token == token:
            self.hits += 1
            self._entries.move_to_end(digest)
            try:
                return check_decoded_token(decoded, **checks)
            except TokenError as exc:
                if exc.reason == "expired":
                    self._entries.pop(digest, None)  # never outlives its token
                raise
        self.misses += 1
        decoded = decode_access_token(token, keys=keys, issuer=issuer, audience=audience)
        access = check_decoded_token(decoded, **checks)  # only a token that passed everything is kept
        remember(self._entries, digest, decoded, self.max_entries)
        return access


__all__ = [
    "ACTIONS",
    "ALGORITHM",
    "AccessToken",
    "DecodedToken",
    "Grant",
    "Grants",
    "KeySet",
    "Revocations",
    "VerifiedTokenCache",
    "build_claims",
    "check_decoded_token",
    "nodes_overlap",
    "decode_access_token",
    "public_jwk",
    "sign_token",
    "node_matches",
    "verify_access_token",
]
