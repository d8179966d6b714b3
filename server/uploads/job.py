"""The build job of a study's assets, run as its own process (``python -m server.uploads.job JOB_ID``, started by
:func:`server.uploads.service.start_build` with the server's settings in its environment).

Stages (``build_jobs.stage``; ``done``/``total`` count each stage's steps):

1. ``building``: one step per asset.  The job describes the assets as a clip set (:func:`assets_config`: each
   asset an animation with its kind, source file and frames; the ``fps``, character and conditions of the clip
   set in the var directory, or of the default clip-set file when there is none), validated as a clip-set file
   is, and builds each animation through the stimulus pipeline
   (:func:`server.studies.pipeline.build_animations`: the character loaded and verified once; any common rig,
   BVH or glTF, as ``clips build`` does); the clips are merged into the clip set (an asset's clips replace its
   earlier ones; the manifest is replaced last, in one step).
2. ``rendering``: one step per video missing: every clip's and the pairs the study's design (with the new
   animations) and every other study show, with the size and shadows the videos have already
   (:func:`server.media.build.rendered_settings`, :func:`server.studies.pipeline.render`, one worker process
   so the server keeps a core).
3. ``study``: the assets' animations are added to the study's design (its comparisons rebuilt over the videos).
4. ``done`` (state ``done``), or state ``failed`` with ``error`` at the stage where it failed.

Builds into one clip set take turns (an ``flock`` on ``<assets dir>/.build.lock`` for the server's clip set, which
every upload goes into; on ``.build.lock`` beside an inline ``[clips]`` clip set, one per owner): a job whose
clip set is busy waits for its turn.  The API starts one build per researcher and ``ANIMSTUDY_BUILDS_MAX`` in
all (:func:`server.uploads.service.check_build_slot`).

The same runner runs the jobs of the commands ``render`` and ``study create`` (``build_jobs.kind``;
:mod:`server.uploads.commands`), and any job that ``animstudy serve`` resumes
(:func:`server.uploads.service.resume_lost_jobs`).
"""

from __future__ import annotations

import fcntl
import json
import os
import resource
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from server.config import Settings
from server.db import make_engine, session_factory
from server.errors import ServiceError
from server.studies.models import Study, StudyState
from server.studies.studyfile import Clips

from .commands import run_command
from .models import BuildJob, BuildState, JobKind, StudyAsset
from .progress import BuildError, Progress, finish, rendering
from .service import asset_path, study_clips

# --- the clip-set description of the assets ---------------------------------------------------------------

def current_clip_set(clips_dir: Path) -> Any:
    """The manifest of the clip set in ``clips_dir``, None if there is none; one that cannot be read stops the
    build (merging into it would drop the clips every other study shows)."""
    from server.clipset.manifest import MANIFEST, ManifestError, read_clip_manifest

    if not (clips_dir / MANIFEST).exists():
        return None
    try:
        return read_clip_manifest(clips_dir)
    except ManifestError as exc:
        raise BuildError(f"{exc}; the uploaded clips are added to it, so it must be readable first") from None


@dataclass(frozen=True)
class BaseClipSet:
    """What the assets' clips share with the clip set they join: ``fps``, ``[character]`` (``relocate`` and the
    body, a :class:`server.clipset.config.CharacterConfig`) and the ``conditions`` (id, method, params)."""

    fps: int
    relocate: tuple[str, ...]
    character: Any
    conditions: list[tuple[str, str, dict[str, Any]]]


def base_clip_set(data_dir: Path, clips_dir: Path) -> BaseClipSet:
    """The clip set in ``clips_dir`` (so the new animations have every condition the others have, on the same
    character, whose files must not have changed since), or the default clip-set file when there is none.  The
    manifest does not record ``relocate``: the default file's is used."""
    from server.clipset.build import record_config
    from server.clipset.config import load_config

    default = load_config()
    manifest = current_clip_set(clips_dir)
    if manifest is None:
        return BaseClipSet(default.fps, default.relocate, default.character,
                           [(c.id, c.method, c.params_dict()) for c in default.conditions])
    character, _ = record_config(data_dir, manifest.character.model_dump() if manifest.character else None)
    conditions = list({c.condition: (c.condition, c.method, c.params) for c in manifest.clips}.values())
    fps = manifest.clips[0].fps if manifest.clips else default.fps
    return BaseClipSet(fps, default.relocate, character, conditions)


