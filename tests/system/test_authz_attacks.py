"""Attacks on the token issuer: forged tokens and refused TLS handshakes.

Tokens come from a real daemon (subprocess, mutual TLS); forgeries are built from
them or signed with the daemon's own key read from its registry (the worst case: an
attacker holding the signing key with the wrong claims). Every forgery must be
refused by ``verify_access_token`` with the right reason, using the daemon's JWKS
and revocation feed as an interceptor would.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import socket
import ssl
import subprocess
import time
from pathlib import Path

import pytest
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import rsa

from authz_server.db import open_registry
from authz_server.keys import load_private, protection
from authz_server.registry import Registry
from cryptoros.errors import TokenError
from cryptoros.tokens import KeySet, Revocations, sign_token, verify_access_token
from tests.support import client_hello, require
from tests.authz_support import ok, read_pem_der

ISS, AUD = "cryptoros-authz", "cryptoros"


@pytest.fixture(scope="module")
def real(daemon):
    """A genuine token of alice, the JWKS, and the daemon's signing key."""
    status, body = daemon.token("alice")
    assert status == 200
    jwks = daemon.get_json("/.well-known/jwks.json")
    engine = open_registry(daemon.db)
    try:
        active = Registry(engine).active_key()
    finally:
        engine.dispose()
    key = load_private(active.private_pem, active.encrypted,
                       protection(str(daemon.workdir / "signing.pass")), active.kid)
    return {"token": body["access_token"], "jwks": jwks, "keys": KeySet.from_jwks(jwks), "key": key,
            "kid": active.kid, "alice_der": read_pem_der(daemon.cert_of("alice")[0]),
            "bob_der": read_pem_der(daemon.cert_of("bob")[0])}


