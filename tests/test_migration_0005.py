"""Migration 0005 (the study's page settings) on a database populated at revision 0004: nothing moves, and an
existing study reads as English with the default wording and gate (what its participants saw)."""

from __future__ import annotations

import random

import pytest
import sqlalchemy as sa
from sqlalchemy.orm import Session

from server.db import migrate
from server.research.export import export_rows
from server.studies import service
from server.studies.models import Study
from tests.conftest import DATABASES, _fresh_engine
from tests.test_migration_0004 import populate_0003

TABLES = ("studies", "sessions", "trials", "votes", "comparisons", "stimuli")


# Columns added by 0005 and later migrations (each test compares what existed before its migration).
LATER_COLUMNS = ("page", "device", "stimulus_set_id", "public_id", "screening", "pilot")


def dump(conn: sa.Connection) -> dict[str, list[tuple]]:
    out = {}
    for table in TABLES:
        cols = [c["name"] for c in sa.inspect(conn).get_columns(table) if c["name"] not in LATER_COLUMNS]
        quoted = ", ".join(f'"{c}"' for c in cols)
        rows = conn.execute(sa.text(f"SELECT {quoted} FROM {table} ORDER BY 1")).all()
        out[table] = [tuple(map(str, r)) for r in rows]
    return out


@pytest.mark.parametrize("kind", DATABASES)
def test_0005_adds_the_page_and_keeps_everything(kind, tmp_path_factory):
    engine = _fresh_engine(kind, tmp_path_factory, database="test_animstudy_migration_0005")
    try:
        migrate(engine, "0003")
        with engine.begin() as conn:
            study_id = populate_0003(conn, random.Random(5))
        migrate(engine, "0004")
        with engine.connect() as conn:
            before = dump(conn)
            assert "page" not in {c["name"] for c in sa.inspect(conn).get_columns("studies")}
        assert sum(len(rows) for rows in before.values()) > 100

        migrate(engine)

        with engine.connect() as conn:
            assert dump(conn) == before
            assert conn.scalar(sa.text("SELECT page FROM studies")) is None
            assert conn.scalar(sa.text("SELECT count(*) FROM sessions WHERE device IS NOT NULL")) == 0
        with Session(engine) as db:
            page = service.definition(db.get(Study, study_id)).page
            assert (page.lang, page.dir, page.device_gate.min_scale) == ("en", "ltr", 0.8)
            assert page.chrome.submit == "Submit vote" and page.chrome.next == "Continue"
            rows = list(export_rows(db, db.get(Study, study_id)))
            assert rows and all(r["viewport_width"] is None and r["video_scaled"] is None for r in rows)
    finally:
        engine.dispose()
