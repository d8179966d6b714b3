"""The default study of ``animstudy serve`` is a job of the job table (kind ``default``) like every other, so a
server stopped mid-render is taken up again: a lost default job is claimed and run again (the same row, not a
second one), and it fails as a job does, with its message stored (issue 37).

The clip set is built from a data directory without motions, so the job fails at once without rendering."""

from __future__ import annotations

import subprocess
import sys

from sqlalchemy import select
from sqlalchemy.orm import Session

from server import cli
from server.config import Settings
from server.db import make_engine, migrate, session_factory
from server.jobs.control import lost
from server.jobs.models import BuildJob, BuildState, JobKind
from server.pipeline.jobs import KINDS, prepare_default


def _settings(tmp_path, monkeypatch) -> Settings:
    empty = tmp_path / "data"
    empty.mkdir()
    monkeypatch.setenv("ANIMSTUDY_DATA_DIR", str(empty))
    monkeypatch.setenv("ANIMSTUDY_VAR_DIR", str(tmp_path / "var"))
    monkeypatch.setenv("ANIMSTUDY_SECRET_KEY", "jobs test secret 0123456789abcdef")
    monkeypatch.delenv("ANIMSTUDY_DATABASE_URL", raising=False)
    monkeypatch.delenv("DATABASE_URL", raising=False)
    monkeypatch.delenv("ANIMSTUDY_DASK_SCHEDULER", raising=False)
    return Settings()


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_every_kind_is_registered_once():
    assert set(KINDS) == set(JobKind)


def test_the_default_study_is_a_job_that_fails_with_its_message(tmp_path, monkeypatch, capsys):
    settings = _settings(tmp_path, monkeypatch)
    engine = make_engine(settings.sqlalchemy_url)
    migrate(engine)
    job = prepare_default(settings, session_factory(engine), echo=lambda _m: None)
    assert job is not None and job.kind == JobKind.default and job.state == BuildState.failed
    assert job.error and "Traceback" not in job.error
    with Session(engine) as session:
        assert session.scalars(select(BuildJob.kind)).all() == [JobKind.default]
    engine.dispose()
    assert cli.main(["serve", "--port", "1"]) == 2  # the next start tries again, and says why it cannot serve
    assert "(job 2)" in capsys.readouterr().err


def test_a_lost_default_job_is_claimed_and_run_again_not_doubled(tmp_path, monkeypatch):
    settings = _settings(tmp_path, monkeypatch)
    engine = make_engine(settings.sqlalchemy_url)
    migrate(engine)
    with Session(engine) as session:
        session.add(BuildJob(kind=JobKind.default, params={}, state=BuildState.running, stage="rendering",
                             pid=_dead_pid()))
        session.commit()
        assert lost(session.scalars(select(BuildJob)).one())
    job = prepare_default(settings, session_factory(engine), echo=lambda _m: None)
    assert job is not None and job.id == 1 and job.state == BuildState.failed  # the same row, run to its end
    with Session(engine) as session:
        assert len(session.scalars(select(BuildJob)).all()) == 1
    engine.dispose()
