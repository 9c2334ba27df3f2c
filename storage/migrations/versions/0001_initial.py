"""The initial index: models and sessions.

Written out table by table rather than from storage.schema, so that later changes to the schema
module never rewrite what this revision created (tests/storage/test_session_index.py checks that the
migrations and storage.schema agree).

Revision ID: 0001
Revises:
Create Date: 2026-11-21
"""

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "models",
        sa.Column("pk", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("tenant", sa.String(64), nullable=False, server_default=""),
        sa.Column("id", sa.String(80), nullable=False),
        sa.Column("name", sa.String(64), nullable=False),
        sa.Column("version", sa.Integer, nullable=False),
        sa.Column("builtin", sa.Boolean, nullable=False, server_default=sa.false()),
        sa.Column("nq", sa.Integer, nullable=False),
        sa.Column("nv", sa.Integer, nullable=False),
        sa.Column("nu", sa.Integer, nullable=False),
        sa.Column("na", sa.Integer, nullable=False),
        sa.Column("nsensor", sa.Integer, nullable=False),
        sa.Column("nbody", sa.Integer, nullable=False),
        sa.Column("timestep", sa.Float, nullable=False),
        sa.Column("description_json", sa.Text, nullable=False),
        sa.Column("tags", sa.Text, nullable=False, server_default=""),
        sa.Column("blob_path", sa.Text, nullable=False),
        sa.Column("size_bytes", sa.BigInteger, nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("pk", name="pk_models"),
        sa.UniqueConstraint("tenant", "id", name="uq_models_tenant_id"),
        sa.UniqueConstraint("tenant", "name", "version", name="uq_models_tenant_name_version"),
    )
    op.create_table(
        "sessions",
        sa.Column("session_id", sa.String(36), nullable=False),
        sa.Column("tenant", sa.String(64), nullable=False, server_default=""),
        sa.Column("model_id", sa.String(80), nullable=False),
        sa.Column("model_name", sa.String(64), nullable=False),
        sa.Column("model_version", sa.Integer, nullable=False),
        sa.Column("scenario", sa.String(16), nullable=False),
        sa.Column("clock", sa.String(16), nullable=False),
        sa.Column("dt", sa.Float, nullable=False),
        sa.Column("estimator_json", sa.Text, nullable=False),
        sa.Column("subject_pseudonym", sa.String(64), nullable=False, server_default=""),
        sa.Column("subject_attributes_json", sa.Text, nullable=False, server_default="{}"),
        sa.Column("started_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("ended_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("status", sa.String(16), nullable=False),
        sa.Column("ticks", sa.BigInteger, nullable=False, server_default="0"),
        sa.Column("frames", sa.BigInteger, nullable=False, server_default="0"),
        sa.Column("measured", sa.BigInteger, nullable=False, server_default="0"),
        sa.Column("predicted", sa.BigInteger, nullable=False, server_default="0"),
        sa.Column("corrected", sa.BigInteger, nullable=False, server_default="0"),
        sa.Column("rejected", sa.BigInteger, nullable=False, server_default="0"),
        sa.Column("late", sa.BigInteger, nullable=False, server_default="0"),
        sa.Column("mean_compute_us", sa.Float, nullable=False, server_default="0"),
        sa.Column("max_compute_us", sa.Float, nullable=False, server_default="0"),
        sa.Column("duration", sa.Float, nullable=False, server_default="0"),
        sa.Column("stats_json", sa.Text, nullable=False, server_default="{}"),
        sa.Column("location", sa.Text, nullable=False, server_default=""),
        sa.Column("log_path", sa.Text, nullable=False, server_default=""),
        sa.PrimaryKeyConstraint("session_id", name="pk_sessions"),
    )
    op.create_index("ix_sessions_tenant_started", "sessions", ["tenant", "started_at"])
    op.create_index("ix_sessions_tenant_pseudonym", "sessions", ["tenant", "subject_pseudonym"])
    op.create_index("ix_sessions_status", "sessions", ["status"])


def downgrade() -> None:
    op.drop_index("ix_sessions_status", table_name="sessions")
    op.drop_index("ix_sessions_tenant_pseudonym", table_name="sessions")
    op.drop_index("ix_sessions_tenant_started", table_name="sessions")
    op.drop_table("sessions")
    op.drop_table("models")