def assets_config(assets: Sequence[StudyAsset], asset_file: Callable[[StudyAsset], Path],
                  base: BaseClipSet) -> Any:
    """The clip-set description (:class:`server.clipset.config.ClipSetConfig`) of ``assets``: each an animation
    with its kind, source file and frames, on the fps, character and conditions of ``base``; validated as a
    clip-set file is (ConfigError names the asset)."""
    from server.clipset.config import clip_set_config

    animations = {a.name: {"kind": a.kind, "source": str(asset_file(a)), "frames": [a.first_frame, a.last_frame],
                           **_playback(a), **_reading(a, asset_file(a))} for a in assets}
    conditions = [{"id": cid, "method": method, **({"params": params} if params else {})}
                  for cid, method, params in base.conditions]
    return clip_set_config(animations, conditions, base.fps, base.relocate, base.character, "the study's assets")


def _playback(asset: StudyAsset) -> dict[str, Any]:
    """Kind ``other``: the playback inspecting the file suggested (a take that travels loops: played ping-pong it
    would move backwards, and the build refuses that); the other kinds play as their kind does."""
    playback = ((asset.report or {}).get("suggested") or {}).get("playback")
    return {"playback": playback} if asset.kind == "other" and playback in ("loop", "pingpong") else {}


def _reading(asset: StudyAsset, path: Path) -> dict[str, Any]:
    """How the researcher said to read the asset's file (units, up axis, a joint mapping, build in spite of the
    fidelity gate), as clip-set animation fields; a mapping is written beside the file (the clip set names files)."""
    report = asset.report or {}
    options = report.get("options", {})
    fields: dict[str, Any] = {key: options[key] for key in ("units", "up_axis") if options.get(key)}
    if options.get("mapping"):
        mapping = path.with_name(f"{asset.name}.mapping.json")
        mapping.write_text(json.dumps(options["mapping"]), encoding="utf-8")
        fields["mapping"] = str(mapping)
    if report.get("accept_unfaithful"):
        fields["accept_unfaithful"] = True
    return fields


# --- merging into the clip set -----------------------------------------------------------------------------------

def check_names(clips_dir: Path, assets: Sequence[StudyAsset], asset_file: Callable[[StudyAsset], Path]) -> None:
    """An asset may not take the name of an animation of the clip set that comes from another file.  The clip set
    is the server's, one namespace for every researcher: the name may be another researcher's upload, so the
    message is the same whoever's it is and says nothing of it (not that it is an upload, nor whose, nor that it
    exists)."""
    manifest = current_clip_set(clips_dir)
    if manifest is None:
        return
    sources = {c.animation: str(c.source.get("file")) for c in manifest.clips}
    for a in assets:
        if a.name in sources and sources[a.name] != str(asset_file(a)):
            raise BuildError(f"asset {a.filename!r}: {a.name!r} cannot be the name of an uploaded animation on this "
                             "server; delete the asset and upload it again with another name (API: name=)")


def merge_clips(clips_dir: Path, built: list[Any]) -> Path:
    """:func:`server.clipset.manifest.merge_clip_set`, its errors as the job's (the clip set must be readable
    first: the uploaded clips are added to it)."""
    from server.clipset.manifest import ManifestError, merge_clip_set

    current_clip_set(clips_dir)  # an unreadable one stops the build, saying so
    try:
        return merge_clip_set(clips_dir, built)
    except ManifestError as exc:
        raise BuildError(str(exc)) from None


# --- the job ---------------------------------------------------------------------------------------------------

def run(settings: Settings, factory: sessionmaker[Session], job_id: int,
        echo: Callable[[str], None] | None = None) -> None:
    """Run the job ``job_id`` to its end (from what is missing, when it is resumed); every failure is stored in
    the job (never raised).  A command's job (:class:`JobKind` render, study) runs :func:`commands.run_command`;
    ``echo`` prints its messages."""
    with factory() as session:
        job = session.get(BuildJob, job_id)
        kind, params = (job.kind, job.params) if job is not None else (JobKind.upload, None)
    if kind != JobKind.upload:
        progress = Progress(factory, job_id, echo=echo)
        progress(state=BuildState.running, stage="building", message=f"{kind} job {job_id}", pid=os.getpid())
        finish(progress, lambda: run_command(settings, factory, job_id, kind, params or {}, progress))
        return
    progress = Progress(factory, job_id, settings)
    lock_path = build_lock(settings, factory, job_id)
    lock_path.parent.mkdir(parents=True, exist_ok=True)
    with lock_path.open("w") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            # Another build into the same clip set: this one takes its turn after it (the API allows one build
            # per researcher and ANIMSTUDY_BUILDS_MAX in all), instead of failing and being refused again.
            progress(message="waiting for another build into the same clip set to finish")
            fcntl.flock(lock, fcntl.LOCK_EX)
        progress(state=BuildState.running, stage="building", message="reading the assets", pid=os.getpid())
        finish(progress, lambda: _run(settings, factory, job_id, progress))


