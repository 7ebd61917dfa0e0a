"""A throwaway PostgreSQL cluster for the registry tests (session scope).

Load with ``pytest_plugins = ["tests.postgres_fixture"]`` in a test module. The
cluster (:func:`cryptoros.lab.postgres.postgres_cluster`) lives in a temp dir on a
free loopback port, is owned by the ``postgres`` user when the tests run as root
(``initdb`` refuses root), and is stopped and deleted in a ``finally``. Each test
gets its own fresh database from ``postgres_url``. Where the server binaries are
missing the tests skip (fail under ``CI=true``) via :func:`tests.support.missing`.
"""

from __future__ import annotations

import uuid
from collections.abc import Iterator

import pytest

from cryptoros.lab.postgres import create_database, postgres_cluster, postgres_unavailable
from tests.support import missing


@pytest.fixture(scope="session")
def postgres_server() -> Iterator[str]:
    """URL of the ``postgres`` database of a throwaway cluster (superuser, trust auth)."""
    reason = postgres_unavailable()
    if reason is not None:
        missing(reason)
    with postgres_cluster() as url:
        yield url


@pytest.fixture
def postgres_url(postgres_server: str) -> Iterator[str]:
    """A fresh, empty database on the throwaway cluster, dropped afterwards."""
    import psycopg

    name = "t_" + uuid.uuid4().hex[:12]
    url = create_database(postgres_server, name)
    try:
        yield url
    finally:
        plain = postgres_server.replace("postgresql+psycopg://", "postgresql://")
        with psycopg.connect(plain, autocommit=True, connect_timeout=10) as conn:
            conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
