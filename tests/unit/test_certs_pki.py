"""The certs.pki library API and the pki / other_pki fixtures other tests rely on."""

from __future__ import annotations

import dataclasses
import datetime as dt
import hashlib
import ipaddress
import json
import os
import socket
import ssl
import stat
import threading
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.x509 import verification

from certs.pki import (
    KEY_TYPES,
    KINDS,
    PKI,
    cert_fingerprint_sha256,
    load_certificate,
    load_private_key,
    manager_identity_uri,
    request,
)
from cryptoros.errors import CryptorosError, PKIError


def test_constants_and_identity_uri():
    assert KEY_TYPES == ("ec-p256", "rsa2048", "rsa3072")
    assert KINDS == ("manager", "interceptor", "server", "master")
    assert manager_identity_uri("robots.example", "mng1") == "spiffe://robots.example/manager/mng1"
    assert issubclass(PKIError, CryptorosError)


def test_fixture_issue_and_fingerprint(pki):
    out = pki.issue("mng1")
    assert out.name == "mng1" and out.key_path is not None
    cert = load_certificate(out.cert_path)
    der = cert.public_bytes(serialization.Encoding.DER)
    assert out.fingerprint_sha256 == hashlib.sha256(der).hexdigest() == cert_fingerprint_sha256(out.cert_path)
    assert out.serial == cert.serial_number
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert san.get_values_for_type(x509.IPAddress) == [ipaddress.ip_address("127.0.0.1")]
    assert san.get_values_for_type(x509.DNSName) == ["localhost"]
    assert stat.S_IMODE(out.key_path.stat().st_mode) == 0o600
    load_private_key(out.key_path, None)  # the fixture's keys are not encrypted
    with pytest.raises(dataclasses.FrozenInstanceError):
        out.name = "other"  # type: ignore[misc]


def test_fixture_revoke_rewrites_crl(pki):
    a, b = pki.issue("a"), pki.issue("b")
    crl_path = pki.revoke("a")
    assert crl_path == pki.crl
    crl = x509.load_pem_x509_crl(crl_path.read_bytes())
    assert crl.get_revoked_certificate_by_serial_number(a.serial) is not None
    assert crl.get_revoked_certificate_by_serial_number(b.serial) is None
    status = {r.name: r.status for r in pki.pki.list()}
    assert status == {"a": "revoked", "b": "valid"}
    with pytest.raises(PKIError, match="revoked"):
        pki.pki.verify(a.cert_path)
    pki.pki.verify(b.cert_path)


def test_other_pki_is_unrelated(pki, other_pki):
    mine, theirs = pki.issue("mng1"), other_pki.issue("mng1")
    with pytest.raises(PKIError, match="not issued by this CA"):
        pki.pki.verify(theirs.cert_path)
    other_pki.pki.verify(theirs.cert_path)
    assert mine.fingerprint_sha256 != theirs.fingerprint_sha256
    assert pki.ca_cert.read_bytes() != other_pki.ca_cert.read_bytes()


def test_encrypted_ca_and_keys(tmp_path: Path):
    PKI.init(tmp_path / "p", passphrase=b"ca-pass", trust_domain="t.example")
    with pytest.raises(PKIError, match="passphrase"):
        PKI.init(tmp_path / "q")  # neither a passphrase nor unsafe_no_passphrase
    with pytest.raises(PKIError, match="exists"):
        PKI.init(tmp_path / "p", unsafe_no_passphrase=True)
    with pytest.raises(PKIError, match="wrong passphrase"):
        PKI.open(tmp_path / "p", passphrase=b"nope").issue("x", unsafe_no_passphrase=True)
    with pytest.raises(PKIError, match="passphrase is required"):
        PKI.open(tmp_path / "p").issue("x", unsafe_no_passphrase=True)
    assert not (tmp_path / "p" / "issued" / "x.crt").exists()
    ca = PKI.open(tmp_path / "p", passphrase=b"ca-pass")
    assert ca.trust_domain == "t.example"
    out = ca.issue("x", kind="server", key_type="rsa2048", passphrase=b"leaf")
    assert isinstance(load_private_key(out.key_path, b"leaf").key_size, int)
    with pytest.raises(PKIError):
        load_private_key(out.key_path, b"bad")
    with pytest.raises(PKIError):
        load_private_key(out.key_path, None)
    index = json.loads((tmp_path / "p" / "index.json").read_text())
    rec = index["certificates"][0]
    assert set(rec) >= {"serial", "name", "kind", "fingerprint", "not_after", "status", "revoked_at", "reason"}
    assert rec["kind"] == "server" and rec["fingerprint"] == out.fingerprint_sha256


