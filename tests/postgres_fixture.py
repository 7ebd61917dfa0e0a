"""A throwaway PostgreSQL cluster for the registry tests (session scope).

Load with ``pytest_plugins = ["tests.postgres_fixture"]`` in a test module. The
cluster lives in a temp dir on a free loopback port, is owned by the ``postgres``
user when the tests run as root (``initdb`` refuses root), and is stopped and deleted
in a ``finally``. Each test gets its own fresh database from ``postgres_url``.
Where the server binaries are missing the tests skip (fail under ``CI=true``) via
:func:`tests.support.missing`.
"""

from __future__ import annotations

import glob
import os
import pwd
import shlex
import shutil
import subprocess
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.support import free_port, missing


def _as_postgres(cmd: list[str], *, timeout: float) -> subprocess.CompletedProcess:
    line = " ".join(shlex.quote(c) for c in cmd)
    if os.geteuid() == 0:
        args = ["su", "postgres", "-s", "/bin/sh", "-c", line]
    else:
        args = ["/bin/sh", "-c", line]
    return subprocess.run(args, capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="session")
def postgres_server() -> Iterator[str]:
    """URL of the ``postgres`` database of a throwaway cluster (superuser, trust auth)."""
    bins = sorted(glob.glob("/usr/lib/postgresql/*/bin"))
    if not bins or not Path(bins[-1], "initdb").exists():
        missing("PostgreSQL server binaries not found under /usr/lib/postgresql/*/bin "
                "(Debian package postgresql; scripts/install-system-parts installs it)")
    bindir = bins[-1]
    if os.geteuid() == 0:
        try:
            pw = pwd.getpwnam("postgres")
        except KeyError:
            missing("running as root and there is no 'postgres' user to run initdb as")
        if shutil.which("su") is None:
            missing("running as root and 'su' is not available to run initdb as postgres")
    base = Path(tempfile.mkdtemp(prefix="cryptoros-pg-"))
    if os.geteuid() == 0:
        os.chown(base, pw.pw_uid, pw.pw_gid)
    data = base / "data"
    port = free_port()
    started = False
    try:
        r = _as_postgres([f"{bindir}/initdb", "-D", str(data), "-A", "trust", "-U", "postgres",
                          "--no-sync", "-E", "UTF8"], timeout=120)
        if r.returncode != 0:
            pytest.fail(f"initdb failed: {r.stderr.strip() or r.stdout.strip()}")
        opts = f"-p {port} -k {base} -c listen_addresses=127.0.0.1 -c fsync=off -c full_page_writes=off"
        r = _as_postgres([f"{bindir}/pg_ctl", "-D", str(data), "-o", opts, "-l", str(base / "pg.log"),
                          "-w", "-t", "60", "start"], timeout=90)
        if r.returncode != 0:
            log = (base / "pg.log").read_text() if (base / "pg.log").exists() else ""
            pytest.fail(f"pg_ctl start failed: {r.stderr.strip()} {log[-2000:]}")
        started = True
        yield f"postgresql+psycopg://postgres@127.0.0.1:{port}/postgres"
    finally:
        if started:
            _as_postgres([f"{bindir}/pg_ctl", "-D", str(data), "-m", "fast", "-w", "-t", "30", "stop"], timeout=60)
        shutil.rmtree(base, ignore_errors=True)


@pytest.fixture
def postgres_url(postgres_server: str) -> Iterator[str]:
    """A fresh, empty database on the throwaway cluster, dropped afterwards."""
    import psycopg

    name = "t_" + uuid.uuid4().hex[:12]
    plain = postgres_server.replace("postgresql+psycopg://", "postgresql://")
    with psycopg.connect(plain, autocommit=True, connect_timeout=10) as conn:
        conn.execute(f'CREATE DATABASE "{name}"')
    try:
        yield postgres_server.rsplit("/", 1)[0] + "/" + name
    finally:
        with psycopg.connect(plain, autocommit=True, connect_timeout=10) as conn:
            conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
