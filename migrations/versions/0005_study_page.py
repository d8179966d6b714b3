"""The study's page settings (issue 17): language, the page's own wording, the device gate.

One nullable JSON column ``studies.page`` (``server.studies.page.Page``).  Existing studies keep NULL, which the
server reads as the defaults (English, the default wording, minimum scale 0.8): what their participants saw.
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


def downgrade() -> None:
    with op.batch_alter_table("studies") as batch:
        batch.drop_column("page")
