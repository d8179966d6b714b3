"""The HTTP face of the build job of a study's uploads: start it, read its progress."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request, status

from server.deps import SessionDep, SettingsDep
from server.jobs.control import job_json, latest_job
from server.researchers.deps import ResearcherDep
from server.studies.service import managed_study
from server.uploads.service import draft_study

from .jobs import start_build as queue_build

router = APIRouter(prefix="/api/v1", tags=["assets"])


@router.post("/studies/{slug}/assets/build", status_code=status.HTTP_202_ACCEPTED)
def start_build(slug: str, request: Request, session: SessionDep, settings: SettingsDep,
                researcher: ResearcherDep) -> dict[str, Any]:
    """Start building the clips of the study's assets, rendering their videos and adding their animations to
    the study's design, in the background; poll ``GET .../assets/build`` for its progress."""
    study = draft_study(session, slug, researcher)
    return job_json(queue_build(session, settings, request.app.state.engine, study)) or {}


@router.get("/studies/{slug}/assets/build")
def read_build(slug: str, session: SessionDep, researcher: ResearcherDep) -> dict[str, Any] | None:
    """The latest build job of the study: ``state`` (queued, running, done, failed), ``stage``, ``done`` of
    ``total`` steps of the stage, ``message``, ``error``; null if it never had one."""
    return job_json(latest_job(session, managed_study(session, slug, researcher)))