def b64(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode()


def unb64(s: str) -> bytes:
    return base64.urlsafe_b64decode(s + "=" * (-len(s) % 4))


def parts(token: str) -> tuple[dict, dict, str]:
    h, p, s = token.split(".")
    return json.loads(unb64(h)), json.loads(unb64(p)), s


def refused(real, token: str, *, der: bytes | None = None, revocations: Revocations | None = None) -> str:
    with pytest.raises(TokenError) as info:
        verify_access_token(token, keys=real["keys"], issuer=ISS, audience=AUD,
                            peer_cert_der=der or real["alice_der"], revocations=revocations)
    return info.value.reason


def resign(real, **changes) -> str:
    _, claims, _ = parts(real["token"])
    claims.update(changes)
    return sign_token(claims, real["key"], real["kid"])


def test_the_genuine_token_verifies(real):
    tok = verify_access_token(real["token"], keys=real["keys"], issuer=ISS, audience=AUD,
                              peer_cert_der=real["alice_der"])
    assert tok.subject == "alice"


def test_alg_none_is_refused(real):
    header, claims, _ = parts(real["token"])
    forged = b64(json.dumps({"alg": "none", "typ": "at+jwt", "kid": header["kid"]}).encode()) + "." + \
        b64(json.dumps(claims).encode()) + "."
    assert refused(real, forged) == "bad_algorithm"


def test_hs256_signed_with_the_rsa_public_key_is_refused(real):
    header, claims, _ = parts(real["token"])
    jwk_pem = real["key"].public_key().public_bytes(serialization.Encoding.PEM,
                                                    serialization.PublicFormat.SubjectPublicKeyInfo)
    signing_input = b64(json.dumps({"alg": "HS256", "typ": "at+jwt", "kid": header["kid"]}).encode()) + "." + \
        b64(json.dumps(claims).encode())
    sig = hmac.new(jwk_pem, signing_input.encode(), hashlib.sha256).digest()
    assert refused(real, signing_input + "." + b64(sig)) == "bad_algorithm"


def test_expired_token_is_refused(real):
    now = int(time.time())
    assert refused(real, resign(real, iat=now - 900, nbf=now - 900, exp=now - 600)) == "expired"
    # and the genuine token, once its lifetime is over
    with pytest.raises(TokenError) as info:
        verify_access_token(real["token"], keys=real["keys"], issuer=ISS, audience=AUD,
                            peer_cert_der=real["alice_der"], now=parts(real["token"])[1]["exp"] + 10)
    assert info.value.reason == "expired"


def test_not_yet_valid_token_is_refused(real):
    now = int(time.time())
    assert refused(real, resign(real, iat=now + 600, nbf=now + 600, exp=now + 900)) == "not_yet_valid"


def test_wrong_audience_is_refused(real):
    assert refused(real, resign(real, aud="some-other-service")) == "bad_audience"


def test_wrong_issuer_is_refused(real):
    assert refused(real, resign(real, iss="https://evil.example")) == "bad_issuer"


def test_unknown_kid_is_refused(real):
    _, claims, _ = parts(real["token"])
    assert refused(real, sign_token(claims, real["key"], "no-such-kid")) == "unknown_kid"


def test_payload_edited_after_signing_is_refused(real):
    h, p, s = real["token"].split(".")
    claims = json.loads(unb64(p))
    claims["grants"]["/talker"]["publish"].append(["/cmd_vel", "geometry_msgs/Twist"])
    assert refused(real, f"{h}.{b64(json.dumps(claims).encode())}.{s}") == "bad_signature"
    claims = json.loads(unb64(p))
    claims["sub"] = "bob"
    assert refused(real, f"{h}.{b64(json.dumps(claims).encode())}.{s}") == "bad_signature"


def test_token_signed_by_another_key_is_refused(real):
    _, claims, _ = parts(real["token"])
    other = rsa.generate_private_key(public_exponent=65537, key_size=2048)
    assert refused(real, sign_token(claims, other, real["kid"])) == "bad_signature"


def test_token_presented_over_another_certificate_is_refused(real):
    # bob's interceptor replays alice's token on its own TLS connection
    assert refused(real, real["token"], der=real["bob_der"]) == "cnf_mismatch"
    # a token whose cnf names another certificate, signed with the real key
    assert refused(real, resign(real, cnf={"x5t#S256": b64(hashlib.sha256(real["bob_der"]).digest())})) \
        == "cnf_mismatch"


def _feed(daemon) -> Revocations:
    feed = daemon.get_json("/revocations")
    return Revocations(revoked_jtis=frozenset(feed["revoked_jtis"]),
                       disabled_subjects=frozenset(feed["disabled_managers"]))


def test_revoked_jti_is_refused(daemon, real):
    status, body = daemon.token("bob")
    token = body["access_token"]
    jti = parts(token)[1]["jti"]
    ok(daemon.cli("revoke-token", jti))
    deadline = time.monotonic() + 5
    while jti not in (rev := _feed(daemon)).revoked_jtis:
        assert time.monotonic() < deadline, "revoked jti not in the feed within 5 s"
        time.sleep(0.2)
    assert refused(real, token, der=real["bob_der"], revocations=rev) == "revoked"


def test_token_of_a_disabled_manager_is_refused(daemon, real):
    ok(daemon.cli("grant", "bob", "publish", "/client", "/status", "std_msgs/String"))
    status, body = daemon.token("bob")
    token = body["access_token"]
    ok(daemon.cli("disable-manager", "bob"))
    try:
        deadline = time.monotonic() + 5
        while "bob" not in (rev := _feed(daemon)).disabled_subjects:
            assert time.monotonic() < deadline
            time.sleep(0.2)
        # refused on the subject alone, even without the jti revocation that came with it
        only_subject = Revocations(disabled_subjects=rev.disabled_subjects)
        assert refused(real, token, der=real["bob_der"], revocations=only_subject) == "subject_disabled"
        assert parts(token)[1]["jti"] in rev.revoked_jtis
        time.sleep(1.1)  # past the daemon's 1 s grants cache
        assert daemon.token("bob") == (403, {"error": "access_denied"})
    finally:
        ok(daemon.cli("enable-manager", "bob"))


# ---------------------------------------------------------------------- TLS handshakes
def _attempt(daemon, ctx: ssl.SSLContext) -> bytes:
    """Connect, handshake, ask for a token; return whatever came back (b'' if refused)."""
    got = b""
    with socket.create_connection(("127.0.0.1", daemon.port), timeout=5) as raw:
        try:
            with ctx.wrap_socket(raw, server_hostname="127.0.0.1") as tls:
                tls.sendall(b"POST /token HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: "
                            b"application/x-www-form-urlencoded\r\nContent-Length: 29\r\n\r\n"
                            b"grant_type=client_credentials")
                while chunk := tls.recv(4096):
                    got += chunk
                    if b"\r\n\r\n" in got:
                        break
        except (ssl.SSLError, ConnectionResetError, BrokenPipeError):
            pass
    return got


def _ctx(daemon, cert: Path | None, key: Path | None, version: ssl.TLSVersion) -> ssl.SSLContext:
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    ctx.load_verify_locations(str(daemon.pki.ca_cert))
    ctx.minimum_version = ctx.maximum_version = version
    if cert is not None:
        ctx.load_cert_chain(str(cert), str(key))
    return ctx


VERSIONS = [ssl.TLSVersion.TLSv1_2, ssl.TLSVersion.TLSv1_3]


@pytest.mark.parametrize("version", VERSIONS, ids=["tls1.2", "tls1.3"])
def test_control_a_registered_client_gets_through(daemon, version):
    cert, key = daemon.cert_of("alice")
    assert _attempt(daemon, _ctx(daemon, cert, key, version)).startswith(b"HTTP/1.1 200")


@pytest.mark.parametrize("version", VERSIONS, ids=["tls1.2", "tls1.3"])
def test_client_without_certificate_fails_the_handshake(daemon, version):
    assert _attempt(daemon, _ctx(daemon, None, None, version)) == b""


@pytest.mark.parametrize("version", VERSIONS, ids=["tls1.2", "tls1.3"])
def test_client_with_certificate_of_another_ca_fails_the_handshake(daemon, version):
    other = daemon.team.other_pki.pki
    assert _attempt(daemon, _ctx(daemon, other.cert_path_for("alice"), other.key_path_for("alice"), version)) == b""


@pytest.mark.parametrize("version", VERSIONS, ids=["tls1.2", "tls1.3"])
def test_client_with_revoked_certificate_fails_the_handshake(daemon, version):
    cert, key = daemon.cert_of("mallory")  # registered in the registry, revoked in the CRL
    assert _attempt(daemon, _ctx(daemon, cert, key, version)) == b""
    assert "mallory" not in daemon.cli("audit", "--manager", "mallory").stdout


def _s_client(daemon, *extra: str) -> subprocess.CompletedProcess:
    openssl = require("openssl")["openssl"]
    cert, key = daemon.cert_of("alice")
    return subprocess.run(
        [openssl, "s_client", "-connect", f"127.0.0.1:{daemon.port}", "-CAfile", str(daemon.pki.ca_cert),
         "-cert", str(cert), "-key", str(key), "-brief", *extra],
        stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=15,
    )


@pytest.mark.openssl
def test_openssl_control_strict_offer_succeeds(daemon):
    r = _s_client(daemon, "-tls1_2")
    assert r.returncode == 0, r.stderr
    assert "ECDHE" in r.stderr and ("GCM" in r.stderr or "CHACHA20" in r.stderr)


@pytest.mark.openssl
@pytest.mark.parametrize(
    "offer",
    [
        ("-tls1_2", "-cipher", "AES128-SHA"),
        ("-tls1_2", "-cipher", "ECDHE-RSA-AES128-SHA:ECDHE-ECDSA-AES128-SHA"),
        ("-tls1_2", "-cipher", "AES128-GCM-SHA256"),  # static RSA key exchange, no forward secrecy
        ("-tls1_1", "-cipher", "DEFAULT:@SECLEVEL=0"),
        ("-tls1", "-cipher", "DEFAULT:@SECLEVEL=0"),
    ],
    ids=["AES128-SHA", "ECDHE-CBC-SHA1", "static-RSA-GCM", "TLS1.1", "TLS1.0"],
)
def test_weak_offers_fail_the_handshake(daemon, offer):
    r = _s_client(daemon, *offer)
    assert r.returncode != 0, r.stdout + r.stderr
    assert "CONNECTION ESTABLISHED" not in r.stderr
    err = r.stderr.lower()
    # the offer really left this client (not refused locally) and the server ended it
    assert "no cipher match" not in err and "no ciphers available" not in err, r.stderr
    assert any(s in err for s in ("alert", "handshake failure", "unexpected eof", "unsupported protocol")), r.stderr


# Debian's OpenSSL 3 cannot offer 3DES or RC4 any more (``openssl ciphers DES-CBC3-SHA``
# fails), so those offers are spoken byte for byte with the lead's ClientHello builder.
@pytest.mark.parametrize(
    ("version", "suites"),
    [(0x0303, [0x000A]), (0x0303, [0x0005]), (0x0302, [0xC02B, 0xC02C])],
    ids=["DES-CBC3-SHA", "RC4-SHA", "TLS1.1-strong-suites"],
)
def test_raw_weak_client_hello_gets_an_alert_from_the_daemon(daemon, version, suites):
    with socket.create_connection(("127.0.0.1", daemon.port), timeout=5) as raw:
        raw.sendall(client_hello(version, suites))
        reply = raw.recv(7)
    # No ServerHello: an alert record or, as asyncio's TLS layer does, a plain close
    # (it drops the alert OpenSSL wrote). Either way no handshake takes place.
    assert reply in (b"",) or reply[:1] == b"\x15", f"expected no ServerHello, got {reply!r}"


def test_raw_client_hello_control_gets_a_server_hello(daemon):
    with socket.create_connection(("127.0.0.1", daemon.port), timeout=5) as raw:
        raw.sendall(client_hello(0x0303, [0xC02B]))  # ECDHE-ECDSA-AES128-GCM-SHA256
        reply = raw.recv(6)
    assert reply[:1] == b"\x16" and reply[5:6] == b"\x02"
