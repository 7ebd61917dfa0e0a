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
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import jwt
from cryptography.hazmat.primitives.asymmetric import rsa
from jwt.algorithms import RSAAlgorithm

from cryptoros.errors import TokenError
from cryptoros.lru import remember
from cryptoros.names import (
    NODE_WILDCARD,
    PARAM_TYPE,
    is_node_pattern,
    validate_graph_name,
    validate_namespace,
    validate_node_name,
    validate_type,
)
from cryptoros.pemfiles import cert_serial, cert_thumbprint_s256

ALGORITHM = "RS256"
TOKEN_TYPE = "at+jwt"
#: Parameter grants: ``name`` is a namespace, ``type`` is always :data:`PARAM_TYPE`;
#: ``write_param`` implies ``read_param``.
PARAM_ACTIONS = ("read_param", "write_param")
ACTIONS = ("publish", "subscribe", "serve", "call", *PARAM_ACTIONS)
REQUIRED_CLAIMS = ("iss", "aud", "sub", "iat", "nbf", "exp", "jti", "cnf", "grants")
MAX_TOKEN_BYTES = 64 * 1024


@dataclass(frozen=True, kw_only=True, order=True)
class Grant:
    """One registry row: ``node`` may ``action`` the topic or service ``name`` of ``type``."""

    node: str
    action: str
    name: str
    type: str

    def __post_init__(self) -> None:
        if self.action not in ACTIONS:
            raise ValueError(f"unknown action {self.action!r}; expected one of {', '.join(ACTIONS)}")
        validate_node_name(self.node)
        if self.action in PARAM_ACTIONS:
            validate_namespace(self.name)
            if self.type != PARAM_TYPE:
                raise ValueError(f"a parameter grant has type {PARAM_TYPE!r}, not {self.type!r}")
        else:
            validate_graph_name(self.name)
            validate_type(self.type)


def node_matches(granted: str, node: str) -> bool:
    """Whether the node name of a grant covers the caller ``node``: the one decision,
    used by every :class:`Grants` method (so every interceptor decides alike).

    ``*`` covers every node; a prefix pattern ``/rostopic_*`` covers every name that
    starts with ``/rostopic_`` and has at least one character more (``/`` included);
    any other grant covers exactly its own name (``/talker`` never ``/talker2``)."""
    if granted == NODE_WILDCARD:
        return True
    if is_node_pattern(granted):
        return len(node) >= len(granted) and node.startswith(granted[:-1])
    return granted == node


def nodes_overlap(a: str, b: str) -> bool:
    """Whether two grants' node names can name one node: equal names, a pattern and a
    name it covers, or two patterns one of whose prefixes starts the other's. ``*`` (any
    node of its own manager) overlaps nothing here: it names no node another manager
    could register."""
    if NODE_WILDCARD in (a, b):
        return False
    if is_node_pattern(a) and is_node_pattern(b):
        return a[:-1].startswith(b[:-1]) or b[:-1].startswith(a[:-1])
    if is_node_pattern(b):
        a, b = b, a
    return node_matches(a, b)


