"""Durable jobs of every kind (issue 29): ``build_jobs`` holds the command-line renders and study creations too,
not only the builds of a study's uploads.  ``kind`` says which (``upload``, ``render``, ``study``; every existing
row is an ``upload`` job), ``params`` what a resumed job runs again (None for an upload job: its study says it),
and ``study_id`` may be empty (a render belongs to no study).  Existing rows keep every value."""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0011"
down_revision = "0010"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("build_jobs") as batch:
        batch.add_column(sa.Column("kind", sa.String(16), nullable=False, server_default="upload"))
        batch.add_column(sa.Column("params", sa.JSON(), nullable=True))
        batch.alter_column("study_id", existing_type=sa.Integer(), nullable=True)


def downgrade() -> None:
    # The jobs 0010 cannot hold (no study, another kind) go; the upload jobs stay as they were.
    op.execute("DELETE FROM build_jobs WHERE kind <> 'upload' OR study_id IS NULL")
    with op.batch_alter_table("build_jobs") as batch:
        batch.alter_column("study_id", existing_type=sa.Integer(), nullable=False)
        batch.drop_column("params")
        batch.drop_column("kind")
