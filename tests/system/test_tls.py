"""The shared TLS context factory over real sockets and against the openssl binary."""

from __future__ import annotations

import socket
import ssl
import threading
import time

import pytest

from cryptoros.errors import ConfigError
from cryptoros.tls import STRICT_TLS12_CIPHERS, TLSConfig, client_context, describe_suites, server_context
from tests.support import client_hello, require, run

FS_AEAD_TLS12 = {
    "ECDHE-ECDSA-AES256-GCM-SHA384",
    "ECDHE-RSA-AES256-GCM-SHA384",
    "ECDHE-ECDSA-AES128-GCM-SHA256",
    "ECDHE-RSA-AES128-GCM-SHA256",
    "ECDHE-ECDSA-CHACHA20-POLY1305",
    "ECDHE-RSA-CHACHA20-POLY1305",
}
TLS13 = {"TLS_AES_256_GCM_SHA384", "TLS_CHACHA20_POLY1305_SHA256", "TLS_AES_128_GCM_SHA256"}


class OneShotServer:
    """Accepts one TLS connection on loopback and records how the handshake went."""

    def __init__(self, ctx: ssl.SSLContext) -> None:
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.sock.settimeout(10)
        self.port = self.sock.getsockname()[1]
        self.ctx = ctx
        self.error: Exception | None = None
        self.peer_der: bytes | None = None
        self.cipher: tuple | None = None
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        try:
            conn, _ = self.sock.accept()
            conn.settimeout(10)
            with self.ctx.wrap_socket(conn, server_side=True) as tls:
                self.peer_der = tls.getpeercert(binary_form=True)
                self.cipher = tls.cipher()
                tls.sendall(b"ok")
                tls.recv(1)
        except Exception as exc:  # recorded for the test to assert on
            self.error = exc
        finally:
            self.sock.close()

    def join(self) -> None:
        self.thread.join(timeout=15)
        assert not self.thread.is_alive()


def tls_config(issued, ca, **kw) -> TLSConfig:
    return TLSConfig(ca_file=ca, cert_file=issued.cert_path, key_file=issued.key_path, **kw)


def connect(server: OneShotServer, ctx: ssl.SSLContext) -> bytes:
    with socket.create_connection(("127.0.0.1", server.port), timeout=10) as raw:
        with ctx.wrap_socket(raw, server_hostname="localhost") as tls:
            data = tls.recv(2)
            tls.sendall(b"x")
            return data


@pytest.fixture
def server_cfg(pki):
    return tls_config(pki.issue("authz", kind="server"), pki.ca_cert, crl_file=pki.crl)


def test_mutual_tls_handshake_uses_strict_suites(pki, server_cfg):
    server = OneShotServer(server_context(server_cfg))
    client = pki.issue("robot1")
    assert connect(server, client_context(tls_config(client, pki.ca_cert))) == b"ok"
    server.join()
    assert server.error is None
    assert server.peer_der == ssl.PEM_cert_to_DER_cert(client.cert_path.read_text())
    name, version, _ = server.cipher
    assert version in ("TLSv1.2", "TLSv1.3")
    assert name in FS_AEAD_TLS12 | TLS13


def test_pin_tls12_negotiates_tls12_fs_aead(pki):
    cfg = tls_config(pki.issue("authz", kind="server"), pki.ca_cert, pin_tls12=True)
    server = OneShotServer(server_context(cfg))
    connect(server, client_context(tls_config(pki.issue("robot1"), pki.ca_cert)))
    server.join()
    assert server.error is None
    assert server.cipher[1] == "TLSv1.2"
    assert server.cipher[0] in FS_AEAD_TLS12


def test_suite_list_is_forward_secret_aead_only(server_cfg):
    suites = set(describe_suites(server_context(server_cfg)))
    assert suites == FS_AEAD_TLS12 | TLS13


def test_client_without_certificate_fails_handshake(pki, server_cfg):
    server = OneShotServer(server_context(server_cfg))
    ctx = ssl.create_default_context(cafile=str(pki.ca_cert))
    with pytest.raises((ssl.SSLError, ConnectionError)):
        connect(server, ctx)
    server.join()
    assert isinstance(server.error, ssl.SSLError)
    assert server.peer_der is None


def test_client_of_another_ca_fails_handshake(pki, other_pki, server_cfg):
    server = OneShotServer(server_context(server_cfg))
    intruder = other_pki.issue("robot1")
    # The intruder trusts our CA so that only *our* check of *its* certificate decides.
    ctx = client_context(TLSConfig(ca_file=pki.ca_cert, cert_file=intruder.cert_path, key_file=intruder.key_path))
    with pytest.raises((ssl.SSLError, ConnectionError)):
        connect(server, ctx)
    server.join()
    assert isinstance(server.error, ssl.SSLError)
    assert "certificate" in str(server.error).lower()


