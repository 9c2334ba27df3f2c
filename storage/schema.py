"""The SQL index's tables (SQLAlchemy Core): registered models and stored sessions.

The schema changes only through Alembic migrations in storage/migrations/versions; `jitdyn.storage.db`
applies them at start. Every row carries a `tenant`, and every read filters on it.
"""

from __future__ import annotations

import sqlalchemy as sa

__all__ = ["metadata", "model_blobs", "model_costs", "models", "session_leases", "session_log", "sessions"]

metadata = sa.MetaData(
    naming_convention={
        "ix": "ix_%(table_name)s_%(column_0_N_name)s",
        "uq": "uq_%(table_name)s_%(column_0_N_name)s",
        "pk": "pk_%(table_name)s",
    }
)

models = sa.Table(
    "models",
    metadata,
    sa.Column("pk", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("tenant", sa.String(64), nullable=False, server_default=""),
    # "sha256:<hex>" of the MJCF and its assets; unique within a tenant.
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
    # Joints, actuators and the registrant's metadata, as JSON text.
    sa.Column("description_json", sa.Text, nullable=False),
    # Space-separated tags, for filtering with LIKE without a join.
    sa.Column("tags", sa.Text, nullable=False, server_default=""),
    # Path of the stored MJCF and assets (a zip), relative to the data root.
    sa.Column("blob_path", sa.Text, nullable=False),
    sa.Column("size_bytes", sa.BigInteger, nullable=False),
    sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
    sa.UniqueConstraint("tenant", "id"),
    sa.UniqueConstraint("tenant", "name", "version"),
)

# The MJCF and assets of each registered model (the zip of registry.store), by content id: the
# shared copy every replica fetches and caches in its own data folder. Not per tenant: a content id
# is a hash of the content, so two tenants' identical models share one row.
model_blobs = sa.Table(
    "model_blobs",
    metadata,
    sa.Column("id", sa.String(80), primary_key=True),
    sa.Column("zip", sa.LargeBinary, nullable=False),
)

# What a tick of each estimator candidate costs on a model (server/runtime/choice.py), measured once
# when the model is registered, by content id like `model_blobs`: the same content costs the same,
# and every replica sharing the index chooses from the same stored figures
# (docs/decisions/0204-the-estimator-chosen-by-stored-cost.md).
model_costs = sa.Table(
    "model_costs",
    metadata,
    sa.Column("id", sa.String(80), primary_key=True),
    # A JSON list of {"scenario", "estimator", "sigma_points", "steps": [...], "seconds": [...]}.
    sa.Column("costs_json", sa.Text, nullable=False),
    sa.Column("measured_at", sa.DateTime(timezone=True), nullable=False),
)

sessions = sa.Table(
    "sessions",
    metadata,
    sa.Column("session_id", sa.String(36), primary_key=True),
    sa.Column("tenant", sa.String(64), nullable=False, server_default=""),
    sa.Column("model_id", sa.String(80), nullable=False),
    sa.Column("model_name", sa.String(64), nullable=False),
    sa.Column("model_version", sa.Integer, nullable=False),
    # Enum names without their prefix: PASSIVE, CONTROLLED, EXTERNAL; REALTIME, LOCKSTEP.
    sa.Column("scenario", sa.String(16), nullable=False),
    sa.Column("clock", sa.String(16), nullable=False),
    sa.Column("dt", sa.Float, nullable=False),
    sa.Column("estimator_json", sa.Text, nullable=False),
    # HMAC-SHA256 of the subject id (hex); "" without a subject. Never the id itself.
    sa.Column("subject_pseudonym", sa.String(64), nullable=False, server_default=""),
    sa.Column("subject_attributes_json", sa.Text, nullable=False, server_default="{}"),
    sa.Column("started_at", sa.DateTime(timezone=True), nullable=False),
    sa.Column("ended_at", sa.DateTime(timezone=True), nullable=True),
    # OPEN, COMPLETE, RECOVERED, FAILED.
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
    # Summary statistics of the session (e.g. torque ranges per joint), as JSON text.
    sa.Column("stats_json", sa.Text, nullable=False, server_default="{}"),
    # The Parquet file: its URI on the data root (s3://..., file://...), or a path relative to the
    # data folder of the server that stored it (no data root, or not yet published); "" until compacted.
    sa.Column("location", sa.Text, nullable=False, server_default=""),
    # The crash-safe log, relative to the data root; "" once compacted.
    sa.Column("log_path", sa.Text, nullable=False, server_default=""),
    sa.Index("ix_sessions_tenant_started", "tenant", "started_at"),
    sa.Index("ix_sessions_tenant_pseudonym", "tenant", "subject_pseudonym"),
    sa.Index("ix_sessions_status", "status"),
)

# Replicas sharing a PostgreSQL index (storage/shared.py): who owns an open session, under which
# epoch (a write under an older epoch is refused: fencing), until when; and its log, one row per
# commit window (an Arrow IPC record batch), until the session is compacted to Parquet.
session_leases = sa.Table(
    "session_leases",
    metadata,
    sa.Column("session_id", sa.String(36), primary_key=True),
    sa.Column("tenant", sa.String(64), nullable=False, server_default=""),
    # A random id per server process ("" while no stream holds the session); never a host name.
    sa.Column("owner", sa.String(64), nullable=False, server_default=""),
    sa.Column("epoch", sa.BigInteger, nullable=False),
    sa.Column("expires_at", sa.DateTime(timezone=True), nullable=False),
    # The highest result seq committed here with everything before it; NULL before any.
    sa.Column("durable_seq", sa.BigInteger, nullable=True),
    sa.Column("header_json", sa.Text, nullable=False),
    # What a session nobody resumes is stored as: RECOVERED (its server died) or ABANDONED.
    sa.Column("ended_as", sa.String(16), nullable=False, server_default="RECOVERED"),
    # The lease epoch of the newest resume token presented for the session (0: none yet); a token
    # of an older epoch is stale (docs/decisions/0164-bound-resume-tokens.md).
    sa.Column("token_epoch", sa.BigInteger, nullable=False, server_default="0"),
    sa.Index("ix_session_leases_expires_at", "expires_at"),
)

session_log = sa.Table(
    "session_log",
    metadata,
    sa.Column("pk", sa.BigInteger().with_variant(sa.Integer, "sqlite"), primary_key=True, autoincrement=True),
    sa.Column("session_id", sa.String(36), nullable=False),
    sa.Column("epoch", sa.BigInteger, nullable=False),
    sa.Column("data", sa.LargeBinary, nullable=False),
    # Records of the session's stream under this epoch before this window: a retried commit
    # (its first try's COMMIT may have landed) stores the window once.
    sa.Column("first_record", sa.BigInteger, nullable=True),
    sa.Index("ix_session_log_session_id_pk", "session_id", "pk"),
    sa.Index("uq_session_log_window", "session_id", "epoch", "first_record", unique=True),
)
