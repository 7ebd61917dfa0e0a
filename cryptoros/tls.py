"""The one TLS context factory every cryptoros program uses.

Policy, in the spirit of the CryptoROS paper's cipher string
``TLSv1.2:!LOW:!EXPORT:!MD5:!aNULL:!ADH:!AECDH:!DES:!eNULL:!RC2:!RC4`` but tightened to
forward-secret AEAD suites only:

- minimum TLS 1.2 (optionally pinned to exactly 1.2 with ``pin_tls12``);
- TLS 1.2 suites: ECDHE key exchange with AES-GCM or ChaCha20-Poly1305, nothing else
  (no static RSA key exchange, no CBC, no SHA-1 MACs, no DHE);
- TLS 1.3 suites are OpenSSL's defaults, which are all AEAD and forward secret
  (Python's ``ssl`` cannot narrow them further);
- mutual authentication: a server context *requires* a client certificate chaining to
  the configured CA; a client context verifies the server the same way;
- when a CRL file is configured, the peer's leaf certificate is checked against it,
  and a CA with no CRL then fails verification (fail closed).

``python -m cryptoros.tls`` prints the suites that result on this machine.
"""

from __future__ import annotations

import ssl
from dataclasses import dataclass
from pathlib import Path

from cryptoros.errors import ConfigError, TokenError
from cryptoros import pemfiles

#: The paper's cipher configuration string (seed 003, Eq. 5), kept for reference.
PAPER_CIPHER_STRING = "TLSv1.2:!LOW:!EXPORT:!MD5:!aNULL:!ADH:!AECDH:!DES:!eNULL:!RC2:!RC4"

#: What cryptoros uses for TLS 1.2: the paper's exclusions, tightened to ECDHE + AEAD.
STRICT_TLS12_CIPHERS = (
    "ECDHE+AESGCM:ECDHE+CHACHA20:"
    "!LOW:!EXPORT:!MD5:!aNULL:!ADH:!AECDH:!DES:!eNULL:!RC2:!RC4:!3DES:!SHA1:!PSK:!SRP:!DSS"
)


@dataclass(frozen=True, kw_only=True)
class TLSConfig:
    """Where a program's TLS material lives. Validated on construction."""

    ca_file: Path
    cert_file: Path
    key_file: Path
    key_passphrase: bytes | None = None
    crl_file: Path | None = None
    pin_tls12: bool = False

    def __post_init__(self) -> None:
        for label in ("ca_file", "cert_file", "key_file", "crl_file"):
            value = getattr(self, label)
            if value is None:
                continue
            path = Path(value)
            object.__setattr__(self, label, path)
            if not path.is_file():
                raise ConfigError(f"TLS {label.replace('_', ' ')} not found: {path}")


def _base_context(protocol: int, cfg: TLSConfig) -> ssl.SSLContext:
    ctx = ssl.SSLContext(protocol)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    if cfg.pin_tls12:
        ctx.maximum_version = ssl.TLSVersion.TLSv1_2
    ctx.set_ciphers(STRICT_TLS12_CIPHERS)
    ctx.options |= ssl.OP_NO_COMPRESSION | ssl.OP_NO_RENEGOTIATION | ssl.OP_CIPHER_SERVER_PREFERENCE
    ctx.verify_mode = ssl.CERT_REQUIRED
    try:
        ctx.load_verify_locations(cafile=str(cfg.ca_file))
        if cfg.crl_file is not None:
            ctx.load_verify_locations(cafile=str(cfg.crl_file))
            ctx.verify_flags |= ssl.VERIFY_CRL_CHECK_LEAF
        ctx.load_cert_chain(str(cfg.cert_file), str(cfg.key_file), password=cfg.key_passphrase or _no_password)
    except ssl.SSLError as exc:
        raise ConfigError(f"cannot load TLS material ({cfg.cert_file}, {cfg.key_file}): {exc.reason or exc}") from exc
    return ctx


def _no_password() -> bytes:
    # Called by OpenSSL only if the key file is encrypted and no passphrase was given.
    raise ConfigError("the TLS private key is encrypted and no passphrase was given")


def server_context(cfg: TLSConfig) -> ssl.SSLContext:
    """A server context that requires and verifies a client certificate.

    It sends no TLS 1.3 session tickets: asyncio clients cannot use them, and each
    carries the client certificate (about 1.7 KB per connection, measured)."""
    ctx = _base_context(ssl.PROTOCOL_TLS_SERVER, cfg)
    ctx.num_tickets = 0
    return ctx


def client_context(cfg: TLSConfig, *, check_hostname: bool = True) -> ssl.SSLContext:
    """A client context that presents our certificate and verifies the server's.

    ``check_hostname=False`` is for peers addressed by an identity other than their
    host name (interceptors check the peer's identity URI themselves); the chain is
    verified against the CA either way.
    """
    ctx = _base_context(ssl.PROTOCOL_TLS_CLIENT, cfg)
    ctx.check_hostname = check_hostname
    return ctx


def peer_cert_der(ssl_object: ssl.SSLObject | ssl.SSLSocket | None) -> bytes:
    """The DER bytes of the verified peer certificate; no certificate is a denial."""
    der = ssl_object.getpeercert(binary_form=True) if ssl_object is not None else None
    if not der:
        raise TokenError("no_peer_certificate", "the TLS peer presented no certificate")
    return der


#: The fingerprints of a DER certificate live in :mod:`cryptoros.pemfiles`; kept here
#: for the callers that import them from this module.
cert_thumbprint_s256 = pemfiles.cert_thumbprint_s256
cert_fingerprint_sha256 = pemfiles.cert_fingerprint_sha256


def describe_suites(ctx: ssl.SSLContext) -> list[str]:
    """Names of the suites a context may negotiate, TLS 1.3 ones included."""
    return [c["name"] for c in ctx.get_ciphers()]


def _main() -> None:  # pragma: no cover - documentation helper
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    ctx.set_ciphers(STRICT_TLS12_CIPHERS)
    print(f"{ssl.OPENSSL_VERSION}")
    for c in ctx.get_ciphers():
        print(f"{c['protocol']:8s} {c['name']}")


if __name__ == "__main__":  # pragma: no cover
    _main()
