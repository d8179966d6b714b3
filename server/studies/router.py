from __future__ import annotations

import csv
import io
from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import PlainTextResponse, Response

from server.deps import ResearcherDep, SessionDep, SettingsDep

from . import service
from .models import StudyState
from .results import study_results
from .schemas import ExportJson, StudyPublic, StudyStateRead

router = APIRouter(prefix="/api/v1", tags=["studies"])
DATA_DICTIONARY = Path(__file__).with_name("DATA_DICTIONARY.md")


@router.get("/studies/{slug}", response_model=StudyPublic)
def read_study(slug: str, session: SessionDep) -> StudyPublic:
    study = service.get_study(session, slug)
    return StudyPublic(slug=study.slug, title=study.title, state=study.state, texts=study.texts,
                       consent_version=study.consent_version, trials_total=service.trials_total(study))


@router.post("/studies/{slug}/open", response_model=StudyStateRead)
def open_study(slug: str, session: SessionDep, _: ResearcherDep) -> StudyStateRead:
    study = service.set_state(session, service.get_study(session, slug), StudyState.open)
    return StudyStateRead(slug=study.slug, state=study.state)


@router.post("/studies/{slug}/close", response_model=StudyStateRead)
def close_study(slug: str, session: SessionDep, _: ResearcherDep) -> StudyStateRead:
    study = service.set_state(session, service.get_study(session, slug), StudyState.closed)
    return StudyStateRead(slug=study.slug, state=study.state)


# A text cell beginning with one of these is a formula (or becomes one) in Excel, LibreOffice and Google Sheets.
FORMULA_STARTS = ("=", "+", "-", "@", "\t", "\r")


def csv_cell(value: object) -> object:
    """A value as a CSV cell: booleans ``true``/``false``, None empty, and text that a spreadsheet would evaluate
    (participant-supplied ids could be ``=HYPERLINK(...)``) prefixed with ``'``, which spreadsheets show as text.
    Numbers stay numbers: a score of -2 is not text."""
    if isinstance(value, bool):
        return str(value).lower()
    if value is None:
        return ""
    if isinstance(value, str) and value.startswith(FORMULA_STARTS):
        return "'" + value
    return value


@router.get("/studies/{slug}/export.csv", response_class=Response,
            responses={200: {"content": {"text/csv": {}}}})
def export_csv(slug: str, session: SessionDep, _: ResearcherDep) -> Response:
    study = service.get_study(session, slug)
    buffer = io.StringIO()
    # RFC 4180 line ends: with "\n" alone the csv module would not quote a value holding a bare "\r", and every
    # reader would split the row there.
    writer = csv.DictWriter(buffer, fieldnames=service.EXPORT_COLUMNS, lineterminator="\r\n")
    writer.writeheader()
    for row in service.export_rows(session, study):
        writer.writerow({k: csv_cell(v) for k, v in row.items()})
    return Response(buffer.getvalue(), media_type="text/csv; charset=utf-8",
                    headers={"Content-Disposition": f'attachment; filename="{study.slug}-votes.csv"'})


@router.get("/studies/{slug}/export.json", response_model=ExportJson)
def export_json(slug: str, session: SessionDep, _: ResearcherDep) -> ExportJson:
    study = service.get_study(session, slug)
    return ExportJson(study={"slug": study.slug, "title": study.title, "state": study.state,
                             "design": study.design, "consent_version": study.consent_version},
                      columns=list(service.EXPORT_COLUMNS), votes=list(service.export_rows(session, study)))


@router.get("/data-dictionary", response_class=PlainTextResponse)
def data_dictionary() -> str:
    """The columns of the exports, documented (Markdown)."""
    return DATA_DICTIONARY.read_text(encoding="utf-8")


@router.get("/studies/{slug}/results")
def results(slug: str, session: SessionDep, settings: SettingsDep, _: ResearcherDep) -> dict:
    """Progress and statistics (participants are the unit of analysis; see ``methods`` in the answer)."""
    study = service.get_study(session, slug)
    return study_results(session, study, settings.clips_dir, settings.benchmark_path)
