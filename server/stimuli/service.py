"""Stimulus sets: the content of what a study shows, its digest, its completeness, and the files it keeps.

A set is made when a study is created (and again when a draft's design changes) from the render manifest (the
videos and posters of its clips and side-by-side pairs) and the clip manifest (the clips' methods and metrics, the
character).  It records the sha256 of every video and poster, so its digest (sha256 of its canonical JSON) names
exactly the bytes participants see.  Opening a study checks that every file of its set is there with those bytes;
from then on the set is pinned: rendering never deletes or replaces a file (names are hashes of what decides the
pixels, and renders write only missing names), and ``animstudy gc`` deletes only files no study's set uses.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field
from sqlalchemy import column, select, table
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from server.clipset.manifest import ManifestError, read_clip_manifest
from server.media.manifest import RenderManifest, read_render_manifest
from server.media.plan import MEDIA_NAME

from .models import StimulusSet

VERSION = 1


class _Model(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class SetFile(_Model):
    """A video and its poster (names in the media directory) with the sha256 of their bytes (None: the file was
    not there when the set was made, so the set is incomplete)."""

    video: str
    poster: str
    video_sha256: str | None
    poster_sha256: str | None


class SetClip(SetFile):
    """A clip the study shows, with its video and what the clip manifest said of it when the set was made."""

    id: str
    animation: str
    condition: str
    frames: int = Field(ge=1)
    fps: int = Field(ge=1)
    method: str | None = None
    params: dict[str, Any] = Field(default_factory=dict)
    key_count: int | None = None
    metrics: dict[str, float | int | None] = Field(default_factory=dict)
    identical_to: str | None = None  # the first clip of the set with the same arrays (so the same video)


class SetPair(SetFile):
    """A side-by-side video: clip ``left`` beside clip ``right`` (ids of :attr:`SetContent.clips`)."""

    left: str
    right: str


class SetContent(_Model):
    """What a study shows, complete: written into ``stimulus_sets.content``; its :meth:`digest` names it."""

    version: Literal[1] = VERSION
    render: dict[str, Any] = Field(default_factory=dict)  # the render settings of the videos
    character: dict[str, Any] | None = None  # the clip manifest's character (files with their sha256)
    clips: list[SetClip]
    pairs: list[SetPair]

    def as_json(self) -> dict[str, Any]:
        return self.model_dump(mode="json")

    def digest(self) -> str:
        return content_digest(self.as_json())

    def hashes(self) -> dict[str, str | None]:
        """File name -> sha256 of every video and poster of the set."""
        out: dict[str, str | None] = {}
        for f in [*self.clips, *self.pairs]:
            out[f.video] = f.video_sha256
            out[f.poster] = f.poster_sha256
        return out


def content_digest(content: dict[str, Any]) -> str:
    """sha256 of the canonical JSON of a set's content (sorted keys, no spaces, UTF-8): its name.  Migration 0007
    writes the same form without importing this module."""
    text = json.dumps(content, sort_keys=True, separators=(",", ":"), ensure_ascii=False)
    return hashlib.sha256(text.encode()).hexdigest()


@lru_cache(maxsize=4096)
def _sha256(path: str, _stamp: tuple[int, int, int, int]) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def file_sha256(path: Path) -> str | None:
    """sha256 of a file's bytes (None if it is not there); cached on (inode, size, mtime, ctime): renders set
    every video's mtime to one fixed time, but any write changes the ctime."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    try:
        return _sha256(str(path), (st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns))
    except OSError:
        return None


def make_content(media: RenderManifest, clip_ids: Sequence[str], pairs: Sequence[tuple[str, str]],
                 media_dir: Path | None = None, clips_dir: Path | None = None) -> SetContent:
    """The set of the clips ``clip_ids`` and the pair videos ``pairs`` (left, right) of ``media``, hashing the
    files in ``media_dir`` (None: not hashed, the set is incomplete) and taking the clips' methods, metrics and the
    character from the clip manifest in ``clips_dir`` (when there is one)."""
    def sha(name: str) -> str | None:
        return file_sha256(media_dir / name) if media_dir is not None else None

    entries, character = {}, None
    if clips_dir is not None:
        try:
            manifest = read_clip_manifest(clips_dir)
            entries = {c.id: c for c in manifest.clips}
            character = manifest.character.model_dump(mode="json") if manifest.character else None
        except ManifestError:
            pass  # a set over videos whose clip set is gone: no metrics, the videos are what counts
    first_with_video: dict[str, str] = {}
    clips = []
    for cid in dict.fromkeys(clip_ids):
        r = media.clips[cid]
        e = entries.get(cid)
        # Clips with identical arrays share one video (server.media.build): no need to hash the arrays.
        same = first_with_video.setdefault(r.video, cid)
        clips.append(SetClip(id=cid, animation=r.animation, condition=r.condition, frames=r.frames, fps=r.fps,
                             video=r.video, poster=r.poster, video_sha256=sha(r.video), poster_sha256=sha(r.poster),
                             method=e.method if e else None, params=dict(e.params) if e else {},
                             key_count=e.key_count if e else None, metrics=dict(e.metrics) if e else {},
                             identical_to=same if same != cid else None))
    videos = media.pair_videos()
    posters = {(p.left, p.right): p.poster for p in media.pairs}
    set_pairs = [SetPair(left=left, right=right, video=videos[(left, right)], poster=posters[(left, right)],
                         video_sha256=sha(videos[(left, right)]), poster_sha256=sha(posters[(left, right)]))
                 for left, right in dict.fromkeys(pairs)]
    return SetContent(render=dict(media.settings), character=character, clips=clips, pairs=set_pairs)


