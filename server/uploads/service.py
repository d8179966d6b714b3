"""A draft study's assets: motion files uploaded by its researcher, validated by inspecting them
(:func:`anim_core.clips.sources.inspect_source`) before anything is stored, listed, changed and deleted; who may use
the animations built from them; and the ``[clips]`` a study was created with through the API, stored beside them.
The build job that turns them into clips and videos is :func:`server.pipeline.jobs.build_job`.

Files live in ``<assets dir>/<study id>/<filename>`` (``Settings.assets_dir``); an upload is streamed into its own
folder under ``<assets dir>/.incoming/`` (the same file system), inspected there, and only then linked into place
and recorded in one step, so a failed upload leaves nothing.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import time
import uuid
from pathlib import Path
from typing import Any

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from server.clipset.config import NAME
from server.config import Settings
from server.errors import Conflict, NotFound, Unprocessable
from server.jobs.control import check_not_building
from server.researchers.models import Researcher
from server.studies.models import Study, StudyState
from server.studies.service import managed_study
from server.studies.studyfile import Clips

from .models import AnimationShare, StudyAsset

#: What an upload may be: a motion file :func:`~anim_core.clips.sources.inspect_source` reads.  No ``.bvh.gz``: a
#: compressed file could unpack to far more than the size limit allows.
EXTENSIONS = (".bvh", ".glb", ".gltf")
FILENAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._ -]{0,99}$")
#: Memory inspecting an upload may take: ``MEMORY_PER_BYTE`` × its size + ``MEMORY_BASE`` (issue 26).  The part
#: that does not grow with the file's bytes grows with its frames × joints (a BVH joint without channels costs
#: nothing in the file and as much as any other in memory): inspecting a 1000-joint BVH took 258 bytes per
#: frame·joint, so the motion may have at most that memory / :data:`BYTES_PER_FRAME_JOINT` frame·joints.
MEMORY_PER_BYTE = 50
MEMORY_BASE = 200_000_000
BYTES_PER_FRAME_JOINT = 300
INCOMING = ".incoming"
STALE_INCOMING_S = 24 * 3600


def check_filename(filename: str) -> str:
    """The file name of an upload, or 422 saying what is wrong with it (paths, NUL, extension, characters)."""
    if "\x00" in filename:
        raise Unprocessable("filename: must not contain a NUL character")
    if "/" in filename or "\\" in filename:
        raise Unprocessable(f"filename: {filename!r} is a path; give the file's name only (no / or \\)")
    if filename in ("", ".", "..") or filename.startswith("."):
        raise Unprocessable(f"filename: {filename!r} must not be empty or start with '.'")
    if not filename.lower().endswith(EXTENSIONS):
        raise Unprocessable(f"filename: {filename!r} is not a motion file; expected {', '.join(EXTENSIONS)}")
    if not FILENAME.fullmatch(filename):
        raise Unprocessable(f"filename: {filename!r} may hold only letters, digits, '.', '_', '-' and spaces "
                            f"(at most 100, the first a letter or digit)")
    return filename


def animation_name(filename: str, name: str | None = None) -> str:
    """The animation an asset becomes: ``name`` if given (checked), else made from the file name's stem
    (lower case, other characters as ``_``, at most 32)."""
    if name is not None:
        if not NAME.fullmatch(name):
            raise Unprocessable(f"name: {name!r} must be 1..32 lower-case letters, digits or '_' (no '-'), "
                                f"the first a letter or digit")
        return name
    stem = filename.rsplit(".", 1)[0].lower()
    made = re.sub(r"[^a-z0-9]+", "_", stem).strip("_")[:32].rstrip("_")
    return made or "motion"


def draft_study(session: Session, slug: str, researcher: Researcher) -> Study:
    """The study if ``researcher`` manages it (403) and it is a draft (409: its assets are fixed once it opens)."""
    study = managed_study(session, slug, researcher)
    if study.state != StudyState.draft:
        raise Conflict(f"study {slug!r} is {study.state}; assets can change only while it is a draft")
    return study


def check_free(session: Session, study: Study, filename: str, name: str) -> None:
    """409 if the study has an asset of that file name or animation name already."""
    for column, value, what in ((StudyAsset.filename, filename, "file"), (StudyAsset.name, name, "animation")):
        if session.scalar(select(StudyAsset.id).where(StudyAsset.study_id == study.id, column == value)):
            raise Conflict(f"study {study.slug!r} has an asset with the {what} name {value!r} already; delete it "
                           f"first or choose another name")


def incoming_path(settings: Settings, filename: str) -> Path:
    """A fresh folder for one upload under the assets dir, and the file's path in it (named as uploaded, so that
    inspection errors name the user's file).  Folders left by uploads that never ended (the server was killed
    meanwhile) are removed after :data:`STALE_INCOMING_S`."""
    root = settings.assets_dir / INCOMING
    root.mkdir(parents=True, exist_ok=True)
    now = time.time()
    for old in root.iterdir():
        try:
            if now - old.stat().st_mtime > STALE_INCOMING_S:
                shutil.rmtree(old, ignore_errors=True)
        except OSError:  # removed by another request meanwhile
            pass
    folder = root / uuid.uuid4().hex
    folder.mkdir()
    return folder / filename


def discard(path: Path) -> None:
    """Remove an incoming upload (its file and folder)."""
    shutil.rmtree(path.parent, ignore_errors=True)


def asset_path(settings: Settings, asset: StudyAsset) -> Path:
    return settings.study_assets_dir(asset.study_id) / asset.filename


def report_json(report: Any, motions: list[str]) -> dict[str, Any]:
    """What inspecting a file found (:class:`anim_core.clips.sources.MotionReport`), as stored and served."""
    n = report.normalized
    m = n.mapping
    return {"motion": report.name, "motions": motions, "joints": len(m.source_names), "convention": m.convention,
            "units": n.units, "metres_per_unit": n.metres_per_unit, "up_axis": n.up_axis, "notes": list(n.notes),
            "fps": report.fps, "frames": report.n_frames, "duration_s": report.duration,
            "contacts": {k: [list(p) for p in v] for k, v in report.contacts.items()},
            "suggested": {"kind": report.kind, "frames": list(report.frames), "reason": report.reason,
                          "playback": report.playback},
            "mapping": [{"joint": d.canonical, "source": d.source, "reason": d.reason} for d in m.decisions],
            "unmapped": list(m.unmapped)}


def check_options(units: str | None, up_axis: str | None, mapping: Any) -> dict[str, Any]:
    """How to read a file where the detection cannot tell (``units``, ``up_axis``, an explicit joint ``mapping``
    ``{character joint: file joint}``), checked; 422 naming the field and the choices.  None: detect."""
    from anim_core.rig.rigmap import CANONICAL_NAMES, UNITS

    if units is not None and units not in UNITS:
        raise Unprocessable(f"units: {units!r} is not a unit; one of {', '.join(UNITS)} (or leave it out to detect "
                            f"it from the leg length)")
    if up_axis is not None and up_axis not in ("y", "z"):
        raise Unprocessable(f"up axis: {up_axis!r}; 'y' or 'z' (or leave it out to detect it from the motion)")
    if mapping is not None:
        if not isinstance(mapping, dict) or not all(isinstance(k, str) and isinstance(v, str)
                                                    for k, v in mapping.items()):
            raise Unprocessable("mapping: an object of character joint -> file joint names, e.g. "
                                "{\"LeftUpLeg\": \"thigh_l\"}")
        if unknown := sorted(set(mapping) - set(CANONICAL_NAMES)):
            raise Unprocessable(f"mapping: {unknown[0]!r} is not a character joint; they are "
                                f"{', '.join(CANONICAL_NAMES)}")
    return {k: v for k, v in (("units", units), ("up_axis", up_axis), ("mapping", mapping or None))
            if v is not None}


def max_frame_joints(size_bytes: int) -> int:
    """The frames × joints an upload of ``size_bytes`` may hold (see :data:`MEMORY_PER_BYTE`)."""
    return (MEMORY_PER_BYTE * size_bytes + MEMORY_BASE) // BYTES_PER_FRAME_JOINT


#: Said after an upload that does not read, so the researcher knows what to change.
NEXT_STEP = {
    "RigMapError": "choose the units, the up axis or a joint mapping in the upload form (API: units=, up=, "
                   "mapping=) and upload the file again",
    "BvhError": "correct the file there (or export it again) and upload it again",
    "GltfError": "export the file again from your tool (glTF 2.0, one skinned character) and upload it again",
}


def inspect_upload(path: Path, options: dict[str, Any] | None = None) -> dict[str, Any]:
    """Inspect an uploaded file read with ``options`` (:func:`check_options`): its report (with the options), or
    422 with the reader's message (file, line, what is wrong) and what to do next.  A glTF with several animations
    gives its first one (the report names the others).  A motion of more frames × joints than
    :func:`max_frame_joints` allows for the file's size is refused before it is read."""
    from anim_core.clips.sources import inspect_source

    options = options or {}
    try:
        reports = inspect_source(path, options.get("mapping"), options.get("units"), options.get("up_axis"),
                                 max_frame_joints=max_frame_joints(path.stat().st_size))
    except (ValueError, OSError, RecursionError, MemoryError) as exc:  # BvhError, GltfError, RigMapError ...
        message = str(exc) or f"{path.name}: cannot be read ({type(exc).__name__})"
        step = NEXT_STEP.get(type(exc).__name__, "check the file and upload it again")
        raise Unprocessable(f"{message.rstrip('.')}. To go on: {step}") from None
    if not reports:
        raise Unprocessable(f"{path.name}: holds no motion; upload a file with an animation")
    return {**report_json(reports[0], [r.name for r in reports]), "options": options}


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        while chunk := f.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()


