from __future__ import annotations

from datetime import datetime

from sqlalchemy import String, false
from sqlalchemy.orm import Mapped, mapped_column

from server.db import Base, UTCDateTime, utcnow


class Researcher(Base):
    __tablename__ = "researchers"
    __table_args__ = ({"sqlite_autoincrement": True},)  # ids never reused (migration 0012): owners, shares

    id: Mapped[int] = mapped_column(primary_key=True)
    email: Mapped[str] = mapped_column(String(254), unique=True)
    password_hash: Mapped[str] = mapped_column(String(200))
    is_admin: Mapped[bool] = mapped_column(default=False, server_default=false())  # sees and manages every study
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
