"""Each model's estimator costs, measured once when it is registered: a REALTIME session's estimator
is chosen from them (docs/decisions/0204-the-estimator-chosen-by-stored-cost.md). Models registered
before have no row until their first open measures them.

Revision ID: 0006_model_costs
Revises: 0005_token_epoch
Create Date: 2026-11-29
"""

import sqlalchemy as sa
from alembic import op

revision = "0006_model_costs"
down_revision = "0005_token_epoch"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "model_costs",
        sa.Column("id", sa.String(80), nullable=False),
        sa.Column("costs_json", sa.Text, nullable=False),
        sa.Column("measured_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("id", name="pk_model_costs"),
    )


def downgrade() -> None:
    op.drop_table("model_costs")
