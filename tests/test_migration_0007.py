"""Migration 0007 (stimulus sets) on a database populated at revision 0006 with its videos on disk: every existing
study is pinned to the files it shows now, every trial shows the same bytes as before, the export names their
sha256, and going back to 0006 keeps everything else."""

from __future__ import annotations

import hashlib
import random

import pytest
import sqlalchemy as sa
from sqlalchemy.orm import Session

from server.db import downgrade, migrate
from server.research.export import export_rows
from server.stimuli.service import SetContent
from server.studies import service
from server.studies.models import Study
from tests.conftest import DATABASES, _fresh_engine
from tests.test_migration_0004 import populate_0003
from tests.test_migration_0005 import dump

SHOWN = """
SELECT t.id, CASE WHEN t.reference_side = 'left' THEN c.video_reference_left ELSE c.video_reference_right END
FROM trials t JOIN comparisons c ON t.comparison_id = c.id ORDER BY t.id
"""


def write_media(conn: sa.Connection, media_dir, rng: random.Random) -> set[str]:
    """A file of random bytes for every video and poster the database names; returns the names."""
    names = {n for row in conn.execute(sa.text("SELECT video, poster FROM stimuli")) for n in row}
    for left, right in conn.execute(sa.text("SELECT video_reference_left, video_reference_right FROM comparisons")):
        names |= {left, right, left.rsplit(".", 1)[0] + ".jpg", right.rsplit(".", 1)[0] + ".jpg"}
    media_dir.mkdir(parents=True, exist_ok=True)
    for name in names:
        (media_dir / name).write_bytes(rng.randbytes(rng.randint(100, 3000)))
    return names


@pytest.mark.parametrize("kind", DATABASES)
def test_0007_pins_every_study_to_the_bytes_it_shows(kind, tmp_path_factory, tmp_path):
    engine = _fresh_engine(kind, tmp_path_factory, database="test_animstudy_migration_0007")
    media = tmp_path / "media"
    try:
        migrate(engine, "0003")
        with engine.begin() as conn:
            study_id = populate_0003(conn, random.Random(7))
        migrate(engine, "0006")
        with engine.connect() as conn:
            before = dump(conn)
            write_media(conn, media, random.Random(70))
            shown_before = {tid: (media / name).read_bytes() for tid, name in conn.execute(sa.text(SHOWN))}
        assert len(shown_before) > 100

        migrate(engine, media_dir=media)

        with engine.connect() as conn:
            after = dump(conn)
            shown_after = {tid: (media / name).read_bytes() for tid, name in conn.execute(sa.text(SHOWN))}
        assert shown_after == shown_before  # every trial shows the same file, byte for byte
        assert {t: rows for t, rows in after.items() if t != "studies"} == {
            t: rows for t, rows in before.items() if t != "studies"}
        with Session(engine) as db:
            study = db.get(Study, study_id)
            assert study.stimulus_set is not None
            content = SetContent.model_validate(study.stimulus_set.content)
            assert content.digest() == study.stimulus_set.digest  # the migration's digest is the service's
            assert len(content.clips) == 16 and len(content.pairs) == 8 * 2 + 1 + 2  # tests, catch, practice
            hashes = content.hashes()
            for name, sha in hashes.items():
                assert sha == hashlib.sha256((media / name).read_bytes()).hexdigest(), name
            # The export names the bytes each vote was given on: the pair video played, and each side's clip.
            rows = list(export_rows(db, study))
            assert rows and all(r["stimulus_set"] == study.stimulus_set.digest for r in rows)
            clip_video = {(s.animation, s.condition): s.video for s in study.stimuli}
            for r in rows:
                left = r["reference_condition"] if r["reference_side"] == "left" else r["test_condition"]
                right = r["test_condition"] if r["reference_side"] == "left" else r["reference_condition"]
                left_bytes = (media / clip_video[(r["animation"], left)]).read_bytes()
                right_bytes = (media / clip_video[(r["animation"], right)]).read_bytes()
                assert r["left_video"] == hashlib.sha256(left_bytes).hexdigest()
                assert r["right_video"] == hashlib.sha256(right_bytes).hexdigest()
            played = {hashlib.sha256(b).hexdigest() for b in shown_before.values()}
            assert {r["pair_video"] for r in rows} <= played

        downgrade(engine, "0006")
        with engine.connect() as conn:
            assert dump(conn) == before
            assert "stimulus_sets" not in sa.inspect(conn).get_table_names()
    finally:
        engine.dispose()


@pytest.mark.parametrize("kind", DATABASES)
def test_0007_without_the_files_records_no_hash_and_the_study_keeps_running(kind, tmp_path_factory, tmp_path):
    """A database migrated where its videos are not (another var directory): the study keeps its rows and stays
    open, its set records no hash (the export leaves them empty), and opening it again is refused."""
    engine = _fresh_engine(kind, tmp_path_factory, database="test_animstudy_migration_0007")
    try:
        migrate(engine, "0003")
        with engine.begin() as conn:
            study_id = populate_0003(conn, random.Random(8))
        migrate(engine, media_dir=tmp_path / "nothing-here")
        with Session(engine) as db:
            study = db.get(Study, study_id)
            assert study.state == "open"
            content = SetContent.model_validate(study.stimulus_set.content)
            assert set(content.hashes().values()) == {None}
            rows = list(export_rows(db, study))
            assert rows and {r["left_video"] for r in rows} == {None}
            with pytest.raises(service.Conflict, match="stimulus set is incomplete"):
                service.open_study(db, study, tmp_path / "nothing-here")
    finally:
        engine.dispose()
