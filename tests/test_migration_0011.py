"""Migration 0011 (jobs of every kind) on a database populated at 0010 with upload jobs: every row of every table
stays as it was, the existing jobs read as upload jobs without params, a command's job (no study) can be stored,
and going back to 0010 drops only the jobs 0010 cannot hold."""

from __future__ import annotations

import os
import random

import pytest
import sqlalchemy as sa

from server.db import downgrade, migrate
from tests.conftest import DATABASES, _fresh_engine
from tests.test_migration_0004 import populate_0003
from tests.test_migration_0005 import dump

JOB_COLUMNS = ("id", "study_id", "state", "stage", "done", "total", "message", "error", "pid", "created_at",
               "updated_at", "finished_at")


def jobs(conn: sa.Connection) -> list[tuple]:
    quoted = ", ".join(f'"{c}"' for c in JOB_COLUMNS)
    return [tuple(map(str, r)) for r in conn.execute(sa.text(f"SELECT {quoted} FROM build_jobs ORDER BY id"))]


@pytest.mark.parametrize("kind", DATABASES)
def test_0011_keeps_the_upload_jobs_and_takes_command_jobs(kind, tmp_path_factory, tmp_path):
    database = None
    if kind == "postgresql":
        database = f"{sa.make_url(os.environ['TEST_DATABASE_URL']).database}_migration_0011"
    engine = _fresh_engine(kind, tmp_path_factory, database=database)
    try:
        migrate(engine, "0003")
        with engine.begin() as conn:
            study_id = populate_0003(conn, random.Random(13))
        migrate(engine, "0010", media_dir=tmp_path / "media")
        with engine.begin() as conn:
            for i, (state, error, pid) in enumerate([("done", None, 11), ("failed", "no such joint 'Hips'", 12),
                                                     ("running", None, 13)], 1):
                conn.execute(sa.text(
                    "INSERT INTO build_jobs (study_id, state, stage, done, total, message, error, pid, created_at, "
                    "updated_at) VALUES (:study, :state, 'rendering', 3, 7, 'm', :error, :pid, :at, :at)"),
                    {"study": study_id, "state": state, "error": error, "pid": pid, "at": f"2026-01-0{i} 10:00:00"})
        with engine.connect() as conn:
            before, jobs_before = dump(conn), jobs(conn)
        assert sum(map(len, before.values())) > 100 and len(jobs_before) == 3

        migrate(engine, "0011")
        with engine.connect() as conn:
            assert dump(conn) == before
            assert jobs(conn) == jobs_before
            assert conn.execute(sa.text("SELECT DISTINCT kind FROM build_jobs")).scalars().all() == ["upload"]
            assert conn.scalar(sa.text("SELECT count(*) FROM build_jobs WHERE params IS NOT NULL")) == 0
        with engine.begin() as conn:
            conn.execute(sa.text("INSERT INTO build_jobs (kind, params, state, stage, done, total, message, "
                                 "created_at, updated_at) VALUES ('render', '{\"out\": \"/v\"}', 'running', "
                                 "'rendering', 0, 4, '', '2026-02-01 10:00:00', '2026-02-01 10:00:00')"))
        with engine.connect() as conn:
            assert conn.scalar(sa.text("SELECT count(*) FROM build_jobs WHERE study_id IS NULL")) == 1

        downgrade(engine, "0010")
        with engine.connect() as conn:
            assert dump(conn) == before
            assert jobs(conn) == jobs_before  # the render job went, the upload jobs stayed
            assert "kind" not in {c["name"] for c in sa.inspect(conn).get_columns("build_jobs")}
    finally:
        engine.dispose()
