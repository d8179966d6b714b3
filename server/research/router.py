from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, Body, Depends, Query, Request, status
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, PlainTextResponse, Response
from pydantic import ValidationError
from sqlalchemy.orm import Session

from server.clipset.config import NAME_PATTERN
from server.deps import SessionDep, SettingsDep
from server.errors import Conflict, Unprocessable
from server.jobs.control import job_json
from server.jobs.progress import scrub
from server.media.manifest import ManifestError, RenderManifest, read_render_manifest
from server.participants import service as participants
from server.pipeline import stimuli as pipeline
from server.pipeline.jobs import create_building
from server.researchers.deps import ResearcherDep
from server.researchers.models import Researcher
from server.studies import pilot, service
from server.studies.columns import data_dictionary_json, data_dictionary_markdown
from server.studies.models import StudyState
from server.studies.page import Page
from server.studies.scale import public as public_scale
from server.studies.schemas import ExportJson, StudyPublic, StudyStateRead, StudySummary
from server.studies.studyfile import StudyFile, StudyFileError, parse_study_text
from server.uploads.service import study_clips, usable_animations

from . import export
from .results import study_results
from .service import study_summary

router = APIRouter(prefix="/api/v1", tags=["studies"])
MAX_STUDY_FILE_BYTES = 200_000
PilotQuery = Annotated[bool, Query(description="include the researcher's pilot (preview) sessions")]


@router.get("/studies", response_model=list[StudySummary])
def list_studies(session: SessionDep, researcher: ResearcherDep) -> list[StudySummary]:
    """The researcher's studies (an admin's: every study), with their participant counts."""
    return [study_summary(session, s) for s in service.visible_studies(session, researcher)]


def render_manifest(settings: Any, folder: Path | None = None) -> RenderManifest:
    """The render manifest of the server's clip set (or the one in ``folder``); 409 when the videos are missing
    or their manifest is old or corrupt (the message says to render, and names no server path)."""
    try:
        return read_render_manifest(folder or settings.media_dir)
    except ManifestError as exc:
        raise Conflict(scrub(f"{exc}; `animstudy study create` renders what a study needs", settings)) from None


def usable(session: Session, settings: Any, researcher: Researcher, media: RenderManifest) -> set[str]:
    """The animations of the rendered videos ``researcher`` may use: another researcher's uploads are unknown to
    them (unless shared), in errors too."""
    return usable_animations(session, settings, researcher, sorted({a for a, _ in media.clip_index()}))


BUILDING = {202: {"description": "a study file with inline [clips]: the draft study and the build job that builds "
                                  "and renders its clips (poll GET /studies/{slug}/assets/build)",
                   "content": {"application/json": {"example": {"study": {"slug": "..."},
                                                                "build": {"state": "queued"}}}}}}


@router.post("/studies", response_model=StudySummary, status_code=status.HTTP_201_CREATED, responses=BUILDING)
def create_study(body: StudyFile, request: Request, session: SessionDep, settings: SettingsDep,
                 researcher: ResearcherDep) -> StudySummary | JSONResponse:
    """A draft study from a study file's content (as JSON) over the rendered videos.  With inline ``[clips]``
    the clips it needs are built and rendered by a build job first: 202 with the draft and the job, whose
    progress ``GET /studies/{slug}/assets/build`` shows; the study gets its comparisons when the job is done."""
    if body.clips is not None:
        study, job = create_building(session, settings, request.app.state.engine, body, researcher)
        return JSONResponse({"study": study_summary(session, study).model_dump(mode="json"),
                             "build": job_json(job)}, status_code=status.HTTP_202_ACCEPTED)
    media = render_manifest(settings)
    return study_summary(session, service.create_study(session, media, body, owner=researcher,
                                                 media_dir=settings.media_dir, clips_dir=settings.clips_dir,
                                                 animations=usable(session, settings, researcher, media)))


async def study_file_text(request: Request) -> str:
    """The request body as the text of a study file (TOML)."""
    raw = await request.body()
    if len(raw) > MAX_STUDY_FILE_BYTES:
        raise Unprocessable(f"a study file may hold at most {MAX_STUDY_FILE_BYTES} bytes")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        raise Unprocessable("the study file is not UTF-8 text") from None


