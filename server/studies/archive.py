"""Study archives: one file with a study's study file, its pinned stimulus set and every video and poster of it,
to rerun the study elsewhere with identical stimuli (the idea of JATOS's study archive).

An archive is a ZIP file (members stored, not compressed: the videos are compressed already):

- ``archive.json``: ``format`` (``animstudy-study-archive``), ``version`` (:data:`VERSION`), ``study`` (the study
  file as JSON), ``stimulus_set`` (``digest`` and ``content``, :class:`~server.stimuli.service.SetContent`);
- ``media/<name>`` for every file of the set.

Importing checks everything before it writes anything: the archive is complete (ZIP CRCs and sizes), of a
version this animstudy reads, the set's digest is its content's, and every file has the sha256 the set records.
Files go into the media directory under temporary names and are renamed only when all are there; the study is
created in one transaction; if that fails, the files it added are removed again.
"""

from __future__ import annotations

import hashlib
import json
import os
import zipfile
from pathlib import Path
from typing import Any

from pydantic import ValidationError
from sqlalchemy import select
from sqlalchemy.orm import Session

from server.errors import Conflict, Unprocessable
from server.media.build import DIVIDER_PX, MEDIA_NAME
from server.media.manifest import RenderedClip, RenderedPair, RenderManifest
from server.researchers.models import Researcher
from server.stimuli.service import SetContent, content_digest, content_of, file_sha256, missing

from . import service as studies
from .models import Study
from .studyfile import StudyFile

FORMAT = "animstudy-study-archive"
VERSION = 1
INDEX = "archive.json"


class ArchiveError(Unprocessable):
    """The archive cannot be imported; nothing was written."""


def export_archive(study: Study, media_dir: Path, out: Path) -> Path:
    """Write the archive of ``study`` (which must have a complete stimulus set) to ``out``, through a
    temporary file."""
    if study.stimulus_set is None:
        raise Conflict(f"study {study.slug!r} has no stimulus set to archive")
    content = content_of(study.stimulus_set)
    if lacking := missing(content, media_dir):
        raise Conflict(f"study {study.slug!r}: its stimulus set is incomplete ({'; '.join(lacking[:5])}); "
                       "an archive must hold every file")
    index = {"format": FORMAT, "version": VERSION,
             "study": studies.definition(study).model_dump(mode="json"),
             "stimulus_set": {"digest": study.stimulus_set.digest, "content": study.stimulus_set.content}}
    out = Path(out)
    tmp = out.with_name(f".{out.name}.tmp")
    with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED) as z:
        z.writestr(INDEX, json.dumps(index, indent=1, sort_keys=True))
        for name in sorted(content.hashes()):
            z.write(media_dir / name, f"media/{name}")
    tmp.replace(out)
    return out


def _read(path: Path) -> tuple[StudyFile, SetContent, dict[str, bytes]]:
    """Everything in the archive, checked; ArchiveError says what is wrong."""
    try:
        with zipfile.ZipFile(path) as z:
            bad = z.testzip()  # every member's CRC: a truncated or altered archive fails here
            if bad is not None:
                raise ArchiveError(f"the archive is damaged: {bad} does not match its checksum")
            names = set(z.namelist())
            if INDEX not in names:
                raise ArchiveError(f"the file is not a study archive: it has no {INDEX}")
            index = json.loads(z.read(INDEX))
            if not isinstance(index, dict) or index.get("format") != FORMAT:
                raise ArchiveError("the file is not an animstudy study archive")
            version = index.get("version")
            if not isinstance(version, int) or version > VERSION:
                raise ArchiveError(f"the archive is of version {version!r}, made by a newer animstudy; this one "
                                   f"reads version {VERSION} — upgrade animstudy to import it")
            digest = index.get("stimulus_set", {}).get("digest")
            raw_content = index.get("stimulus_set", {}).get("content")
            if not isinstance(raw_content, dict) or content_digest(raw_content) != digest:
                raise ArchiveError("the archive's stimulus set does not match its digest (altered)")
            content = SetContent.model_validate(raw_content)
            study_file = StudyFile.model_validate(index.get("study"))
            files: dict[str, bytes] = {}
            for name, sha in content.hashes().items():
                if not MEDIA_NAME.fullmatch(name):
                    raise ArchiveError(f"the archive names a file {name!r} that is not a video or poster name")
                member = f"media/{name}"
                if member not in names:
                    raise ArchiveError(f"the archive lacks the file {name} of its stimulus set")
                data = z.read(member)
                if sha is None or _sha256(data) != sha:
                    raise ArchiveError(f"the file {name} in the archive has other bytes than its stimulus set "
                                       "records (altered)")
                files[name] = data
    except (zipfile.BadZipFile, EOFError, OSError, zipfile.LargeZipFile) as exc:
        raise ArchiveError(f"the archive is truncated or not a ZIP file ({exc})") from None
    except (ValueError, ValidationError) as exc:  # JSON, the set's or the study file's schema
        raise ArchiveError(f"the archive's index is invalid ({str(exc).splitlines()[0]})") from None
    return study_file, content, files


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def render_manifest(content: SetContent) -> RenderManifest:
    """The render manifest a set was made from (its clips and pairs)."""
    width, height = int(content.render.get("width", 640)), int(content.render.get("height", 480))

    def video(f: Any, w: int, clip: Any) -> dict[str, Any]:
        return {"video": f.video, "poster": f.poster, "frames": clip.frames, "fps": clip.fps, "width": w,
                "height": height}

    clips = {c.id: c for c in content.clips}
    return RenderManifest(
        settings=dict(content.render),
        clips={c.id: RenderedClip(clip=c.id, animation=c.animation, condition=c.condition, **video(c, width, c))
               for c in content.clips},
        pairs=[RenderedPair(left=p.left, right=p.right, **video(p, 2 * width + DIVIDER_PX, clips[p.left]))
               for p in content.pairs])


def import_archive(session: Session, path: Path, media_dir: Path, owner: Researcher | None = None) -> Study:
    """Recreate the archived study (a draft) with the same stimulus set, byte for byte.  409 if a study with
    its slug exists (a second import of the same archive) or a file of the same name has other bytes."""
    study_file, content, files = _read(Path(path))
    if session.scalar(select(Study.id).where(Study.slug == study_file.slug)) is not None:
        raise Conflict(f"a study with slug {study_file.slug!r} exists already (imported before?); nothing was "
                       "imported")
    clashes = [n for n in files if (media_dir / n).exists() and file_sha256(media_dir / n) != _sha256(files[n])]
    if clashes:
        raise Conflict(f"the media directory has {len(clashes)} file(s) of the same name with other bytes; "
                       "nothing was imported")
    media_dir.mkdir(parents=True, exist_ok=True)
    added: list[Path] = []
    try:
        temps = []
        for name, data in files.items():
            if (media_dir / name).exists():
                continue
            tmp = media_dir / f".{name}.import.tmp"
            tmp.write_bytes(data)
            temps.append((tmp, media_dir / name))
        for tmp, final in temps:
            os.replace(tmp, final)
            added.append(final)
        study = studies.create_study(session, render_manifest(content), study_file, owner, media_dir=media_dir,
                                     stimulus_set=content)
    except BaseException:
        session.rollback()
        for f in added:
            f.unlink(missing_ok=True)
        for f in media_dir.glob(".*.import.tmp"):
            f.unlink(missing_ok=True)
        raise
    return study
