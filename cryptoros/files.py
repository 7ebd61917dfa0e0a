"""Reading a file an operator named: a regular file, of a bounded size.

A path to ``/dev/zero``, ``/dev/urandom`` or a FIFO (a typo, a symlink left behind)
made every tool that read a certificate, key, passphrase, configuration or policy hang
and grow without limit (CLI audit: 9.6 GB in 8 s). :func:`read_bounded` refuses what is
not a regular file and what is larger than the caller's limit, with an :class:`OSError`
whose ``strerror`` says which, so each caller's one-line "cannot read ..." message
carries it. :func:`open_to_others` says when a file holding a secret (a private key,
a passphrase) may be read by users other than its owner. :func:`sync` makes a file or
a directory's entries durable (a rename is not, until its directory is synced).
"""

from __future__ import annotations

import errno
import os
import stat
from collections.abc import Iterable

#: certificates, keys, CSRs and CRLs (a CRL of 100,000 revocations is about 4 MB)
PEM_LIMIT = 16 << 20
#: a passphrase file
PASSPHRASE_LIMIT = 64 << 10
#: a configuration file (TOML)
CONFIG_LIMIT = 4 << 20
#: a policy document (YAML, SROS2 XML)
POLICY_LIMIT = 64 << 20


def _units(n: int) -> str:
    return f"{n >> 20} MiB" if n >= 1 << 20 else f"{n >> 10} KiB"


def read_bounded(path: str | os.PathLike[str], limit: int) -> bytes:
    """The bytes of the regular file at ``path``, at most ``limit`` of them; OSError
    otherwise (not a regular file, larger, or unreadable). Opened without blocking, so a
    FIFO is refused rather than waited on."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise OSError(errno.EINVAL, "not a regular file (a device, FIFO or directory)", str(path))
        chunks, size = [], 0
        while chunk := os.read(fd, min(1 << 20, limit + 1 - size)):
            chunks.append(chunk)
            size += len(chunk)
            if size > limit:
                raise OSError(errno.EFBIG, f"larger than {_units(limit)}, the most read from such a file", str(path))
        return b"".join(chunks)
    finally:
        os.close(fd)


def open_to_others(named: Iterable[tuple[str, str | os.PathLike[str] | None]]) -> list[str]:
    """One warning line for each file of ``named`` ((what it holds, path): "the TLS key",
    a passphrase file; a path of None skipped) that grants its group or other users any
    access (``mode & 0o077``): the file, its mode and the fix. A file that cannot be read
    is left to its reader to report."""
    lines = []
    for what, path in named:
        if path is None:
            continue
        try:
            mode = stat.S_IMODE(os.stat(path).st_mode)
        except OSError:
            continue
        loose = mode & 0o077
        if loose:
            who = " and ".join(name for name, bits in (("its group", 0o070), ("other users", 0o007)) if loose & bits)
            lines.append(f"{what} {path} has mode {mode:04o}, open to {who} on this host: chmod 600 {path}")
    return lines


def sync(path: str | os.PathLike[str]) -> None:
    """fsync a file, or a directory (its entries: the files renamed into it)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


__all__ = ["CONFIG_LIMIT", "PASSPHRASE_LIMIT", "PEM_LIMIT", "POLICY_LIMIT", "open_to_others", "read_bounded", "sync"]