def store_upload(session: Session, settings: Settings, study: Study, incoming: Path, name: str,
                 options: dict[str, Any] | None = None) -> StudyAsset:
    """Validate the streamed file ``incoming`` and, if it is good, put it in place and record it (both or
    neither); the incoming folder is removed either way.  The file is inspected before any query, so no
    transaction is open meanwhile."""
    try:
        report = inspect_upload(incoming, options)
        check_free(session, study, incoming.name, name)
        asset = StudyAsset(study_id=study.id, name=name, filename=incoming.name,
                           size_bytes=incoming.stat().st_size, sha256=_sha256(incoming),
                           kind=report["suggested"]["kind"], first_frame=report["suggested"]["frames"][0],
                           last_frame=report["suggested"]["frames"][1], report=report)
        dest = asset_path(settings, asset)
        dest.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(incoming, dest)  # never replaces: a file left there by anything else is a conflict
        except FileExistsError:
            raise Conflict(f"a file {incoming.name!r} exists in the study's assets already") from None
        try:
            session.add(asset)
            session.commit()
        except BaseException as exc:
            session.rollback()
            dest.unlink(missing_ok=True)
            if isinstance(exc, IntegrityError):  # a concurrent upload of the same name won
                raise Conflict(f"study {study.slug!r} has an asset named {name!r} or {incoming.name!r} "
                               f"already") from None
            raise
        return asset
    finally:
        discard(incoming)


