"""The one way cryptoros reads a passphrase: from a file or an environment variable.

One rule everywhere (the PKI CLI, the authz daemon and its CLI, the interceptor):

* a file holds the passphrase as written; one trailing newline (``\\n`` or
  ``\\r\\n``, as an editor or ``echo`` leaves it) is removed, nothing else, so a
  passphrase may begin or end with spaces;
* an environment variable holds it as is;
* an empty passphrase is an error (:class:`PassphraseError`), from a file or from a
  variable that is set: an empty passphrase encrypts nothing.

Interactive prompts stay with the CLIs that offer them (``cryptoros-certs``).
"""

from __future__ import annotations

import os
from collections.abc import Mapping

from cryptoros.files import PASSPHRASE_LIMIT, read_bounded
from cryptoros.errors import ConfigError

__all__ = ["PassphraseError", "from_env", "read_file", "read_passphrase"]


class PassphraseError(ConfigError):
    """A passphrase file could not be read, or a passphrase is empty."""


def _strip_one_newline(data: bytes) -> bytes:
    if data.endswith(b"\r\n"):
        return data[:-2]
    if data.endswith(b"\n"):
        return data[:-1]
    return data


def read_file(path: str | os.PathLike[str]) -> bytes:
    """The passphrase in the file at ``path``, without one trailing newline."""
    try:
        data = read_bounded(path, PASSPHRASE_LIMIT)
    except OSError as err:
        raise PassphraseError(f"cannot read passphrase file {path}: {err.strerror}") from err
    value = _strip_one_newline(data)
    if not value:
        raise PassphraseError(f"passphrase file {path} is empty")
    return value


def from_env(name: str, environ: Mapping[str, str] | None = None) -> bytes | None:
    """The passphrase in the environment variable ``name``; None if it is not set."""
    env = os.environ if environ is None else environ
    if name not in env:
        return None
    value = env[name]
    if not value:
        raise PassphraseError(f"${name} is set but empty")
    return value.encode()


def read_passphrase(
    path: str | os.PathLike[str] | None = None,
    env: str | None = None,
    *,
    environ: Mapping[str, str] | None = None,
) -> bytes | None:
    """The passphrase from the file at ``path`` if given, else from the environment
    variable ``env`` if set, else None."""
    if path:
        return read_file(path)
    if env:
        return from_env(env, environ)
    return None
