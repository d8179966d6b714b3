from __future__ import annotations

import secrets
from datetime import datetime
from enum import StrEnum
from typing import Any

from sqlalchemy import JSON, BigInteger, ForeignKey, String, UniqueConstraint, false
from sqlalchemy.orm import Mapped, mapped_column, relationship

from server.db import Base, UTCDateTime, utcnow
from server.studies.models import Comparison, Study


class SessionState(StrEnum):
    active = "active"
    completed = "completed"
    withdrawn = "withdrawn"


class ParticipantSession(Base):
    """An anonymous participant.  After withdrawal only the row (state, times) stays, for the withdrawal count."""

    __tablename__ = "sessions"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    study_id: Mapped[int] = mapped_column(ForeignKey("studies.id", ondelete="CASCADE"), index=True)
    token_hash: Mapped[str | None] = mapped_column(String(64), unique=True)
    seed: Mapped[int] = mapped_column(BigInteger)
    trials_total: Mapped[int]  # fixed when the trials are drawn
    state: Mapped[str] = mapped_column(String(16), default=SessionState.active)
    consent_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    consent_version: Mapped[str | None] = mapped_column(String(40))
    answers: Mapped[dict[str, Any] | None] = mapped_column(JSON)  # question id -> answer (studyfile.Question)
    external: Mapped[dict[str, Any] | None] = mapped_column(JSON)  # the study's accepted URL parameters
    device: Mapped[dict[str, Any] | None] = mapped_column(JSON)  # schemas.DeviceReport at the start (0005)
    # A researcher's pilot session (0009): left out of results and exports unless asked for, deletable at once.
    pilot: Mapped[bool] = mapped_column(default=False, server_default=false())
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    completed_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    withdrawn_at: Mapped[datetime | None] = mapped_column(UTCDateTime)

    study: Mapped[Study] = relationship()
    trials: Mapped[list[Trial]] = relationship(back_populates="session", cascade="all, delete-orphan",
                                               order_by="Trial.index")


def new_public_id() -> str:
    """A trial's id in the API: 128 random bits, so it tells nothing of how many sessions or trials exist."""
    return secrets.token_hex(16)


class Trial(Base):
    __tablename__ = "trials"
    __table_args__ = (UniqueConstraint("session_id", "index"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    # Null only for trials of before migration 0008 that it has not reached (it fills every row).
    public_id: Mapped[str | None] = mapped_column(String(32), unique=True, index=True, default=new_public_id)
    session_id: Mapped[str] = mapped_column(ForeignKey("sessions.id", ondelete="CASCADE"), index=True)
    index: Mapped[int]
    comparison_id: Mapped[int] = mapped_column(ForeignKey("comparisons.id"))
    reference_side: Mapped[str] = mapped_column(String(8))  # where the reference is; the test is opposite
    practice: Mapped[bool] = mapped_column(default=False)

    session: Mapped[ParticipantSession] = relationship(back_populates="trials")
    comparison: Mapped[Comparison] = relationship()


class Vote(Base):
    """One answer to one trial, stored exactly once (unique trial; unique idempotency key per session)."""

    __tablename__ = "votes"
    __table_args__ = (UniqueConstraint("session_id", "idempotency_key"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    trial_id: Mapped[int] = mapped_column(ForeignKey("trials.id", ondelete="CASCADE"), unique=True)
    session_id: Mapped[str] = mapped_column(ForeignKey("sessions.id", ondelete="CASCADE"), index=True)
    choice: Mapped[str] = mapped_column(String(16))
    score: Mapped[int]
    rt_ms: Mapped[int]
    idempotency_key: Mapped[str] = mapped_column(String(200))
    request_hash: Mapped[str] = mapped_column(String(64))
    extra: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    answered_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)


class PlaybackEvent(Base):
    """Something the participant's browser reported: a video that would not load, playback trouble."""

    __tablename__ = "playback_events"

    id: Mapped[int] = mapped_column(primary_key=True)
    session_id: Mapped[str] = mapped_column(ForeignKey("sessions.id", ondelete="CASCADE"), index=True)
    trial_id: Mapped[int | None] = mapped_column(ForeignKey("trials.id", ondelete="CASCADE"))
    kind: Mapped[str] = mapped_column(String(32))
    detail: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
