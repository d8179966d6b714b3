"""The browser side: the participant page and the static files it loads (no CDN; everything works offline)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import FileResponse, RedirectResponse

from .config import REPO_ROOT
from .deps import SessionDep
from .errors import NotFound
from .studies.service import default_study

STATIC_DIR = REPO_ROOT / "static"
router = APIRouter(include_in_schema=False)


@router.get("/")
def index(session: SessionDep) -> RedirectResponse:
    """The default study (the open one created first: the thesis study that ``animstudy serve`` creates), so a
    bare address leads participants somewhere useful."""
    study = default_study(session)
    if study is None:
        raise NotFound("no study is open")
    return RedirectResponse(f"/s/{study.slug}")


@router.get("/s/{slug}")
@router.get("/study/{slug}")
def participant_page(slug: str) -> FileResponse:
    # The page itself is the same for every study; it reads its texts from the API.
    return FileResponse(STATIC_DIR / "participant.html", headers={"Cache-Control": "no-cache"})


@router.get("/dashboard")
def dashboard_page() -> FileResponse:
    """The researcher dashboard (it asks for a login; the data comes from the authenticated API)."""
    return FileResponse(STATIC_DIR / "dashboard.html", headers={"Cache-Control": "no-cache"})


@router.get("/dashboard/studies")
def studies_page() -> FileResponse:
    """The dashboard's list of studies: create, edit texts, open, close (data from the authenticated API)."""
    return FileResponse(STATIC_DIR / "studies.html", headers={"Cache-Control": "no-cache"})
