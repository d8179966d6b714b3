"""Files served with validators taken from their content, never from the file system.

Starlette's ``FileResponse`` sends ``Last-Modified`` (the modification time) and an ``ETag`` made from the
modification time and size; on the videos these told which side of a comparison was the hybrid (written first)
and the increment.  Here the ``ETag`` is a name for the content (the media file's own content-hash name, or the
SHA-256 of a page or static file), there is no ``Last-Modified``, ``If-None-Match`` is answered 304, ``HEAD`` is
answered like ``GET`` without the body, and an invalid ``Range`` is ignored (RFC 9110 section 14.2) rather than
refused; an unsatisfiable one stays 416.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Mapping
from functools import lru_cache
from pathlib import Path

from starlette.datastructures import Headers
from starlette.responses import FileResponse, MalformedRangeHeader, Response
from starlette.staticfiles import StaticFiles
from starlette.types import Receive, Scope, Send

# Headers a 304 repeats from the 200 it stands for (RFC 9110 section 15.4.5).
_NOT_MODIFIED_KEEP = ("etag", "cache-control", "vary")


class ContentFileResponse(FileResponse):
    def __init__(self, path: str | os.PathLike[str], etag: str, headers: Mapping[str, str] | None = None,
                 media_type: str | None = None, status_code: int = 200,
                 stat_result: os.stat_result | None = None) -> None:
        super().__init__(path, status_code=status_code, media_type=media_type, stat_result=stat_result,
                         headers={**(headers or {}), "ETag": f'"{etag}"'})

    def set_stat_headers(self, stat_result: os.stat_result) -> None:
        self.headers.setdefault("content-length", str(stat_result.st_size))

    def _should_use_range(self, http_if_range: str) -> bool:
        return http_if_range == self.headers["etag"]

    @classmethod
    def _parse_range_header(cls, http_range: str, file_size: int) -> list[tuple[int, int]]:
        try:
            return super()._parse_range_header(http_range, file_size)
        except MalformedRangeHeader:
            return []  # ignored: the whole file

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if self.status_code == 200 and _matches(Headers(scope=scope).get("if-none-match"), self.headers["etag"]):
            kept = {k: v for k, v in self.headers.items() if k in _NOT_MODIFIED_KEEP}
            await Response(status_code=304, headers=kept)(scope, receive, send)
            return
        await super().__call__(scope, receive, send)


def _matches(if_none_match: str | None, etag: str) -> bool:
    """The weak comparison of RFC 9110 section 13.1.2."""
    if not if_none_match:
        return False
    tags = [t.strip().removeprefix("W/") for t in if_none_match.split(",")]
    return "*" in tags or etag.removeprefix("W/") in tags


@lru_cache(maxsize=512)
def _digest(path: str, _mtime_ns: int, _size: int) -> str:
    # The file's time is only the cache key (a changed file is hashed again); it never reaches a header.
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:32]


def content_tag(path: Path, stat_result: os.stat_result | None = None) -> str:
    """A short SHA-256 of the file's bytes."""
    st = stat_result or path.stat()
    return _digest(str(path), st.st_mtime_ns, st.st_size)


def page_response(path: Path) -> ContentFileResponse:
    """A page: revalidated on every load (``no-cache``), cheaply, with ``If-None-Match``."""
    return ContentFileResponse(path, content_tag(path), headers={"Cache-Control": "no-cache"})


class ContentStaticFiles(StaticFiles):
    """``StaticFiles`` with :class:`ContentFileResponse` (scripts and styles are revalidated on every load)."""

    def file_response(self, full_path: str | os.PathLike[str], stat_result: os.stat_result, scope: Scope,
                      status_code: int = 200) -> Response:
        return ContentFileResponse(full_path, content_tag(Path(full_path), stat_result), status_code=status_code,
                                   stat_result=stat_result, headers={"Cache-Control": "no-cache"})
