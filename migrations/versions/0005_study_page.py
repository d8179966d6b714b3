"""The study's page settings and the device each session started on (issue 17).

A nullable JSON column ``studies.page`` (``server.studies.page.Page``): existing studies keep NULL, which the
server reads as the defaults (English, the default wording, minimum scale 0.8), what their participants saw.
A nullable JSON column ``sessions.device`` (what the device gate measured at the start): NULL for earlier
sessions, whose export columns stay empty.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("studies") as batch:
        batch.add_column(sa.Column("page", sa.JSON(), nullable=True))
    with op.batch_alter_table("sessions") as batch:
        batch.add_column(sa.Column("device", sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("sessions") as batch:
        batch.drop_column("device")
    with op.batch_alter_table("studies") as batch:
        batch.drop_column("page")
