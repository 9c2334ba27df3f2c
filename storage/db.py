"""Opening the SQL index: an engine for a URL, migrated to the newest schema with Alembic.

engine = open_index("sqlite:///jitdyn-data/index.sqlite")      # the embedded default
engine = open_index("postgresql+psycopg://127.0.0.1/test")      # several servers, one index
"""

from __future__ import annotations

import contextlib
import fcntl
import re
from collections.abc import Iterator
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


# Any constant shared by every jitdyn process: the key of the PostgreSQL advisory lock that
# serialises migrations ("jitdyn" in ASCII).
_MIGRATION_LOCK_KEY = 0x6A6974647966


@contextlib.contextmanager
def _migration_lock(engine: sa.Engine) -> Iterator[None]:
    """Held while migrating, so that servers starting together (the processes of one `jitdyn serve
    --processes N`, or several servers on one PostgreSQL index) migrate one after the other: the
    second finds the schema at head. Without it, both inserted into alembic_version and one died
    with a UniqueViolation."""
    database = engine.url.database or ""
    if engine.dialect.name == "postgresql":
        with engine.connect() as conn:
            conn.execute(sa.text("SELECT pg_advisory_lock(:key)"), {"key": _MIGRATION_LOCK_KEY})
            try:
                yield
            finally:
                conn.execute(sa.text("SELECT pg_advisory_unlock(:key)"), {"key": _MIGRATION_LOCK_KEY})
                conn.commit()
    elif engine.dialect.name == "sqlite" and database not in ("", ":memory:"):
        with open(f"{database}.migrate.lock", "a+b") as lock:
            fcntl.flock(lock.fileno(), fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(lock.fileno(), fcntl.LOCK_UN)
    else:
        yield


def upgrade(engine: sa.Engine) -> None:
    """Apply every migration not yet applied (idempotent; safe when processes start together)."""
    with _migration_lock(engine):
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
    elif url.startswith("postgresql"):
        # A lost database (restarted, or cut off) is found in seconds, not at the kernel's TCP
        # timeout, and connections it dropped are replaced, not handed out dead.
        kwargs["connect_args"] = {
            "connect_timeout": 3,
            # A database behind a cut link: writes unacknowledged for 5 s fail instead of hanging.
            "tcp_user_timeout": 5000,
            "keepalives": 1,
            "keepalives_idle": 5,
            "keepalives_interval": 2,
            "keepalives_count": 2,
        }
        kwargs["pool_pre_ping"] = True
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

    with _migration_lock(engine):
        if schema is not None:
            # Under the lock too: CREATE SCHEMA IF NOT EXISTS races (a unique violation) as well.
            with engine.begin() as conn:
                conn.execute(sa.text(f'CREATE SCHEMA IF NOT EXISTS "{schema}"'))
        command.upgrade(_alembic_config(engine), "head")
    return engine
