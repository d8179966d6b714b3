from __future__ import annotations

from datetime import datetime
from typing import Any

from sqlalchemy import JSON, String
from sqlalchemy.orm import Mapped, mapped_column

from server.db import Base, UTCDateTime, utcnow


class StimulusSet(Base):
    """One stimulus set: ``content`` (:class:`server.stimuli.service.SetContent` as JSON) and ``digest``, the
    sha256 of its canonical JSON, which names it.  Rows are never changed: another content is another row."""

    __tablename__ = "stimulus_sets"
    __table_args__ = ({"sqlite_autoincrement": True},)  # ids never reused (migration 0012)

    id: Mapped[int] = mapped_column(primary_key=True)
    digest: Mapped[str] = mapped_column(String(64), unique=True)
    content: Mapped[dict[str, Any]] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