def list_assets(session: Session, study: Study) -> list[StudyAsset]:
    return list(session.scalars(select(StudyAsset).where(StudyAsset.study_id == study.id).order_by(StudyAsset.id)))


def get_asset(session: Session, study: Study, name: str) -> StudyAsset:
    asset = session.scalar(select(StudyAsset).where(StudyAsset.study_id == study.id, StudyAsset.name == name))
    if asset is None:
        raise NotFound(f"study {study.slug!r} has no asset {name!r}")
    return asset


def update_asset(session: Session, study: Study, asset: StudyAsset, kind: str | None,
                 frames: tuple[int, int] | None, options: dict[str, Any] | None = None,
                 settings: Settings | None = None) -> StudyAsset:
    """Change what the asset's clips are built from: the clip-set ``kind``, the source ``frames`` (inclusive) and
    how the file is read (``options``, :func:`check_options`: the file is inspected again with them; its new
    suggestion is taken unless kind or frames are given too)."""
    from server.clipset.config import KINDS

    check_not_building(session, study)
    if options is not None:
        if settings is None:
            raise ValueError("changing how a file is read needs the settings (where the file is)")
        report = inspect_upload(asset_path(settings, asset), options)
        if asset.report.get("accept_unfaithful"):
            report["accept_unfaithful"] = True
        asset.report = report
        asset.kind = report["suggested"]["kind"]
        asset.first_frame, asset.last_frame = report["suggested"]["frames"]
    if kind is not None:
        if kind not in KINDS:
            raise Unprocessable(f"kind: {kind!r} is not a kind of the clip set; one of {', '.join(KINDS)}")
        asset.kind = kind
    if frames is not None:
        first, last = frames
        count = asset.report["frames"]
        if not 0 <= first < last < count:
            raise Unprocessable(f"frames: [{first}, {last}] must be increasing frames of the file's 0..{count - 1}")
        asset.first_frame, asset.last_frame = first, last
    session.commit()
    return asset


