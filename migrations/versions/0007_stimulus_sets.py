"""Stimulus sets and shared animations (issue 25): new tables ``stimulus_sets`` and ``animation_shares`` (empty:
nothing was shared before), and ``studies.stimulus_set_id``.

Every existing study is pinned to the stimuli it shows now: its set lists the clips of its ``stimuli`` rows and
the pair videos of its ``comparisons`` rows, by the names participants are served, with the sha256 of each file
found in the media directory (``media_dir`` handed over by ``server.db.migrate``; a file not there is recorded
without a hash, and the export leaves its hash empty), the clips' methods and metrics from the clip manifest
and the render settings from the render manifest when they are readable.  No row of another table changes, so
every trial shows the same file as before.  The content is written as ``server.stimuli.service.SetContent``
dumps it, and its digest is that module's ``content_digest`` (repeated here: migrations do not import the app).
"""

from __future__ import annotations

import hashlib
import json
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import sqlalchemy as sa
from alembic import context, op

revision = "0007"
down_revision = "0006"
branch_labels = None
depends_on = None


def _digest(content: dict[str, Any]) -> str:
    text = json.dumps(content, sort_keys=True, separators=(",", ":"), ensure_ascii=False)
    return hashlib.sha256(text.encode()).hexdigest()


def _sha256(path: Path | None) -> str | None:
    if path is None or not path.is_file():
        return None
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _json(path: Path | None) -> Any:
    if path is None:
        return None
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def _dir(name: str) -> Path | None:
    value = context.config.attributes.get(name)
    return Path(value) if value else None


def upgrade() -> None:
    op.create_table(
        "stimulus_sets",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("digest", sa.String(length=64), nullable=False),
        sa.Column("content", sa.JSON(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_stimulus_sets")),
        sa.UniqueConstraint("digest", name=op.f("uq_stimulus_sets_digest")),
    )
    with op.batch_alter_table("studies") as batch:
        batch.add_column(sa.Column("stimulus_set_id", sa.Integer(), nullable=True))
        batch.create_index(batch.f("ix_studies_stimulus_set_id"), ["stimulus_set_id"], unique=False)
        batch.create_foreign_key(batch.f("fk_studies_stimulus_set_id_stimulus_sets"), "stimulus_sets",
                                 ["stimulus_set_id"], ["id"])
    op.create_table(
        "animation_shares",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("study_id", sa.Integer(), nullable=False),
        sa.Column("animation", sa.String(length=32), nullable=False),
        sa.Column("researcher_id", sa.Integer(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(["study_id"], ["studies.id"], name=op.f("fk_animation_shares_study_id_studies"),
                                ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["researcher_id"], ["researchers.id"],
                                name=op.f("fk_animation_shares_researcher_id_researchers"), ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_animation_shares")),
        sa.UniqueConstraint("study_id", "animation", "researcher_id", name=op.f("uq_animation_shares_study_id")),
    )
    with op.batch_alter_table("animation_shares") as batch:
        batch.create_index(batch.f("ix_animation_shares_study_id"), ["study_id"], unique=False)
        batch.create_index(batch.f("ix_animation_shares_researcher_id"), ["researcher_id"], unique=False)
    _pin_existing()


def _pin_existing() -> None:
    media_dir, clips_dir = _dir("media_dir"), _dir("clips_dir")
    render = _json(media_dir / "manifest.json" if media_dir else None)
    clip_manifest = _json(clips_dir / "manifest.json" if clips_dir else None)
    settings = render.get("settings", {}) if isinstance(render, dict) and render.get("version") == 2 else {}
    entries: dict[str, dict[str, Any]] = {}
    character = None
    if isinstance(clip_manifest, dict) and clip_manifest.get("version") == 2:
        entries = {c["id"]: c for c in clip_manifest.get("clips", []) if isinstance(c, dict) and "id" in c}
        character = clip_manifest.get("character")

    def sha(name: str) -> str | None:
        return _sha256(media_dir / name) if media_dir is not None else None

    conn = op.get_bind()
    studies = sa.table("studies", sa.column("id", sa.Integer), sa.column("stimulus_set_id", sa.Integer))
    sets = sa.table("stimulus_sets", sa.column("id", sa.Integer), sa.column("digest", sa.String),
                    sa.column("content", sa.JSON), sa.column("created_at", sa.DateTime(timezone=True)))
    for (study_id,) in conn.execute(sa.text("SELECT id FROM studies ORDER BY id")).all():
        stimuli = conn.execute(sa.text(
            "SELECT id, clip_id, animation, condition, video, poster, frames, fps FROM stimuli "
            "WHERE study_id = :s ORDER BY id"), {"s": study_id}).all()
        if not stimuli:
            continue
        clip_of = {row.id: row.clip_id for row in stimuli}
        first_with_video: dict[str, str] = {}
        clips = []
        for row in stimuli:
            e = entries.get(row.clip_id, {})
            same = first_with_video.setdefault(row.video, row.clip_id)
            clips.append({
                "video": row.video, "poster": row.poster, "video_sha256": sha(row.video),
                "poster_sha256": sha(row.poster), "id": row.clip_id, "animation": row.animation,
                "condition": row.condition, "frames": row.frames, "fps": row.fps, "method": e.get("method"),
                "params": e.get("params") or {}, "key_count": e.get("key_count"), "metrics": e.get("metrics") or {},
                "identical_to": same if same != row.clip_id else None})
        pairs: dict[tuple[str, str], str] = {}
        for c in conn.execute(sa.text(
                "SELECT reference_id, test_id, video_reference_left, video_reference_right FROM comparisons "
                "WHERE study_id = :s ORDER BY id"), {"s": study_id}).all():
            ref, test = clip_of[c.reference_id], clip_of[c.test_id]
            pairs.setdefault((ref, test), c.video_reference_left)
            pairs.setdefault((test, ref), c.video_reference_right)
        content = {"version": 1, "render": settings, "character": character, "clips": clips, "pairs": [
            {"video": video, "poster": video.rsplit(".", 1)[0] + ".jpg", "video_sha256": sha(video),
             "poster_sha256": sha(video.rsplit(".", 1)[0] + ".jpg"), "left": left, "right": right}
            for (left, right), video in pairs.items()]}
        digest = _digest(content)
        set_id = conn.scalar(sa.text("SELECT id FROM stimulus_sets WHERE digest = :d"), {"d": digest})
        if set_id is None:
            conn.execute(sa.insert(sets).values(digest=digest, content=content, created_at=datetime.now(UTC)))
            set_id = conn.scalar(sa.text("SELECT id FROM stimulus_sets WHERE digest = :d"), {"d": digest})
        conn.execute(sa.update(studies).where(studies.c.id == study_id).values(stimulus_set_id=set_id))


def downgrade() -> None:
    op.drop_table("animation_shares")
    with op.batch_alter_table("studies") as batch:
        batch.drop_constraint(batch.f("fk_studies_stimulus_set_id_stimulus_sets"), type_="foreignkey")
        batch.drop_index(batch.f("ix_studies_stimulus_set_id"))
        batch.drop_column("stimulus_set_id")
    op.drop_table("stimulus_sets")
