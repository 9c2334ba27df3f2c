"""The initial index: models and sessions.

Revision ID: 0001
Revises:
Create Date: 2026-11-21
"""

from alembic import op

from storage.schema import metadata

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None


def upgrade() -> None:
    bind = op.get_bind()
    metadata.create_all(bind, tables=[metadata.tables["models"], metadata.tables["sessions"]])


def downgrade() -> None:
    bind = op.get_bind()
    metadata.drop_all(bind, tables=[metadata.tables["sessions"], metadata.tables["models"]])
