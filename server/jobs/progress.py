"""A job's progress and outcome as its row of ``build_jobs`` holds them, shared by every kind of job
(:data:`server.pipeline.jobs.KINDS`)."""

from __future__ import annotations

import re
import threading
import traceback
from collections.abc import Callable
from typing import Any

from sqlalchemy import update
from sqlalchemy.orm import Session, sessionmaker

from server.config import Settings
from server.db import utcnow
from server.errors import ServiceError

from .models import BuildJob, BuildState

STAGES = ("queued", "building", "rendering", "study", "done")


class BuildError(Exception):
    """A step of the build cannot be done; the message is what the researcher reads."""


class Progress:
    """Writes the job's progress to its row (one short transaction per update); ``settings``: messages scrubbed
    of server paths (a researcher reads them); ``echo``: each message printed too (a command's job)."""

    def __init__(self, factory: sessionmaker[Session], job_id: int, settings: Settings | None = None,
                 echo: Callable[[str], None] | None = None) -> None:
        self.factory = factory
        self.job_id = job_id
        self.settings = settings
        self.echo = echo
        self._lock = threading.Lock()

    def __call__(self, stage: str | None = None, done: int | None = None, total: int | None = None,
                 message: str | None = None, **values: Any) -> None:
        changes = {k: v for k, v in (("stage", stage), ("done", done), ("total", total), ("message", message))
                   if v is not None}
        changes.update(values)
        if self.echo is not None and message:
            self.echo(message)
        for key in ("message", "error"):
            if key in changes and self.settings is not None:
                changes[key] = scrub(str(changes[key]), self.settings)
        if "message" in changes:
            changes["message"] = str(changes["message"])[-2000:]
        with self._lock, self.factory() as session:
            session.execute(update(BuildJob).where(BuildJob.id == self.job_id).values(**changes,
                                                                                     updated_at=utcnow()))
            session.commit()


def scrub(message: str, settings: Settings) -> str:
    """``message`` as a researcher may read it: no server path (an asset file by its name alone, the var and data
    directories by name)."""
    message = re.sub(re.escape(str(settings.assets_dir)) + r"/\d+/", "", message)
    for path, name in ((settings.var, "<var dir>"), (settings.data, "<data dir>")):
        message = message.replace(str(path), name)
    return message


def finish(progress: Progress, work: Callable[[], None]) -> None:
    """Run ``work`` and store the job's outcome: done, or failed with the message of what went wrong."""
    try:
        work()
    except Exception as exc:  # every failure ends the job with its message, none is a traceback to the user
        if isinstance(exc, ServiceError):
            message = exc.detail
        elif isinstance(exc, BuildError | ValueError):
            message = str(exc)
        else:
            message = f"{type(exc).__name__}: {exc}"
            traceback.print_exc()  # into the job's log
        progress(state=BuildState.failed, error=message, finished_at=utcnow())
        return
    progress(state=BuildState.done, stage="done", message="done", finished_at=utcnow())


def rendering(progress: Progress) -> Callable[[int, int], None]:
    """The job's per-video progress (stage ``rendering``) as :func:`server.media.build.render_media` reports it."""
    def videos_done(done: int, total: int) -> None:
        progress(stage="rendering", done=done, total=total)
    return videos_done
