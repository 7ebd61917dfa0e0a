"""The one token-verification function against every token attack the issue lists.

Each forged token is built the way an attacker would build it (PyJWT or raw base64),
and each must be refused with the reason that names the failure.
"""

from __future__ import annotations

import base64
import json

import jwt
import pytest
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import rsa
from hypothesis import given, settings
from hypothesis import strategies as st

from cryptoros.errors import TokenError
from cryptoros.grants import Grant, Grants
from cryptoros.tokens import KeySet, Revocations, build_claims, public_jwk, sign_token, verify_access_token

NOW = 1_800_000_000
ISS, AUD = "cryptoros-authz", "cryptoros"
CERT_A = b"certificate A, DER bytes stand-in"
CERT_B = b"certificate B, DER bytes stand-in"


@pytest.fixture(scope="module")
def signing_key() -> rsa.RSAPrivateKey:
    return rsa.generate_private_key(public_exponent=65537, key_size=2048)


@pytest.fixture(scope="module")
def other_key() -> rsa.RSAPrivateKey:
    return rsa.generate_private_key(public_exponent=65537, key_size=2048)


@pytest.fixture(scope="module")
def keys(signing_key) -> KeySet:
    return KeySet.from_jwks({"keys": [public_jwk(signing_key.public_key(), "k1")]})


GRANTS = Grants(
    [
        Grant(node="/talker", action="publish", name="/chatter", type="std_msgs/String"),
        Grant(node="/listener", action="subscribe", name="/chatter", type="std_msgs/String"),
        Grant(node="*", action="call", name="/add_two_ints", type="rospy_tutorials/AddTwoInts"),
    ]
)


def claims(**overrides):
    c = build_claims(issuer=ISS, audience=AUD, subject="robot1", grants=GRANTS, cert_der=CERT_A, now=NOW, lifetime=300)
    c.update(overrides)
    return c


def verify(token, keys, *, cert=CERT_A, now=NOW + 10, revocations=None):
    return verify_access_token(
        token, keys=keys, issuer=ISS, audience=AUD, peer_cert_der=cert, now=now, revocations=revocations
    )


def reason_of(token, keys, **kw) -> str:
    with pytest.raises(TokenError) as info:
        verify(token, keys, **kw)
    return info.value.reason


