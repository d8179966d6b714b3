"""Migration 0012 (ids never reused, issue 36) on a database populated at 0011: every row of every table stays as
it was; on SQLite the id of a deleted study (the last one made, and one the server's clip set still names as the
folder of an upload) is not given again, nor a deleted build job's; PostgreSQL is left as it was (its sequences
never go back); going back to 0011 keeps every row too."""

from __future__ import annotations

import json
import os
import random

import pytest
import sqlalchemy as sa

from server.db import downgrade, migrate
from tests.conftest import DATABASES, _fresh_engine
from tests.test_migration_0004 import populate_0003

NOW = "2026-11-30 10:00:00"


def everything(conn: sa.Connection) -> dict[str, list[tuple]]:
    """Every row of every table (every column), in id order."""
    out = {}
    for table in sorted(set(sa.inspect(conn).get_table_names()) - {"alembic_version"}):
        out[table] = [tuple(map(str, r)) for r in conn.execute(sa.text(f'SELECT * FROM "{table}" ORDER BY 1'))]
    return out


def new_study(conn: sa.Connection, slug: str) -> int:
    conn.execute(sa.text(
        "INSERT INTO studies (slug, title, texts, consent_version, scale, questions, design, recruitment, state, "
        "created_at) SELECT :slug, title, texts, consent_version, scale, questions, design, recruitment, 'draft', "
        ":at FROM studies WHERE slug = 'thesis'"), {"slug": slug, "at": NOW})
    return conn.scalar(sa.text("SELECT id FROM studies WHERE slug = :slug"), {"slug": slug})


def new_job(conn: sa.Connection, study_id: int) -> int:
    conn.execute(sa.text("INSERT INTO build_jobs (study_id, kind, state, stage, done, total, message, created_at, "
                         "updated_at) VALUES (:s, 'upload', 'done', 'done', 1, 1, '', :at, :at)"),
                 {"s": study_id, "at": NOW})
    return conn.scalar(sa.text("SELECT max(id) FROM build_jobs"))


@pytest.mark.parametrize("kind", DATABASES)
def test_0012_keeps_every_row_and_never_gives_a_deleted_id_again(kind, tmp_path_factory, tmp_path):
    database = None
    if kind == "postgresql":
        database = f"{sa.make_url(os.environ['TEST_DATABASE_URL']).database}_migration_0012"
    engine = _fresh_engine(kind, tmp_path_factory, database=database)
    clips_dir = tmp_path / "var" / "clips"
    try:
        migrate(engine, "0003")
        with engine.begin() as conn:
            populate_0003(conn, random.Random(12))
        migrate(engine, "0011", media_dir=tmp_path / "var" / "media")
        with engine.begin() as conn:
            kept = new_study(conn, "kept")
            new_job(conn, kept)
            deleted = new_study(conn, "deleted")  # a draft, the last one made, deleted with its job
            conn.execute(sa.text("DELETE FROM build_jobs WHERE id = :j"), {"j": new_job(conn, deleted)})
            conn.execute(sa.text("DELETE FROM studies WHERE id = :s"), {"s": deleted})
        # the server's clip set still has the clips of an upload of a study deleted long ago (id 40)
        clips_dir.mkdir(parents=True)
        upload = tmp_path / "var" / "assets" / "40" / "private.bvh"
        (clips_dir / "manifest.json").write_text(json.dumps({"clips": [
            {"id": "private-keyframe", "animation": "private", "source": {"file": str(upload)}},
            {"id": "walk-keyframe", "animation": "walk", "source": {"file": "/data/mocap/walk.bvh"}}]}))
        with engine.connect() as conn:
            before = everything(conn)
        assert sum(map(len, before.values())) > 100

        migrate(engine, "0012", clips_dir=clips_dir)
        with engine.connect() as conn:
            assert everything(conn) == before
        with engine.begin() as conn:
            again = new_study(conn, "next")
        assert again > deleted
        if kind == "sqlite":
            assert again == 41  # above every study id the clip set names
        # from now on, no id of a deleted row is given again (SQLite reused the largest one before)
        for table, make in (("studies", lambda conn: new_study(conn, "last")),
                            ("build_jobs", lambda conn: new_job(conn, kept))):
            with engine.begin() as conn:
                last = make(conn)
                conn.execute(sa.text(f"DELETE FROM {table} WHERE id = :i"), {"i": last})
            with engine.begin() as conn:
                assert make(conn) > last, table
        if kind == "sqlite":
            with engine.connect() as conn:
                tables = conn.execute(sa.text("SELECT name FROM sqlite_master WHERE type = 'table' AND sql LIKE "
                                              "'%AUTOINCREMENT%' ORDER BY name")).scalars().all()
            assert tables == ["animation_shares", "build_jobs", "researchers", "stimulus_sets", "studies",
                              "study_assets"]

        with engine.connect() as conn:
            after = everything(conn)
        downgrade(engine, "0011")
        with engine.connect() as conn:
            assert everything(conn) == after
    finally:
        engine.dispose()
