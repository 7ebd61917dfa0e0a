"""Alembic environment for the cryptoros-authz registry.

Run programmatically by :func:`authz_server.db.upgrade`, which hands over an open
connection in ``config.attributes["connection"]``. Offline (SQL script) mode is
supported for operators who want to review the DDL.
"""

from __future__ import annotations

from alembic import context

from authz_server.models import Base

config = context.config
target_metadata = Base.metadata


def run_migrations_offline() -> None:
    context.configure(
        url=config.get_main_option("sqlalchemy.url"),
        target_metadata=target_metadata,
        literal_binds=True,
        render_as_batch=True,
    )
    with context.begin_transaction():
        context.run_migrations()


def run_migrations_online() -> None:
    connection = config.attributes.get("connection")
    if connection is None:  # pragma: no cover - the CLI always passes a connection
        raise RuntimeError("cryptoros-authz migrations run through authz_server.db.upgrade()")
    context.configure(connection=connection, target_metadata=target_metadata, render_as_batch=True)
    with context.begin_transaction():
        context.run_migrations()


if context.is_offline_mode():
    run_migrations_offline()
else:
    run_migrations_online()
