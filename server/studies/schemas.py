from __future__ import annotations

from typing import Any

from pydantic import BaseModel


class StudyPublic(BaseModel):
    """What anyone may see: no design details that reveal which side is which."""

    slug: str
    title: str
    state: str
    texts: dict[str, str]
    consent_version: str
    trials_total: int


class StudyStateRead(BaseModel):
    slug: str
    state: str


class ExportJson(BaseModel):
    study: dict[str, Any]
    columns: list[str]
    votes: list[dict[str, Any]]
