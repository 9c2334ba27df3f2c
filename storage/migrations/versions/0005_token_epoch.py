"""Bound resume tokens: each session's lease keeps the epoch of the newest resume token presented
for it, and a token of an older epoch is refused as stale
(docs/decisions/0164-bound-resume-tokens.md).

Revision ID: 0005_token_epoch
Revises: 0004_window_keys
Create Date: 2026-11-28
"""

import sqlalchemy as sa
from alembic import op

revision = "0005_token_epoch"
down_revision = "0004_window_keys"
branch_labels = None
depends_on = None


def _schema() -> str | None:
    """The schema the index lives in (storage.db's schema_translate_map): ALTER is not translated."""
    return op.get_context().version_table_schema


def upgrade() -> None:
    # 0 in the leases of sessions open across the upgrade: no token presented yet.
    op.add_column(
        "session_leases",
        sa.Column("token_epoch", sa.BigInteger, nullable=False, server_default="0"),
        schema=_schema(),
    )


def downgrade() -> None:
    op.drop_column("session_leases", "token_epoch", schema=_schema())
