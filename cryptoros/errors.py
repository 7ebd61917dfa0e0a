"""The one error family of cryptoros.

Every error raised on purpose by cryptoros code derives from :class:`CryptorosError`.
The split follows h11: :class:`RemoteProtocolError` means a peer sent something we
refuse (garbage, a bad token, a forbidden request); :class:`LocalProtocolError` means
our own code misused an API. A peer is only ever told an opaque denial; the log gets
the reason carried by the exception.
"""

from __future__ import annotations


class CryptorosError(Exception):
    """Root of every error cryptoros raises on purpose."""


class ConfigError(CryptorosError):
    """A configuration file, flag or environment variable is missing or invalid."""


class LocalProtocolError(CryptorosError):
    """Our own code used a protocol object wrongly (a bug on this side)."""


class RemoteProtocolError(CryptorosError):
    """A peer sent bytes that do not follow the protocol (never a crash)."""


class PKIError(CryptorosError):
    """A certificate, key, CSR or CRL operation failed (bad file, wrong passphrase...)."""


class TokenError(CryptorosError):
    """An access token was refused. ``reason`` is a short machine-readable code for
    logs and metrics; the peer only ever sees an opaque denial."""

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason
        self.detail = detail


class PolicyDenied(CryptorosError):
    """A request was checked against the registry or a token's grants and refused."""

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason
        self.detail = detail


class RegistryError(CryptorosError):
    """A registry operation was refused: unknown manager, invalid name or type..."""


__all__ = [
    "CryptorosError",
    "ConfigError",
    "LocalProtocolError",
    "RemoteProtocolError",
    "PKIError",
    "TokenError",
    "PolicyDenied",
    "RegistryError",
]
