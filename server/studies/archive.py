"""Study archives: one file with a study's study file, its pinned stimulus set and every video and poster of it,
to rerun the study elsewhere with identical stimuli (the idea of JATOS's study archive).

An archive is a ZIP file (members stored, not compressed: the videos are compressed already):

- ``archive.json``: ``format`` (``animstudy-study-archive``), ``version`` (:data:`VERSION`), ``study`` (the study
  file as JSON), ``stimulus_set`` (``digest`` and ``content``, :class:`~server.stimuli.service.SetContent`);
- ``media/<name>`` for every file of the set.

Importing checks everything before it writes anything: the archive is within :class:`ArchiveLimits` (members,
sizes, compression ratio, read from the ZIP directory before any member is), holds nothing but its index and
the set's files, is of a version this animstudy reads, the set's digest is its content's, and every file has the
sha256 the set records (checked as it is copied, in blocks: never a whole file in memory).
Files go into the media directory under temporary names and are renamed only when all are there; the study is
created in one transaction; if that fails, the files it added are removed again.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import ValidationError
from sqlalchemy import select
from sqlalchemy.orm import Session

from server.errors import Conflict, Unprocessable
from server.media.manifest import RenderedClip, RenderedPair, RenderManifest
from server.media.plan import DIVIDER_PX, MEDIA_NAME
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


@dataclass(frozen=True)
class ArchiveLimits:
    """What an archive may hold, checked from its ZIP directory before a member is read (the sizes there bound what
    reading it gives: Python's zipfile stops at the recorded size and checks the CRC).  A study's archive holds its
    index and one stored (uncompressed) file per video and poster: a few hundred members of a few MB each."""

    members: int = 20_000
    member_bytes: int = 512 * 2**20
    total_bytes: int = 8 * 2**30
    index_bytes: int = 16 * 2**20
    #: uncompressed / compressed size of a member over 1 MiB (videos are stored: 1; a bomb: about 1000)
    ratio: float = 50.0


COMPRESSIONS = {zipfile.ZIP_STORED: "stored", zipfile.ZIP_DEFLATED: "deflate", zipfile.ZIP_BZIP2: "bzip2",
                zipfile.ZIP_LZMA: "lzma"}
NESTED_TOO_DEEPLY = "the archive's index is nested too deeply"
# A member's entry in the ZIP directory: 46 bytes and its name (media names have 35 characters), with room for
# extra fields.
DIRECTORY_BYTES_PER_MEMBER = 1024


def _size(n: float) -> str:
    return f"{n:.0f} bytes" if n < 2**20 else f"{n / 2**20:.1f} MiB"


def _check_end_record(path: Path, limits: ArchiveLimits) -> None:
    """Refuse an archive whose end record declares more members, or a larger central directory, than ``limits``
    allow, before ``zipfile`` builds an object per member (200,000 junk members took 110 MiB).  A file without an
    end record is left to ``zipfile`` to refuse."""
    with open(path, "rb") as f:
        size = f.seek(0, os.SEEK_END)
        f.seek(max(0, size - 22 - 65535))  # the end record (22 bytes) and its comment (at most 65535)
        tail = f.read()
        at = tail.rfind(b"PK\x05\x06")
        if at < 0 or len(tail) < at + 22:
            return
        members = int.from_bytes(tail[at + 10:at + 12], "little")
        directory = int.from_bytes(tail[at + 12:at + 16], "little")
        if (members == 0xFFFF or directory == 0xFFFFFFFF) and at >= 20 and tail[at - 20:at - 16] == b"PK\x06\x07":
            f.seek(int.from_bytes(tail[at - 12:at - 4], "little"))  # the ZIP64 end record: 8-byte fields
            record = f.read(56)
            if record[:4] == b"PK\x06\x06" and len(record) == 56:
                members = int.from_bytes(record[32:40], "little")
                directory = int.from_bytes(record[40:48], "little")
    if members > limits.members:
        raise ArchiveError(f"the archive has {members} members, more than the {limits.members} a study archive "
                           "may hold")
    if directory > DIRECTORY_BYTES_PER_MEMBER * limits.members:
        raise ArchiveError(f"the archive's directory is {_size(directory)}, more than "
                           f"{_size(DIRECTORY_BYTES_PER_MEMBER * limits.members)} for {limits.members} members")


def _check_directory(z: zipfile.ZipFile, limits: ArchiveLimits) -> dict[str, zipfile.ZipInfo]:
    """The members by name, once :class:`ArchiveLimits` and the compression methods are checked (nothing read)."""
    infos = z.infolist()
    if len(infos) > limits.members:
        raise ArchiveError(f"the archive has {len(infos)} members, more than the {limits.members} a study archive "
                           "may hold")
    members: dict[str, zipfile.ZipInfo] = {}
    total = 0
    for info in infos:
        name = info.filename
        if name in members:
            raise ArchiveError(f"the archive holds {name!r} twice")
        if info.compress_type not in COMPRESSIONS:
            raise ArchiveError(f"{name!r} uses compression method {info.compress_type}; a study archive uses "
                               f"{', '.join(COMPRESSIONS.values())}")
        if info.file_size > limits.member_bytes:
            raise ArchiveError(f"{name!r} is {_size(info.file_size)} uncompressed, larger than the "
                               f"{_size(limits.member_bytes)} a file of a study archive may be")
        if info.file_size > 2**20 and info.file_size > limits.ratio * max(info.compress_size, 1):
            raise ArchiveError(f"{name!r} would inflate {info.file_size / max(info.compress_size, 1):.0f}-fold "
                               f"(at most {limits.ratio:.0f}): compressed to hide its size, it is refused unread")
        total += info.file_size
        members[name] = info
    if total > limits.total_bytes:
        raise ArchiveError(f"the archive's files are {_size(total)} in all, more than its limit of "
                           f"{_size(limits.total_bytes)}")
    index = members.get(INDEX)
    if index is None:
        raise ArchiveError(f"the file is not a study archive: it has no {INDEX}")
    if index.file_size > limits.index_bytes:
        raise ArchiveError(f"the archive has an {INDEX} of {_size(index.file_size)}, more than the "
                           f"{_size(limits.index_bytes)} an index may be")
    return members


def _index(raw: bytes) -> tuple[StudyFile, SetContent]:
    """The study file and the stimulus set of an archive's index, checked; ArchiveError says what is wrong."""
    try:
        index = json.loads(raw)
    except RecursionError:  # json recurses per level of [ or {
        raise ArchiveError(NESTED_TOO_DEEPLY) from None
    if not isinstance(index, dict) or index.get("format") != FORMAT:
        raise ArchiveError("the file is not an animstudy study archive")
    version = index.get("version")
    if not isinstance(version, int) or isinstance(version, bool) or version > VERSION:
        raise ArchiveError(f"the archive is of version {version!r}, made by a newer animstudy; this one "
                           f"reads version {VERSION} — upgrade animstudy to import it")
    stimulus_set = index.get("stimulus_set")
    if not isinstance(stimulus_set, dict):
        raise ArchiveError(f"the archive's index is invalid (stimulus_set is a {type(stimulus_set).__name__}, "
                           "not a table with digest and content)")
    raw_content = stimulus_set.get("content")
    if not isinstance(raw_content, dict) or content_digest(raw_content) != stimulus_set.get("digest"):
        raise ArchiveError("the archive's stimulus set does not match its digest (altered)")
    content = SetContent.model_validate(raw_content)
    if not content.clips or not content.pairs:
        raise ArchiveError("the archive's stimulus set has no clips or no pairs: there is nothing to show")
    clips = {c.id for c in content.clips}
    for pair in content.pairs:
        if unknown := [c for c in (pair.left, pair.right) if c not in clips]:
            raise ArchiveError(f"the archive's stimulus set pairs clip {unknown[0]!r}, which it does not have")
    for name, sha in content.hashes().items():
        if not MEDIA_NAME.fullmatch(name):
            raise ArchiveError(f"the archive names a file {name!r} that is not a video or poster name")
        if sha is None:
            raise ArchiveError(f"the archive's stimulus set records no sha256 for {name} (incomplete)")
    return StudyFile.model_validate(index.get("study")), content


def _read(z: zipfile.ZipFile, limits: ArchiveLimits) -> tuple[StudyFile, SetContent]:
    """The archive's study file and stimulus set, its directory checked against ``limits`` and every member
    accounted for; ArchiveError says what is wrong.  The media are not read here (see :func:`_extract`)."""
    try:
        members = _check_directory(z, limits)
        study_file, content = _index(z.read(INDEX))
    except (ValueError, ValidationError) as exc:  # JSON, the set's or the study file's schema
        raise ArchiveError(f"the archive's index is invalid ({str(exc).splitlines()[0]})") from None
    except RecursionError:  # pydantic on a deep value
        raise ArchiveError(NESTED_TOO_DEEPLY) from None
    expected = {f"media/{name}" for name in content.hashes()}
    for member in members:
        if member != INDEX and member not in expected:
            raise ArchiveError(f"the archive holds {member!r}, which is not part of a study archive (only "
                               f"{INDEX} and the files of its stimulus set)")
    if lacking := sorted(expected - members.keys()):
        raise ArchiveError(f"the archive lacks the file {lacking[0].removeprefix('media/')} of its stimulus set")
    return study_file, content


def _extract(z: zipfile.ZipFile, name: str, sha: str, out: Path) -> None:
    """The member ``media/<name>`` written to ``out`` in blocks, its sha256 checked (ArchiveError otherwise)."""
    h = hashlib.sha256()
    with z.open(f"media/{name}") as src, open(out, "wb") as dst:
        for block in iter(lambda: src.read(1 << 20), b""):
            h.update(block)
            dst.write(block)
    if h.hexdigest() != sha:
        raise ArchiveError(f"the file {name} in the archive has other bytes than its stimulus set records (altered)")


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


def import_archive(session: Session, path: Path, media_dir: Path, owner: Researcher | None = None,
                   limits: ArchiveLimits = ArchiveLimits()) -> Study:
    """Recreate the archived study (a draft) with the same stimulus set, byte for byte.  409 if a study with
    its slug exists (a second import of the same archive) or a file of the same name has other bytes;
    :class:`ArchiveError` (nothing written) if the archive is damaged, altered, malformed or over ``limits``."""
    added: list[Path] = []
    try:
        _check_end_record(Path(path), limits)
        with zipfile.ZipFile(Path(path)) as z:
            study_file, content = _read(z, limits)
            hashes = {name: sha for name, sha in content.hashes().items() if sha is not None}
            if session.scalar(select(Study.id).where(Study.slug == study_file.slug)) is not None:
                raise Conflict(f"a study with slug {study_file.slug!r} exists already (imported before?); nothing "
                               "was imported")
            clashes = [n for n, sha in hashes.items() if (media_dir / n).exists() and file_sha256(media_dir / n) != sha]
            if clashes:
                raise Conflict(f"the media directory has {len(clashes)} file(s) of the same name with other bytes; "
                               "nothing was imported")
            wanted = [n for n in hashes if not (media_dir / n).exists()]
            media_dir.mkdir(parents=True, exist_ok=True)
            need = sum(z.getinfo(f"media/{n}").file_size for n in wanted)
            if need > (free := shutil.disk_usage(media_dir).free):
                raise ArchiveError(f"the archive's files need {_size(need)}; the media directory has {_size(free)} "
                                   "free")
            temps = []
            for name in wanted:  # into temporary names first: a failure leaves no file of the set behind
                tmp = media_dir / f".{name}.import.tmp"
                temps.append((tmp, media_dir / name))
                _extract(z, name, hashes[name], tmp)
        for tmp, final in temps:
            os.replace(tmp, final)
            added.append(final)
        return studies.create_study(session, render_manifest(content), study_file, owner, media_dir=media_dir,
                                    stimulus_set=content)
    except BaseException as exc:
        session.rollback()
        for f in added:
            f.unlink(missing_ok=True)
        for f in media_dir.glob(".*.import.tmp"):
            f.unlink(missing_ok=True)
        if isinstance(exc, zipfile.BadZipFile) and "CRC" in str(exc):
            raise ArchiveError(f"the archive is damaged: {exc}") from None
        if isinstance(exc, (zipfile.BadZipFile, EOFError, zipfile.LargeZipFile, NotImplementedError)):
            raise ArchiveError(f"the archive is truncated or not a ZIP file ({exc})") from None
        # An OSError without a file name is a seek or read past a truncated archive's end; one with a name is
        # about a file (the archive missing, the media directory not writable) and says so itself.
        if isinstance(exc, OSError) and exc.filename is None and exc.errno != errno.ENOSPC:
            raise ArchiveError(f"the archive is truncated or not a ZIP file ({exc})") from None
        raise
