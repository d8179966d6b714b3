"""Durable jobs: `animstudy render` is a job of the database (kind ``render``) with per-video progress; killed
with -9 mid-job, it is resumed the way ``animstudy serve`` resumes lost jobs at start-up, finishes, and renders
only the videos that were missing (counted), leaving the finished ones untouched.

A small clip set (two animations, two conditions, 96x72 without shadows) keeps it short."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from sqlalchemy import select
from sqlalchemy.orm import Session

from server.clipset.build import build_clip_set
from server.clipset.manifest import write_clip_set
from server.config import Settings
from server.db import migrate
from server.jobs.control import resume_lost_jobs
from server.jobs.models import BuildJob, BuildState, JobKind
from server.media.manifest import read_render_manifest
from tests.conftest import DATABASES, _fresh_engine
from tests.server_fixtures import small_clip_config
from tests.test_cluster import broken_clip_set

ROOT = Path(__file__).resolve().parents[1]
SECRET = "job resume test secret"


@pytest.fixture(scope="module")
def clips_dir(data, tmp_path_factory):
    out = tmp_path_factory.mktemp("clips")
    write_clip_set(build_clip_set(data, small_clip_config()), out)
    return out


def _videos(out: Path) -> dict[str, int]:
    """Finished videos (with their poster) and their inodes: a video rendered again is a new file."""
    if not out.is_dir():
        return {}
    return {f.name: f.stat().st_ino for f in out.iterdir() if f.suffix == ".mp4" and f.with_suffix(".jpg").is_file()}


@pytest.mark.slow  # tens of seconds (the parallel run's slowest; still run by `make test`)
@pytest.mark.parametrize("kind", DATABASES)
def test_a_render_killed_mid_job_is_resumed_and_renders_only_what_was_missing(kind, data, clips_dir, tmp_path,
                                                                              tmp_path_factory, monkeypatch):
    database = None
    if kind == "postgresql":
        database = f"{__import__('sqlalchemy').make_url(os.environ['TEST_DATABASE_URL']).database}_resume"
    engine = _fresh_engine(kind, tmp_path_factory, database=database)
    url = engine.url.render_as_string(hide_password=False)
    migrate(engine)
    study = tmp_path / "small.toml"
    text = (ROOT / "studies" / "example.toml").read_text(encoding="utf-8")
    study.write_text(text.replace('conditions = ["hybrid1", "hybrid2"]', 'conditions = ["hybrid0"]')
                     .replace('animations = ["walk", "run"]', 'animations = ["run", "idle"]'), encoding="utf-8")
    out = tmp_path / "media"
    env = {**os.environ, "DATABASE_URL": url, "ANIMSTUDY_VAR_DIR": str(tmp_path / "var"),
           "ANIMSTUDY_SECRET_KEY": SECRET, "ANIMSTUDY_DATA_DIR": str(data), "PYTHONPATH": str(ROOT)}
    env.pop("ANIMSTUDY_DASK_SCHEDULER", None)
    first = subprocess.Popen([sys.executable, "-m", "server.cli", "render", "--clips", str(clips_dir), "--out",
                              str(out), "--study", str(study), "--workers", "1", "--width", "96", "--height", "72",
                              "--no-shadows"], env=env, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 240
        while not _videos(out):
            assert first.poll() is None, f"the render ended before it was killed: {first.stderr.read()[-2000:]}"
            assert time.monotonic() < deadline, "no video was stored"
            time.sleep(0.05)
    finally:
        first.kill()
        first.wait(10)
    before = _videos(out)
    with Session(engine) as session:
        job = session.scalars(select(BuildJob)).one()
        assert (job.kind, job.state, job.pid, job.study_id) == (JobKind.render, BuildState.running, first.pid, None)
        # Progress per video; the kill may come between videos and their row's update (in one process a clip's
        # render finishes its own video and the pairs it completes at once), so the row may count fewer.
        total = job.total
        assert job.stage == "rendering" and total >= 8 and job.done <= len(before) < total

    for key, value in env.items():
        if key.startswith("ANIMSTUDY_") or key == "DATABASE_URL":
            monkeypatch.setenv(key, value)
    settings = Settings()
    with Session(engine) as session:
        resumed = resume_lost_jobs(session, settings, engine)
        assert [j.id for j in resumed] == [job.id]
        assert resume_lost_jobs(session, settings, engine) == []  # running again: not lost, not resumed twice
    deadline = time.monotonic() + 300
    while True:
        with Session(engine) as session:
            again = session.get(BuildJob, job.id)
            if again.state not in (BuildState.queued, BuildState.running):
                break
        assert time.monotonic() < deadline, f"the resumed job did not finish: {again.stage} {again.message}"
        time.sleep(0.5)
    log = (tmp_path / "var" / "jobs" / f"{job.id}.log").read_text(errors="replace")
    assert again.state == BuildState.done, f"{again.error}\n{log[-3000:]}"
    # Only the missing videos were rendered: the plan counted them, and the finished ones are the same files.
    missing = total - len(before)
    assert (again.done, again.total) == (missing, missing), log[-3000:]
    assert f"{total} videos, {len(before)} up to date, {missing} to render" in log
    after = _videos(out)
    assert len(after) == total and {name: after[name] for name in before} == before
    manifest = read_render_manifest(out)
    assert {p.video for p in manifest.pairs} | {c.video for c in manifest.clips.values()} == set(after)
    engine.dispose()


@pytest.mark.parametrize("kind", DATABASES)
def test_a_clip_that_fails_fails_the_job_naming_it_and_the_other_videos_are_stored(kind, data, clips_dir, tmp_path,
                                                                                   tmp_path_factory, monkeypatch,
                                                                                   capsys):
    from server.cli import main

    database = None
    if kind == "postgresql":
        database = f"{__import__('sqlalchemy').make_url(os.environ['TEST_DATABASE_URL']).database}_failing"
    engine = _fresh_engine(kind, tmp_path_factory, database=database)
    broken, bad = broken_clip_set(clips_dir, tmp_path / "clips")
    study = tmp_path / "small.toml"
    text = (ROOT / "studies" / "example.toml").read_text(encoding="utf-8")
    study.write_text(text.replace('conditions = ["hybrid1", "hybrid2"]', 'conditions = ["hybrid0"]')
                     .replace('animations = ["walk", "run"]', 'animations = ["run", "idle"]'), encoding="utf-8")
    for key, value in {"DATABASE_URL": engine.url.render_as_string(hide_password=False),
                       "ANIMSTUDY_VAR_DIR": str(tmp_path / "var"), "ANIMSTUDY_SECRET_KEY": SECRET}.items():
        monkeypatch.setenv(key, value)
    monkeypatch.delenv("ANIMSTUDY_DASK_SCHEDULER", raising=False)
    out = tmp_path / "media"
    assert main(["render", "--clips", str(broken), "--out", str(out), "--study", str(study), "--workers", "2",
                 "--width", "96", "--height", "72", "--no-shadows"]) == 2
    assert f"rendering clip {bad.id} (idle) failed" in capsys.readouterr().err
    with Session(engine) as session:
        job = session.scalars(select(BuildJob)).one()
        assert job.state == BuildState.failed and f"clip {bad.id}" in job.error
        # The other animation's videos were rendered and stored (on two local workers a task is one animation, so
        # the broken clip's animation fails as a whole; tests/test_cluster.py checks per-video tasks).
        failed = job.error.count("rendering clip")
        assert failed >= 1 and 0 < job.done < job.total, job.error
    assert len(_videos(out)) == job.done
    engine.dispose()