def test_request_and_sign_csr_api(pki, tmp_path: Path):
    key_path, csr_path = request("rob1", tmp_path / "robot", passphrase=b"pw", sans=("IP:127.0.0.5",))
    out = pki.pki.sign_csr(csr_path, kind="interceptor")
    assert out.key_path is None and out.name == "rob1"
    cert = load_certificate(out.cert_path)
    assert cert.public_key() == load_private_key(key_path, b"pw").public_key()
    revoked_serial = pki.pki.revoke(out.serial)  # by int serial
    assert revoked_serial == out.serial
    with pytest.raises(PKIError, match="already revoked"):
        pki.pki.revoke("rob1")
    with pytest.raises(PKIError, match="no certificate"):
        pki.pki.revoke("nobody")


def test_days_are_capped_by_the_ca(tmp_path: Path):
    ca = PKI.init(tmp_path / "p", days=10, unsafe_no_passphrase=True)
    out = ca.issue("long", days=365, unsafe_no_passphrase=True)
    assert load_certificate(out.cert_path).not_valid_after_utc <= ca.ca_cert.not_valid_after_utc


def test_strict_webpki_verifier_accepts_client_and_server_certs(pki):
    """cryptography's RFC 5280 / CABF verifier (stricter than OpenSSL) accepts our certs."""
    out = pki.issue("icp1", kind="interceptor", sans=("IP:127.0.0.2",))
    store = verification.Store([load_certificate(pki.ca_cert)])
    leaf = load_certificate(out.cert_path)
    builder = verification.PolicyBuilder().store(store).time(dt.datetime.now(dt.timezone.utc))
    client = builder.build_client_verifier().verify(leaf, [])
    assert x509.UniformResourceIdentifier("spiffe://cryptoros.local/interceptor/icp1") in client.subjects
    builder.build_server_verifier(verification.IPAddress(ipaddress.ip_address("127.0.0.2"))).verify(leaf, [])


def test_mutual_tls_handshake_on_loopback(pki, other_pki):
    """Python's ssl (OpenSSL) completes mutual TLS with our certs, and refuses a foreign CA."""
    server_id = pki.issue("icp1", kind="interceptor", sans=("IP:127.0.0.1",))
    client_id = pki.issue("mng1", kind="manager")
    stranger = other_pki.issue("mng1", kind="manager")

    def server_ctx() -> ssl.SSLContext:
        ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        ctx.minimum_version = ssl.TLSVersion.TLSv1_2
        ctx.load_cert_chain(server_id.cert_path, server_id.key_path)
        ctx.load_verify_locations(pki.ca_cert)
        ctx.verify_mode = ssl.CERT_REQUIRED
        return ctx

    def client_ctx(identity) -> ssl.SSLContext:
        ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
        ctx.minimum_version = ssl.TLSVersion.TLSv1_2
        ctx.load_verify_locations(pki.ca_cert)
        ctx.load_cert_chain(identity.cert_path, identity.key_path)
        return ctx

    def handshake(identity) -> tuple[bool, object]:
        result: dict = {}
        with socket.create_server(("127.0.0.1", 0)) as listener:
            listener.settimeout(5)
            port = listener.getsockname()[1]

            def serve() -> None:
                try:
                    conn, _ = listener.accept()
                    conn.settimeout(5)
                    with server_ctx().wrap_socket(conn, server_side=True) as tls:
                        result["peer"] = tls.getpeercert()
                        tls.sendall(b"ok")
                except (ssl.SSLError, OSError) as err:
                    result["error"] = err

            t = threading.Thread(target=serve, daemon=True)
            t.start()
            try:
                with socket.create_connection(("127.0.0.1", port), timeout=5) as raw:
                    with client_ctx(identity).wrap_socket(raw, server_hostname="127.0.0.1") as tls:
                        tls.recv(2)
            except (ssl.SSLError, OSError):
                pass
            t.join(timeout=5)
        return "peer" in result, result.get("peer") or result.get("error")

    accepted, peer = handshake(client_id)
    assert accepted, peer
    assert ("URI", "spiffe://cryptoros.local/manager/mng1") in peer["subjectAltName"]
    accepted, err = handshake(stranger)
    assert not accepted, err


def test_a_renewal_stopped_before_its_files_are_in_place_leaves_the_new_serial_listed_and_revocable(tmp_path,
                                                                                                   monkeypatch):
    """CLI audit: a renew killed between its file moves left a certificate the CA had
    signed in a temporary file that no index listed, so `revoke` could not name it. The
    index is now written before the files."""
    from certs import files

    pki = PKI.init(tmp_path / "pki", unsafe_no_passphrase=True)
    pki.issue("robot_k", unsafe_no_passphrase=True)
    serials_before = {r.serial for r in pki.list()}

    commit = files.FileSet.commit

    def killed(self) -> None:  # as if SIGKILL came before the key and certificate moved in
        if any(final.suffix == ".key" for _tmp, final in self.staged):
            raise KeyboardInterrupt
        commit(self)

    monkeypatch.setattr(files.FileSet, "commit", killed)
    with pytest.raises(KeyboardInterrupt):
        pki.renew("robot_k", unsafe_no_passphrase=True)
    monkeypatch.undo()
    new = {r.serial for r in PKI.open(tmp_path / "pki").list()} - serials_before
    assert len(new) == 1, "the signed certificate is not in the index"
    PKI.open(tmp_path / "pki").revoke(new.pop())  # and revocable by its serial


