from __future__ import annotations

from datetime import datetime
from enum import StrEnum
from typing import Any

from sqlalchemy import JSON, ForeignKey, String, UniqueConstraint
from sqlalchemy.orm import Mapped, mapped_column, relationship

from server.db import Base, UTCDateTime, utcnow
from server.researchers.models import Researcher
from server.stimuli.models import StimulusSet


class StudyState(StrEnum):
    draft = "draft"
    open = "open"
    closed = "closed"


class ComparisonKind(StrEnum):
    test = "test"  # the reference condition against a test condition: analysed
    catch = "catch"  # the same clip on both sides: checks attention, not analysed as a comparison
    practice = "practice"  # shown first, never analysed


class Study(Base):
    """A study: the sections of its study file (``studyfile.StudyFile``) as JSON, its state and its owner."""

    __tablename__ = "studies"
    # Ids are never reused, on SQLite too (migration 0012): an id names the study's files, preview links, build
    # jobs and the uploads other studies may be shown; a deleted draft's id must not become another's.
    __table_args__ = ({"sqlite_autoincrement": True},)

    id: Mapped[int] = mapped_column(primary_key=True)
    slug: Mapped[str] = mapped_column(String(64), unique=True)
    title: Mapped[str] = mapped_column(String(200))
    texts: Mapped[dict[str, Any]] = mapped_column(JSON)  # information, consent, instructions, thanks, contact
    consent_version: Mapped[str] = mapped_column(String(40))
    scale: Mapped[dict[str, Any]] = mapped_column(JSON)
    questions: Mapped[list[dict[str, Any]]] = mapped_column(JSON)
    design: Mapped[dict[str, Any]] = mapped_column(JSON)
    recruitment: Mapped[dict[str, Any]] = mapped_column(JSON)
    page: Mapped[dict[str, Any] | None] = mapped_column(JSON)  # studyfile.Page; NULL (before 0005): the defaults
    screening: Mapped[dict[str, Any] | None] = mapped_column(JSON)  # screening.Screening; NULL (before 0009): catch
    owner_id: Mapped[int | None] = mapped_column(ForeignKey("researchers.id", ondelete="SET NULL"), index=True)
    state: Mapped[str] = mapped_column(String(16), default=StudyState.draft)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    opened_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    closed_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    # What it shows (server.stimuli); NULL only for a study made over media without a manifest.  Pinned (never
    # changed again) once it has opened.
    stimulus_set_id: Mapped[int | None] = mapped_column(ForeignKey("stimulus_sets.id"), index=True)

    owner: Mapped[Researcher | None] = relationship()
    stimulus_set: Mapped[StimulusSet | None] = relationship()
    stimuli: Mapped[list[Stimulus]] = relationship(back_populates="study", cascade="all, delete-orphan")
    comparisons: Mapped[list[Comparison]] = relationship(back_populates="study", cascade="all, delete-orphan",
                                                         order_by="Comparison.id")


class Stimulus(Base):
    """A rendered clip of one animation in one condition (as the render manifest names them)."""

    __tablename__ = "stimuli"
    __table_args__ = (UniqueConstraint("study_id", "clip_id"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    study_id: Mapped[int] = mapped_column(ForeignKey("studies.id", ondelete="CASCADE"), index=True)
    clip_id: Mapped[str] = mapped_column(String(64))
    animation: Mapped[str] = mapped_column(String(32))
    condition: Mapped[str] = mapped_column(String(32))
    video: Mapped[str] = mapped_column(String(64))
    poster: Mapped[str] = mapped_column(String(64))
    frames: Mapped[int]
    fps: Mapped[int]

    study: Mapped[Study] = relationship(back_populates="stimuli")


class Comparison(Base):
    """Reference stimulus against test stimulus (a catch trial: a stimulus against itself), with the
    side-by-side video of each side order."""

    __tablename__ = "comparisons"

    id: Mapped[int] = mapped_column(primary_key=True)
    study_id: Mapped[int] = mapped_column(ForeignKey("studies.id", ondelete="CASCADE"), index=True)
    kind: Mapped[str] = mapped_column(String(16), default=ComparisonKind.test)
    reference_id: Mapped[int] = mapped_column(ForeignKey("stimuli.id"))
    test_id: Mapped[int] = mapped_column(ForeignKey("stimuli.id"))
    video_reference_left: Mapped[str] = mapped_column(String(64))
    video_reference_right: Mapped[str] = mapped_column(String(64))

    study: Mapped[Study] = relationship(back_populates="comparisons")
    reference: Mapped[Stimulus] = relationship(foreign_keys=[reference_id])
    test: Mapped[Stimulus] = relationship(foreign_keys=[test_id])

    def video(self, reference_side: str) -> str:
        return self.video_reference_left if reference_side == "left" else self.video_reference_right
