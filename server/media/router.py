"""Serving the pre-rendered videos and posters: opaque names only, byte ranges, long-lived caching, and headers
that depend on nothing but the name and the size (see ``server.files``)."""

from __future__ import annotations

from fastapi import APIRouter

from server.deps import SettingsDep
from server.errors import NotFound
from server.files import ContentFileResponse

from .plan import MEDIA_NAME

router = APIRouter(tags=["media"])
# A name is the hash of the content, so a URL never changes meaning: cache it for a year.
CACHE_CONTROL = "public, max-age=31536000, immutable"


@router.get("/media/{name}", response_class=ContentFileResponse)
@router.head("/media/{name}", response_class=ContentFileResponse, include_in_schema=False)
def media(name: str, settings: SettingsDep) -> ContentFileResponse:
    """A video or poster by its opaque name (HTTP Range requests are answered with 206; ``If-None-Match`` with
    its name as the ``ETag`` with 304)."""
    path = settings.media_dir / name
    if not MEDIA_NAME.fullmatch(name) or not path.is_file():  # also keeps the manifest and anything else private
        raise NotFound("no such media file")
    media_type = "video/mp4" if name.endswith(".mp4") else "image/jpeg"
    return ContentFileResponse(path, etag=name, media_type=media_type, headers={"Cache-Control": CACHE_CONTROL})
