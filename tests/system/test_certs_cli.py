"""cryptoros-certs run as a real subprocess: every verb, passphrases, --force, bad input."""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.hazmat.primitives.asymmetric import ec, rsa
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from certs.pki import PKIError, load_private_key
from tests.support import run, script

TD = "robots.example"


def certs(*args, input: str | None = None, env: dict | None = None, cwd: Path | None = None):
    full_env = {k: v for k, v in os.environ.items() if not k.startswith("CRYPTOROS_")}
    full_env.update(env or {})
    return run([script("cryptoros-certs"), *map(str, args)], input=input if input is not None else "",
               env=full_env, cwd=cwd, timeout=30)


def ok(*args, **kw):
    r = certs(*args, **kw)
    assert r.returncode == 0, f"{args}: exit {r.returncode}\n{r.stdout}\n{r.stderr}"
    return r


def assert_bad_input(r, *needles: str, prompts: int = 0) -> None:
    """Exit status 2, exactly one line on stderr (after any prompts), no traceback."""
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert all("assphrase" in line for line in lines[:prompts]), r.stderr
    lines = lines[prompts:]
    assert len(lines) == 1, r.stderr
    assert "Traceback" not in r.stderr
    assert lines[0].startswith("cryptoros-certs: error:")
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


def load_cert(path: Path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


def no_temp_files(directory: Path) -> bool:
    return not [p for p in directory.rglob("*.tmp")]


def snapshot(directory: Path) -> dict[str, bytes]:
    return {str(p.relative_to(directory)): p.read_bytes() for p in sorted(directory.rglob("*")) if p.is_file() and p.name != ".lock"}


@pytest.fixture
def ca(tmp_path: Path) -> Path:
    d = tmp_path / "pki"
    ok("init", "--dir", d, "--trust-domain", TD, "--unsafe-no-passphrase")
    return d


@pytest.fixture
def pwfile(tmp_path: Path) -> Path:
    p = tmp_path / "pass.txt"
    p.write_text("correct horse\n")
    return p


# ----------------------------------------------------------------- init


def test_init_writes_ca_layout_and_empty_crl(ca: Path):
    for rel in ("ca.crt", "private/ca.key", "crl.pem", "index.json", "issued", "csr"):
        assert (ca / rel).exists(), rel
    assert stat.S_IMODE((ca / "private" / "ca.key").stat().st_mode) == 0o600
    cert = load_cert(ca / "ca.crt")
    bc = cert.extensions.get_extension_for_class(x509.BasicConstraints)
    assert bc.critical and bc.value.ca
    ku = cert.extensions.get_extension_for_class(x509.KeyUsage)
    assert ku.critical and ku.value.key_cert_sign and ku.value.crl_sign
    crl = x509.load_pem_x509_crl((ca / "crl.pem").read_bytes())
    assert len(list(crl)) == 0 and crl.is_signature_valid(cert.public_key())
    index = json.loads((ca / "index.json").read_text())
    assert index["trust_domain"] == TD and index["certificates"] == []


def test_init_refuses_to_overwrite_without_force(ca: Path):
    before = (ca / "ca.crt").read_bytes()
    assert_bad_input(certs("init", "--dir", ca, "--unsafe-no-passphrase"), "exists", "--force")
    assert (ca / "ca.crt").read_bytes() == before
    ok("init", "--dir", ca, "--unsafe-no-passphrase", "--force")
    assert (ca / "ca.crt").read_bytes() != before


@pytest.mark.parametrize("key_type,cls,size", [("rsa3072", rsa.RSAPublicKey, 3072), ("ec-p256", ec.EllipticCurvePublicKey, 256)])
def test_init_key_types(tmp_path: Path, key_type, cls, size):
    ok("init", "--dir", tmp_path / "p", "--key-type", key_type, "--unsafe-no-passphrase")
    key = load_cert(tmp_path / "p" / "ca.crt").public_key()
    assert isinstance(key, cls) and key.key_size == size


# ----------------------------------------------------------------- issue


def test_issue_manager_has_v3_extensions_and_identity_uri(ca: Path, pwfile: Path):
    r = ok("issue", "mng1", "--dir", ca, "--kind", "manager", "--passphrase-file", pwfile)
    assert "issued/mng1.crt" in r.stdout
    cert = load_cert(ca / "issued" / "mng1.crt")
    ext = cert.extensions
    bc = ext.get_extension_for_class(x509.BasicConstraints)
    assert bc.critical and bc.value.ca is False
    ku = ext.get_extension_for_class(x509.KeyUsage)
    assert ku.critical and ku.value.digital_signature and not ku.value.key_cert_sign
    eku = ext.get_extension_for_class(x509.ExtendedKeyUsage).value
    assert set(eku) == {ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH}
    san = ext.get_extension_for_class(x509.SubjectAlternativeName).value
    assert san.get_values_for_type(x509.UniformResourceIdentifier) == [f"spiffe://{TD}/manager/mng1"]
    assert san.get_values_for_type(x509.DNSName) == ["mng1"]
    assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == "mng1"
    assert cert.issuer == load_cert(ca / "ca.crt").subject
    key_path = ca / "private" / "mng1.key"
    assert stat.S_IMODE(key_path.stat().st_mode) == 0o600
    assert b"ENCRYPTED PRIVATE KEY" in key_path.read_bytes()
    key = load_private_key(key_path, b"correct horse")
    assert key.public_key().public_numbers() == cert.public_key().public_numbers()
    with pytest.raises(PKIError):
        load_private_key(key_path, b"wrong")


def test_issue_interceptor_with_ip_san(ca: Path):
    ok("issue", "icp2", "--dir", ca, "--kind", "interceptor", "--san", "IP:127.0.0.2", "--san", "DNS:localhost",
       "--unsafe-no-passphrase")
    san = load_cert(ca / "issued" / "icp2.crt").extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert [str(a) for a in san.get_values_for_type(x509.IPAddress)] == ["127.0.0.2"]
    assert san.get_values_for_type(x509.DNSName) == ["localhost"]  # --san replaces the default DNS name
    assert san.get_values_for_type(x509.UniformResourceIdentifier) == [f"spiffe://{TD}/interceptor/icp2"]


@pytest.mark.parametrize("kind", ["server", "master"])
def test_issue_other_kinds(ca: Path, kind: str):
    ok("issue", f"{kind}1", "--dir", ca, "--kind", kind, "--unsafe-no-passphrase")
    san = load_cert(ca / "issued" / f"{kind}1.crt").extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert f"spiffe://{TD}/{kind}/{kind}1" in san.get_values_for_type(x509.UniformResourceIdentifier)


def test_issue_rsa2048(ca: Path):
    ok("issue", "r1", "--dir", ca, "--key-type", "rsa2048", "--unsafe-no-passphrase", "--days", "30")
    cert = load_cert(ca / "issued" / "r1.crt")
    assert isinstance(cert.public_key(), rsa.RSAPublicKey) and cert.public_key().key_size == 2048
    assert cert.extensions.get_extension_for_class(x509.KeyUsage).value.key_encipherment
    assert 29 <= (cert.not_valid_after_utc - cert.not_valid_before_utc).days <= 30


def test_issue_force(ca: Path):
    ok("issue", "mng1", "--dir", ca, "--unsafe-no-passphrase")
    before = snapshot(ca)
    assert_bad_input(certs("issue", "mng1", "--dir", ca, "--unsafe-no-passphrase"), "exists", "--force")
    assert snapshot(ca) == before
    ok("issue", "mng1", "--dir", ca, "--unsafe-no-passphrase", "--force")
    assert (ca / "issued" / "mng1.crt").read_bytes() != before["issued/mng1.crt"]
    assert len(json.loads((ca / "index.json").read_text())["certificates"]) == 2


# ----------------------------------------------------------------- passphrases


def test_passphrase_from_env(ca: Path):
    ok("issue", "mng1", "--dir", ca, env={"CRYPTOROS_PASSPHRASE": "from-env"})
    load_private_key(ca / "private" / "mng1.key", b"from-env")


def test_passphrase_from_prompt(ca: Path):
    r = ok("issue", "mng1", "--dir", ca, input="typed in\ntyped in\n")
    assert "Passphrase" in r.stderr
    load_private_key(ca / "private" / "mng1.key", b"typed in")


def test_prompt_mismatch_or_eof_writes_nothing(ca: Path):
    before = snapshot(ca)
    assert_bad_input(certs("issue", "mng1", "--dir", ca, input="one\ntwo\n"), "do not match", prompts=2)
    assert_bad_input(certs("issue", "mng1", "--dir", ca, input=""), "passphrase", prompts=1)
    assert snapshot(ca) == before and no_temp_files(ca)


def test_encrypted_ca_needs_its_passphrase(tmp_path: Path, pwfile: Path):
    d = tmp_path / "pki"
    ok("init", "--dir", d, "--passphrase-file", pwfile)
    assert b"ENCRYPTED PRIVATE KEY" in (d / "private" / "ca.key").read_bytes()
    before = snapshot(d)
    wrong = tmp_path / "wrong.txt"
    wrong.write_text("nope\n")
    assert_bad_input(certs("issue", "a", "--dir", d, "--unsafe-no-passphrase", "--ca-passphrase-file", wrong),
                     "wrong passphrase")
    assert_bad_input(certs("issue", "a", "--dir", d, "--unsafe-no-passphrase",
                           env={"CRYPTOROS_CA_PASSPHRASE": "nope"}), "wrong passphrase")
    assert snapshot(d) == before and no_temp_files(d)
    ok("issue", "a", "--dir", d, "--unsafe-no-passphrase", "--ca-passphrase-file", pwfile)
    ok("issue", "b", "--dir", d, "--unsafe-no-passphrase", env={"CRYPTOROS_CA_PASSPHRASE": "correct horse"})
    # CA passphrase typed at the prompt, then the new key's passphrase twice
    ok("issue", "c", "--dir", d, input="correct horse\nkey pass\nkey pass\n")
    load_private_key(d / "private" / "c.key", b"key pass")
    ok("crl", "--dir", d, "--ca-passphrase-file", pwfile)


# ----------------------------------------------------------------- request + sign


def test_request_then_sign(tmp_path: Path, ca: Path, pwfile: Path):
    robot = tmp_path / "robot"
    ok("request", "mng7", "--out-dir", robot, "--passphrase-file", pwfile, "--san", "IP:127.0.0.7")
    key_path, csr_path = robot / "mng7.key", robot / "mng7.csr"
    assert stat.S_IMODE(key_path.stat().st_mode) == 0o600
    x509.load_pem_x509_csr(csr_path.read_bytes())
    r = ok("sign", csr_path, "--dir", ca, "--kind", "manager")
    assert "key:" not in r.stdout
    cert = load_cert(ca / "issued" / "mng7.crt")
    key = load_private_key(key_path, b"correct horse")
    assert key.public_key().public_numbers() == cert.public_key().public_numbers()
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert [str(a) for a in san.get_values_for_type(x509.IPAddress)] == ["127.0.0.7"]
    assert san.get_values_for_type(x509.UniformResourceIdentifier) == [f"spiffe://{TD}/manager/mng7"]
    assert (ca / "csr" / "mng7.csr").exists()
    assert not (ca / "private" / "mng7.key").exists()
    # again without --force: refused, with --force and another name: fine
    assert_bad_input(certs("sign", csr_path, "--dir", ca), "exists")
    ok("sign", csr_path, "--dir", ca, "--name", "mng8", "--kind", "interceptor", "--san", "IP:127.0.0.8")
    assert_bad_input(certs("request", "mng7", "--out-dir", robot, "--unsafe-no-passphrase"), "exists")


def test_sign_rejects_non_csr(tmp_path: Path, ca: Path):
    junk = tmp_path / "junk.csr"
    junk.write_text("-----BEGIN CERTIFICATE REQUEST-----\nnot base64\n-----END CERTIFICATE REQUEST-----\n")
    before = snapshot(ca)
    assert_bad_input(certs("sign", junk, "--dir", ca), "not a certificate signing request")
    assert_bad_input(certs("sign", ca / "ca.crt", "--dir", ca), "not a certificate signing request")
    assert_bad_input(certs("sign", tmp_path / "missing.csr", "--dir", ca), "missing.csr")
    assert snapshot(ca) == before


# ----------------------------------------------------------------- revoke, crl, list, show, verify


def test_revoke_by_name_and_serial_updates_crl(ca: Path):
    ok("issue", "a", "--dir", ca, "--unsafe-no-passphrase")
    ok("issue", "b", "--dir", ca, "--unsafe-no-passphrase")
    ok("issue", "c", "--dir", ca, "--unsafe-no-passphrase")
    ok("revoke", "a", "--dir", ca, "--reason", "key_compromise")
    records = {r["name"]: r for r in json.loads(ok("list", "--dir", ca, "--json").stdout)}
    ok("revoke", format(records["b"]["serial"], "x"), "--dir", ca)  # hex as printed by 'list'
    records = {r["name"]: r for r in json.loads(ok("list", "--dir", ca, "--json").stdout)}
    assert records["a"]["status"] == "revoked" and records["a"]["reason"] == "key_compromise"
    assert records["a"]["revoked_at"]
    assert records["b"]["status"] == "revoked" and records["c"]["status"] == "valid"
    crl = x509.load_pem_x509_crl((ca / "crl.pem").read_bytes())
    assert {e.serial_number for e in crl} == {records["a"]["serial"], records["b"]["serial"]}
    entry = crl.get_revoked_certificate_by_serial_number(records["a"]["serial"])
    assert entry.extensions.get_extension_for_class(x509.CRLReason).value.reason == x509.ReasonFlags.key_compromise
    table = ok("list", "--dir", ca).stdout
    assert "revoked" in table and "valid" in table
    assert_bad_input(certs("revoke", "a", "--dir", ca), "already revoked")
    assert_bad_input(certs("revoke", "nobody", "--dir", ca), "nobody")


def test_crl_verb_increments_number(ca: Path):
    def number() -> int:
        crl = x509.load_pem_x509_crl((ca / "crl.pem").read_bytes())
        return crl.extensions.get_extension_for_class(x509.CRLNumber).value.crl_number

    first = number()
    r = ok("crl", "--dir", ca, "--days", "2")
    assert "revoked: 0" in r.stdout
    assert number() == first + 1
    crl = x509.load_pem_x509_crl((ca / "crl.pem").read_bytes())
    assert 1 <= (crl.next_update_utc - crl.last_update_utc).days <= 2


def test_show_is_readable(ca: Path):
    ok("issue", "icp1", "--dir", ca, "--kind", "interceptor", "--san", "IP:127.0.0.2", "--unsafe-no-passphrase")
    out = ok("show", "icp1", "--dir", ca).stdout
    for needle in ("Version: 3", "Serial Number", "Issuer: O = cryptoros", "Subject: O = cryptoros, OU = interceptor, CN = icp1",
                   "X509v3 Basic Constraints: critical", "CA:FALSE", "X509v3 Key Usage: critical",
                   "TLS Web Server Authentication, TLS Web Client Authentication",
                   f"URI:spiffe://{TD}/interceptor/icp1", "IP Address:127.0.0.2", "SHA256 Fingerprint", "Status: valid"):
        assert needle in out, needle
    assert "CA:TRUE" in ok("show", "ca", "--dir", ca).stdout
    assert "BEGIN CERTIFICATE" in ok("show", ca / "issued" / "icp1.crt", "--pem").stdout
    assert_bad_input(certs("show", "nobody", "--dir", ca), "nobody")


def test_verify(ca: Path, tmp_path: Path):
    ok("issue", "good", "--dir", ca, "--unsafe-no-passphrase")
    ok("issue", "gone", "--dir", ca, "--unsafe-no-passphrase")
    ok("revoke", "gone", "--dir", ca)
    assert "OK" in ok("verify", ca / "issued" / "good.crt", "--dir", ca).stdout
    assert "OK" in ok("verify", "good", "--dir", ca).stdout
    r = certs("verify", "gone", "--dir", ca)
    assert r.returncode == 1 and "revoked" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    other = tmp_path / "other"
    ok("init", "--dir", other, "--unsafe-no-passphrase")
    ok("issue", "good", "--dir", other, "--unsafe-no-passphrase")
    r = certs("verify", other / "issued" / "good.crt", "--dir", ca)
    assert r.returncode == 1 and "not issued by this CA" in r.stderr
    r = certs("verify", other / "issued" / "good.crt", "--ca-file", ca / "ca.crt")
    assert r.returncode == 1
    assert_bad_input(certs("verify", ca / "index.json", "--dir", ca), "not an X.509 certificate")


# ----------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    "args,needle",
    [
        (["issue", "x", "--san", "IP:127.0.0.999"], "bad SAN"),
        (["issue", "x", "--san", "localhost"], "bad SAN"),
        (["issue", "x", "--san", "FOO:bar"], "bad SAN"),
        (["issue", "x", "--san", "DNS:bad host"], "bad SAN"),
        (["issue", "../evil"], "invalid name"),
        (["issue", "ca"], "reserved"),
        (["issue", "x", "--kind", "robot"], "robot"),
        (["issue", "x", "--key-type", "dsa1024"], "dsa1024"),
        (["issue", "x", "--passphrase-file", "/nonexistent/pass"], "/nonexistent/pass"),
        (["issue", "x", "--days", "99999999"], "--days"),  # CLI audit: an OverflowError traceback
        (["revoke", "nobody"], "nobody"),
        (["revoke", "0xdeadbeef"], "0xdeadbeef"),
        (["nosuchverb"], "nosuchverb"),
    ],
)
def test_bad_input_is_one_line_exit_2(ca: Path, args, needle):
    before = snapshot(ca)
    r = certs(*args, "--dir", ca, "--unsafe-no-passphrase") if args[0] == "issue" and "--passphrase-file" not in args \
        else certs(*args, "--dir", ca)
    assert_bad_input(r, needle)
    assert snapshot(ca) == before and no_temp_files(ca)


