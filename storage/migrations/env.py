"""Alembic environment: runs the migrations on the engine storage.db hands over."""

from __future__ import annotations

from alembic import context

from jitdyn.storage.schema import metadata

engine = context.config.attributes["engine"]
with engine.begin() as connection:
    schema = (connection.get_execution_options().get("schema_translate_map") or {}).get(None)
    context.configure(
        connection=connection,
        target_metadata=metadata,
        version_table_schema=schema,
        render_as_batch=connection.dialect.name == "sqlite",
    )
    context.run_migrations()
