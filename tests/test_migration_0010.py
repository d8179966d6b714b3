"""Migration 0010 (limits shared through the database) on a database populated at 0007: every row of every
table stays as it was, the two new tables start empty and take the limits' rows, and going back to 0007 keeps
everything else."""

from __future__ import annotations

import os
import random

import pytest
import sqlalchemy as sa
from sqlalchemy.orm import Session

from server.db import downgrade, migrate
from server.security import LoginLimiter, RateLimiter
from tests.conftest import DATABASES, _fresh_engine
from tests.test_migration_0004 import populate_0003
from tests.test_migration_0005 import dump


@pytest.mark.parametrize("kind", DATABASES)
def test_0010_adds_the_limit_tables_and_keeps_everything(kind, tmp_path_factory, tmp_path):
    database = None
    if kind == "postgresql":
        database = f"{sa.make_url(os.environ['TEST_DATABASE_URL']).database}_migration_0010"
    engine = _fresh_engine(kind, tmp_path_factory, database=database)
    try:
        migrate(engine, "0003")
        with engine.begin() as conn:
            populate_0003(conn, random.Random(11))
        migrate(engine, "0007", media_dir=tmp_path / "media")
        with engine.connect() as conn:
            before = dump(conn)
        assert sum(map(len, before.values())) > 100

        migrate(engine, "0010")
        with engine.connect() as conn:
            assert dump(conn) == before
            assert conn.scalar(sa.text("SELECT count(*) FROM rate_events")) == 0
            assert conn.scalar(sa.text("SELECT count(*) FROM known_logins")) == 0
        with Session(engine) as session:
            limiter = RateLimiter(2, clock=lambda: 1000.0)
            assert [limiter.hit(session, "203.0.113.1") for _ in range(3)][:2] == [None, None]
            LoginLimiter(clock=lambda: 1000.0).succeeded(session, "203.0.113.1", "a@example.org")
        with engine.connect() as conn:
            assert conn.scalar(sa.text("SELECT count(*) FROM rate_events")) == 2
            assert conn.scalar(sa.text("SELECT count(*) FROM known_logins")) == 1

        downgrade(engine, "0007")
        with engine.connect() as conn:
            assert dump(conn) == before
            assert not sa.inspect(conn).has_table("rate_events")
    finally:
        engine.dispose()
