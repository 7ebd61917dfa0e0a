"""Real tokens (RS256, a real key) bound to real certificates of a throwaway CA, and a
:class:`~interceptor.verifier.PeerVerifier` that asks no authorization server: for the
unit tests of the verifier (its token cache, its cuts)."""

from __future__ import annotations

import pytest
from cryptography.hazmat.primitives.asymmetric import rsa

from cryptoros.grants import Grant, Grants
from cryptoros.tokens import KeySet, build_claims, public_jwk, sign_token
from interceptor.verifier import PeerVerifier
from tests.authz_support import read_pem_der

ISS, AUD = "cryptoros-authz", "cryptoros"
NOW = 1_800_000_000
LIFETIME = 300
GRANTS = Grants([Grant(node="/talker", action="publish", name="/chatter", type="std_msgs/String")])


@pytest.fixture(scope="module")
def signing_key() -> rsa.RSAPrivateKey:
    return rsa.generate_private_key(public_exponent=65537, key_size=2048)


@pytest.fixture
def certs(pki) -> dict[str, bytes]:
    return {name: read_pem_der(pki.issue(name).cert_path) for name in ("alice", "bob")}


class Clock:
    def __init__(self, now: float) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


def make_verifier(signing_key, clock: Clock, **kw) -> PeerVerifier:
    # No authorization server is asked: verify() uses the keys and feed it holds.
    verifier = PeerVerifier(None, issuer=ISS, audience=AUD, poll_interval=1, clock=clock, **kw)
    verifier.keys = KeySet.from_jwks({"keys": [public_jwk(signing_key.public_key(), "k1")]})
    return verifier


def token_for(signing_key, cert_der: bytes, *, subject: str = "alice", now: int = NOW, kid: str = "k1") -> str:
    claims = build_claims(issuer=ISS, audience=AUD, subject=subject, grants=GRANTS, cert_der=cert_der, now=now,
                          lifetime=LIFETIME)
    return sign_token(claims, signing_key, kid)
