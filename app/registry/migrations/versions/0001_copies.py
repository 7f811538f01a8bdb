"""The copies table.

Revision ID: 0001
Revises:
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "copies",
        sa.Column("id", sa.BigInteger().with_variant(sa.Integer(), "sqlite"), primary_key=True,
                  autoincrement=True),
        sa.Column("asset_id", sa.String(200), nullable=False),
        sa.Column("recipient", sa.String(500), nullable=False),
        sa.Column("codeword", sa.LargeBinary(), nullable=False),
        sa.Column("codeword_bits", sa.Integer(), nullable=False),
        sa.Column("method", sa.String(32), nullable=False),
        sa.Column("strength", sa.Float(), nullable=False),
        sa.Column("issued_at", sa.DateTime(timezone=True), nullable=False),
        sa.UniqueConstraint("asset_id", "recipient", name="uq_copies_asset_recipient"),
    )
    op.create_index("ix_copies_group", "copies", ["asset_id", "method", "codeword_bits"])


def downgrade() -> None:
    op.drop_index("ix_copies_group", table_name="copies")
    op.drop_table("copies")
