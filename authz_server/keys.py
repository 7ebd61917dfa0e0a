"""RSA signing keys: generation, storage encryption, ``kid``, loading.

A key's ``kid`` is its RFC 7638 JWK thumbprint, so the same key always has the same
id and a JWKS entry can be checked against its id. Private keys are stored as PKCS#8
PEM, encrypted with the operator's passphrase; storing one in clear needs the
explicit ``unsafe_no_passphrase`` switch.

``cryptography`` is imported by the functions that use it: every ``cryptoros-authz``
call imports this module for its constants and :class:`KeyProtection`, and most calls
never touch a key (the import took 30 ms of a call's 0.45 s of CPU).
"""

from __future__ import annotations

import base64
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from cryptoros.errors import ConfigError, PKIError
from cryptoros.passphrase import read_passphrase

if TYPE_CHECKING:
    from cryptography.hazmat.primitives.asymmetric import rsa

RSA_BITS = 2048
PASSPHRASE_ENV = "CRYPTOROS_AUTHZ_KEY_PASSPHRASE"


@dataclass(frozen=True)
class KeyProtection:
    """How private signing keys are protected at rest. Build with :func:`protection`."""

    passphrase: bytes | None
    unsafe_no_passphrase: bool = False
    #: the file the passphrase was read from (None: the environment, or none)
    passphrase_file: Path | None = None

    def __post_init__(self) -> None:
        if self.passphrase is None and not self.unsafe_no_passphrase:
            raise ConfigError(
                "signing keys need a passphrase: --signing-key-passphrase-file FILE or "
                f"{PASSPHRASE_ENV}, or --unsafe-no-passphrase to store them in clear"
            )
        if self.passphrase is not None and len(self.passphrase) < 8:
            raise ConfigError("the signing key passphrase must be at least 8 bytes")


def protection(passphrase_file: str | None, *, unsafe_no_passphrase: bool = False) -> KeyProtection:
    """Passphrase from a file, else the environment, else none
    (:func:`cryptoros.passphrase.read_passphrase`: the one rule)."""
    passphrase = read_passphrase(passphrase_file, PASSPHRASE_ENV)
    if passphrase is not None and unsafe_no_passphrase:
        raise ConfigError("--unsafe-no-passphrase given together with a passphrase")
    return KeyProtection(passphrase=passphrase, unsafe_no_passphrase=unsafe_no_passphrase,
                         passphrase_file=Path(passphrase_file) if passphrase_file else None)


def _b64u_int(n: int) -> str:
    raw = n.to_bytes((n.bit_length() + 7) // 8, "big")
    return base64.urlsafe_b64encode(raw).rstrip(b"=").decode("ascii")


def jwk_thumbprint(public_key: rsa.RSAPublicKey) -> str:
    """RFC 7638 thumbprint (SHA-256, base64url) of an RSA public key."""
    nums = public_key.public_numbers()
    canonical = json.dumps({"e": _b64u_int(nums.e), "kty": "RSA", "n": _b64u_int(nums.n)},
                           separators=(",", ":"), sort_keys=True)
    return base64.urlsafe_b64encode(hashlib.sha256(canonical.encode()).digest()).rstrip(b"=").decode()


@dataclass(frozen=True)
class NewKey:
    kid: str
    private_pem: bytes
    public_pem: str
    encrypted: bool


def generate(prot: KeyProtection, bits: int = RSA_BITS) -> NewKey:
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import rsa

    key = rsa.generate_private_key(public_exponent=65537, key_size=bits)
    enc: serialization.KeySerializationEncryption
    if prot.passphrase is not None:
        enc = serialization.BestAvailableEncryption(prot.passphrase)
    else:
        enc = serialization.NoEncryption()
    private_pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, enc)
    public_pem = key.public_key().public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
    ).decode("ascii")
    return NewKey(jwk_thumbprint(key.public_key()), private_pem, public_pem, prot.passphrase is not None)


def load_private(private_pem: bytes, encrypted: bool, prot: KeyProtection, kid: str) -> rsa.RSAPrivateKey:
    from cryptography.hazmat.primitives.asymmetric import rsa

    from cryptoros import pemfiles

    if encrypted and prot.passphrase is None:
        raise ConfigError(f"signing key {kid} is encrypted: give its passphrase (--signing-key-passphrase-file or {PASSPHRASE_ENV})")
    try:
        key = pemfiles.parse_private_key(private_pem, prot.passphrase if encrypted else None, f"signing key {kid}")
    except PKIError as exc:
        raise ConfigError(f"cannot decrypt signing key {kid}: wrong passphrase?") from exc
    if not isinstance(key, rsa.RSAPrivateKey):  # pragma: no cover - we only store RSA
        raise ConfigError(f"signing key {kid} is not an RSA key")
    return key


def load_public(public_pem: str) -> rsa.RSAPublicKey:
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import rsa

    key = serialization.load_pem_public_key(public_pem.encode("ascii"))
    if not isinstance(key, rsa.RSAPublicKey):  # pragma: no cover
        raise ConfigError("stored public key is not RSA")
    return key