@router.post("/studies/file", response_model=StudySummary, status_code=status.HTTP_201_CREATED, responses=BUILDING,
             openapi_extra={"requestBody": {"required": True,
                                            "content": {"text/plain": {"schema": {"type": "string"}}}}})
def create_study_from_file(text: Annotated[str, Depends(study_file_text)], request: Request, session: SessionDep,
                           settings: SettingsDep, researcher: ResearcherDep) -> StudySummary | JSONResponse:
    """As ``POST /studies``, from the study file itself (TOML text as the body): errors name field and line."""
    try:
        study_file = parse_study_text(text, "the study file")
    except StudyFileError as exc:
        raise RequestValidationError([{"loc": ("body",), "msg": e, "type": "value_error"} for e in exc.errors]
                                     ) from None
    return create_study(study_file, request, session, settings, researcher)


@router.get("/studies/{slug}/definition", response_model=StudyFile)
def read_definition(slug: str, session: SessionDep, researcher: ResearcherDep) -> StudyFile:
    return service.definition(service.managed_study(session, slug, researcher))


@router.patch("/studies/{slug}", response_model=StudySummary)
def patch_study(slug: str, session: SessionDep, settings: SettingsDep, researcher: ResearcherDep,
                body: dict[str, Any] = Body(..., description="sections of the study file to change")  # noqa: B008
                ) -> StudySummary:
    """Title, texts, scale, questions and recruitment until the study first opens; the design while it is a
    draft; otherwise 409."""
    study = service.managed_study(session, slug, researcher)
    media, clips_dir, animations = None, settings.clips_dir, None
    if "design" in body:
        if (clips := study_clips(settings, study.id)) is not None:  # over its own clip set (data-dir motions)
            place = pipeline.inline_place(settings, clips, "the study file", study.owner_id)
            media, clips_dir = render_manifest(settings, place.render_dir), place.clips_dir
        else:
            media = render_manifest(settings)
            animations = usable(session, settings, researcher, media)
    try:
        participants.update_study(session, study, body, media, settings.media_dir, clips_dir, animations)
    except ValidationError as exc:
        session.rollback()
        raise RequestValidationError([{**e, "loc": ("body", *e["loc"])} for e in exc.errors()]) from None
    return study_summary(session, study)


@router.delete("/studies/{slug}", status_code=status.HTTP_204_NO_CONTENT)
def delete_study(slug: str, session: SessionDep, settings: SettingsDep, researcher: ResearcherDep) -> Response:
    participants.delete_study(session, service.managed_study(session, slug, researcher), settings)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.get("/page-defaults")
def page_defaults() -> dict[str, Any]:
    """The participant page's default language, wording and gate (for a link to a study that does not exist)."""
    return Page().public()


@router.get("/studies/{slug}", response_model=StudyPublic)
def read_study(slug: str, session: SessionDep, settings: SettingsDep,
               preview: Annotated[str | None, Query(max_length=2000, description="a researcher's preview token: "
                                                    "a draft study too")] = None) -> StudyPublic:
    study = (pilot.previewed_study(session, slug, preview, settings.secret) if preview is not None
             else service.public_study(session, slug))
    return StudyPublic(slug=study.slug, title=study.title, state=study.state, texts=study.texts,
                       consent_version=study.consent_version, trials_total=service.trials_total(study),
                       scale=public_scale(study.scale), questions=study.questions,
                       parameters=study.recruitment["parameters"],
                       page=Page.model_validate(study.page or {}).public())


@router.post("/studies/{slug}/open", response_model=StudyStateRead)
def open_study(slug: str, session: SessionDep, settings: SettingsDep, researcher: ResearcherDep) -> StudyStateRead:
    """Open the study once every file of its stimulus set is there (409 naming what is missing); pins the set."""
    study = service.open_study(session, service.managed_study(session, slug, researcher), settings.media_dir)
    return StudyStateRead(slug=study.slug, state=study.state)


@router.post("/studies/{slug}/close", response_model=StudyStateRead)
def close_study(slug: str, session: SessionDep, researcher: ResearcherDep) -> StudyStateRead:
    study = service.set_state(session, service.managed_study(session, slug, researcher), StudyState.closed)
    return StudyStateRead(slug=study.slug, state=study.state)