def _crl_serials(pki: PKI) -> set[int]:
    return {e.serial_number for e in x509.load_pem_x509_crl(pki.crl_path.read_bytes())}


def test_a_revoke_stopped_before_its_index_write_leaves_the_certificate_refused(tmp_path, monkeypatch):
    """Audit: revoke wrote the index, then the CRL; a stop in between left a certificate
    the index called revoked that every interceptor still accepted. The CRL comes first
    now: a stop before the index leaves it refused, and repeating the revoke finishes it."""
    import certs.pki as pkimod

    pki = PKI.init(tmp_path / "pki", unsafe_no_passphrase=True)
    lost = pki.issue("lost", unsafe_no_passphrase=True)
    write_file = pkimod.write_file

    def killed_at_index(path, data, **kw):  # as if SIGKILL came before the index was written
        if Path(path).name == "index.json":
            raise KeyboardInterrupt
        return write_file(path, data, **kw)

    monkeypatch.setattr(pkimod, "write_file", killed_at_index)
    with pytest.raises(KeyboardInterrupt):
        pki.revoke("lost", reason="key_compromise")
    monkeypatch.undo()
    pki = PKI.open(tmp_path / "pki")
    with pytest.raises(PKIError, match="revoked"):
        pki.verify(lost.cert_path)
    assert [r.status for r in pki.list()] == ["valid"]
    assert any("revoke 0x" in line for line in pki.crl_disagreements())
    assert pki.revoke("lost", reason="key_compromise") == lost.serial  # finishes it
    assert [(r.status, r.reason) for r in pki.list()] == [("revoked", "key_compromise")]
    assert pki.crl_disagreements() == []


def test_a_crl_signed_later_keeps_what_a_half_finished_revoke_put_in_it(tmp_path, monkeypatch):
    """A CRL listing a serial the index calls valid (a revoke stopped half-way) is never
    re-signed without it: `crl` records the revocation instead of undoing it."""
    import certs.pki as pkimod

    pki = PKI.init(tmp_path / "pki", unsafe_no_passphrase=True)
    lost = pki.issue("lost", unsafe_no_passphrase=True)
    write_file = pkimod.write_file
    monkeypatch.setattr(pkimod, "write_file", lambda path, data, **kw: (
        (_ for _ in ()).throw(KeyboardInterrupt) if Path(path).name == "index.json" else write_file(path, data, **kw)))
    with pytest.raises(KeyboardInterrupt):
        pki.revoke("lost", reason="superseded")
    monkeypatch.undo()
    pki.write_crl()
    assert lost.serial in _crl_serials(pki)
    assert [(r.status, r.reason) for r in pki.list()] == [("revoked", "superseded")]


def test_revoking_what_the_index_calls_revoked_but_the_crl_lacks_re_signs_the_crl(pki):
    """Audit: a retried revoke said 'already revoked' while the CRL lacked the serial."""
    lost = pki.issue("lost")
    before = pki.crl.read_bytes()
    pki.pki.revoke("lost")
    pki.crl.write_bytes(before)  # the CRL of before the revoke, as if its write had failed
    assert lost.serial not in _crl_serials(pki.pki)
    assert len(pki.pki.crl_disagreements()) == 1
    assert pki.pki.revoke("lost") == lost.serial
    assert lost.serial in _crl_serials(pki.pki)
    assert pki.pki.crl_disagreements() == []
    with pytest.raises(PKIError, match="already revoked"):
        pki.pki.revoke("lost")  # both say so now


