"""The shared tier of replicas sharing a PostgreSQL index: session leases with an epoch (fencing),
and the sessions' logs, one row per commit window, until the session is compacted to Parquet.

Revision ID: 0002_shared_log
Revises: 0001
Create Date: 2026-12-02
"""

import sqlalchemy as sa
from alembic import op

revision = "0002_shared_log"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "session_leases",
        sa.Column("session_id", sa.String(36), primary_key=True),
        sa.Column("tenant", sa.String(64), nullable=False, server_default=""),
        sa.Column("owner", sa.String(64), nullable=False, server_default=""),
        sa.Column("epoch", sa.BigInteger, nullable=False),
        sa.Column("expires_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("durable_seq", sa.BigInteger, nullable=True),
        sa.Column("header_json", sa.Text, nullable=False),
        sa.Column("ended_as", sa.String(16), nullable=False, server_default="RECOVERED"),
        sa.Index("ix_session_leases_expires_at", "expires_at"),
    )
    op.create_table(
        "session_log",
        sa.Column(
            "pk", sa.BigInteger().with_variant(sa.Integer, "sqlite"), primary_key=True, autoincrement=True
        ),
        sa.Column("session_id", sa.String(36), nullable=False),
        sa.Column("epoch", sa.BigInteger, nullable=False),
        sa.Column("data", sa.LargeBinary, nullable=False),
        sa.Index("ix_session_log_session_id_pk", "session_id", "pk"),
    )


def downgrade() -> None:
    op.drop_table("session_log")
    op.drop_table("session_leases")
