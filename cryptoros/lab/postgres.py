"""A throwaway PostgreSQL cluster on loopback, for tests and benchmarks alike.

:func:`postgres_unavailable` says why no cluster can be made here (no server binaries
under ``/usr/lib/postgresql/*/bin``, or root without a ``postgres`` user or ``su``),
or None. :func:`postgres_cluster` makes one in a temp dir on a free loopback port:
``initdb`` runs as the ``postgres`` user when we are root (it refuses root), the
server has fsync off (throwaway data), and it is stopped and deleted in a
``finally``. It yields the SQLAlchemy URL of its ``postgres`` database (superuser,
trust authentication on loopback only).
"""

from __future__ import annotations

import contextlib
import glob
import os
import pwd
import shlex
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

from cryptoros.lab.processes import NetworkError, free_port

__all__ = ["create_database", "postgres_bindir", "postgres_cluster", "postgres_unavailable", "postmaster_pid"]


def postgres_bindir() -> str | None:
    """The newest PostgreSQL server's bin directory (Debian layout), or None."""
    bins = sorted(glob.glob("/usr/lib/postgresql/*/bin"), key=lambda p: int(Path(p).parent.name)
                  if Path(p).parent.name.isdigit() else 0)
    return bins[-1] if bins and Path(bins[-1], "initdb").exists() else None


def postgres_unavailable() -> str | None:
    """Why no throwaway cluster can be started here, or None when one can."""
    if postgres_bindir() is None:
        return ("PostgreSQL server binaries not found under /usr/lib/postgresql/*/bin "
                "(Debian package postgresql; scripts/install-system-parts installs it)")
    if os.geteuid() == 0:
        try:
            pwd.getpwnam("postgres")
        except KeyError:
            return "running as root and there is no 'postgres' user to run initdb as"
        if shutil.which("su") is None:
            return "running as root and 'su' is not available to run initdb as postgres"
    return None


def _as_postgres(cmd: list[str], *, timeout: float) -> subprocess.CompletedProcess:
    line = " ".join(shlex.quote(c) for c in cmd)
    args = ["su", "postgres", "-s", "/bin/sh", "-c", line] if os.geteuid() == 0 else ["/bin/sh", "-c", line]
    return subprocess.run(args, capture_output=True, text=True, timeout=timeout)


@contextlib.contextmanager
def postgres_cluster(*, max_connections: int = 100) -> Iterator[str]:
    """URL (``postgresql+psycopg://postgres@127.0.0.1:PORT/postgres``) of a fresh
    cluster, stopped and deleted when the block ends; NetworkError if it cannot start."""
    reason = postgres_unavailable()
    if reason is not None:
        raise NetworkError(reason)
    bindir = postgres_bindir()
    base = Path(tempfile.mkdtemp(prefix="cryptoros-pg-"))
    if os.geteuid() == 0:
        pw = pwd.getpwnam("postgres")
        os.chown(base, pw.pw_uid, pw.pw_gid)
    data = base / "data"
    port = free_port()
    started = False
    try:
        r = _as_postgres([f"{bindir}/initdb", "-D", str(data), "-A", "trust", "-U", "postgres",
                          "--no-sync", "-E", "UTF8"], timeout=120)
        if r.returncode != 0:
            raise NetworkError(f"initdb failed: {r.stderr.strip() or r.stdout.strip()}")
        opts = (f"-p {port} -k {base} -c listen_addresses=127.0.0.1 -c fsync=off -c full_page_writes=off "
                f"-c max_connections={int(max_connections)}")
        r = _as_postgres([f"{bindir}/pg_ctl", "-D", str(data), "-o", opts, "-l", str(base / "pg.log"),
                          "-w", "-t", "60", "start"], timeout=90)
        if r.returncode != 0:
            log = (base / "pg.log").read_text() if (base / "pg.log").exists() else ""
            raise NetworkError(f"pg_ctl start failed: {r.stderr.strip()} {log[-2000:]}")
        started = True
        yield f"postgresql+psycopg://postgres@127.0.0.1:{port}/postgres"
    finally:
        if started:
            _as_postgres([f"{bindir}/pg_ctl", "-D", str(data), "-m", "fast", "-w", "-t", "30", "stop"], timeout=60)
        shutil.rmtree(base, ignore_errors=True)


def create_database(server_url: str, name: str) -> str:
    """Create database ``name`` on the cluster of ``server_url``; returns its URL."""
    import psycopg

    plain = server_url.replace("postgresql+psycopg://", "postgresql://")
    with psycopg.connect(plain, autocommit=True, connect_timeout=10) as conn:
        conn.execute(f'CREATE DATABASE "{name}"')
    return server_url.rsplit("/", 1)[0] + "/" + name


def postmaster_pid(server_url: str) -> int | None:
    """Pid of the cluster's server process (``pg_backend_pid``'s parent), or None."""
    import psycopg

    plain = server_url.replace("postgresql+psycopg://", "postgresql://")
    try:
        with psycopg.connect(plain, autocommit=True, connect_timeout=10) as conn:
            backend = conn.execute("SELECT pg_backend_pid()").fetchone()[0]
            stat = Path(f"/proc/{backend}/stat").read_text()  # while the backend lives
        return int(stat.rsplit(")", 1)[1].split()[1])
    except (OSError, psycopg.Error, ValueError, IndexError):
        return None