def build_lock(settings: Settings, factory: sessionmaker[Session], job_id: int) -> Path:
    """The lock that builds into one clip set take turns on: beside the study's own clip set (inline
    ``[clips]``, one per owner), or the server's (every upload goes into it)."""
    from server.studies import pipeline

    with factory() as session:
        job = session.get(BuildJob, job_id)
        study = session.get(Study, job.study_id) if job is not None and job.study_id is not None else None
        owner_id = study.owner_id if study is not None else None
    try:
        clips = study_clips(settings, study.id) if study is not None else None
        if clips is not None:
            return pipeline.inline_place(settings, clips, "the study file", owner_id).clips_dir.parent / ".build.lock"
    except (ValueError, ServiceError):  # unreadable [clips]: the build itself says so, under the server's lock
        pass
    return settings.assets_dir / ".build.lock"


def draft(session: Session, study_id: int) -> Study:
    """The job's study, still a draft (it may have been opened or deleted meanwhile)."""
    study = session.get(Study, study_id)
    if study is None:
        raise BuildError("the study was deleted")
    if study.state != StudyState.draft:
        raise BuildError(f"the study is {study.state}, no longer a draft: its assets and design stay as they are")
    return study


def _run(settings: Settings, factory: sessionmaker[Session], job_id: int, progress: Progress) -> None:
    from server.clipset.build import AnimationError
    from server.media.build import rendered_settings
    from server.participants.service import update_study
    from server.studies import pipeline
    from server.studies.design import Design
    from server.studies.pipeline import build_animations

    place = pipeline.server_place(settings)

    with factory() as session:
        job = session.get(BuildJob, job_id)
        if job is None:
            raise BuildError(f"no build job {job_id}")
        study = draft(session, job.study_id)
        assets = list(session.scalars(select(StudyAsset).where(StudyAsset.study_id == job.study_id)
                                      .order_by(StudyAsset.id)))
        session.expunge_all()
    clips = study_clips(settings, study.id)
    if clips is not None:
        return _run_clips(settings, factory, study.id, clips, progress)
    if not assets:
        raise BuildError("the study has no assets")
    files = {a.id: asset_path(settings, a) for a in assets}

    def asset_file(a: StudyAsset) -> Path:
        return files[a.id]

    missing = [a.filename for a in assets if not asset_file(a).is_file()]
    if missing:
        raise BuildError(f"the asset files {', '.join(missing)} are missing on the server; upload them again")
    check_names(settings.clips_dir, assets, asset_file)
    try:
        config = assets_config(assets, asset_file, base_clip_set(settings.data, settings.clips_dir))
    except ValueError as exc:  # ConfigError: names the asset and the field
        raise BuildError(str(exc)) from None

    def each(k: int, name: str) -> None:
        progress(stage="building", done=k, total=len(assets), message=f"{name}: building its clips")

    try:
        built = build_animations(settings.data, config, dict.fromkeys(config.animations, config.conditions),
                                 lambda m: progress(message=m.strip()), each, settings.dask_scheduler)
    except AnimationError as exc:  # ConfigError, AssetError of an asset: they name the field and the file
        raise BuildError(f"asset {exc}") from None
    merge_clips(settings.clips_dir, built)
    progress(stage="building", done=len(assets), total=len(assets), message=f"{len(built)} clips built")

    with factory() as session:
        study = draft(session, study.id)
        design = Design.model_validate(study.design)
        animations = list(dict.fromkeys([*design.animations, *(a.name for a in assets)]))
        new_design = design.model_copy(update={"animations": animations})
        Design.model_validate(new_design.model_dump())
        pairs = pipeline.pairs(session, place, new_design, settings.media_dir)
    media = _render(settings, place, pairs, rendered_settings(settings.media_dir), progress, every_clip=True)

    progress(stage="study", done=0, total=1, message="adding the animations to the study's design")
    with factory() as session:
        study = draft(session, study.id)
        update_study(session, study, {"design": new_design.model_dump()}, media, settings.media_dir,
                     settings.clips_dir)
    progress(stage="study", done=1, total=1, message=f"the design shows {', '.join(animations)}")


