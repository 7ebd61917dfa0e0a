"""The one error family of cryptoros.

Every error raised on purpose by cryptoros code derives from :class:`CryptorosError`.
The split follows h11: :class:`RemoteProtocolError` means a peer sent something we
refuse (garbage, a bad token, a forbidden request); :class:`LocalProtocolError` means
our own code misused an API. A peer is only ever told an opaque denial; the log gets
the reason carried by the exception.

Every error carries ``reason``, a short machine-readable code for logs and metrics, and
``detail``, the human-readable rest. A refusal (:class:`Refusal`: :class:`TokenError`,
:class:`PolicyDenied`) is raised with its code first; any other error with a message
alone, which becomes its ``detail``; its ``reason`` is then its class's
``default_reason`` (``malformed`` for :class:`RemoteProtocolError`), else its class name:
a code from a short fixed set either way, fit for a metric label.
"""

from __future__ import annotations


class CryptorosError(Exception):
    """Root of every error cryptoros raises on purpose. ``str()`` of it is
    ``"<reason>: <detail>"`` when raised with a code, else the message."""

    #: the reason of one raised without a code (None: its class name)
    default_reason: str | None = None

    def __init__(self, detail: str = "", *, reason: str = "") -> None:
        super().__init__(f"{reason}: {detail}" if reason and detail else detail or reason)
        self.reason = reason or self.default_reason or type(self).__name__
        self.detail = detail


#: What a peer, or the network to it, can make one operation fail with: an error of ours
#: (a refusal, a protocol error) or a socket error, which covers a reset
#: (ConnectionError), a timeout (asyncio.TimeoutError is TimeoutError, an OSError) and a
#: TLS failure (ssl.SSLError). Catch it where such a failure ends that operation alone.
PEER_FAILURES: tuple[type[Exception], ...] = (CryptorosError, OSError)


class ConfigError(CryptorosError):
    """A configuration file, flag or environment variable is missing or invalid."""


class LocalProtocolError(CryptorosError):
    """Our own code used a protocol object wrongly (a bug on this side)."""


class RemoteProtocolError(CryptorosError):
    """A peer sent bytes that do not follow the protocol (never a crash)."""

    default_reason = "malformed"


class PKIError(CryptorosError):
    """A certificate, key, CSR or CRL operation failed (bad file, wrong passphrase...)."""


class Refusal(CryptorosError):
    """Something a peer asked for or showed was refused; raised with its reason code
    first (``Refusal("not_granted", "no grant for /chatter")``). The peer only ever sees
    an opaque denial."""

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(detail, reason=reason)


class TokenError(Refusal):
    """An access token was refused."""


class PolicyDenied(Refusal):
    """A request was checked against the registry or a token's grants and refused.
    ``missing``: the grant that would have allowed it, ``(action, node, name, type)``
    (type ``None`` when the request does not say it), when one would."""

    def __init__(self, reason: str, detail: str = "", *,
                 missing: tuple[str, str, str, str | None] | None = None) -> None:
        super().__init__(reason, detail)
        self.missing = missing


class RegistryError(CryptorosError):
    """A registry operation was refused: unknown manager, invalid name or type..."""


__all__ = [
    "CryptorosError",
    "PEER_FAILURES",
    "Refusal",
    "ConfigError",
    "LocalProtocolError",
    "RemoteProtocolError",
    "PKIError",
    "TokenError",
    "PolicyDenied",
    "RegistryError",
]
