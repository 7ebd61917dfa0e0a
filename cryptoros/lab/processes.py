"""Processes and ports of the lab, one copy for tests, demo and bench alike.

:func:`free_port` (a port from the OS, optionally never handed out twice),
:func:`wait_port` (bounded wait on observable readiness: something accepts),
:func:`stop` (SIGTERM, then SIGKILL, bounded: every process started is stopped in a
``finally``), :func:`log_tail` (why a child died) and :class:`NetworkError`.
"""

from __future__ import annotations

import contextlib
import os
import random
import signal
import socket
import subprocess
import time
from pathlib import Path

from cryptoros.errors import CryptorosError
from cryptoros.exposure import ephemeral_ports

__all__ = ["NetworkError", "free_port", "log_tail", "stop", "wait_port"]


class NetworkError(CryptorosError, RuntimeError):
    """A part of the benchmark network did not come up."""


#: where :func:`free_port` picks: below the kernel's range of ephemeral ports (Linux's
#: default is 32768-60999), above the well-known ones and rosmaster's 11311
_PICK_FROM = 20000


def _ephemeral_low() -> int:
    return ephemeral_ports()[0]


#: ``i/n``: pick in the i-th of n equal slices of the range (labs run side by side on one
#: host, e.g. parallel test workers: tests/conftest.py sets it per worker)
PORT_SLICE_ENV = "CRYPTOROS_LAB_PORT_SLICE"


def _pick_range(low: int) -> range | None:
    span = range(_PICK_FROM, low)
    try:
        index, count = (int(x) for x in os.environ.get(PORT_SLICE_ENV, "").split("/"))
    except ValueError:
        index, count = 0, 1
    if count > 1 and 0 <= index < count:
        size = len(span) // count
        span = range(span.start + index * size, span.start + (index + 1) * size)
    return span if len(span) >= 1000 else None


def free_port(host: str = "127.0.0.1", taken: set[int] | None = None) -> int:
    """A port nothing listens on now, for a child to listen on a moment later; with
    ``taken``, also one not handed out before (and it is added there).

    Picked at random below the kernel's ephemeral range: a port the kernel handed out
    (bind to 0) was often the local port of another process's outgoing connection by the
    time the child bound it ("address already in use": a fresh run's interceptor, with
    the other test worker's connections all around it). Outside that range no outgoing
    connection takes it; only another such pick could: two labs side by side picked the
    same port in one run of three test workers (one's local master, then the other's
    authorization daemon, which could not listen), so each lab may be given its own
    slice of the range (:data:`PORT_SLICE_ENV`)."""
    span = _pick_range(_ephemeral_low())
    for _ in range(200):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind((host, random.choice(span) if span is not None else 0))
            except OSError:
                continue  # in use: another pick
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
