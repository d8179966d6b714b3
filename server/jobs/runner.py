"""The runner: one job run to its end in this process, whatever its kind; what each kind does is given by the
caller (the registry, :data:`server.pipeline.jobs.KINDS`), so this package knows none of them.

A job's row is made first (:func:`run_in_this_process` for a command, :func:`server.jobs.control.launch` for the
API's builds); :func:`run` marks it running with this process's pid, runs the kind's function and stores its
outcome (:func:`server.jobs.progress.finish`).  A job run again after its process died (resumed) runs from the
start: every kind makes only what is missing.
"""

from __future__ import annotations

import fcntl
import os
import resource
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from server.config import Settings

from .models import BuildJob, BuildState, JobKind
from .progress import Progress, finish

#: What a kind runs: ``(settings, factory, job_id, params, progress)``; its failures raised (stored by the runner).
Work = Callable[[Settings, sessionmaker[Session], int, dict[str, Any], Progress], None]


@dataclass(frozen=True)
class Kind:
    """One kind of job.  ``for_researchers``: its messages are read by a researcher through the API (server paths
    scrubbed, nothing printed) rather than printed by a command; ``lock``: the file jobs of the kind take turns
    on (None: they run at once); ``started``: the first message (None: ``"<kind> job <id>"``)."""

    work: Work
    for_researchers: bool = False
    lock: Callable[[Settings, sessionmaker[Session], int], Path] | None = None
    started: str | None = None


def run(settings: Settings, factory: sessionmaker[Session], job_id: int, kinds: Mapping[str, Kind],
        echo: Callable[[str], None] | None = None) -> None:
    """Run the job ``job_id`` to its end (from what is missing, when it is resumed); every failure is stored in
    the job (never raised).  ``echo`` prints the messages of a command's job."""
    with factory() as session:
        job = session.get(BuildJob, job_id)
        # A row deleted meanwhile runs as the build it most likely was, which then says the job is gone.
        name, params = (job.kind, job.params or {}) if job is not None else (JobKind.upload, {})
    kind = kinds.get(name)
    if kind is None:
        progress = Progress(factory, job_id, echo=echo)
        progress(state=BuildState.failed, error=f"a job of unknown kind {name!r}")
        return
    progress = Progress(factory, job_id, settings) if kind.for_researchers else Progress(factory, job_id, echo=echo)
    started = kind.started or f"{name} job {job_id}"
    if kind.lock is None:
        progress(state=BuildState.running, stage="building", message=started, pid=os.getpid())
        finish(progress, lambda: kind.work(settings, factory, job_id, params, progress))
        return
    lock_path = kind.lock(settings, factory, job_id)
    lock_path.parent.mkdir(parents=True, exist_ok=True)
    with lock_path.open("w") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            # Another job on the same lock: this one takes its turn after it (the API allows one build per
            # researcher and ANIMSTUDY_BUILDS_MAX in all), instead of failing and being refused again.
            progress(message="waiting for another build into the same clip set to finish")
            fcntl.flock(lock, fcntl.LOCK_EX)
        progress(state=BuildState.running, stage="building", message=started, pid=os.getpid())
        finish(progress, lambda: kind.work(settings, factory, job_id, params, progress))


def run_in_this_process(settings: Settings, kind: JobKind, params: dict[str, Any], kinds: Mapping[str, Kind],
                        echo: Callable[[str], None] = lambda m: print(m, flush=True),
                        study_id: int | None = None) -> BuildJob:
    """Make a job and run it here (its ``pid`` this process's); returns the finished row."""
    from server.db import make_engine, migrate, session_factory

    engine = make_engine(settings.sqlalchemy_url)
    try:
        migrate(engine, media_dir=settings.media_dir, clips_dir=settings.clips_dir)
        factory = session_factory(engine)
        with factory() as session:
            job = BuildJob(kind=kind, params=params, study_id=study_id, state=BuildState.queued, stage="queued",
                           message="starting", pid=os.getpid())
            session.add(job)
            session.commit()
            job_id = job.id
        run(settings, factory, job_id, kinds, echo=echo)
        with factory() as session:
            finished = session.get(BuildJob, job_id)
            assert finished is not None
            session.expunge(finished)
            return finished
    finally:
        engine.dispose()


def limit_memory(megabytes: int) -> None:
    """Cap this process's address space (``ANIMSTUDY_BUILD_MEMORY_MB``; 0: no cap): a build that would take more
    fails with a MemoryError, stored in the job, instead of taking the server's memory."""
    if megabytes > 0:
        resource.setrlimit(resource.RLIMIT_AS, (megabytes << 20, megabytes << 20))

