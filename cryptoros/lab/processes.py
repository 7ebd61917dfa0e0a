"""Processes and ports of the lab, one copy for tests, demo and bench alike.

:func:`free_port` (a port from the OS, optionally never handed out twice),
:func:`wait_port` (bounded wait on observable readiness: something accepts),
:func:`stop` (SIGTERM, then SIGKILL, bounded: every process started is stopped in a
``finally``), :func:`log_tail` (why a child died) and :class:`NetworkError`.
"""

from __future__ import annotations

import contextlib
import signal
import socket
import subprocess
import time
from pathlib import Path

from cryptoros.errors import CryptorosError

__all__ = ["NetworkError", "free_port", "log_tail", "stop", "wait_port"]


class NetworkError(CryptorosError, RuntimeError):
    """A part of the benchmark network did not come up."""


def free_port(host: str = "127.0.0.1", taken: set[int] | None = None) -> int:
    """A port nothing listens on now; with ``taken``, also one not handed out before
    (the kernel may give the same free port twice in a row, and two listeners of one
    host picked that way would collide when they start), and it is added there."""
    for _ in range(100):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.bind((host, 0))
            port = s.getsockname()[1]
        if taken is None:
            return port
        if port not in taken:
            taken.add(port)
            return port
    raise NetworkError(f"no free port on {host} that was not handed out already")


def log_tail(path: Path | None, lines: int = 12) -> str:
    """The last lines of a child's log, for an error saying why it died."""
    if path is None or not path.exists():
        return ""
    tail = path.read_text(errors="replace").splitlines()[-lines:]
    return "\n".join(["", f"last lines of {path.name}:"] + [f"  {line}" for line in tail]) if tail else ""


def wait_port(host: str, port: int, timeout: float, proc: subprocess.Popen | None = None, what: str = "",
              log: Path | None = None) -> None:
    """Bounded wait until something accepts on ``host:port`` (``log``: the child's
    log, whose tail the error shows when it exits first)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc is not None and proc.poll() is not None:
            raise NetworkError(f"{what or proc.args[0]} exited with {proc.returncode} before listening on "
                               f"{host}:{port}{log_tail(log)}")
        with contextlib.suppress(OSError), socket.create_connection((host, port), timeout=0.5):
            return
        time.sleep(0.05)
    raise NetworkError(f"{what or 'nothing'} listened on {host}:{port} within {timeout:.0f} s")


def stop(proc: subprocess.Popen | None, timeout: float = 5.0) -> None:
    """SIGTERM, then SIGKILL after ``timeout``: bounded."""
    if proc is None or proc.poll() is not None:
        return
    with contextlib.suppress(ProcessLookupError):
        proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            proc.kill()
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(timeout=timeout)
