"""sessions.trials_total: the number of trials, stored with the session

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-22 03:55:00

The vote path needs it on every request (is this the last vote? how many are answered?); counting the trials
each time was one query per vote.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("sessions", schema=None) as batch_op:
        batch_op.add_column(sa.Column("trials_total", sa.Integer(), nullable=True))
    op.execute("UPDATE sessions SET trials_total = (SELECT count(*) FROM trials WHERE trials.session_id = sessions.id)")
    with op.batch_alter_table("sessions", schema=None) as batch_op:
        batch_op.alter_column("trials_total", existing_type=sa.Integer(), nullable=False)


def downgrade() -> None:
    with op.batch_alter_table("sessions", schema=None) as batch_op:
        batch_op.drop_column("trials_total")
