"""Certificate renewal with an overlap: a manager's previous certificate and until when
it is still accepted (``set-cert --overlap``).

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-26
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    # plain nullable columns (SQLite cannot add a UNIQUE column in place): the registry
    # keeps a fingerprint bound to one manager at most, in either column, itself
    op.add_column("manager", sa.Column("previous_fingerprint", sa.String(64), nullable=True))
    op.add_column("manager", sa.Column("previous_until", sa.Integer, nullable=True))
    op.create_index("ix_manager_previous_fingerprint", "manager", ["previous_fingerprint"])


def downgrade() -> None:
    op.drop_index("ix_manager_previous_fingerprint", table_name="manager")
    with op.batch_alter_table("manager") as batch:
        batch.drop_column("previous_until")
        batch.drop_column("previous_fingerprint")
