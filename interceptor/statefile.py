"""The interceptor's files in ``state_dir``: written whole or not at all, owner-only,
and the lock that lets one instance of a configuration use them."""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import tempfile
from pathlib import Path
from typing import IO, Any

from cryptoros.errors import CryptorosError


class InstanceRunning(CryptorosError):
    """Another interceptor holds this state_dir's lock (or it cannot be taken)."""

    exit_code = 1


def write_private_json(path: Path, data: Any, *, encoded: bool = False) -> None:
    """Write ``data`` as JSON to ``path`` atomically (a temporary file of its own renamed
    over it: two writers at once, a thread's and a stop's, never share one), mode 0600,
    creating the directory; OSError when it cannot. ``encoded``: ``data`` is the JSON
    text already."""
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")  # mode 0600
    try:
        with os.fdopen(fd, "w") as f:
            if encoded:
                f.write(data)
            else:
                json.dump(data, f)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def _private_dir(path: Path) -> None:
    """Make ``path`` (and its parents) with mode 0700; an existing one is narrowed to
    0700 (its files hold this host's relay table and node owners)."""
    path.mkdir(mode=0o700, parents=True, exist_ok=True)
    if path.stat().st_mode & 0o077:
        path.chmod(0o700)


def lock_instance(state_dir: Path, manager: str) -> IO[str]:
    """Take ``<state_dir>/<manager>.lock`` (``fcntl.flock``, exclusive, not waiting) and
    write this process's pid into it; hold the returned file open for the process's
    life (the kernel releases the lock when it exits, however it exits). Taken before
    any state is read or written: a second start of the same configuration raises
    :class:`InstanceRunning` naming the running pid, having changed nothing."""
    path = state_dir / f"{manager}.lock"
    try:
        _private_dir(state_dir)
        lock = open(os.open(path, os.O_RDWR | os.O_CREAT, 0o600), "r+", encoding="ascii")
    except OSError as exc:
        raise InstanceRunning(f"cannot take the instance lock {path}: {exc.strerror or exc} "
                              f"(set state_dir to a directory this user may write)") from None
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        holder = lock.read(32).strip() or "unknown"
        lock.close()
        raise InstanceRunning(f"another interceptor runs with this configuration (pid {holder}, lock {path}): "
                              f"stop it first; nothing was changed") from None
    lock.seek(0)
    lock.truncate()
    lock.write(f"{os.getpid()}\n")
    lock.flush()
    return lock


__all__ = ["InstanceRunning", "lock_instance", "write_private_json"]