def test_a_certificate_cut_to_its_cas_end_says_so(tmp_path: Path):
    """CLI audit: `issue --days 365` under a CA that ends tomorrow gave a certificate of
    one day without a word."""
    short = tmp_path / "short"
    ok("init", "--dir", short, "--days", "1", "--unsafe-no-passphrase")
    r = ok("issue", "robot_x", "--dir", short, "--days", "365", "--unsafe-no-passphrase")
    assert "not 365 days: the CA itself ends then" in r.stderr
    r = ok("issue", "robot_y", "--dir", short, "--days", "1", "--unsafe-no-passphrase")
    assert "valid until:" in r.stdout and not r.stderr


def test_not_a_pki_dir(tmp_path: Path):
    assert_bad_input(certs("list", "--dir", tmp_path / "nothing"), "not a PKI directory")
    assert_bad_input(certs("issue", "x", "--dir", tmp_path / "nothing", "--unsafe-no-passphrase"), "not a PKI directory")


def test_passphrase_file_and_unsafe_exclude_each_other(tmp_path: Path, pwfile: Path):
    assert_bad_input(certs("init", "--dir", tmp_path / "p", "--passphrase-file", pwfile, "--unsafe-no-passphrase"),
                     "exclude")
    assert not (tmp_path / "p" / "ca.crt").exists()


