"""Idempotent commit windows: each row of the shared log says where its window starts in its
stream (records before it under its epoch), and one window is stored once, however often its
commit is retried (docs/decisions/0162-idempotent-windows-and-fenced-objects.md).

Revision ID: 0004_window_keys
Revises: 0003_model_blobs
Create Date: 2026-11-28
"""

import sqlalchemy as sa
from alembic import op

revision = "0004_window_keys"
down_revision = "0003_model_blobs"
branch_labels = None
depends_on = None


def _schema() -> str | None:
    """The schema the index lives in (storage.db's schema_translate_map): ALTER is not translated."""
    return op.get_context().version_table_schema


def upgrade() -> None:
    # NULL in rows written before: PostgreSQL's unique index leaves NULLs apart.
    op.add_column("session_log", sa.Column("first_record", sa.BigInteger, nullable=True), schema=_schema())
    op.create_index(
        "uq_session_log_window",
        "session_log",
        ["session_id", "epoch", "first_record"],
        unique=True,
        schema=_schema(),
    )


def downgrade() -> None:
    op.drop_index("uq_session_log_window", table_name="session_log", schema=_schema())
    op.drop_column("session_log", "first_record", schema=_schema())
