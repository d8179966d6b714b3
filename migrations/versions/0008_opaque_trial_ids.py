"""Opaque trial ids (issue 26): ``trials.public_id``, 32 random hex digits, is the trial's id in the API instead of
the row id (a counter that told how many trials, hence sessions, exist).

Every existing trial gets its own random id here, so sessions in progress go on; the API still takes the old row
ids in a vote's path and an event's ``trial_id`` (a page loaded before the upgrade holds them), it only no longer
gives them out.  Nothing else changes; downgrading drops the column.
"""

from __future__ import annotations

import secrets

import sqlalchemy as sa
from alembic import op

revision = "0008"
down_revision = "0007"
branch_labels = None
depends_on = None

BATCH = 1000


def upgrade() -> None:
    op.add_column("trials", sa.Column("public_id", sa.String(length=32), nullable=True))
    conn = op.get_bind()
    trials = sa.table("trials", sa.column("id", sa.Integer()), sa.column("public_id", sa.String(32)))
    update = trials.update().where(trials.c.id == sa.bindparam("row_id")).values(public_id=sa.bindparam("value"))
    last = 0
    while True:
        ids = conn.execute(sa.select(trials.c.id).where(trials.c.id > last).order_by(trials.c.id).limit(BATCH)
                           ).scalars().all()
        if not ids:
            break
        conn.execute(update, [{"row_id": i, "value": secrets.token_hex(16)} for i in ids])
        last = ids[-1]
    op.create_index(op.f("ix_trials_public_id"), "trials", ["public_id"], unique=True)


def downgrade() -> None:
    op.drop_index(op.f("ix_trials_public_id"), table_name="trials")
    with op.batch_alter_table("trials") as batch:
        batch.drop_column("public_id")
