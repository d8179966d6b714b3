from __future__ import annotations

from datetime import datetime
from enum import StrEnum
from typing import Any

from sqlalchemy import JSON, BigInteger, ForeignKey, String, Text, UniqueConstraint
from sqlalchemy.orm import Mapped, mapped_column

from server.db import Base, UTCDateTime, utcnow


class StudyAsset(Base):
    """A motion file uploaded into a study: stored as ``<assets dir>/<study id>/<filename>``, validated when it
    arrived; ``report`` is what inspecting it found (:func:`server.uploads.service.report_json`) and ``kind`` /
    ``first_frame`` / ``last_frame`` what its clips are built from (the suggestion unless the researcher changed
    it).  ``name`` is the animation it becomes in the clip set."""

    __tablename__ = "study_assets"
    __table_args__ = (UniqueConstraint("study_id", "filename", name="uq_study_assets_filename"),
                      UniqueConstraint("study_id", "name", name="uq_study_assets_name"),
                      {"sqlite_autoincrement": True})  # ids never reused (migration 0012)

    id: Mapped[int] = mapped_column(primary_key=True)
    study_id: Mapped[int] = mapped_column(ForeignKey("studies.id", ondelete="CASCADE"), index=True)
    name: Mapped[str] = mapped_column(String(32))
    filename: Mapped[str] = mapped_column(String(100))
    size_bytes: Mapped[int] = mapped_column(BigInteger)
    sha256: Mapped[str] = mapped_column(String(64))
    kind: Mapped[str] = mapped_column(String(16))
    first_frame: Mapped[int]
    last_frame: Mapped[int]
    report: Mapped[dict[str, Any]] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)


class BuildState(StrEnum):
    queued = "queued"
    running = "running"
    done = "done"
    failed = "failed"


class JobKind(StrEnum):
    upload = "upload"  # the build of a study's uploaded assets (the dashboard's)
    render = "render"  # `animstudy render`
    study = "study"  # `animstudy study create`


class BuildJob(Base):
    """One run of a job (:class:`JobKind`: the build of a study's assets, or a command's render or study
    creation): its progress as the dashboard polls it.  ``stage`` is one of :data:`server.uploads.progress.STAGES`;
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


class AnimationShare(Base):
    """The animation ``animation`` built from an upload of study ``study_id`` may be used by researcher
    ``researcher_id`` too (besides the study's owner and admins): sharing is explicit, one named researcher at a
    time."""

    __tablename__ = "animation_shares"
    __table_args__ = (UniqueConstraint("study_id", "animation", "researcher_id",
                                       name="uq_animation_shares_study_id"),
                      {"sqlite_autoincrement": True})  # ids never reused (migration 0012)

    id: Mapped[int] = mapped_column(primary_key=True)
    study_id: Mapped[int] = mapped_column(ForeignKey("studies.id", ondelete="CASCADE"), index=True)
    animation: Mapped[str] = mapped_column(String(32))
    researcher_id: Mapped[int] = mapped_column(ForeignKey("researchers.id", ondelete="CASCADE"), index=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