class Grants:
    """An immutable set of grants, as carried in a token."""

    __slots__ = ("_grants", "_index")

    def __init__(self, grants: Iterable[Grant] = ()) -> None:
        self._grants = frozenset(grants)
        index: dict[tuple[str, str, str], list[str]] = {}
        for g in self._grants:
            index.setdefault((g.action, g.name, g.type), []).append(g.node)
        #: (action, name, type) -> granted node names (exact, ``*`` or patterns)
        self._index = {k: tuple(v) for k, v in index.items()}

    def __iter__(self) -> Iterator[Grant]:
        return iter(sorted(self._grants))

    def __len__(self) -> int:
        return len(self._grants)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Grants) and other._grants == self._grants

    def __hash__(self) -> int:
        return hash(self._grants)

    def __repr__(self) -> str:
        return f"Grants({sorted(self._grants)!r})"

    def allows(self, action: str, node: str, name: str, type: str) -> bool:
        """Exact match on action, name and type; the node by :func:`node_matches`."""
        return any(node_matches(granted, node) for granted in self._index.get((action, name, type), ()))

    def any_node_allows(self, action: str, name: str, type_name: str) -> bool:
        """Whether some node of the manager may ``action`` ``name`` with ``type_name``."""
        return (action, name, type_name) in self._index

    def types_for(self, action: str, node: str, name: str) -> frozenset[str]:
        """The types ``node`` may ``action`` the topic or service ``name`` with."""
        return frozenset(
            g.type
            for g in self._grants
            if g.action == action and g.name == name and node_matches(g.node, node)
        )

    def param_allows(self, access: str, node: str, key: str) -> bool:
        """Whether ``node`` may ``access`` ("read" or "write") the global parameter
        ``key`` under a granted namespace (``write_param`` implies read)."""
        actions = ("write_param",) if access == "write" else ("read_param", "write_param")
        return any(
            g.action in actions and node_matches(g.node, node) and in_namespace(key, g.name) for g in self._grants
        )

    def param_namespaces(self, node: str) -> frozenset[str]:
        """The namespaces ``node`` may read (for pruning namespace reads)."""
        return frozenset(g.name for g in self._grants if g.action in PARAM_ACTIONS and node_matches(g.node, node))

    def names_node(self, node: str) -> bool:
        """Whether any grant covers ``node`` (exactly, ``*`` or a prefix pattern): the
        node is this manager's, so it may register that name at the master."""
        return any(node_matches(g.node, node) for g in self._grants)

    def names_node_beyond_wildcard(self, node: str) -> bool:
        """Whether a grant other than the bare wildcard ``*`` covers ``node`` (its exact
        name or a prefix pattern)."""
        return any(g.node != NODE_WILDCARD and node_matches(g.node, node) for g in self._grants)

    def names_node_exactly(self, node: str) -> bool:
        """Whether a grant names ``node`` itself (not through ``*`` or a pattern): the
        registry gives this manager that very name."""
        return any(g.node == node for g in self._grants)

    def names(self) -> frozenset[str]:
        """The topics and services named by any grant (parameter namespaces excluded)."""
        return frozenset(g.name for g in self._grants if g.action not in PARAM_ACTIONS)

    def narrowed_to(self, peer: Grants) -> Grants:
        """What a peer holding ``peer`` needs to judge streams with this manager, and no
        more (no parameter grants, nothing on a name the peer holds no grant on):

        - the topic and service grants on names ``peer`` holds a grant on;
        - the calls and subscriptions of endpoints ROS serves under a node's own name
          (``<node>/get_loggers``, ``<node>/set_parameters`` ...: allowed to any node a
          grant names) of nodes ``peer``'s grants name (``/cam_*`` names ``/cam_front``);
        - for each such endpoint ``peer`` calls or subscribes of a node these grants
          name, the serve or publish grant that node has without a grant row."""
        from cryptoros.policy.infrastructure import ROS1_OPENED_BY, ros1_own_endpoint

        keep = peer.names()
        kept = [g for g in self._grants if g.action not in PARAM_ACTIONS and g.name in keep]
        for mine, theirs, implied in ((self, peer, False), (peer, self, True)):
            for g in mine._grants:
                own = ros1_own_endpoint(g.action, g.name) if g.action in ROS1_OPENED_BY else None
                if own is None or own[1] != g.type or not theirs.names_node(own[0]):
                    continue
                kept.append(Grant(node=own[0], action=ROS1_OPENED_BY[g.action], name=g.name, type=g.type)
                            if implied else g)
        return Grants(kept)

    def to_claim(self) -> dict[str, dict[str, list[list[str]]]]:
        claim: dict[str, dict[str, list[list[str]]]] = {}
        for g in sorted(self._grants):
            claim.setdefault(g.node, {}).setdefault(g.action, []).append([g.name, g.type])
        return claim

    @classmethod
    def from_claim(cls, claim: Any) -> Grants:
        """Parse the ``grants`` claim strictly; anything unexpected is ``malformed``."""
        if not isinstance(claim, Mapping):
            raise TokenError("malformed", "grants claim is not an object")
        grants = []
        try:
            for node, actions in claim.items():
                if not isinstance(actions, Mapping):
                    raise TokenError("malformed", f"grants for {node!r} are not an object")
                for action, rows in actions.items():
                    if not isinstance(rows, list):
                        raise TokenError("malformed", f"grants {node!r}/{action!r} are not a list")
                    for row in rows:
                        if not (isinstance(row, list) and len(row) == 2 and all(isinstance(x, str) for x in row)):
                            raise TokenError("malformed", f"grant row {row!r} is not [name, type]")
                        grants.append(Grant(node=node, action=action, name=row[0], type=row[1]))
        except TokenError:
            raise
        except Exception as exc:  # invalid names, types or actions
            raise TokenError("malformed", f"invalid grant: {exc}") from exc
        return cls(grants)


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


def in_namespace(key: str, namespace: str) -> bool:
    """``/a/b`` is in ``/a`` and in ``/``; ``/ab`` is not in ``/a``."""
    return namespace == "/" or key == namespace or key.startswith(namespace + "/")


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
