"""Model content in the index: replicas that share the index but not a data folder open each
other's models (docs/decisions/0100-model-content-in-the-index.md).

Revision ID: 0003_model_blobs
Revises: 0002_shared_log
Create Date: 2026-11-25
"""

import sqlalchemy as sa
from alembic import op

revision = "0003_model_blobs"
down_revision = "0002_shared_log"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "model_blobs",
        sa.Column("id", sa.String(80), nullable=False),
        sa.Column("zip", sa.LargeBinary, nullable=False),
        sa.PrimaryKeyConstraint("id", name="pk_model_blobs"),
    )


def downgrade() -> None:
    op.drop_table("model_blobs")
