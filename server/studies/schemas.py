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
    scale: dict[str, Any]
    questions: list[dict[str, Any]]
    parameters: list[str]  # the URL parameters of the participant link the page passes on (e.g. PROLIFIC_PID)


class StudyStateRead(BaseModel):
    slug: str
    state: str


class StudySummary(BaseModel):
    slug: str
    title: str
    state: str
    owner: str | None
    started: int
    completed: int
    votes: int
    trials_total: int
    participant_url: str
    editable: dict[str, bool]


class ExportJson(BaseModel):
    study: dict[str, Any]
    columns: list[str]
    votes: list[dict[str, Any]]