def accept_unfaithful(session: Session, asset: StudyAsset, accept: bool) -> StudyAsset:
    """Build the asset's clips even if the fidelity gate fails (docs/motion-from-the-wild.md); they are marked."""
    asset.report = {**asset.report, "accept_unfaithful": accept}  # a new dict: the JSON column sees the change
    session.commit()
    return asset


def delete_asset(session: Session, settings: Settings, study: Study, asset: StudyAsset) -> None:
    """Remove the asset's row and file (its clips, once built, stay in the clip set until it is rebuilt)."""
    check_not_building(session, study)
    path = asset_path(settings, asset)
    session.delete(asset)
    session.commit()
    path.unlink(missing_ok=True)


# --- who may use an uploaded animation ---------------------------------------------------------------------------

def animation_origins(settings: Settings, clips_dir: Path | None = None) -> dict[str, int]:
    """Animation of the clip set -> the id of the study whose upload it was built from (the build job names the
    asset file ``<assets dir>/<study id>/<file>`` as its source).  Animations from anywhere else (the data
    directory, a clip-set file of the operator) are absent: every researcher may use them."""
    from server.clipset.manifest import ManifestError, read_clip_manifest

    try:
        clips = read_clip_manifest(clips_dir or settings.clips_dir).clips
    except ManifestError:
        return {}
    assets = settings.assets_dir.resolve()
    out = {}
    for c in clips:
        source = Path(str(c.source.get("file", "")))
        if source.is_absolute() and source.is_relative_to(assets):
            parts = source.relative_to(assets).parts
            if len(parts) == 2 and parts[0].isdigit():
                out[c.animation] = int(parts[0])
    return out


def usable_animations(session: Session, settings: Settings, researcher: Researcher,
                      animations: set[str] | list[str]) -> set[str]:
    """Those of ``animations`` that ``researcher`` may use: every one for an admin; otherwise the ones not built
    from an upload, the ones from uploads into their own studies, and the ones shared with them.  (An upload of a
    deleted study: admins only.)"""
    if researcher.is_admin:
        return set(animations)
    origins = animation_origins(settings)
    private = {a: origins[a] for a in animations if a in origins}
    if not private:
        return set(animations)
    owners = dict(session.execute(select(Study.id, Study.owner_id).where(Study.id.in_(set(private.values())))).all())
    shared = set(session.execute(select(AnimationShare.study_id, AnimationShare.animation).where(
        AnimationShare.researcher_id == researcher.id)).all())
    return {a for a in animations if a not in private or owners.get(private[a]) == researcher.id
            or (private[a], a) in shared}


def check_animation_of(session: Session, settings: Settings, study: Study, name: str) -> str:
    """``name`` if it is an asset of ``study`` or an animation built from one (404 otherwise)."""
    has_asset = session.scalar(select(StudyAsset.id).where(StudyAsset.study_id == study.id,
                                                          StudyAsset.name == name)) is not None
    if not has_asset and animation_origins(settings).get(name) != study.id:
        raise NotFound(f"study {study.slug!r} has no asset {name!r}")
    return name