def store(session: Session, content: SetContent) -> StimulusSet:
    """The row of ``content``: the existing one with its digest, or a new one (a concurrent insert of the same
    content is the same set)."""
    digest = content.digest()
    found = session.scalar(select(StimulusSet).where(StimulusSet.digest == digest))
    if found is not None:
        return found
    row = StimulusSet(digest=digest, content=content.as_json())
    try:
        with session.begin_nested():
            session.add(row)
    except IntegrityError:
        found = session.scalar(select(StimulusSet).where(StimulusSet.digest == digest))
        if found is None:
            raise
        return found
    return row


def content_of(row: StimulusSet) -> SetContent:
    return SetContent.model_validate(row.content)


def missing(content: SetContent, media_dir: Path) -> list[str]:
    """What keeps the set from being shown as recorded, one line per clip or pair, naming animation and
    conditions (never a path): files absent, unhashed, or with other bytes than the set records."""
    clips = {c.id: c for c in content.clips}

    def problem(f: SetFile) -> str | None:
        for name, recorded in ((f.video, f.video_sha256), (f.poster, f.poster_sha256)):
            actual = file_sha256(media_dir / name)
            if actual is None:
                return f"its {'video' if name.endswith('.mp4') else 'poster'} is not rendered"
            if recorded is None:
                return "it was not rendered when the set was made"
            if actual != recorded:
                return "its file has other bytes than the set records"
        return None

    out = []
    for c in content.clips:
        if (why := problem(c)) is not None:
            out.append(f"{c.animation} {c.condition}: {why}")
    for p in content.pairs:
        if (why := problem(p)) is not None:
            left, right = clips.get(p.left), clips.get(p.right)
            name = (f"{left.animation} {left.condition} | {right.condition}" if left and right
                    else f"{p.left} | {p.right}")
            out.append(f"{name}: {why}")
    return out


# --- collecting unreferenced files -------------------------------------------------------------------------------

def referenced(session: Session) -> set[str]:
    """Every file name a study's set uses (draft, open or closed)."""
    # The studies table by name: studies depend on stimulus sets, not the other way round.
    studies = table("studies", column("stimulus_set_id"))
    rows = session.scalars(select(StimulusSet).where(StimulusSet.id.in_(
        select(studies.c.stimulus_set_id).where(studies.c.stimulus_set_id.is_not(None)))))
    return {name for row in rows for name in content_of(row).hashes()}


def rendered(media_dir: Path) -> set[str]:
    """The files of the media directory's render manifest (what the next study created uses)."""
    try:
        m = read_render_manifest(media_dir)
    except ManifestError:
        return set()
    return {n for v in [*m.clips.values(), *m.pairs] for n in (v.video, v.poster)}


@dataclass(frozen=True)
class Garbage:
    files: list[Path]  # media files nothing refers to, sorted by name
    size_bytes: int  # their size
    kept: int  # media files kept


def garbage(session: Session, media_dir: Path, manifest_dirs: Sequence[Path] = ()) -> Garbage:
    """The videos and posters of ``media_dir`` that neither a study's set nor a render manifest (the one in
    ``media_dir`` and those in ``manifest_dirs``) uses (temporary files are a running render's; it removes them
    itself)."""
    keep = referenced(session) | rendered(media_dir)
    for d in manifest_dirs:
        keep |= rendered(d)
    files: Iterable[Path] = sorted(media_dir.iterdir()) if media_dir.is_dir() else []
    media = [f for f in files if MEDIA_NAME.fullmatch(f.name) and f.is_file()]
    unused = [f for f in media if f.name not in keep]
    return Garbage(unused, sum(f.stat().st_size for f in unused), len(media) - len(unused))


def collect(session: Session, media_dir: Path, manifest_dirs: Sequence[Path] = (), dry_run: bool = False
            ) -> Garbage:
    """Delete :func:`garbage` (unless ``dry_run``); returns what was (or would be) deleted."""
    found = garbage(session, media_dir, manifest_dirs)
    if not dry_run:
        for f in found.files:
            f.unlink(missing_ok=True)
    return found
