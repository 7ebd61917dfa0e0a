"""Initial registry: managers and their grants, signing keys, revocations, audit log.

Revision ID: 0001
Revises:
Create Date: 2025-11-21
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None

NAME_LEN = 256


def _grant_table(table: str, column: str) -> None:
    op.create_table(
        table,
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("manager_id", sa.Integer, sa.ForeignKey("manager.id", ondelete="CASCADE"), nullable=False),
        sa.Column("name", sa.String(NAME_LEN), nullable=False),
        sa.Column(column, sa.String(NAME_LEN), nullable=False),
        sa.Column("data_type", sa.String(NAME_LEN), nullable=False),
        sa.UniqueConstraint("manager_id", "name", column, "data_type", name=f"uq_{table}"),
    )
    op.create_index(f"ix_{table}_manager_id", table, ["manager_id"])


def upgrade() -> None:
    op.create_table(
        "manager",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("name", sa.String(128), nullable=False, unique=True),
        sa.Column("cert_fingerprint", sa.String(64), nullable=True, unique=True),
        sa.Column("enabled", sa.Boolean, nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
    )
    _grant_table("publisher", "topic")
    _grant_table("subscriber", "topic")
    _grant_table("service", "service")
    _grant_table("service_client", "service")

    op.create_table(
        "revoked_token",
        sa.Column("jti", sa.String(64), primary_key=True),
        sa.Column("expires_at", sa.Integer, nullable=False),
        sa.Column("revoked_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("reason", sa.String(256), nullable=False),
    )
    op.create_index("ix_revoked_token_expires_at", "revoked_token", ["expires_at"])

    op.create_table(
        "audit_log",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("event", sa.String(16), nullable=False),
        sa.Column("manager", sa.String(128), nullable=True),
        sa.Column("cert_fingerprint", sa.String(64), nullable=True),
        sa.Column("remote", sa.String(128), nullable=True),
        sa.Column("reason", sa.String(256), nullable=False),
        sa.Column("jti", sa.String(64), nullable=True),
        sa.Column("kid", sa.String(64), nullable=True),
        sa.Column("expires_at", sa.Integer, nullable=True),
    )
    op.create_index("ix_audit_log_at", "audit_log", ["at"])
    op.create_index("ix_audit_log_manager", "audit_log", ["manager"])
    op.create_index("ix_audit_log_jti", "audit_log", ["jti"])
    op.create_index("ix_audit_log_kid_expires", "audit_log", ["kid", "expires_at"])

    op.create_table(
        "signing_key",
        sa.Column("kid", sa.String(64), primary_key=True),
        sa.Column("algorithm", sa.String(16), nullable=False),
        sa.Column("private_pem", sa.LargeBinary, nullable=False),
        sa.Column("public_pem", sa.Text, nullable=False),
        sa.Column("encrypted", sa.Boolean, nullable=False),
        sa.Column("active", sa.Boolean, nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("retired_at", sa.DateTime(timezone=True), nullable=True),
    )

    op.create_table(
        "registry_state",
        sa.Column("key", sa.String(64), primary_key=True),
        sa.Column("value", sa.Integer, nullable=False),
    )


def downgrade() -> None:
    for table in (
        "registry_state",
        "signing_key",
        "audit_log",
        "revoked_token",
        "service_client",
        "service",
        "subscriber",
        "publisher",
        "manager",
    ):
        op.drop_table(table)