def test_revocation_is_checked_by_the_application_and_an_out_of_date_crl_still_revokes(pki, tmp_path):
    """OpenSSL does not check the CRL (it would refuse every peer once the CRL is out of
    date, and a fleet stopped whole 7 days after its CRL was signed): the handshake's
    certificate check does (PeerCertificateCheck, run on every handshake), and an
    out-of-date CRL's serials are still refused (a revocation never lapses)."""
    from cryptoros.errors import TokenError
    from cryptoros.pemfiles import cert_der
    from cryptoros.tls import PeerCertificateCheck

    client, kept = pki.issue("robot1"), pki.issue("robot2")
    server_issued = pki.issue("authz", kind="server")
    crl = pki.expired_crl(tmp_path / "old-crl.pem", client.serial)
    server = OneShotServer(server_context(tls_config(server_issued, pki.ca_cert, crl_file=crl)))
    connect(server, client_context(tls_config(kept, pki.ca_cert)))  # an out-of-date CRL stops nobody else
    server.join()
    assert server.error is None
    check = PeerCertificateCheck(crl)
    assert check.next_update is not None and check.next_update < time.time()
    with pytest.raises(TokenError) as refused:
        check.check(cert_der(client.cert_path))
    assert refused.value.reason == "certificate_revoked"
    check.check(cert_der(kept.cert_path))


def test_missing_or_encrypted_material_is_a_config_error(pki, tmp_path):
    issued = pki.issue("robot1")
    with pytest.raises(ConfigError, match="not found"):
        TLSConfig(ca_file=tmp_path / "nope.pem", cert_file=issued.cert_path, key_file=issued.key_path)
    encrypted = pki.pki.issue("robot2", passphrase=b"correct horse battery staple")
    cfg = TLSConfig(ca_file=pki.ca_cert, cert_file=encrypted.cert_path, key_file=encrypted.key_path)
    with pytest.raises(ConfigError):
        server_context(cfg)
    good = TLSConfig(
        ca_file=pki.ca_cert,
        cert_file=encrypted.cert_path,
        key_file=encrypted.key_path,
        key_passphrase=b"correct horse battery staple",
    )
    assert server_context(good).verify_mode == ssl.CERT_REQUIRED


@pytest.mark.parametrize(
    "offer",
    [
        # @SECLEVEL=0 makes the openssl client really offer what its defaults forbid.
        ["-tls1_2", "-cipher", "AES128-SHA@SECLEVEL=0"],
        ["-tls1_2", "-cipher", "ECDHE-ECDSA-AES128-SHA@SECLEVEL=0"],
        ["-tls1_1", "-cipher", "DEFAULT@SECLEVEL=0"],
    ],
    ids=["AES128-SHA", "ECDHE-CBC-SHA1", "TLS1.1"],
)
def test_weak_offers_fail_handshake_with_openssl(pki, server_cfg, offer):
    openssl = require("openssl")["openssl"]
    server = OneShotServer(server_context(server_cfg))
    client = pki.issue("robot1")
    result = run(
        [openssl, "s_client", "-connect", f"127.0.0.1:{server.port}", "-CAfile", str(pki.ca_cert),
         "-cert", str(client.cert_path), "-key", str(client.key_path), *offer],
        input="", timeout=20,
    )
    server.join()
    assert result.returncode != 0
    # The offer reached our server and our server refused it.
    assert isinstance(server.error, ssl.SSLError), server.error
    assert server.cipher is None


def test_strict_string_excludes_what_the_paper_excludes():
    for token in ("!LOW", "!EXPORT", "!MD5", "!aNULL", "!ADH", "!AECDH", "!DES", "!eNULL", "!RC2", "!RC4"):
        assert token in STRICT_TLS12_CIPHERS


@pytest.mark.parametrize(
    ("version", "suites"),
    [
        (0x0303, [0x000A]),  # TLS_RSA_WITH_3DES_EDE_CBC_SHA (DES-CBC3-SHA)
        (0x0303, [0x0005]),  # TLS_RSA_WITH_RC4_128_SHA
        (0x0303, [0x002F, 0x0035]),  # AES128-SHA, AES256-SHA (static RSA, CBC)
        (0x0303, [0x009C]),  # AES128-GCM-SHA256: AEAD but no forward secrecy
        (0x0302, [0xC02B, 0xC02F]),  # TLS 1.1 offering strong suites
    ],
    ids=["DES-CBC3-SHA", "RC4-SHA", "AES-CBC-SHA", "RSA-kx-GCM", "TLS1.1"],
)
def test_weak_raw_client_hello_gets_an_alert(server_cfg, version, suites):
    server = OneShotServer(server_context(server_cfg))
    with socket.create_connection(("127.0.0.1", server.port), timeout=10) as raw:
        raw.sendall(client_hello(version, suites))
        reply = raw.recv(7)
    server.join()
    assert reply[:1] == b"\x15", f"expected a TLS alert record, got {reply!r}"  # alert, no ServerHello
    assert isinstance(server.error, ssl.SSLError)
    assert server.cipher is None


def test_raw_client_hello_with_a_strict_suite_gets_a_server_hello(server_cfg):
    """The hand-built hello is valid: offered a suite we allow, the server answers."""
    server = OneShotServer(server_context(server_cfg))
    with socket.create_connection(("127.0.0.1", server.port), timeout=10) as raw:
        raw.sendall(client_hello(0x0303, [0xC02B]))  # ECDHE-ECDSA-AES128-GCM-SHA256
        reply = raw.recv(6)
    server.join()
    assert reply[:1] == b"\x16" and reply[5:6] == b"\x02"  # handshake record, ServerHello
