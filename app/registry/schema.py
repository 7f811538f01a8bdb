"""The registry's tables as SQLAlchemy Core objects (the newest migration's schema)."""

from __future__ import annotations

import sqlalchemy as sa

#: longest asset id and recipient (characters)
MAX_ASSET_ID = 200
MAX_RECIPIENT = 500

metadata = sa.MetaData()

copies = sa.Table(
    "copies",
    metadata,
    sa.Column("id", sa.BigInteger().with_variant(sa.Integer(), "sqlite"), primary_key=True,
              autoincrement=True),
    sa.Column("asset_id", sa.String(MAX_ASSET_ID), nullable=False),
    sa.Column("recipient", sa.String(MAX_RECIPIENT), nullable=False),
    sa.Column("codeword", sa.LargeBinary(), nullable=False),
    sa.Column("codeword_bits", sa.Integer(), nullable=False),
    sa.Column("method", sa.String(32), nullable=False),
    sa.Column("strength", sa.Float(), nullable=False),
    sa.Column("issued_at", sa.DateTime(timezone=True), nullable=False),
    sa.UniqueConstraint("asset_id", "recipient", name="uq_copies_asset_recipient"),
    sa.Index("ix_copies_group", "asset_id", "method", "codeword_bits"),
)