def share_animation(session: Session, settings: Settings, study: Study, name: str, email: str) -> list[str]:
    """Let the researcher ``email`` use the animation ``name`` of ``study``'s uploads in their studies; returns
    everyone it is shared with."""
    from server.researchers.service import normalize_email

    check_animation_of(session, settings, study, name)
    other = session.scalar(select(Researcher).where(Researcher.email == normalize_email(email)))
    if other is None:
        raise Unprocessable(f"email: no researcher account {email!r}")
    if other.id != study.owner_id and session.scalar(select(AnimationShare.id).where(
            AnimationShare.study_id == study.id, AnimationShare.animation == name,
            AnimationShare.researcher_id == other.id)) is None:
        session.add(AnimationShare(study_id=study.id, animation=name, researcher_id=other.id))
        session.commit()
    return shared_with(session, study, name)


def unshare_animation(session: Session, settings: Settings, study: Study, name: str, email: str) -> list[str]:
    """Stop sharing (studies the other researcher made with it keep their pinned stimuli)."""
    from server.researchers.service import normalize_email

    check_animation_of(session, settings, study, name)
    other = session.scalar(select(Researcher.id).where(Researcher.email == normalize_email(email)))
    for share in session.scalars(select(AnimationShare).where(
            AnimationShare.study_id == study.id, AnimationShare.animation == name,
            AnimationShare.researcher_id == other)):
        session.delete(share)
    session.commit()
    return shared_with(session, study, name)


def shared_with(session: Session, study: Study, name: str) -> list[str]:
    return list(session.scalars(select(Researcher.email).join(
        AnimationShare, AnimationShare.researcher_id == Researcher.id).where(
        AnimationShare.study_id == study.id, AnimationShare.animation == name).order_by(Researcher.email)))


# --- a study file's [clips], built by the job -----------------------------------------------------------------

#: Beside a study's uploads: the ``[clips]`` of the study file it was created with through the API, its clip set
#: (its build job builds and renders it; a change of its design is made over it).
STUDY_CLIPS = "study-clips.json"


def study_clips_path(settings: Settings, study_id: int) -> Path:
    return settings.study_assets_dir(study_id) / STUDY_CLIPS


def study_clips(settings: Settings, study_id: int) -> Clips | None:
    """The ``[clips]`` a study was created with through the API, None for a study over the server's clip set."""
    path = study_clips_path(settings, study_id)
    try:
        return Clips.model_validate_json(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:  # written by create_building only
        raise Conflict(f"the study's [clips] cannot be read ({type(exc).__name__}); delete the study and create "
                       "it again") from None


def check_takes_uploads(settings: Settings, study: Study) -> None:
    """409 for a study with its own clip set: uploads are built into the server's."""
    if study_clips_path(settings, study.id).is_file():
        raise Conflict(f"study {study.slug!r} has its own clip set ([clips] of its study file); uploads go into a "
                       "study over the server's clip set")


def check_data_file(settings: Settings, name: str | None, where: str) -> None:
    """422 unless ``name`` is a file of the server's data directory given relative to it (through the API no
    other file of the server may be read; the message never shows a server path)."""
    from server.assets import AssetError, resolve

    if name is None:
        return
    path = Path(name)
    if path.is_absolute() or ".." in path.parts:
        raise Unprocessable(f"{where}: a file of the server's data directory, named relative to it (e.g. "
                            "'mocap/cmu/113_21_idle_30fps.bvh.gz'); no absolute path or '..'")
    try:
        resolve(settings.data, name)
    except AssetError:
        raise Unprocessable(f"{where}: the server's data directory has no file {name!r}") from None


def asset_json(asset: StudyAsset) -> dict[str, Any]:
    return {"name": asset.name, "filename": asset.filename, "size_bytes": asset.size_bytes, "sha256": asset.sha256,
            "kind": asset.kind, "frames": [asset.first_frame, asset.last_frame], "report": asset.report,
            "created_at": asset.created_at.isoformat()}
