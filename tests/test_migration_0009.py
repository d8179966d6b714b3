"""Migration 0009 (screening rules, pilot sessions) on a database populated at revision 0006: nothing existing
changes, existing studies read as screening by catch trials alone, existing sessions are not pilots, and going
back to 0006 keeps everything."""

from __future__ import annotations

import random

import pytest
import sqlalchemy as sa
from sqlalchemy.orm import Session

from server.db import downgrade, migrate
from server.participants.models import ParticipantSession
from server.research.export import export_rows
from server.studies.models import Study
from server.studies.service import screening_rules
from tests.conftest import DATABASES, _fresh_engine
from tests.test_migration_0004 import populate_0003
from tests.test_migration_0005 import dump


@pytest.mark.parametrize("kind", DATABASES)
def test_0009_adds_screening_and_pilot_and_keeps_everything(kind, tmp_path_factory):
    engine = _fresh_engine(kind, tmp_path_factory, database="test_animstudy_migration_0009")
    try:
        migrate(engine, "0003")
        with engine.begin() as conn:
            study_id = populate_0003(conn, random.Random(9))
        migrate(engine, "0006")
        with engine.connect() as conn:
            before = dump(conn)
            assert "pilot" not in {c["name"] for c in sa.inspect(conn).get_columns("sessions")}
        assert sum(len(rows) for rows in before.values()) > 100

        migrate(engine, "0009")

        with engine.connect() as conn:
            assert dump(conn) == before
        with Session(engine) as db:
            study = db.get(Study, study_id)
            assert study.screening is None and screening_rules(study).rules == ["catch"]
            sessions = list(db.scalars(sa.select(ParticipantSession).where(ParticipantSession.study_id == study_id)))
            assert sessions and not any(ps.pilot for ps in sessions)
            rows = list(export_rows(db, study))
            assert rows and all(r["pilot"] is False for r in rows)
            assert {r["outcome"] for r in rows if r["session_state"] == "completed"} <= {"completed", "screened_out"}

        downgrade(engine, "0006")
        with engine.connect() as conn:
            assert dump(conn) == before
            assert "screening" not in {c["name"] for c in sa.inspect(conn).get_columns("studies")}
    finally:
        engine.dispose()
