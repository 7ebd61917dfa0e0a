"""Certificate, key, CRL and CSR files, and certificate fingerprints: one module.

Every part of cryptoros that reads one of these files goes through here, so a bad
file gives the same clear :class:`~cryptoros.errors.PKIError` naming the file
everywhere, and a wrong passphrase is a :class:`WrongPassphrase` (never a bare
``ValueError`` from ``cryptography``). Files may be PEM or DER. ``parse_*`` take bytes
already read (``where`` names them in errors); ``load_*`` read a path first.

Fingerprints of a DER certificate: :func:`cert_fingerprint_sha256` (lowercase hex
SHA-256, the registry's key) and :func:`cert_thumbprint_s256` (RFC 8705
``x5t#S256``: base64url SHA-256 without padding, the token's ``cnf`` binding).
"""

from __future__ import annotations

import base64
import hashlib
import os
import re
from typing import Any

from cryptography import x509
from cryptography.exceptions import UnsupportedAlgorithm
from cryptography.hazmat.primitives import serialization

from cryptoros.files import PEM_LIMIT, read_bounded
from cryptoros.errors import PKIError

__all__ = [
    "WrongPassphrase",
    "cert_der",
    "cert_fingerprint_sha256",
    "cert_serial",
    "cert_thumbprint_s256",
    "key_is_encrypted",
    "load_certificate",
    "load_crl",
    "load_crls",
    "load_csr",
    "load_private_key",
    "parse_certificate",
    "parse_crl",
    "parse_csr",
    "parse_private_key",
]

PathLike = str | os.PathLike


class WrongPassphrase(PKIError):
    """A private key file could not be decrypted: a wrong or missing passphrase."""

    def __init__(self, path: object, detail: str = "wrong passphrase?") -> None:
        super().__init__(f"cannot decrypt key {path}: {detail}")
        self.path = str(path)


def _read(path: PathLike, what: str) -> bytes:
    try:
        return read_bounded(path, PEM_LIMIT)
    except OSError as err:
        raise PKIError(f"cannot read {what} {path}: {err.strerror}") from err


def _is_pem(data: bytes) -> bool:
    return b"-----BEGIN" in data


# ---------------------------------------------------------------- certificates


def parse_certificate(data: bytes, where: object = "certificate") -> x509.Certificate:
    """A certificate from PEM or DER bytes."""
    try:
        return x509.load_pem_x509_certificate(data) if _is_pem(data) else x509.load_der_x509_certificate(data)
    except ValueError as err:
        raise PKIError(f"{where} is not an X.509 certificate (PEM or DER)") from err


def load_certificate(path: PathLike) -> x509.Certificate:
    """The certificate in the PEM or DER file at ``path``."""
    return parse_certificate(_read(path, "certificate"), path)


def cert_der(path: PathLike) -> bytes:
    """The DER bytes of the (first) certificate in the PEM or DER file at ``path``."""
    return load_certificate(path).public_bytes(serialization.Encoding.DER)


def cert_serial(der: bytes) -> int:
    """The serial number of a DER certificate."""
    return parse_certificate(der).serial_number


def cert_thumbprint_s256(der: bytes) -> str:
    """RFC 8705 ``x5t#S256``: base64url(SHA-256(DER)) without padding."""
    return base64.urlsafe_b64encode(hashlib.sha256(der).digest()).rstrip(b"=").decode("ascii")


def cert_fingerprint_sha256(der: bytes) -> str:
    """Lowercase hex SHA-256 of the DER certificate, as stored in the registry."""
    return hashlib.sha256(der).hexdigest()


# ---------------------------------------------------------------- private keys


def key_is_encrypted(path: PathLike) -> bool:
    """True if the key file at ``path`` is passphrase-protected."""
    head = _read(path, "key")[:4096]
    return b"ENCRYPTED PRIVATE KEY" in head or b"Proc-Type: 4,ENCRYPTED" in head


def parse_private_key(data: bytes, passphrase: bytes | str | None, where: object = "key") -> Any:
    """A private key from PEM or DER bytes. An encrypted key needs ``passphrase``;
    a wrong or missing one raises :class:`WrongPassphrase` naming ``where``."""
    if isinstance(passphrase, str):
        passphrase = passphrase.encode()
    encrypted = b"ENCRYPTED" in data[:4096]
    if encrypted and not passphrase:
        raise WrongPassphrase(where, "it is encrypted: a passphrase is required")
    password = passphrase if encrypted else None
    loader = serialization.load_pem_private_key if _is_pem(data) else serialization.load_der_private_key
    try:
        return loader(data, password=password)
    except (ValueError, TypeError, UnsupportedAlgorithm) as err:
        if encrypted:
            raise WrongPassphrase(where) from err
        raise PKIError(f"{where} is not a private key") from err


def load_private_key(path: PathLike, passphrase: bytes | str | None) -> Any:
    """The private key in the PEM or DER file at ``path``."""
    return parse_private_key(_read(path, "key"), passphrase, path)


# ---------------------------------------------------------------- CSRs and CRLs


def parse_csr(data: bytes, where: object = "CSR") -> x509.CertificateSigningRequest:
    """A certificate signing request from PEM or DER bytes, its signature checked."""
    try:
        csr = x509.load_pem_x509_csr(data) if _is_pem(data) else x509.load_der_x509_csr(data)
    except ValueError as err:
        raise PKIError(f"{where} is not a certificate signing request") from err
    if not csr.is_signature_valid:
        raise PKIError(f"the signature of CSR {where} is invalid")
    return csr


def load_csr(path: PathLike) -> x509.CertificateSigningRequest:
    return parse_csr(_read(path, "CSR"), path)


def parse_crl(data: bytes, where: object = "CRL") -> x509.CertificateRevocationList:
    """A certificate revocation list from PEM or DER bytes (signature not checked)."""
    try:
        return x509.load_pem_x509_crl(data) if _is_pem(data) else x509.load_der_x509_crl(data)
    except ValueError as err:
        raise PKIError(f"{where} is not a CRL") from err


def load_certificates(path: PathLike) -> list[x509.Certificate]:
    """Every certificate of a file (a PEM bundle, such as a CA file holding the CA being
    replaced and its successor, or one DER certificate)."""
    data = _read(path, "certificate file")
    try:
        return x509.load_pem_x509_certificates(data) if _is_pem(data) else [x509.load_der_x509_certificate(data)]
    except ValueError as err:
        raise PKIError(f"{path} holds no readable certificate") from err


def issued_by_any(cert: x509.Certificate, cas: list[x509.Certificate]) -> bool:
    """Whether one of ``cas`` signed ``cert`` directly (its issuer name and signature)."""
    from cryptography.exceptions import InvalidSignature

    for ca in cas:
        try:
            cert.verify_directly_issued_by(ca)
            return True
        except (ValueError, TypeError, InvalidSignature):
            continue
    return False


def load_crl(path: PathLike) -> x509.CertificateRevocationList:
    return parse_crl(_read(path, "CRL"), path)


_PEM_CRL = re.compile(rb"-----BEGIN X509 CRL-----.+?-----END X509 CRL-----", re.DOTALL)


def load_crls(path: PathLike) -> list[x509.CertificateRevocationList]:
    """Every CRL of a file (a PEM bundle, as OpenSSL reads one, or one DER CRL)."""
    data = _read(path, "CRL")
    if not _is_pem(data):
        return [parse_crl(data, path)]
    blocks = _PEM_CRL.findall(data)
    if not blocks:
        raise PKIError(f"{path} holds no PEM CRL")
    return [parse_crl(block, path) for block in blocks]