def _render(settings: Settings, place: Any, pairs: list[tuple[str, str]], render: Any, progress: Progress,
            every_clip: bool = False) -> Any:
    """Stage ``rendering``: :func:`server.studies.pipeline.render` with one worker process (the server keeps a
    core), its videos counted as they are stored; returns the render manifest of ``place``."""
    from server.studies import pipeline

    return pipeline.render(settings, place, pairs, render, lambda m: progress(message=m), workers=1,
                           every_clip=every_clip, videos_done=rendering(progress))


def _run_clips(settings: Settings, factory: sessionmaker[Session], study_id: int, clips: Clips,
               progress: Progress) -> None:
    """The job of a study created through the API from a study file with inline ``[clips]``
    (:func:`server.uploads.service.create_building`): what :func:`server.studies.pipeline.prepare` does for
    ``animstudy study create`` (the clips the design needs built into the clip set of those ``[clips]``, their
    videos rendered, at the size of the videos there already), then the study's comparisons and stimulus set."""
    from server.clipset.manifest import MANIFEST
    from server.media.build import rendered_settings
    from server.studies import pipeline
    from server.studies.design import Design
    from server.studies.service import show_design

    with factory() as session:
        study = draft(session, study_id)
        design, owner_id = Design.model_validate(study.design), study.owner_id
    place = pipeline.inline_place(settings, clips, "the study file", owner_id)
    if place.config is None:  # an inline clip set is always described: not reached
        raise BuildError("the study's [clips] describe no clip set")
    progress(stage="building", done=0, total=len(design.animations), message="building the clips the design needs")
    built = pipeline.build(settings.data, place.config, place.clips_dir, design, lambda m: progress(message=m),
                           settings.dask_scheduler)
    progress(stage="building", done=len(design.animations), total=len(design.animations),
             message=f"{built} clips built")
    with factory() as session:
        pairs = pipeline.pairs(session, place, design, settings.media_dir)
    before = place.render_dir if (place.render_dir / MANIFEST).is_file() else settings.media_dir
    media = _render(settings, place, pairs, rendered_settings(before), progress)
    progress(stage="study", done=0, total=1, message="making the study's comparisons over the videos")
    with factory() as session:
        study = draft(session, study_id)
        show_design(session, study, media, settings.media_dir, place.clips_dir)
    progress(stage="study", done=1, total=1, message=f"the study shows {', '.join(design.animations)}")


def run_in_this_process(settings: Settings, kind: JobKind, params: dict[str, Any],
                        echo: Callable[[str], None] = lambda m: print(m, flush=True)) -> BuildJob:
    """Make a command's job and run it here (its ``pid`` this process's); returns the finished row."""
    from server.db import make_engine, migrate, session_factory

    engine = make_engine(settings.sqlalchemy_url)
    try:
        migrate(engine, media_dir=settings.media_dir, clips_dir=settings.clips_dir)
        factory = session_factory(engine)
        with factory() as session:
            job = BuildJob(kind=kind, params=params, state=BuildState.queued, stage="queued", message="starting",
                           pid=os.getpid())
            session.add(job)
            session.commit()
            job_id = job.id
        run(settings, factory, job_id, echo=echo)
        with factory() as session:
            finished = session.get(BuildJob, job_id)
            assert finished is not None
            session.expunge(finished)
            return finished
    finally:
        engine.dispose()


def limit_memory(megabytes: int) -> None:
    """Cap this process's address space (``ANIMSTUDY_BUILD_MEMORY_MB``; 0: no cap): a build that would take more
    fails with a MemoryError, stored in the job, instead of taking the server's memory."""
    if megabytes > 0:
        resource.setrlimit(resource.RLIMIT_AS, (megabytes << 20, megabytes << 20))


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if len(argv) != 1 or not argv[0].isdigit():
        print("usage: python -m server.uploads.job JOB_ID", file=sys.stderr)
        return 2
    settings = Settings()
    limit_memory(settings.build_memory_mb)
    engine = make_engine(settings.sqlalchemy_url)
    try:
        run(settings, session_factory(engine), int(argv[0]), echo=lambda m: print(m, flush=True))  # into its log
    finally:
        engine.dispose()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
