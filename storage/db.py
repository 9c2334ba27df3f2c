"""Opening the SQL index: an engine for a URL, migrated to the newest schema with Alembic.

engine = open_index("sqlite:///jitdyn-data/index.sqlite")      # the embedded default
engine = open_index("postgresql+psycopg://127.0.0.1/test")      # several servers, one index
"""

from __future__ import annotations

import re
from pathlib import Path

import sqlalchemy as sa
from alembic import command
from alembic.config import Config

from jitdyn.errors import InvalidArgument

__all__ = ["default_index_url", "open_index", "upgrade"]

# Interpolated into CREATE SCHEMA, so nothing but a plain identifier.
_IDENTIFIER = re.compile(r"[a-z_][a-z0-9_]{0,62}")
_MIGRATIONS = Path(__file__).resolve().parent / "migrations"


def default_index_url(data_root: Path) -> str:
    """The embedded default: a SQLite file in the data folder."""
    return f"sqlite:///{(data_root / 'index.sqlite').resolve()}"


def _alembic_config(engine: sa.Engine) -> Config:
    config = Config()
    config.set_main_option("script_location", str(_MIGRATIONS))
    config.attributes["engine"] = engine
    return config


def upgrade(engine: sa.Engine) -> None:
    """Apply every migration not yet applied (idempotent)."""
    command.upgrade(_alembic_config(engine), "head")


def open_index(url: str, *, schema: str | None = None) -> sa.Engine:
    """An engine for the index at `url`, migrated to the newest schema.

    `schema` (PostgreSQL only) puts the tables in that schema, created when missing; tests isolate
    each run this way.
    """
    if schema is not None and not _IDENTIFIER.fullmatch(schema):
        raise InvalidArgument(
            f"schema must be a plain SQL identifier ([a-z_][a-z0-9_]*, at most 63), got {schema!r}"
        )
    kwargs: dict[str, object] = {"future": True}
    if url.startswith("sqlite"):
        # Sessions write from the event loop's thread and from the recovery thread.
        kwargs["connect_args"] = {"check_same_thread": False, "timeout": 30}
    if schema is not None:
        kwargs["execution_options"] = {"schema_translate_map": {None: schema}}
    try:
        engine = sa.create_engine(url, **kwargs)
    except (sa.exc.ArgumentError, sa.exc.NoSuchModuleError) as exc:
        raise InvalidArgument(f"index URL {url!r} is not usable: {exc}") from exc
    if url.startswith("sqlite"):

        @sa.event.listens_for(engine, "connect")
        def _sqlite_pragmas(dbapi_connection, _record):  # type: ignore[no-untyped-def]
            cursor = dbapi_connection.cursor()
            cursor.execute("PRAGMA journal_mode=WAL")
            cursor.execute("PRAGMA synchronous=FULL")
            cursor.close()

    if schema is not None:
        with engine.begin() as conn:
            conn.execute(sa.text(f'CREATE SCHEMA IF NOT EXISTS "{schema}"'))
    upgrade(engine)
    return engine
