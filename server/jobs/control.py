"""Process control of jobs: each job runs in a process of its own on this machine (its ``pid`` in its row); a job
whose process is gone while it says it is queued or running is *lost*: read as failed, and resumed (claimed by an
update on the pid it had, so it is resumed once) by ``animstudy serve`` at start-up.  What a job of each kind runs
is :data:`server.pipeline.jobs.KINDS`."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

from sqlalchemy import Engine, select, update
from sqlalchemy.orm import Session

from server.config import Settings
from server.db import utcnow
from server.errors import Conflict
from server.studies.models import Study

from .models import BuildJob, BuildState, JobKind

ACTIVE = (BuildState.queued, BuildState.running)
#: The module a job's process runs (``python -m RUNNER JOB_ID``): the one that knows every kind.
RUNNER = "server.pipeline.jobs"


def _alive(pid: int | None) -> bool:
    if pid is None:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, another user's
        return True
    return True


LOST = "the build process ended unexpectedly (killed, or the server restarted)"


def lost(job: BuildJob) -> bool:
    """Does the job say it is queued or running while its process is gone?  The process runs on this machine
    (the job's ``pid``)."""
    return job.state in ACTIVE and job.pid is not None and not _alive(job.pid)


def running_jobs(session: Session) -> list[BuildJob]:
    """The jobs of every kind that are queued or running and whose process is alive (changes nothing)."""
    return [j for j in session.scalars(select(BuildJob).where(BuildJob.state.in_(list(ACTIVE)))
                                       .order_by(BuildJob.id)).all() if not lost(j)]


def active_jobs(session: Session) -> list[BuildJob]:
    """The upload jobs queued or running (of any study); lost ones are marked failed on the way (``animstudy
    serve`` resumes the ones still marked active when it starts: :func:`resume_lost_jobs`)."""
    active = []
    for job in session.scalars(select(BuildJob).where(BuildJob.state.in_(list(ACTIVE)),
                                                      BuildJob.kind == JobKind.upload)).all():
        if lost(job):
            job.state, job.error, job.finished_at = BuildState.failed, LOST, utcnow()
            session.commit()
        else:
            active.append(job)
    return active


def check_not_building(session: Session, study: Study) -> None:
    if any(j.study_id == study.id for j in active_jobs(session)):
        raise Conflict(f"the assets of study {study.slug!r} are being built; wait until the build has finished")


def latest_job(session: Session, study: Study) -> BuildJob | None:
    """The study's latest upload job (what its dashboard shows)."""
    return session.scalar(select(BuildJob).where(BuildJob.study_id == study.id, BuildJob.kind == JobKind.upload)
                          .order_by(BuildJob.id.desc()).limit(1))


def job_environment(settings: Settings, engine: Engine) -> dict[str, str]:
    """The environment of the job's process: the server's settings and its database (the engine's URL, which
    is the settings' unless the app was given another engine)."""
    env = {**os.environ, "ANIMSTUDY_DATA_DIR": str(settings.data), "ANIMSTUDY_VAR_DIR": str(settings.var),
           "DATABASE_URL": engine.url.render_as_string(hide_password=False)}
    env.pop("ANIMSTUDY_DATABASE_URL", None)
    env["ANIMSTUDY_BUILD_MEMORY_MB"] = str(settings.build_memory_mb)
    if settings.secret_key:
        env["ANIMSTUDY_SECRET_KEY"] = settings.secret_key
    return env


def check_build_slot(session: Session, settings: Settings, owner_id: int | None) -> None:
    """409 while the researcher ``owner_id`` has a build running (one at a time each, naming their own study),
    or while the server runs ``ANIMSTUDY_BUILDS_MAX`` builds (naming none: they may be other researchers').
    Builds into one clip set take turns in the job (:func:`server.pipeline.jobs.run`), so one researcher's long
    build never refuses another's."""
    running = active_jobs(session)
    studies = {s.id: s for s in session.scalars(select(Study).where(Study.id.in_([j.study_id for j in running])))}
    own = [studies[j.study_id] for j in running if j.study_id in studies and studies[j.study_id].owner_id == owner_id]
    if own:
        raise Conflict(f"your build of study {own[0].slug!r} is running; wait until it has finished")
    if len(running) >= settings.builds_max:
        raise Conflict(f"the server is running as many builds as it allows ({settings.builds_max}); try again in "
                       "a few minutes")


def launch(session: Session, settings: Settings, engine: Engine, study: Study) -> BuildJob:
    """Queue the build job of ``study`` (kind ``upload``) and start its process."""
    job = BuildJob(study_id=study.id, state=BuildState.queued, stage="queued", message="starting")
    session.add(job)
    session.commit()
    return start_job(session, settings, engine, job, "w")


def job_log(settings: Settings, job: BuildJob) -> Path:
    """Where the job's process writes its output: beside the study's assets for an upload job."""
    if job.kind == JobKind.upload and job.study_id is not None:
        return settings.study_assets_dir(job.study_id) / "build.log"
    return settings.var / "jobs" / f"{job.id}.log"


def start_job(session: Session, settings: Settings, engine: Engine, job: BuildJob, mode: str = "a") -> BuildJob:
    """Start the process of the queued ``job`` (``python -m server.pipeline.jobs ID``) and record its pid."""
    log_path = job_log(settings, job)
    log_path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with log_path.open(mode, encoding="utf-8") as log:
            proc = subprocess.Popen([sys.executable, "-m", RUNNER, str(job.id)],
                                    env=job_environment(settings, engine), stdout=log, stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL, start_new_session=True)
    except OSError as exc:
        job.state, job.error, job.finished_at = BuildState.failed, f"cannot start the build: {exc}", utcnow()
        session.commit()
        return job
    threading.Thread(target=proc.wait, daemon=True).start()  # reap it when it ends (no zombie)
    job.pid = proc.pid
    session.commit()
    return job


def resume_lost_jobs(session: Session, settings: Settings, engine: Engine) -> list[BuildJob]:
    """Start again every job that says it is queued or running while its process is gone (the server, the
    command or the machine stopped mid-job); each runs from the start and renders only the videos still missing
    (their names say what they show).  A job is claimed by an update on the pid it had, so two instances
    starting together resume it once.  Called by ``animstudy serve`` at start-up."""
    resumed = []
    for job in lost_jobs(session):
        if claim(session, job):
            resumed.append(start_job(session, settings, engine, job))
    return resumed


def lost_jobs(session: Session, kind: JobKind | None = None) -> list[BuildJob]:
    """The jobs (of ``kind``, or every kind) that say they are queued or running while their process is gone."""
    query = select(BuildJob).where(BuildJob.state.in_(list(ACTIVE))).order_by(BuildJob.id)
    if kind is not None:
        query = query.where(BuildJob.kind == kind)
    return [j for j in session.scalars(query).all() if lost(j)]


def claim(session: Session, job: BuildJob) -> bool:
    """Take the lost ``job`` to run it again: an update on the pid it had, so of two processes claiming it
    together one gets it (True; the job is queued again without a pid, refreshed)."""
    claimed = session.execute(
        update(BuildJob).where(BuildJob.id == job.id, BuildJob.pid == job.pid, BuildJob.state.in_(list(ACTIVE)))
        .values(state=BuildState.queued, pid=None, message="resumed: its process had ended",
                updated_at=utcnow())).rowcount
    session.commit()
    if claimed:
        session.refresh(job)
    return bool(claimed)


def job_json(job: BuildJob | None) -> dict[str, Any] | None:
    """The job as the API serves it (a lost job as failed: reads do not write)."""
    if job is None:
        return None
    gone = lost(job)
    return {"id": job.id, "state": BuildState.failed if gone else job.state, "stage": job.stage, "done": job.done,
            "total": job.total, "message": job.message, "error": LOST if gone else job.error,
            "created_at": job.created_at.isoformat(),
            "finished_at": job.finished_at.isoformat() if job.finished_at else None}
