"""The browser side: the participant page and the static files it loads (no CDN; everything works offline)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import RedirectResponse
from sqlalchemy import select

from .config import REPO_ROOT
from .deps import SessionDep
from .errors import NotFound
from .files import ContentFileResponse, page_response
from .studies.models import Study, StudyState

STATIC_DIR = REPO_ROOT / "static"
router = APIRouter(include_in_schema=False)


@router.api_route("/", methods=["GET", "HEAD"])
def index(session: SessionDep) -> RedirectResponse:
    """The open study (the default one first), so a bare address leads participants somewhere useful."""
    slugs = session.scalars(select(Study.slug).where(Study.state == StudyState.open).order_by(Study.id)).all()
    if not slugs:
        raise NotFound("no study is open")
    # A relative Location: never built from the request's Host header.
    return RedirectResponse(f"/study/{'thesis' if 'thesis' in slugs else slugs[0]}")


@router.api_route("/study/{slug}", methods=["GET", "HEAD"])
def participant_page(slug: str) -> ContentFileResponse:
    # The page itself is the same for every study; it reads its texts from the API.
    return page_response(STATIC_DIR / "participant.html")


@router.api_route("/dashboard", methods=["GET", "HEAD"])
def dashboard_page() -> ContentFileResponse:
    """The researcher dashboard (it asks for a login; the data comes from the authenticated API)."""
    return page_response(STATIC_DIR / "dashboard.html")
