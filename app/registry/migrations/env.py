"""Alembic environment: migrations run on the connection :meth:`app.registry.Registry.migrate` passes."""

from __future__ import annotations

from alembic import context

from app.registry.schema import metadata

connection = context.config.attributes["connection"]
context.configure(connection=connection, target_metadata=metadata)
with context.begin_transaction():
    context.run_migrations()
