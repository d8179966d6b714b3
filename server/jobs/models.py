"""The job table: one row per run of a job of any kind (:class:`JobKind`), its progress and outcome."""

from __future__ import annotations

from datetime import datetime
from enum import StrEnum
from typing import Any

from sqlalchemy import JSON, ForeignKey, String, Text
from sqlalchemy.orm import Mapped, mapped_column

from server.db import Base, UTCDateTime, utcnow


class BuildState(StrEnum):
    queued = "queued"
    running = "running"
    done = "done"
    failed = "failed"


class JobKind(StrEnum):
    """What a job runs; each kind is run by one function, registered once (:data:`server.pipeline.jobs.KINDS`)."""

    upload = "upload"  # the build of a study's uploaded assets, or of the inline [clips] it was created with
    render = "render"  # `animstudy render`
    study = "study"  # `animstudy study create`
    archive = "archive"  # `animstudy study import-archive`
    default = "default"  # the default study `animstudy serve` prepares when the database holds none


class BuildJob(Base):
    """One run of a job (:class:`JobKind`: the build of a study's assets, or a command's render or study
    creation): its progress as the dashboard polls it.  ``stage`` is one of :data:`server.jobs.progress.STAGES`;
    ``done``/``total`` count the stage's steps; ``error`` is set when it failed.  ``pid`` is the job's process (a
    job whose process is gone while it says it runs is resumed by ``animstudy serve`` at start-up, and reported
    failed until then); ``params`` what a command's job runs (again, when resumed)."""

    __tablename__ = "build_jobs"
    __table_args__ = ({"sqlite_autoincrement": True},)  # ids never reused (migration 0012): a job's log is named by it

    id: Mapped[int] = mapped_column(primary_key=True)
    kind: Mapped[str] = mapped_column(String(16), default=JobKind.upload, server_default=JobKind.upload.value)
    study_id: Mapped[int | None] = mapped_column(ForeignKey("studies.id", ondelete="CASCADE"), index=True)
    params: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    state: Mapped[str] = mapped_column(String(16), default=BuildState.queued)
    stage: Mapped[str] = mapped_column(String(32), default="queued")
    done: Mapped[int] = mapped_column(default=0)
    total: Mapped[int] = mapped_column(default=0)
    message: Mapped[str] = mapped_column(Text, default="")
    error: Mapped[str | None] = mapped_column(Text)
    pid: Mapped[int | None]
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