@router.get("/studies/{slug}/export.csv", response_class=Response,
            responses={200: {"content": {"text/csv": {}}}})
def export_csv(slug: str, session: SessionDep, researcher: ResearcherDep, pilot: PilotQuery = False) -> Response:
    study = service.managed_study(session, slug, researcher)
    return Response(export.export_csv(session, study, pilot), media_type="text/csv; charset=utf-8",
                    headers={"Content-Disposition": f'attachment; filename="{study.slug}-votes.csv"'})


@router.get("/studies/{slug}/export.json", response_model=ExportJson)
def export_json(slug: str, session: SessionDep, researcher: ResearcherDep, pilot: PilotQuery = False) -> ExportJson:
    return ExportJson(**export.export_document(session, service.managed_study(session, slug, researcher), pilot))


@router.get("/studies/{slug}/export.sureal.json")
def export_sureal(slug: str, session: SessionDep, researcher: ResearcherDep, pilot: PilotQuery = False) -> Response:
    """The analysed votes as a dataset for Netflix's sureal (``sureal --dataset FILE.json --models MLE ...``)."""
    study = service.managed_study(session, slug, researcher)
    return Response(json.dumps(export.export_sureal(session, study, pilot), indent=1),
                    media_type="application/json",
                    headers={"Content-Disposition": f'attachment; filename="{study.slug}-sureal.json"'})


@router.get("/studies/{slug}/export.pwcmp.csv", response_class=Response,
            responses={200: {"content": {"text/csv": {}}}})
def export_pwcmp(slug: str, session: SessionDep, researcher: ResearcherDep, pilot: PilotQuery = False) -> Response:
    """The analysed votes as pairwise comparisons for pwcmp (observer, session, scene, cond1, cond2, selection)."""
    study = service.managed_study(session, slug, researcher)
    return Response(export.export_pwcmp_csv(session, study, pilot), media_type="text/csv; charset=utf-8",
                    headers={"Content-Disposition": f'attachment; filename="{study.slug}-pwcmp.csv"'})


@router.post("/studies/{slug}/preview")
def preview(slug: str, session: SessionDep, settings: SettingsDep, researcher: ResearcherDep) -> dict[str, Any]:
    """A preview link for a pilot run of the study (draft or open): its sessions are marked pilot and left out
    of results and exports unless asked for."""
    study = service.managed_study(session, slug, researcher)
    if study.state not in pilot.PREVIEW_STATES:
        raise Conflict(f"study {slug!r} is {study.state}: pilot sessions start only while it is a draft or open")
    link = pilot.preview_link(study, settings.secret)
    return {"url": link.url, "expires_at": link.expires_at.isoformat(), **participants.pilot_counts(session, study)}


@router.delete("/studies/{slug}/pilot-sessions")
def delete_pilot_sessions(slug: str, session: SessionDep, researcher: ResearcherDep) -> dict[str, int]:
    """Delete every pilot session of the study with every row it made; answers what was deleted."""
    return participants.delete_pilot_sessions(session, service.managed_study(session, slug, researcher))


@router.get("/data-dictionary", response_class=PlainTextResponse)
def data_dictionary() -> str:
    """The columns of the exports, documented (Markdown)."""
    return data_dictionary_markdown()


@router.get("/constants")
def constants() -> dict[str, str]:
    """What the researcher pages check before sending (defined once, in the server): ``name_pattern``, the rule for
    animation names and condition ids, as an HTML ``pattern`` (anchored by the browser)."""
    return {"name_pattern": NAME_PATTERN.removeprefix("^").removesuffix("$")}


@router.get("/data-dictionary.json")
def data_dictionary_as_json() -> dict[str, list[dict[str, str]]]:
    """The same columns as data (name, type, meaning), for scripts that read exports."""
    return data_dictionary_json()


@router.get("/studies/{slug}/results")
def results(slug: str, session: SessionDep, settings: SettingsDep, researcher: ResearcherDep,
            pilot: PilotQuery = False) -> dict:
    """Progress and statistics (participants are the unit of analysis; see ``methods`` in the answer), with the
    study's screening rules applied and, beside them, ``without_screening``."""
    study = service.managed_study(session, slug, researcher)
    return study_results(session, study, settings.benchmark_path, include_pilot=pilot)