def test_revoking_a_name_with_several_valid_certificates_needs_serial_or_all(ca: Path):
    """Day 2: a renewed robot has two valid certificates; revoking by name alone must
    not silently revoke the one in use."""
    ok("issue", "twin", "--dir", ca, "--san", "IP:127.0.0.7", "--unsafe-no-passphrase")
    ok("issue", "twin", "--dir", ca, "--san", "IP:127.0.0.7", "--unsafe-no-passphrase", "--force")
    records = [r for r in json.loads(ok("list", "--dir", ca, "--json").stdout) if r["name"] == "twin"]
    assert len(records) == 2
    old, new = sorted(records, key=lambda r: r["serial"])
    assert_bad_input(certs("revoke", "twin", "--dir", ca), "--serial")
    ok("revoke", "twin", "--dir", ca, "--serial", format(old["serial"], "x"))
    status = {r["serial"]: r["status"] for r in json.loads(ok("list", "--dir", ca, "--json").stdout)}
    assert status[old["serial"]] == "revoked" and status[new["serial"]] == "valid"
    ok("issue", "twin", "--dir", ca, "--san", "IP:127.0.0.7", "--unsafe-no-passphrase", "--force")
    out = ok("revoke", "twin", "--dir", ca, "--all").stdout
    assert out.count("revoked serial") == 2


