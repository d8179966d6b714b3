from __future__ import annotations

from datetime import datetime
from enum import StrEnum
from typing import Any

from sqlalchemy import JSON, ForeignKey, String, Text, UniqueConstraint
from sqlalchemy.orm import Mapped, mapped_column, relationship

from server.db import Base, UTCDateTime, utcnow


class StudyState(StrEnum):
    draft = "draft"
    open = "open"
    closed = "closed"


class ComparisonKind(StrEnum):
    test = "test"  # keyframe against a hybrid increment: analysed
    catch = "catch"  # the same clip on both sides: checks attention, not analysed as a comparison
    practice = "practice"  # shown first, never analysed


class Study(Base):
    __tablename__ = "studies"

    id: Mapped[int] = mapped_column(primary_key=True)
    slug: Mapped[str] = mapped_column(String(64), unique=True)
    title: Mapped[str] = mapped_column(String(200))
    texts: Mapped[dict[str, Any]] = mapped_column(JSON)  # information, consent, instructions, thanks, contact
    consent_version: Mapped[str] = mapped_column(String(40))
    design: Mapped[dict[str, Any]] = mapped_column(JSON)
    state: Mapped[str] = mapped_column(String(16), default=StudyState.draft)
    completion_code: Mapped[str | None] = mapped_column(String(64))
    completion_url: Mapped[str | None] = mapped_column(Text)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    opened_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    closed_at: Mapped[datetime | None] = mapped_column(UTCDateTime)

    stimuli: Mapped[list[Stimulus]] = relationship(back_populates="study", cascade="all, delete-orphan")
    comparisons: Mapped[list[Comparison]] = relationship(back_populates="study", cascade="all, delete-orphan",
                                                         order_by="Comparison.id")


class Stimulus(Base):
    """A rendered clip.  Its method and increment are known to the server only."""

    __tablename__ = "stimuli"
    __table_args__ = (UniqueConstraint("study_id", "clip_id"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    study_id: Mapped[int] = mapped_column(ForeignKey("studies.id", ondelete="CASCADE"), index=True)
    clip_id: Mapped[str] = mapped_column(String(64))
    animation: Mapped[str] = mapped_column(String(32))
    method: Mapped[str] = mapped_column(String(16))
    increment: Mapped[int | None]
    video: Mapped[str] = mapped_column(String(64))
    poster: Mapped[str] = mapped_column(String(64))
    frames: Mapped[int]
    fps: Mapped[int]

    study: Mapped[Study] = relationship(back_populates="stimuli")


class Comparison(Base):
    """Keyframe clip against hybrid clip (or a clip against itself), with its side-by-side video for each side."""

    __tablename__ = "comparisons"

    id: Mapped[int] = mapped_column(primary_key=True)
    study_id: Mapped[int] = mapped_column(ForeignKey("studies.id", ondelete="CASCADE"), index=True)
    kind: Mapped[str] = mapped_column(String(16), default=ComparisonKind.test)
    animation: Mapped[str] = mapped_column(String(32))
    increment: Mapped[int | None]
    keyframe_id: Mapped[int] = mapped_column(ForeignKey("stimuli.id"))
    hybrid_id: Mapped[int] = mapped_column(ForeignKey("stimuli.id"))
    video_hybrid_left: Mapped[str] = mapped_column(String(64))
    video_hybrid_right: Mapped[str] = mapped_column(String(64))

    study: Mapped[Study] = relationship(back_populates="comparisons")
    keyframe: Mapped[Stimulus] = relationship(foreign_keys=[keyframe_id])
    hybrid: Mapped[Stimulus] = relationship(foreign_keys=[hybrid_id])

    def video(self, hybrid_side: str) -> str:
        return self.video_hybrid_left if hybrid_side == "left" else self.video_hybrid_right
