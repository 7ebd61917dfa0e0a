"""Interop with the real openssl binary: verify, pkey -passin, the paper's CSR, CRLs."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from cryptography import x509

from tests.support import require, run, script

pytestmark = pytest.mark.openssl

PASS = "s3cret pass"


@pytest.fixture
def openssl() -> str:
    return require("openssl")["openssl"]


def certs(*args, env: dict | None = None):
    full_env = {k: v for k, v in os.environ.items() if not k.startswith("CRYPTOROS_")}
    full_env.update(env or {})
    r = run([script("cryptoros-certs"), *map(str, args)], input="", env=full_env, timeout=30)
    assert r.returncode == 0, f"{args}: exit {r.returncode}\n{r.stdout}\n{r.stderr}"
    return r


def ossl(openssl: str, *args, ok: bool = True):
    r = run([openssl, *map(str, args)], input="", timeout=30)
    if ok:
        assert r.returncode == 0, f"openssl {args}: exit {r.returncode}\n{r.stdout}\n{r.stderr}"
    return r


@pytest.fixture
def ca(tmp_path: Path) -> Path:
    d = tmp_path / "pki"
    (tmp_path / "ca-pass").write_text("ca pass\n")
    certs("init", "--dir", d, "--passphrase-file", tmp_path / "ca-pass")
    return d


def ca_env() -> dict:
    return {"CRYPTOROS_CA_PASSPHRASE": "ca pass"}


@pytest.mark.parametrize("kind,key_type", [("manager", "ec-p256"), ("interceptor", "rsa2048"), ("server", "ec-p256"),
                                           ("master", "ec-p256")])
def test_openssl_verify_accepts_our_certs_for_tls_server_and_client(openssl, ca: Path, kind, key_type):
    certs("issue", "n1", "--dir", ca, "--kind", kind, "--key-type", key_type, "--san", "IP:127.0.0.2",
          "--unsafe-no-passphrase", env=ca_env())
    cert = ca / "issued" / "n1.crt"
    for purpose in ("sslserver", "sslclient"):
        r = ossl(openssl, "verify", "-CAfile", ca / "ca.crt", "-purpose", purpose, cert)
        assert f"{cert}: OK" in r.stdout
    # the empty CRL written by init makes CRL checking work from the start
    ossl(openssl, "verify", "-crl_check", "-CRLfile", ca / "crl.pem", "-CAfile", ca / "ca.crt", cert)
    ossl(openssl, "verify", "-CAfile", ca / "ca.crt", "-verify_ip", "127.0.0.2", cert)
    text = ossl(openssl, "x509", "-in", cert, "-noout", "-text").stdout
    assert "X509v3 Basic Constraints: critical" in text and "CA:FALSE" in text
    assert "X509v3 Key Usage: critical" in text
    assert "TLS Web Server Authentication, TLS Web Client Authentication" in text
    assert f"URI:spiffe://cryptoros.local/{kind}/n1" in text and "IP Address:127.0.0.2" in text


def test_openssl_rejects_cert_of_another_ca(openssl, ca: Path, tmp_path: Path):
    other = tmp_path / "other"
    certs("init", "--dir", other, "--unsafe-no-passphrase")
    certs("issue", "mng1", "--dir", other, "--unsafe-no-passphrase")
    r = ossl(openssl, "verify", "-CAfile", ca / "ca.crt", other / "issued" / "mng1.crt", ok=False)
    assert r.returncode != 0


def test_openssl_pkey_opens_our_encrypted_keys(openssl, ca: Path, tmp_path: Path):
    pw = tmp_path / "pw"
    pw.write_text(PASS + "\n")
    certs("issue", "mng1", "--dir", ca, "--passphrase-file", pw, env=ca_env())
    certs("request", "rob1", "--out-dir", tmp_path / "robot", "--key-type", "rsa2048", env={"CRYPTOROS_PASSPHRASE": PASS})
    for key in (ca / "private" / "mng1.key", tmp_path / "robot" / "rob1.key", ca / "private" / "ca.key"):
        passin = "pass:ca pass" if key.name == "ca.key" else f"file:{pw}"
        ossl(openssl, "pkey", "-in", key, "-passin", passin, "-noout")
        assert ossl(openssl, "pkey", "-in", key, "-passin", "pass:wrong", "-noout", ok=False).returncode != 0
    # AES-256 (PBES2): the key file says which cipher protects it
    assert "aes-256-cbc" in ossl(openssl, "asn1parse", "-in", ca / "private" / "mng1.key").stdout
    # and the key openssl decrypts is the certificate's key
    pub_key = ossl(openssl, "pkey", "-in", ca / "private" / "mng1.key", "-passin", f"file:{pw}", "-pubout").stdout
    pub_cert = ossl(openssl, "x509", "-in", ca / "issued" / "mng1.crt", "-noout", "-pubkey").stdout
    assert pub_key == pub_cert


def test_we_sign_the_papers_openssl_csr(openssl, ca: Path, tmp_path: Path):
    # the paper: openssl genrsa -aes256 -out mng.key 2048 ; openssl req -new -key mng.key -out mng.csr
    key, csr = tmp_path / "mng.key", tmp_path / "mng.csr"
    ossl(openssl, "genrsa", "-aes256", "-passout", f"pass:{PASS}", "-out", key, "2048")
    ossl(openssl, "req", "-new", "-key", key, "-passin", f"pass:{PASS}", "-subj", "/CN=mng", "-out", csr)
    r = certs("sign", csr, "--dir", ca, "--kind", "manager", env=ca_env())
    cert = ca / "issued" / "mng.crt"
    assert str(cert) in r.stdout
    ossl(openssl, "verify", "-CAfile", ca / "ca.crt", "-purpose", "sslclient", cert)
    pub_key = ossl(openssl, "pkey", "-in", key, "-passin", f"pass:{PASS}", "-pubout").stdout
    assert pub_key == ossl(openssl, "x509", "-in", cert, "-noout", "-pubkey").stdout
    parsed = x509.load_pem_x509_certificate(cert.read_bytes())
    san = parsed.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert "spiffe://cryptoros.local/manager/mng" in san.get_values_for_type(x509.UniformResourceIdentifier)
    # the key openssl made opens with our loader too
    from certs.pki import load_private_key

    load_private_key(key, PASS.encode())


def test_openssl_csr_with_requested_ip_san(openssl, ca: Path, tmp_path: Path):
    key, csr = tmp_path / "icp.key", tmp_path / "icp.csr"
    ossl(openssl, "req", "-new", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes", "-keyout", key,
         "-subj", "/CN=icp3", "-addext", "subjectAltName=IP:127.0.0.3", "-out", csr)
    certs("sign", csr, "--dir", ca, "--kind", "interceptor", env=ca_env())
    ossl(openssl, "verify", "-CAfile", ca / "ca.crt", "-verify_ip", "127.0.0.3", ca / "issued" / "icp3.crt")


def test_revoked_cert_fails_openssl_crl_check(openssl, ca: Path):
    for name in ("keep", "drop"):
        certs("issue", name, "--dir", ca, "--unsafe-no-passphrase", env=ca_env())
    certs("revoke", "drop", "--dir", ca, "--reason", "key_compromise", env=ca_env())
    args = ["verify", "-crl_check", "-CRLfile", ca / "crl.pem", "-CAfile", ca / "ca.crt"]
    r = ossl(openssl, *args, ca / "issued" / "drop.crt", ok=False)
    assert r.returncode != 0 and "certificate revoked" in r.stdout + r.stderr
    ossl(openssl, *args, ca / "issued" / "keep.crt")
    r = ossl(openssl, "crl", "-in", ca / "crl.pem", "-CAfile", ca / "ca.crt", "-noout", "-text")
    assert "verify OK" in r.stdout + r.stderr and "Key Compromise" in r.stdout