def test_renew_keeps_kind_and_names_and_prints_the_next_steps(ca: Path, pwfile: Path):
    """Day 2: `renew NAME` gives a new key and certificate with the same kind and IP/DNS
    names; the old certificate stays valid until revoked by the serial the output names;
    `--same-key` re-certifies the current public key without touching the key file."""
    ok("issue", "robot_r", "--dir", ca, "--kind", "interceptor", "--san", "IP:127.0.0.7", "--san", "DNS:robot-r.lan",
       "--unsafe-no-passphrase")
    first = load_cert(ca / "issued" / "robot_r.crt")
    out = ok("renew", "robot_r", "--dir", ca, "--passphrase-file", pwfile).stdout
    second = load_cert(ca / "issued" / "robot_r.crt")
    assert second.serial_number != first.serial_number
    assert second.public_key().public_numbers() != first.public_key().public_numbers()
    assert isinstance(second.public_key(), ec.EllipticCurvePublicKey)  # same key type
    for cert in (first, second):
        assert cert.subject.get_attributes_for_oid(NameOID.ORGANIZATIONAL_UNIT_NAME)[0].value == "interceptor"
    names = second.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert {str(n.value) for n in names if not isinstance(n, x509.UniformResourceIdentifier)} == \
        {"127.0.0.7", "robot-r.lan"}
    key = load_private_key(ca / "private" / "robot_r.key", b"correct horse")  # encrypted with the new passphrase
    assert key.public_key().public_numbers() == second.public_key().public_numbers()
    assert "set-cert robot_r --fingerprint" in out and "--overlap 600" in out and f"--serial {first.serial_number:x}" in out
    status = {r["serial"]: r["status"] for r in json.loads(ok("list", "--dir", ca, "--json").stdout)}
    assert status[first.serial_number] == "valid" and status[second.serial_number] == "valid"
    ok("revoke", "robot_r", "--dir", ca, "--serial", format(first.serial_number, "x"))

    key_before = (ca / "private" / "robot_r.key").read_bytes()
    ok("renew", "robot_r", "--dir", ca, "--same-key", "--days", "30")
    third = load_cert(ca / "issued" / "robot_r.crt")
    assert third.public_key().public_numbers() == second.public_key().public_numbers()
    assert (ca / "private" / "robot_r.key").read_bytes() == key_before
    assert (third.not_valid_after_utc - third.not_valid_before_utc).days <= 31
    assert no_temp_files(ca)