@pytest.mark.parametrize("stop_after", [0, 1, 2, 3])
def test_init_force_stopped_while_moving_files_leaves_one_whole_ca(tmp_path, monkeypatch, stop_after):
    """Audit: a killed `init --force` left a ca.key of the new CA beside the old ca.crt
    (the old key gone). Whatever move it stops at, the next open has one whole CA,
    and the replaced one is kept as *.old."""
    from certs import files

    d = tmp_path / "pki"
    old = PKI.init(d, unsafe_no_passphrase=True)
    old_crt = old.ca_cert_path.read_bytes()
    replace, moves = os.replace, []

    def killed(src, dst, *a, **kw):  # as if SIGKILL came after `stop_after` of the CA's files moved
        if Path(dst).name in ("ca.crt", "ca.key", "index.json", "crl.pem"):
            if len(moves) == stop_after:
                raise KeyboardInterrupt
            moves.append(dst)
        return replace(src, dst, *a, **kw)

    monkeypatch.setattr(files.os, "replace", killed)
    with pytest.raises(KeyboardInterrupt):
        PKI.init(d, unsafe_no_passphrase=True, force=True)
    monkeypatch.undo()
    pki = PKI.open(d)
    pki.unlock()  # the key belongs to the certificate
    crl = x509.load_pem_x509_crl(pki.crl_path.read_bytes())
    assert crl.is_signature_valid(pki.ca_cert.public_key())
    assert pki.ca_cert_path.read_bytes() != old_crt  # past the point of no return: the new CA
    assert (d / "ca.crt.old").read_bytes() == old_crt and (d / "private" / "ca.key.old").exists()
    assert not (d / ".init.ready").exists()


def test_init_force_stopped_before_it_commits_keeps_the_old_ca(tmp_path, monkeypatch):
    from certs import files

    d = tmp_path / "pki"
    old = PKI.init(d, unsafe_no_passphrase=True)
    old_crt = old.ca_cert_path.read_bytes()
    monkeypatch.setattr(files.os, "rename", lambda *a: (_ for _ in ()).throw(KeyboardInterrupt))
    with pytest.raises(KeyboardInterrupt):
        PKI.init(d, unsafe_no_passphrase=True, force=True)
    monkeypatch.undo()
    pki = PKI.open(d)
    pki.unlock()
    assert pki.ca_cert_path.read_bytes() == old_crt
    PKI.init(d, unsafe_no_passphrase=True, force=True)  # the staging left behind is no obstacle
    assert not (d / ".init.new").exists()


@pytest.mark.parametrize("text", ["[]", '{"certificates": {}}', '{"certificates": [1]}', '"x"',
                                  '{"certificates": [], "crl_number": "2"}'])
def test_an_index_of_the_wrong_shape_is_one_pki_error_naming_it(pki, text):
    """Audit: `echo '[]' > index.json` gave an AttributeError traceback."""
    pki.pki.index_path.write_text(text)
    with pytest.raises(PKIError, match="index.json is not a cryptoros index"):
        PKI.open(pki.directory).list()


@pytest.mark.parametrize("rdns", [
    [x509.RelativeDistinguishedName([x509.NameAttribute(x509.oid.NameOID.COMMON_NAME, "a1"),
                                     x509.NameAttribute(x509.oid.NameOID.COMMON_NAME, "a2")])],
    [x509.RelativeDistinguishedName([x509.NameAttribute(x509.oid.NameOID.COMMON_NAME, "a1")]),
     x509.RelativeDistinguishedName([x509.NameAttribute(x509.oid.NameOID.COMMON_NAME, "a2")])],
], ids=["multi-valued-rdn", "two-cns"])
def test_a_csr_with_an_ambiguous_common_name_is_refused(pki, tmp_path, rdns):
    """Audit: CN=a1+CN=a2 (or two CNs) was signed silently as a1."""
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec

    key = ec.generate_private_key(ec.SECP256R1())
    csr = x509.CertificateSigningRequestBuilder().subject_name(x509.Name(rdns)).sign(key, hashes.SHA256())
    path = tmp_path / "amb.csr"
    path.write_bytes(csr.public_bytes(serialization.Encoding.PEM))
    with pytest.raises(PKIError, match="common name|multi-valued"):
        pki.pki.sign_csr(path)
    assert pki.pki.list() == []
    assert pki.pki.sign_csr(path, name="a1").name == "a1"  # a name given explicitly is no guess


def test_taking_the_lock_removes_only_stale_temp_files_of_our_pattern(pki):
    """Audit: temporary files of killed runs (0600 private-key copies among them) stayed."""
    d = pki.directory
    stale = [d / ".crl.pem.k2j_x9aa.tmp", d / "private" / ".rb.key.abcd1234.tmp"]
    kept = [d / ".crl.pem.keep", d / "private" / "rb.key.abcd1234.tmp", d / "notes.tmp",
            d / "private" / ".rb.key.abcd12345.tmp"]
    fresh = d / "issued" / ".x.crt.zzzzzzzz.tmp"  # changed after this process started
    for path in [*stale, *kept, fresh]:
        path.write_text("x")
    for path in [*stale, *kept]:
        os.utime(path, (1_000_000_000, 1_000_000_000))
    pki.pki.write_crl()
    assert [p for p in stale if p.exists()] == []
    assert all(p.exists() for p in [*kept, fresh])
