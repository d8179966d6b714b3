"""Migration 0013 (threshold designs store their levels, issue 38) on a database populated at 0012: a staircase
study stored without levels gets them, from the server's clip manifest where it has the condition on the ladder
and else from the condition id as the code before read it; a study of another mode, one with levels already and
one whose conditions are neither keep their design; every other row stays as it was; going back removes levels."""

from __future__ import annotations

import json
import os
import random

import pytest
import sqlalchemy as sa

from server.db import downgrade, migrate
from server.studies.design import Design
from tests.conftest import DATABASES, _fresh_engine
from tests.test_migration_0004 import populate_0003
from tests.test_migration_0012 import everything, new_study

STAIRCASE = {"mode": "staircase", "reference": "keyframe", "ladder": "pps", "conditions": ["pps4", "pps12", "pps24"],
             "animations": ["walk"], "repeats": 1, "catch_trials": 0, "trials": 10, "detectable_at": "low"}


def set_design(conn: sa.Connection, study_id: int, design: dict) -> None:
    conn.execute(sa.text("UPDATE studies SET design = :d WHERE id = :i"), {"d": json.dumps(design), "i": study_id})


def design_of(conn: sa.Connection, study_id: int) -> dict:
    value = conn.scalar(sa.text("SELECT design FROM studies WHERE id = :i"), {"i": study_id})
    return value if isinstance(value, dict) else json.loads(value)


@pytest.mark.parametrize("kind", DATABASES)
def test_0013_gives_stored_threshold_studies_their_levels(kind, tmp_path_factory, tmp_path):
    database = None
    if kind == "postgresql":
        database = f"{sa.make_url(os.environ['TEST_DATABASE_URL']).database}_migration_0013"
    engine = _fresh_engine(kind, tmp_path_factory, database=database)
    clips_dir = tmp_path / "var" / "clips"
    clips_dir.mkdir(parents=True)
    # the server's clip set says pps12 is level 11.5 (its id says 12); pps4 and pps24 it does not name
    (clips_dir / "manifest.json").write_text(json.dumps({"clips": [
        {"id": "walk-pps12", "animation": "walk", "condition": "pps12", "ladder": "pps", "level": 11.5},
        {"id": "walk-keyframe", "animation": "walk", "condition": "keyframe", "ladder": None, "level": None}]}))
    try:
        migrate(engine, "0003")
        with engine.begin() as conn:
            populate_0003(conn, random.Random(13))
        migrate(engine, "0012", media_dir=tmp_path / "var" / "media")
        with engine.begin() as conn:
            thesis = conn.scalar(sa.text("SELECT id FROM studies WHERE slug = 'thesis'"))
            staircase, settled, unknown = (new_study(conn, s) for s in ("staircase", "settled", "unknown"))
            set_design(conn, staircase, STAIRCASE)
            set_design(conn, settled, {**STAIRCASE, "levels": {"pps4": 4, "pps12": 12, "pps24": 24}})
            set_design(conn, unknown, {**STAIRCASE, "conditions": ["pps4", "fast", "pps24"]})
        with engine.connect() as conn:
            before = everything(conn)
            designs = {s: design_of(conn, s) for s in (thesis, settled, unknown)}

        migrate(engine, "0013", clips_dir=clips_dir)
        with engine.connect() as conn:
            stored = design_of(conn, staircase)
            assert stored == {**STAIRCASE, "levels": {"pps4": 4.0, "pps12": 11.5, "pps24": 24.0}}
            assert list(Design.model_validate(stored).level_order()) == ["pps24", "pps12", "pps4"]
            assert {s: design_of(conn, s) for s in designs} == designs
            after = everything(conn)
        changed = [r for r in after["studies"] if r not in before["studies"]]
        assert len(changed) == 1 and {t: r for t, r in after.items() if t != "studies"} == {
            t: r for t, r in before.items() if t != "studies"}

        downgrade(engine, "0012")
        with engine.connect() as conn:
            assert design_of(conn, staircase) == STAIRCASE
            assert design_of(conn, settled) == STAIRCASE  # the earlier code knew no levels field
            assert design_of(conn, thesis) == designs[thesis]
    finally:
        engine.dispose()