def test_renew_refuses_what_it_cannot_do_in_one_line(ca: Path, pwfile: Path):
    assert_bad_input(certs("renew", "nobody", "--dir", ca, "--unsafe-no-passphrase"), "issue one first")
    ok("issue", "robot_s", "--dir", ca, "--unsafe-no-passphrase")
    before = snapshot(ca)
    assert_bad_input(certs("renew", "robot_s", "--dir", ca, "--same-key", "--passphrase-file", pwfile), "--same-key")
    assert snapshot(ca) == before
    # CLI audit: a key revoked as compromised was certified again by --same-key, and the
    # output called the revoked serial "still valid"
    ok("revoke", "robot_s", "--dir", ca, "--reason", "key_compromise")
    before = snapshot(ca)
    assert_bad_input(certs("renew", "robot_s", "--dir", ca, "--same-key"), "was revoked (key_compromise)")
    assert snapshot(ca) == before
    out = ok("renew", "robot_s", "--dir", ca, "--unsafe-no-passphrase").stdout  # a new key: renewed
    assert "(revoked)" in out and "still valid" not in out and "--overlap" not in out


# ----------------------------------------------------------------- interrupted changes


def test_a_revoke_whose_crl_write_fails_leaves_the_index_untouched_and_names_crl_pem(ca: Path):
    """Audit: the failed CRL write named a temporary file, the index already said
    revoked, a retry said 'already revoked' and verify said OK."""
    ok("issue", "lost", "--dir", ca, "--unsafe-no-passphrase")
    (ca / "crl.pem").rename(ca / "crl.keep")
    (ca / "crl.pem").mkdir()
    r = certs("revoke", "lost", "--dir", ca, "--reason", "key_compromise")
    assert_bad_input(r, f"{ca / 'crl.pem'}")
    assert ".tmp" not in r.stderr
    assert "revoked" not in ok("list", "--dir", ca).stdout
    (ca / "crl.pem").rmdir()
    (ca / "crl.keep").rename(ca / "crl.pem")
    assert "revoked serial" in ok("revoke", "lost", "--dir", ca, "--reason", "key_compromise").stdout
    assert certs("verify", "lost", "--dir", ca).returncode == 1


