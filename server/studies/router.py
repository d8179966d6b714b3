from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, Body, Depends, Request, status
from fastapi.exceptions import RequestValidationError
from fastapi.responses import PlainTextResponse, Response
from pydantic import ValidationError
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from server.deps import ResearcherDep, SessionDep, SettingsDep
from server.errors import Conflict, Unprocessable
from server.media.manifest import ManifestError, RenderManifest, read_render_manifest
from server.participants.models import ParticipantSession, Vote
from server.researchers.models import Researcher
from server.uploads.service import remove_study_assets, usable_animations

from . import service
from .models import Study, StudyState
from .page import Page
from .results import participant_counts, study_results
from .schemas import ExportJson, StudyPublic, StudyStateRead, StudySummary
from .studyfile import StudyFile, StudyFileError, parse_study_text

router = APIRouter(prefix="/api/v1", tags=["studies"])
DATA_DICTIONARY = Path(__file__).with_name("DATA_DICTIONARY.md")
MAX_STUDY_FILE_BYTES = 200_000


def summary(session: Session, study: Study) -> StudySummary:
    counts = participant_counts(session, study)
    votes = session.scalar(select(func.count(Vote.id)).join(ParticipantSession).where(
        ParticipantSession.study_id == study.id)) or 0
    never_opened = study.opened_at is None
    return StudySummary(slug=study.slug, title=study.title, state=study.state,
                        owner=study.owner.email if study.owner else None, started=counts["started"],
                        completed=counts["completed"], votes=votes, trials_total=service.trials_total(study),
                        participant_url=f"/s/{study.slug}",
                        editable={"texts": never_opened, "recruitment": never_opened,
                                  "design": never_opened and study.state == StudyState.draft})


@router.get("/studies", response_model=list[StudySummary])
def list_studies(session: SessionDep, researcher: ResearcherDep) -> list[StudySummary]:
    """The researcher's studies (an admin's: every study), with their participant counts."""
    return [summary(session, s) for s in service.visible_studies(session, researcher)]


def render_manifest(settings: Any) -> RenderManifest:
    """409 when the videos are missing or their manifest is old or corrupt (the message says to render)."""
    try:
        return read_render_manifest(settings.media_dir)
    except ManifestError as exc:
        raise Conflict(f"{exc}; `animstudy study create` renders what a study needs") from None


def usable(session: Session, settings: Any, researcher: Researcher, media: RenderManifest) -> set[str]:
    """The animations of the rendered videos ``researcher`` may use: another researcher's uploads are unknown to
    them (unless shared), in errors too."""
    return usable_animations(session, settings, researcher, sorted({a for a, _ in media.clip_index()}))


@router.post("/studies", response_model=StudySummary, status_code=status.HTTP_201_CREATED)
def create_study(body: StudyFile, session: SessionDep, settings: SettingsDep,
                 researcher: ResearcherDep) -> StudySummary:
    """A draft study from a study file's content (as JSON) over the rendered videos (``animstudy study create``
    renders what is missing; here the videos must exist)."""
    if body.clips is not None:
        raise Unprocessable("clips.set: a study file that names its clip set is created with `animstudy study "
                            "create FILE` on the server, which builds and renders its clips; through the API a "
                            "study uses the server's clip set and its own uploads")
    media = render_manifest(settings)
    return summary(session, service.create_study(session, media, body, owner=researcher,
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


@router.post("/studies/file", response_model=StudySummary, status_code=status.HTTP_201_CREATED,
             openapi_extra={"requestBody": {"required": True,
                                            "content": {"text/plain": {"schema": {"type": "string"}}}}})
def create_study_from_file(text: Annotated[str, Depends(study_file_text)], session: SessionDep,
                           settings: SettingsDep, researcher: ResearcherDep) -> StudySummary:
    """As ``POST /studies``, from the study file itself (TOML text as the body): errors name field and line."""
    try:
        study_file = parse_study_text(text, "the study file")
    except StudyFileError as exc:
        raise RequestValidationError([{"loc": ("body",), "msg": e, "type": "value_error"} for e in exc.errors]
                                     ) from None
    return create_study(study_file, session, settings, researcher)


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
    media = render_manifest(settings) if "design" in body else None
    try:
        service.update_study(session, study, body, media, settings.media_dir, settings.clips_dir,
                             usable(session, settings, researcher, media) if media is not None else None)
    except ValidationError as exc:
        session.rollback()
        raise RequestValidationError([{**e, "loc": ("body", *e["loc"])} for e in exc.errors()]) from None
    return summary(session, study)


@router.delete("/studies/{slug}", status_code=status.HTTP_204_NO_CONTENT)
def delete_study(slug: str, session: SessionDep, settings: SettingsDep, researcher: ResearcherDep) -> Response:
    study = service.managed_study(session, slug, researcher)
    study_id = study.id
    service.delete_study(session, study)
    remove_study_assets(settings, study_id)  # its asset rows went with it
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.get("/page-defaults")
def page_defaults() -> dict[str, Any]:
    """The participant page's default language, wording and gate (for a link to a study that does not exist)."""
    return Page().public()


@router.get("/studies/{slug}", response_model=StudyPublic)
def read_study(slug: str, session: SessionDep) -> StudyPublic:
    study = service.get_study(session, slug)
    return StudyPublic(slug=study.slug, title=study.title, state=study.state, texts=study.texts,
                       consent_version=study.consent_version, trials_total=service.trials_total(study),
                       scale=study.scale, questions=study.questions,
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
def export_csv(slug: str, session: SessionDep, researcher: ResearcherDep) -> Response:
    study = service.managed_study(session, slug, researcher)
    return Response(service.export_csv(session, study), media_type="text/csv; charset=utf-8",
                    headers={"Content-Disposition": f'attachment; filename="{study.slug}-votes.csv"'})


@router.get("/studies/{slug}/export.json", response_model=ExportJson)
def export_json(slug: str, session: SessionDep, researcher: ResearcherDep) -> ExportJson:
    return ExportJson(**service.export_document(session, service.managed_study(session, slug, researcher)))


@router.get("/data-dictionary", response_class=PlainTextResponse)
def data_dictionary() -> str:
    """The columns of the exports, documented (Markdown)."""
    return DATA_DICTIONARY.read_text(encoding="utf-8")


@router.get("/studies/{slug}/results")
def results(slug: str, session: SessionDep, settings: SettingsDep, researcher: ResearcherDep) -> dict:
    """Progress and statistics (participants are the unit of analysis; see ``methods`` in the answer)."""
    study = service.managed_study(session, slug, researcher)
    return study_results(session, study, settings.benchmark_path)
