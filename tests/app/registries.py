"""Registries for the tests: a SQLite file, and a PostgreSQL database of this run's own.

PostgreSQL: ``$MESHMARK_TEST_POSTGRES_URL`` (default ``postgresql+psycopg://postgres@127.0.0.1:5432/postgres``)
is the server's admin connection; each test gets a fresh database on it, dropped afterwards, so
runs sharing the server never see each other's rows.  Without a server the PostgreSQL cases skip
with the reason.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
import sqlalchemy as sa

from app.registry import Registry, sqlite_url

POSTGRES_URL = os.environ.get("MESHMARK_TEST_POSTGRES_URL",
                              "postgresql+psycopg://postgres@127.0.0.1:5432/postgres")


def _postgres_problem() -> str | None:
    try:
        engine = sa.create_engine(POSTGRES_URL)
        with engine.connect() as conn:
            conn.execute(sa.text("select 1"))
        engine.dispose()
    except Exception as exc:
        return f"no PostgreSQL at {POSTGRES_URL} ({exc.__class__.__name__}); set MESHMARK_TEST_POSTGRES_URL"
    return None


POSTGRES_PROBLEM = _postgres_problem()


@contextmanager
def postgres_database() -> Iterator[str]:
    """The URL of a new, empty database, dropped on exit."""
    if POSTGRES_PROBLEM is not None:
        pytest.skip(POSTGRES_PROBLEM)
    name = f"meshmark_test_{os.getpid()}_{uuid.uuid4().hex[:8]}"
    admin = sa.create_engine(POSTGRES_URL, isolation_level="AUTOCOMMIT")
    with admin.connect() as conn:
        conn.execute(sa.text(f'CREATE DATABASE "{name}"'))
    try:
        yield sa.make_url(POSTGRES_URL).set(database=name).render_as_string(hide_password=False)
    finally:
        with admin.connect() as conn:
            conn.execute(sa.text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


@contextmanager
def registry_of(kind: str, tmp_path: Path) -> Iterator[Registry]:
    """A migrated, empty registry on ``sqlite`` or ``postgresql``."""
    database = postgres_database() if kind == "postgresql" else _nothing(sqlite_url(tmp_path / "r.sqlite3"))
    with database as url:
        reg = Registry(url)
        reg.migrate()
        try:
            yield reg
        finally:
            reg.close()


@contextmanager
def _nothing(url: str) -> Iterator[str]:
    yield url