def test_list_and_verify_warn_when_index_and_crl_disagree_and_revoke_re_signs(ca: Path):
    ok("issue", "lost", "--dir", ca, "--unsafe-no-passphrase")
    before = (ca / "crl.pem").read_bytes()
    ok("revoke", "lost", "--dir", ca)
    (ca / "crl.pem").write_bytes(before)  # the CRL the failed revoke left
    for args in (("list",), ("verify", "lost")):
        r = ok(*args, "--dir", ca)
        assert "warning:" in r.stderr and f"cryptoros-certs crl --dir {ca}" in r.stderr, r.stderr
    r = ok("revoke", "lost", "--dir", ca)
    assert "CRL re-signed" in r.stdout, r.stdout
    assert certs("verify", "lost", "--dir", ca).returncode == 1
    assert ok("list", "--dir", ca).stderr == ""
    assert_bad_input(certs("revoke", "lost", "--dir", ca), "already revoked")


def test_a_ca_key_that_does_not_belong_names_the_fix(ca: Path, tmp_path: Path):
    ok("init", "--dir", tmp_path / "other", "--unsafe-no-passphrase")
    (ca / "private" / "ca.key").write_bytes((tmp_path / "other" / "private" / "ca.key").read_bytes())
    assert_bad_input(certs("crl", "--dir", ca), "does not belong to", "ca.key.old", "init --force")


