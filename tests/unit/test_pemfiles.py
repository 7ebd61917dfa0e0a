"""cryptoros.pemfiles: certificate, key, CRL and CSR files (PEM or DER) and fingerprints."""

from __future__ import annotations

import base64
import hashlib
from pathlib import Path

import pytest
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec

from cryptoros import pemfiles
from cryptoros.errors import CryptorosError, PKIError


def test_certificate_pem_and_der_and_fingerprints(pki, tmp_path: Path):
    issued = pki.issue("mng1")
    cert = pemfiles.load_certificate(issued.cert_path)
    der = cert.public_bytes(serialization.Encoding.DER)
    (tmp_path / "c.der").write_bytes(der)
    assert pemfiles.load_certificate(tmp_path / "c.der") == cert
    assert pemfiles.cert_der(issued.cert_path) == der
    assert pemfiles.cert_serial(der) == cert.serial_number
    assert pemfiles.cert_fingerprint_sha256(der) == hashlib.sha256(der).hexdigest() == issued.fingerprint_sha256
    thumb = pemfiles.cert_thumbprint_s256(der)
    assert base64.urlsafe_b64decode(thumb + "=" * (-len(thumb) % 4)) == hashlib.sha256(der).digest()


def test_bad_files_name_the_file(tmp_path: Path):
    junk = tmp_path / "junk.pem"
    junk.write_bytes(b"-----BEGIN CERTIFICATE-----\nnope\n-----END CERTIFICATE-----\n")
    for load in (pemfiles.load_certificate, pemfiles.load_crl, pemfiles.load_csr):
        with pytest.raises(PKIError, match="junk.pem"):
            load(junk)
        with pytest.raises(PKIError, match="cannot read"):
            load(tmp_path / "missing")
    with pytest.raises(PKIError, match="junk.pem is not a private key"):
        pemfiles.load_private_key(junk, None)


def test_wrong_passphrase_is_its_own_error_naming_the_file(tmp_path: Path):
    key = ec.generate_private_key(ec.SECP256R1())
    path = tmp_path / "k.pem"
    path.write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                       serialization.BestAvailableEncryption(b"right")))
    assert pemfiles.key_is_encrypted(path)
    assert pemfiles.load_private_key(path, b"right").private_numbers() == key.private_numbers()
    assert pemfiles.load_private_key(path, "right").private_numbers() == key.private_numbers()
    with pytest.raises(pemfiles.WrongPassphrase, match=r"k\.pem.*wrong passphrase") as info:
        pemfiles.load_private_key(path, b"wrong")
    assert isinstance(info.value, PKIError) and isinstance(info.value, CryptorosError)
    assert info.value.path == str(path)
    with pytest.raises(pemfiles.WrongPassphrase, match="passphrase is required"):
        pemfiles.load_private_key(path, None)


def test_crl_and_csr(pki):
    pki.issue("mng1")
    crl_path = pki.revoke("mng1")
    crl = pemfiles.load_crl(crl_path)
    assert len(list(crl)) == 1
    assert pemfiles.parse_crl(crl.public_bytes(serialization.Encoding.DER)) == crl
