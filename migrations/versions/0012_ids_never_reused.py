"""Ids are never reused, on SQLite too (issue 36).  SQLite gives a new row the largest id + 1, so the id of a deleted
draft (the last one made) went to the next study: a preview link of the deleted draft opened it, and the uploads
of the deleted draft (named ``<assets>/<study id>/<file>`` in the server's clip set) became the new study's, of
another researcher.  ``AUTOINCREMENT`` keeps the largest id ever given in ``sqlite_sequence``; the tables whose
ids name files, links or other researchers' rights get it (their rows are copied as they are: batch mode
recreates each table).  The sequence of ``studies`` starts above every study id the server's clip set still
names (the uploads of drafts deleted before this migration).  PostgreSQL's sequences never go back: nothing to do
there."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import sqlalchemy as sa
from alembic import context, op

revision = "0012"
down_revision = "0011"
branch_labels = None
depends_on = None

TABLES = ("researchers", "stimulus_sets", "studies", "study_assets", "build_jobs", "animation_shares")
UPLOAD = re.compile(r"[/\\]assets[/\\](\d+)[/\\][^/\\]+$")


def _recreate(autoincrement: bool) -> None:
    for table in TABLES:
        with op.batch_alter_table(table, recreate="always",
                                  table_kwargs={"sqlite_autoincrement": autoincrement}):
            pass


def _named_study_ids(clips_dir: Path | None) -> list[int]:
    """The study ids the server's clip set names as the folder of an upload (deleted studies' too)."""
    if clips_dir is None:
        return []
    try:
        manifest = json.loads((Path(clips_dir) / "manifest.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return []
    ids = []
    for clip in manifest.get("clips", []) if isinstance(manifest, dict) else []:
        source: Any = clip.get("source") if isinstance(clip, dict) else None
        match = UPLOAD.search(str(source.get("file", ""))) if isinstance(source, dict) else None
        if match:
            ids.append(int(match.group(1)))
    return ids


def upgrade() -> None:
    if op.get_bind().dialect.name != "sqlite":
        return
    _recreate(True)
    floor = max(_named_study_ids(context.config.attributes.get("clips_dir")), default=0)
    bind = op.get_bind()
    current = bind.scalar(sa.text("SELECT seq FROM sqlite_sequence WHERE name = 'studies'"))
    if current is None:
        bind.execute(sa.text("INSERT INTO sqlite_sequence (name, seq) VALUES ('studies', :seq)"), {"seq": floor})
    elif current < floor:
        bind.execute(sa.text("UPDATE sqlite_sequence SET seq = :seq WHERE name = 'studies'"), {"seq": floor})


def downgrade() -> None:
    if op.get_bind().dialect.name != "sqlite":
        return
    _recreate(False)