def test_init_force_keeps_the_replaced_ca_as_old_files(ca: Path):
    before = {rel: (ca / rel).read_bytes() for rel in ("ca.crt", "private/ca.key", "index.json", "crl.pem")}
    ok("init", "--dir", ca, "--unsafe-no-passphrase", "--force")
    for rel, data in before.items():
        assert (ca / f"{rel}.old").read_bytes() == data, rel
        assert (ca / rel).read_bytes() != data, rel
    assert stat.S_IMODE((ca / "private" / "ca.key.old").stat().st_mode) == 0o600
    ok("crl", "--dir", ca)  # the new key signs for the new certificate


def test_an_index_of_the_wrong_shape_is_one_line(ca: Path):
    (ca / "index.json").write_text("[]\n")
    assert_bad_input(certs("list", "--dir", ca), "index.json")


def test_sign_refuses_a_csr_with_two_common_names(ca: Path, tmp_path: Path):
    from cryptography.hazmat.primitives import hashes, serialization

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.RelativeDistinguishedName([x509.NameAttribute(NameOID.COMMON_NAME, "a1"),
                                                      x509.NameAttribute(NameOID.COMMON_NAME, "a2")])])
    csr = x509.CertificateSigningRequestBuilder().subject_name(name).sign(key, hashes.SHA256())
    (tmp_path / "amb.csr").write_bytes(csr.public_bytes(serialization.Encoding.PEM))
    assert_bad_input(certs("sign", tmp_path / "amb.csr", "--dir", ca), "multi-valued")
    assert not (ca / "issued" / "a1.crt").exists()


def test_show_says_when_the_certificate_file_is_a_directory(ca: Path):
    (ca / "issued" / "a1.crt").mkdir()
    assert_bad_input(certs("show", "a1", "--dir", ca), "a1.crt is a directory")