def b64(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode()


def test_valid_token_verifies_with_grants(signing_key, keys):
    token = sign_token(claims(), signing_key, "k1")
    access = verify(token, keys)
    assert access.subject == "robot1"
    assert access.expires_at == NOW + 300
    assert access.grants == GRANTS
    assert access.grants.allows("publish", "/talker", "/chatter", "std_msgs/String")
    assert not access.grants.allows("publish", "/talker", "/chatter", "std_msgs/Int32")
    assert not access.grants.allows("publish", "/listener", "/chatter", "std_msgs/String")
    assert access.grants.allows("call", "/any_node", "/add_two_ints", "rospy_tutorials/AddTwoInts")
    assert jwt.get_unverified_header(token) == {"alg": "RS256", "kid": "k1", "typ": "at+jwt"}


def test_alg_none_refused(keys):
    token = f"{b64(json.dumps({'alg': 'none', 'kid': 'k1'}).encode())}.{b64(json.dumps(claims()).encode())}."
    assert reason_of(token, keys) == "bad_algorithm"


def test_hs256_with_public_key_as_secret_refused(signing_key, keys):
    # The classic key-confusion attack: HMAC keyed with the PEM of the RSA public key.
    pem = signing_key.public_key().public_bytes(serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo)
    header = b64(json.dumps({"alg": "HS256", "kid": "k1", "typ": "JWT"}).encode())
    body = b64(json.dumps(claims()).encode())
    import hashlib
    import hmac

    sig = b64(hmac.new(pem, f"{header}.{body}".encode(), hashlib.sha256).digest())
    assert reason_of(f"{header}.{body}.{sig}", keys) == "bad_algorithm"


def test_expired_refused(signing_key, keys):
    token = sign_token(claims(), signing_key, "k1")
    assert reason_of(token, keys, now=NOW + 300 + 6) == "expired"
    assert verify(token, keys, now=NOW + 300 + 4).subject == "robot1"  # within leeway


def test_not_yet_valid_refused(signing_key, keys):
    token = sign_token(claims(nbf=NOW + 100, iat=NOW + 100), signing_key, "k1")
    assert reason_of(token, keys, now=NOW) == "not_yet_valid"


def test_wrong_audience_refused(signing_key, keys):
    assert reason_of(sign_token(claims(aud="someone-else"), signing_key, "k1"), keys) == "bad_audience"


def test_wrong_issuer_refused(signing_key, keys):
    assert reason_of(sign_token(claims(iss="evil-authz"), signing_key, "k1"), keys) == "bad_issuer"


def test_unknown_kid_refused(signing_key, keys):
    assert reason_of(sign_token(claims(), signing_key, "k2"), keys) == "unknown_kid"


def test_payload_edited_after_signing_refused(signing_key, keys):
    header, _, sig = sign_token(claims(), signing_key, "k1").split(".")
    edited = claims()
    edited["grants"]["/talker"]["publish"].append(["/cmd_vel", "geometry_msgs/Twist"])
    assert reason_of(f"{header}.{b64(json.dumps(edited).encode())}.{sig}", keys) == "bad_signature"


def test_signed_by_another_key_refused(other_key, keys):
    assert reason_of(sign_token(claims(), other_key, "k1"), keys) == "bad_signature"


def test_bound_to_another_certificate_refused(signing_key, keys):
    token = sign_token(claims(), signing_key, "k1")
    assert reason_of(token, keys, cert=CERT_B) == "cnf_mismatch"
    assert reason_of(token, keys, cert=None) == "no_peer_certificate"


def test_revoked_jti_refused(signing_key, keys):
    token = sign_token(claims(jti="abc123"), signing_key, "k1")
    assert reason_of(token, keys, revocations=Revocations(revoked_jtis=frozenset({"abc123"}))) == "revoked"


def test_disabled_manager_refused(signing_key, keys):
    token = sign_token(claims(), signing_key, "k1")
    revocations = Revocations(disabled_subjects=frozenset({"robot1"}))
    assert reason_of(token, keys, revocations=revocations) == "subject_disabled"


@pytest.mark.parametrize("claim", ["iss", "aud", "sub", "iat", "nbf", "exp", "jti", "cnf", "grants"])
def test_every_claim_is_required(signing_key, keys, claim):
    c = claims()
    del c[claim]
    assert reason_of(sign_token(c, signing_key, "k1"), keys) in ("missing_claim",)


@pytest.mark.parametrize(
    "bad",
    [
        {"exp": "tomorrow"},
        {"sub": ""},
        {"cnf": {}},
        {"grants": {"/talker": {"publish": [["chatter", "std_msgs/String"]]}}},  # relative name
        {"grants": {"/talker": {"teleport": [["/chatter", "std_msgs/String"]]}}},  # unknown action
        {"grants": ["/chatter"]},
    ],
)
def test_malformed_claims_refused(signing_key, keys, bad):
    assert reason_of(sign_token(claims(**bad), signing_key, "k1"), keys) == "malformed"


def test_jwks_ignores_non_rsa_keys(signing_key):
    jwks = {"keys": [{"kty": "oct", "k": "c2VjcmV0", "kid": "k1"}, public_jwk(signing_key.public_key(), "k9")]}
    assert KeySet.from_jwks(jwks).kids() == ["k9"]


@settings(max_examples=200, deadline=None)
@given(st.text(max_size=300) | st.binary(max_size=300).map(lambda b: b.decode("latin-1")))
def test_any_string_is_a_token_error_never_a_crash(keys, garbage):
    with pytest.raises(TokenError):
        verify(garbage, keys)


def test_grants_claim_round_trips():
    assert Grants.from_claim(GRANTS.to_claim()) == GRANTS
