"""Parameter grants: read and write grants on parameter namespaces.

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-24
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None

NAME_LEN = 256


def upgrade() -> None:
    for table in ("param_reader", "param_writer"):
        op.create_table(
            table,
            sa.Column("id", sa.Integer, primary_key=True),
            sa.Column("manager_id", sa.Integer, sa.ForeignKey("manager.id", ondelete="CASCADE"), nullable=False),
            sa.Column("name", sa.String(NAME_LEN), nullable=False),
            sa.Column("namespace", sa.String(NAME_LEN), nullable=False),
            sa.Column("data_type", sa.String(NAME_LEN), nullable=False),
            sa.UniqueConstraint("manager_id", "name", "namespace", "data_type", name=f"uq_{table}"),
        )
        op.create_index(f"ix_{table}_manager_id", table, ["manager_id"])


def downgrade() -> None:
    for table in ("param_writer", "param_reader"):
        op.drop_index(f"ix_{table}_manager_id", table_name=table)
        op.drop_table(table)
