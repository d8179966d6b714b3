"""The HTML pages: the participant page (one for every study) and the researcher dashboard."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import RedirectResponse

from .config import REPO_ROOT
from .deps import SessionDep
from .errors import NotFound
from .files import ContentFileResponse, page_response
from .studies.service import default_study

STATIC_DIR = REPO_ROOT / "static"
router = APIRouter(include_in_schema=False)


@router.api_route("/", methods=["GET", "HEAD"])
def index(session: SessionDep) -> RedirectResponse:
    """The default study (the open one created first: the thesis study that ``animstudy serve`` creates), so a
    bare address leads participants somewhere useful."""
    study = default_study(session)
    if study is None:
        raise NotFound("no study is open")
    # A relative Location: never built from the request's Host header.
    return RedirectResponse(f"/s/{study.slug}")


@router.api_route("/s/{slug}", methods=["GET", "HEAD"])
@router.api_route("/study/{slug}", methods=["GET", "HEAD"])
def participant_page(slug: str) -> ContentFileResponse:
    # The page itself is the same for every study; it reads its texts from the API.
    return page_response(STATIC_DIR / "participant.html")


@router.api_route("/dashboard", methods=["GET", "HEAD"])
def dashboard_page() -> ContentFileResponse:
    """The researcher dashboard (it asks for a login; the data comes from the authenticated API)."""
    return page_response(STATIC_DIR / "dashboard.html")


@router.api_route("/dashboard/studies", methods=["GET", "HEAD"])
def studies_page() -> ContentFileResponse:
    """The dashboard's list of studies: create, edit texts, open, close (data from the authenticated API)."""
    return page_response(STATIC_DIR / "studies.html")
