"""The registry of issued copies: which codeword went to which recipient of which asset.

SQLAlchemy Core over SQLite (the default: one file, nothing to set up) or PostgreSQL (a URL, for
deployments of several machines); the schema is created and upgraded by Alembic migrations
(:func:`Registry.migrate`, run when the service starts).  A row holds the asset id, the recipient,
the codeword (packed bits), its length, the method, the strength and the time of issue; never
the key.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import sqlalchemy as sa
from alembic import command
from alembic.config import Config
from sqlalchemy.dialects import postgresql, sqlite

from app.registry.schema import copies

MIGRATIONS = Path(__file__).resolve().parent / "migrations"


@dataclass(frozen=True)
class Copy:
    """One issued copy."""

    asset_id: str
    recipient: str
    codeword: bytes       # packed bits (numpy.packbits), big-endian within each byte
    codeword_bits: int
    method: str
    strength: float
    issued_at: dt.datetime


@dataclass(frozen=True)
class Codewords:
    """The codewords of one (method, length) group, in registry order."""

    method: str
    length: int
    asset_ids: list[str]
    recipients: list[str]
    packed: np.ndarray  # (N, ceil(L / 8)) uint8


def sqlite_url(path: Path) -> str:
    return f"sqlite:///{Path(path).expanduser().resolve()}"


class Registry:
    """The copies table behind one database URL (``sqlite:///...`` or ``postgresql+psycopg://...``)."""

    def __init__(self, url: str) -> None:
        if url.startswith("sqlite:///"):
            Path(url.removeprefix("sqlite:///")).parent.mkdir(parents=True, exist_ok=True)
        self.engine = sa.create_engine(url, pool_pre_ping=True)

    def migrate(self) -> None:
        """Create or upgrade the schema to the newest migration."""
        cfg = Config()
        cfg.set_main_option("script_location", str(MIGRATIONS))
        with self.engine.begin() as conn:
            cfg.attributes["connection"] = conn
            command.upgrade(cfg, "head")

    def close(self) -> None:
        self.engine.dispose()

    def find(self, asset_id: str, recipient: str) -> Copy | None:
        with self.engine.connect() as conn:
            row = conn.execute(sa.select(copies).where(copies.c.asset_id == asset_id,
                                                       copies.c.recipient == recipient)).first()
        return _copy(row) if row is not None else None

    def asset_length(self, asset_id: str) -> int | None:
        """The codeword length of the asset's copies (all copies of an asset share it), if any."""
        with self.engine.connect() as conn:
            return conn.execute(sa.select(copies.c.codeword_bits).where(copies.c.asset_id == asset_id)
                                .limit(1)).scalar()

    def issue(self, copy: Copy) -> Copy:
        """Record ``copy`` unless its recipient already has one of that asset; the stored copy
        either way (concurrent issues to one recipient agree on the first one written)."""
        values = {"asset_id": copy.asset_id, "recipient": copy.recipient, "codeword": copy.codeword,
                  "codeword_bits": copy.codeword_bits, "method": copy.method, "strength": copy.strength,
                  "issued_at": copy.issued_at}
        insert = postgresql.insert if self.engine.dialect.name == "postgresql" else sqlite.insert
        with self.engine.begin() as conn:
            conn.execute(insert(copies).values(**values).on_conflict_do_nothing(
                index_elements=["asset_id", "recipient"]))
        stored = self.find(copy.asset_id, copy.recipient)
        assert stored is not None
        return stored

    def issue_many(self, rows: list[Copy]) -> None:
        """Bulk insert (benchmarks, imports); an existing recipient is an error here."""
        with self.engine.begin() as conn:
            conn.execute(sa.insert(copies), [
                {"asset_id": c.asset_id, "recipient": c.recipient, "codeword": c.codeword,
                 "codeword_bits": c.codeword_bits, "method": c.method, "strength": c.strength,
                 "issued_at": c.issued_at} for c in rows])

    def groups(self, asset_id: str | None) -> list[tuple[str, int, int]]:
        """(method, codeword length, copies) of the asset's copies, or of every copy."""
        q = sa.select(copies.c.method, copies.c.codeword_bits, sa.func.count()).group_by(
            copies.c.method, copies.c.codeword_bits).order_by(copies.c.method, copies.c.codeword_bits)
        if asset_id is not None:
            q = q.where(copies.c.asset_id == asset_id)
        with self.engine.connect() as conn:
            return [(m, int(n), int(k)) for m, n, k in conn.execute(q)]

    def codewords(self, asset_id: str | None, method: str, length: int) -> Codewords:
        """Every codeword of one group, packed into one array."""
        q = sa.select(copies.c.asset_id, copies.c.recipient, copies.c.codeword).where(
            copies.c.method == method, copies.c.codeword_bits == length).order_by(copies.c.id)
        if asset_id is not None:
            q = q.where(copies.c.asset_id == asset_id)
        with self.engine.connect() as conn:
            rows = conn.execute(q).all()
        nb = -(-length // 8)
        packed = np.frombuffer(b"".join(bytes(r[2]) for r in rows), np.uint8).reshape(len(rows), nb)
        return Codewords(method, length, [r[0] for r in rows], [r[1] for r in rows], packed)

    def count(self) -> int:
        with self.engine.connect() as conn:
            return int(conn.execute(sa.select(sa.func.count()).select_from(copies)).scalar_one())


def _copy(row: sa.Row) -> Copy:
    issued = row.issued_at
    if issued.tzinfo is None:  # SQLite keeps no zone: every time is written in UTC
        issued = issued.replace(tzinfo=dt.UTC)
    return Copy(row.asset_id, row.recipient, bytes(row.codeword), row.codeword_bits, row.method,
                row.strength, issued)
