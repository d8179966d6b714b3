"""Observer screening and pilot runs (issue 28).

A nullable JSON column ``studies.screening`` (``server.studies.screening.Screening``): existing studies keep NULL,
which the server reads as the default, the catch-trial rule alone — what their results always were.  A boolean
``sessions.pilot`` (a researcher's preview run), false for every existing session.  Question types live in the
existing ``studies.questions`` JSON (an entry without ``type`` is multiple choice, as every existing one is).
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0009"
down_revision = "0008"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("studies") as batch:
        batch.add_column(sa.Column("screening", sa.JSON(), nullable=True))
    with op.batch_alter_table("sessions") as batch:
        batch.add_column(sa.Column("pilot", sa.Boolean(), nullable=False, server_default=sa.false()))


def downgrade() -> None:
    with op.batch_alter_table("sessions") as batch:
        batch.drop_column("pilot")
    with op.batch_alter_table("studies") as batch:
        batch.drop_column("screening")
