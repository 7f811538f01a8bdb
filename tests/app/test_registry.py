"""The registry of issued copies, on SQLite and on a real PostgreSQL server."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np
import pytest
import sqlalchemy as sa

from app.registry import Copy
from core.fingerprint import correlation_scores, pack_codeword, random_codeword
from tests.app.registries import registry_of

KINDS = ["sqlite", "postgresql"]


def _copy(asset: str, recipient: str, bits: np.ndarray, method: str = "ellipsoids") -> Copy:
    return Copy(asset, recipient, pack_codeword(bits), len(bits), method, 0.07,
                dt.datetime(2026, 12, 1, 12, 0, tzinfo=dt.UTC))


@pytest.mark.parametrize("kind", KINDS)
def test_issue_is_idempotent_per_recipient(kind: str, tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    with registry_of(kind, tmp_path) as reg:
        reg.migrate()  # a second upgrade changes nothing
        first, other = random_codeword(rng, 77), random_codeword(rng, 77)
        stored = reg.issue(_copy("asset", "alice", first))
        assert stored == _copy("asset", "alice", first)
        assert reg.issue(_copy("asset", "alice", other)).codeword == pack_codeword(first)
        assert reg.issue(_copy("asset2", "alice", other)).codeword == pack_codeword(other)
        assert reg.find("asset", "bob") is None
        assert reg.asset_length("asset") == 77 and reg.asset_length("nothing") is None
        assert reg.count() == 2
        with reg.engine.connect() as conn:
            assert conn.execute(sa.text("select version_num from alembic_version")).scalar() == "0001"
            columns = {c["name"] for c in sa.inspect(conn).get_columns("copies")}
        assert not any("key" in c for c in columns)


def test_sqlite_and_postgresql_give_the_same_trace(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    rows = [_copy("a", f"r{i}", random_codeword(rng, 100)) for i in range(300)]
    rows += [_copy("b", f"r{i}", random_codeword(rng, 60), "planes") for i in range(50)]
    votes = rng.normal(size=(2, 100))
    answers = []
    for kind in KINDS:
        with registry_of(kind, tmp_path) as reg:
            reg.issue_many(rows)
            group = reg.codewords("a", "ellipsoids", 100)
            answers.append((reg.groups(None), reg.groups("b"), group.recipients,
                            correlation_scores(votes, group.packed, 100).tolist()))
    assert answers[0] == answers[1]
    assert answers[0][0] == [("ellipsoids", 100, 300), ("planes", 60, 50)]
    assert answers[0][2] == [f"r{i}" for i in range(300)]
