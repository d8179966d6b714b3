"""Migration 0008 (opaque trial ids) on a database populated at revision 0006: every trial gets its own random
public id, nothing else moves, a session in progress goes on (by the new id and by the old row id a page loaded
before the upgrade holds), and going back to 0006 keeps everything."""

from __future__ import annotations

import os
import random
import re

import pytest
import sqlalchemy as sa
from sqlalchemy.orm import Session

from server.db import downgrade, migrate
from server.participants.models import ParticipantSession, Trial, Vote
from server.participants.service import authorize_answer
from tests.conftest import DATABASES, _fresh_engine
from tests.test_migration_0004 import populate_0003
from tests.test_migration_0005 import dump


def _database() -> str:
    # Its own PostgreSQL database, named after the test database (parallel runs on one server do not meet).
    name = sa.make_url(os.environ.get("TEST_DATABASE_URL", "postgresql:///test")).database or "test"
    return f"{name}_migration_0008"


@pytest.mark.parametrize("kind", DATABASES)
def test_0008_gives_every_trial_a_random_public_id_and_keeps_everything(kind, tmp_path_factory, monkeypatch):
    engine = _fresh_engine(kind, tmp_path_factory, database=_database())
    try:
        migrate(engine, "0003")
        with engine.begin() as conn:
            populate_0003(conn, random.Random(8))
        migrate(engine, "0006")
        with engine.connect() as conn:
            before = dump(conn)
        assert len(before["trials"]) > 50

        migrate(engine)

        with engine.connect() as conn:
            after = dump(conn)
            public = conn.execute(sa.text("SELECT id, public_id FROM trials ORDER BY id")).all()
        assert after == before  # every column but the new public_id (dump leaves it out)
        ids = [p for _, p in public]
        assert all(re.fullmatch(r"[0-9a-f]{32}", p) for p in ids) and len(set(ids)) == len(ids)

        with Session(engine) as db:
            # a session in progress: its next trial answers to its new id and to its old row id
            ps = next(p for p in db.scalars(sa.select(ParticipantSession)) if p.state == "active"
                      and db.scalar(sa.select(sa.func.count(Vote.id)).where(Vote.session_id == p.id)) < p.trials_total)
            token_hash = ps.token_hash
            trial = db.scalars(sa.select(Trial).where(Trial.session_id == ps.id).order_by(Trial.index)).first()
            sid, row_id, public_id = ps.id, trial.id, trial.public_id
            db.rollback()
            # The populated tokens are not stored, only hashes: this one's hash stands in for the token's.
            monkeypatch.setattr("server.participants.service._hash", lambda token: token_hash)
            assert authorize_answer(db, sid, "token", public_id)[1].id == row_id
            db.rollback()
            assert authorize_answer(db, sid, "token", str(row_id))[1].id == row_id
            db.rollback()
            db.add(Trial(session_id=sid, index=10_000, comparison_id=trial.comparison_id, reference_side="left"))
            db.commit()
            new = db.scalar(sa.select(Trial.public_id).where(Trial.index == 10_000))
            assert re.fullmatch(r"[0-9a-f]{32}", new) and new not in ids

        downgrade(engine, "0006")
        with engine.connect() as conn:
            conn.execute(sa.text('DELETE FROM trials WHERE "index" = 10000'))
            conn.commit()
            assert dump(conn) == before
    finally:
        engine.dispose()
