from __future__ import annotations

from datetime import datetime
from typing import Any

from sqlalchemy import JSON, BigInteger, ForeignKey, String, UniqueConstraint
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
