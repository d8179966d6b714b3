"""The render manifest (``manifest.json`` of ``animstudy render`` in the media directory): the one schema, written
by :func:`server.media.build.render_media` and read here only.  It is never served: only it says what an opaque
video name shows.

Version 2 (this one) names each clip video's animation and condition; readers never parse clip ids.  A manifest of
another version, or one that does not validate, raises :class:`~server.clipset.manifest.ManifestError` saying to
render again.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from server.clipset.manifest import MANIFEST, ManifestError, read_json, write_json

__all__ = ["MANIFEST", "VERSION", "ManifestError", "RenderManifest", "RenderedClip", "RenderedPair",
           "read_render_manifest", "write_render_manifest"]

VERSION = 2


class _Video(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    video: str  # <name>.mp4 in the media directory
    poster: str  # <name>.jpg
    frames: int = Field(ge=1)
    fps: int = Field(ge=1)
    width: int = Field(ge=1)
    height: int = Field(ge=1)


class RenderedClip(_Video):
    """The video of one clip of the clip set (``clip``: its id in the clip manifest)."""

    clip: str
    animation: str
    condition: str


class RenderedPair(_Video):
    """A side-by-side video: clip ``left`` beside clip ``right`` (ids of the clip manifest)."""

    left: str
    right: str


class RenderManifest(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    version: Literal[2] = VERSION
    settings: dict[str, Any] = Field(default_factory=dict)  # the render settings (size, shadows, ...)
    clips: dict[str, RenderedClip]  # by clip id
    pairs: list[RenderedPair]

    def clip_index(self) -> dict[tuple[str, str], str]:
        """(animation, condition) -> clip id."""
        return {(c.animation, c.condition): c.clip for c in self.clips.values()}

    def pair_videos(self) -> dict[tuple[str, str], str]:
        """(left clip id, right clip id) -> video name."""
        return {(p.left, p.right): p.video for p in self.pairs}


def write_render_manifest(media_dir: Path, manifest: RenderManifest) -> Path:
    return write_json(Path(media_dir) / MANIFEST, manifest)


def read_render_manifest(media_dir: Path) -> RenderManifest:
    """The render manifest of ``media_dir``."""
    return read_json(Path(media_dir) / MANIFEST, RenderManifest, "render manifest", "animstudy render")
