"""Learning mode: a manager's learning window, and what its interceptors saw its nodes
do (``observation``: requests a grant allowed, and requests only learning let through).

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-27
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("manager", sa.Column("learning_since", sa.Integer, nullable=True))
    op.add_column("manager", sa.Column("learning_until", sa.Integer, nullable=True))
    op.create_table(
        "observation",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("manager_id", sa.Integer, sa.ForeignKey("manager.id", ondelete="CASCADE"), nullable=False),
        sa.Column("allowed", sa.Boolean, nullable=False),
        sa.Column("action", sa.String(16), nullable=False),
        sa.Column("node", sa.String(256), nullable=False),
        sa.Column("name", sa.String(256), nullable=False),
        sa.Column("data_type", sa.String(256), nullable=False),
        sa.Column("count", sa.Integer, nullable=False),
        sa.Column("first_seen", sa.Integer, nullable=False),
        sa.Column("last_seen", sa.Integer, nullable=False),
        sa.UniqueConstraint("manager_id", "allowed", "action", "node", "name", "data_type", name="uq_observation"),
    )
    op.create_index("ix_observation_manager_id", "observation", ["manager_id"])
    op.create_index("ix_observation_last_seen", "observation", ["last_seen"])


def downgrade() -> None:
    op.drop_index("ix_observation_last_seen", table_name="observation")
    op.drop_index("ix_observation_manager_id", table_name="observation")
    op.drop_table("observation")
    with op.batch_alter_table("manager") as batch:
        batch.drop_column("learning_until")
        batch.drop_column("learning_since")
