"""The kinds of job, each registered once (:data:`KINDS`), and the process that runs one
(``python -m server.pipeline.jobs JOB_ID``, started by :func:`server.jobs.control.start_job` with the server's
settings in its environment).

- ``upload`` (:func:`build_job`): the build of a study's assets, or of the inline ``[clips]`` it was created with
  through the API; queued by :func:`start_build` and :func:`create_building`.
- ``render``, ``study``, ``archive``, ``default``: the commands ``animstudy render``, ``study create``,
  ``study import-archive`` and the default study of ``animstudy serve`` (:mod:`server.pipeline.commands`).

Stages of the build of a study's assets (``build_jobs.stage``; ``done``/``total`` count each stage's steps):

1. ``building``: one step per asset.  The job describes the assets as a clip set
   (:func:`server.pipeline.assets.assets_config`: each asset an animation with its kind, source file and frames;
   the ``fps``, character and conditions of the clip set in the var directory, or of the default clip-set file
   when there is none), validated as a clip-set file is, and builds each animation through the stimulus pipeline
   (:func:`server.pipeline.stimuli.build_animations`: the character loaded and verified once; any common rig,
   BVH or glTF, as ``clips build`` does); the clips are merged into the clip set (an asset's clips replace its
   earlier ones; the manifest is replaced last, in one step).
2. ``rendering``: one step per video missing: every clip's and the pairs the study's design (with the new
   animations) and every other study show, with the size and shadows the videos have already
   (:func:`server.media.plan.rendered_settings`, :func:`server.pipeline.stimuli.render`, one worker process
   so the server keeps a core).
3. ``study``: the assets' animations are added to the study's design (its comparisons rebuilt over the videos).
4. ``done`` (state ``done``), or state ``failed`` with ``error`` at the stage where it failed.

Builds into one clip set take turns (an ``flock`` on ``<assets dir>/.build.lock`` for the server's clip set, which
every upload goes into; on ``.build.lock`` beside an inline ``[clips]`` clip set, one per owner): a job whose
clip set is busy waits for its turn.  The API starts one build per researcher and ``ANIMSTUDY_BUILDS_MAX`` in
all (:func:`server.jobs.control.check_build_slot`).  Any job whose process ended mid-job is resumed by
``animstudy serve`` (:func:`server.jobs.control.resume_lost_jobs`).
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from sqlalchemy import Engine, select
from sqlalchemy.orm import Session, sessionmaker

from server.config import Settings
from server.db import make_engine, session_factory
from server.errors import Conflict, ServiceError, Unprocessable
from server.jobs import runner
from server.jobs.control import check_build_slot, claim, launch, lost_jobs
from server.jobs.models import BuildJob, JobKind
from server.jobs.progress import BuildError, Progress, rendering
from server.researchers.models import Researcher
from server.studies.models import Study, StudyState
from server.studies.studyfile import Clips, StudyFile
from server.uploads.models import StudyAsset
from server.uploads.service import asset_path, check_data_file, list_assets, study_clips, study_clips_path

from . import commands
from . import stimuli as pipeline
from .assets import assets_config, base_clip_set, check_names, merge_clips

# --- the build of a study's assets -------------------------------------------------------------------------------

def build_lock(settings: Settings, factory: sessionmaker[Session], job_id: int) -> Path:
    """The lock that builds into one clip set take turns on: beside the study's own clip set (inline
    ``[clips]``, one per owner), or the server's (every upload goes into it)."""
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


def build_job(settings: Settings, factory: sessionmaker[Session], job_id: int, params: dict[str, Any],
              progress: Progress) -> None:
    """The job of kind ``upload``: the study's assets built into the server's clip set (or the inline
    ``[clips]`` it was created with, :func:`_run_clips`), their videos rendered, their animations added."""
    from server.participants.service import update_study
    from server.studies.design import Design

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
    _build_assets(settings, assets, progress)

    with factory() as session:
        study = draft(session, study.id)
        design = Design.model_validate(study.design)
        animations = list(dict.fromkeys([*design.animations, *(a.name for a in assets)]))
        new_design = design.model_copy(update={"animations": animations})
        Design.model_validate(new_design.model_dump())
        # The server's clip set has its manifest now: the pipeline builds nothing more, and renders every clip.
        media = pipeline.make_stimuli(settings, session, pipeline.server_place(settings), {"": new_design},
                                      progress=lambda m: progress(message=m), workers=1, every_clip=True,
                                      videos_done=rendering(progress))

    progress(stage="study", done=0, total=1, message="adding the animations to the study's design")
    with factory() as session:
        study = draft(session, study.id)
        update_study(session, study, {"design": new_design.model_dump()}, media, settings.media_dir,
                     settings.clips_dir)
    progress(stage="study", done=1, total=1, message=f"the design shows {', '.join(animations)}")


def _build_assets(settings: Settings, assets: list[StudyAsset], progress: Progress) -> None:
    """Stage ``building``: the clips of every asset in all its conditions (again: an asset's clips replace its
    earlier ones), merged into the server's clip set."""
    from server.clipset.build import AnimationError

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
        built = pipeline.build_animations(settings.data, config, dict.fromkeys(config.animations, config.conditions),
                                          lambda m: progress(message=m.strip()), each, settings.dask_scheduler)
    except AnimationError as exc:  # ConfigError, AssetError of an asset: they name the field and the file
        raise BuildError(f"asset {exc}") from None
    merge_clips(settings.clips_dir, built)
    progress(stage="building", done=len(assets), total=len(assets), message=f"{len(built)} clips built")


def _run_clips(settings: Settings, factory: sessionmaker[Session], study_id: int, clips: Clips,
               progress: Progress) -> None:
    """The job of a study created through the API from a study file with inline ``[clips]``
    (:func:`create_building`): what :func:`server.pipeline.stimuli.prepare` does for
    ``animstudy study create`` (the clips the design needs built into the clip set of those ``[clips]``, their
    videos rendered, at the size of the videos there already), then the study's comparisons and stimulus set."""
    from server.studies.design import Design
    from server.studies.service import show_design

    with factory() as session:
        study = draft(session, study_id)
        design, owner_id = Design.model_validate(study.design), study.owner_id
    place = pipeline.inline_place(settings, clips, "the study file", owner_id)
    if place.config is None:  # an inline clip set is always described: not reached
        raise BuildError("the study's [clips] describe no clip set")
    progress(stage="building", done=0, total=len(design.animations), message="building the clips the design needs")

    def built(count: int) -> None:
        progress(stage="building", done=len(design.animations), total=len(design.animations),
                 message=f"{count} clips built")

    with factory() as session:
        media = pipeline.make_stimuli(settings, session, place, {"": design}, progress=lambda m: progress(message=m),
                                      workers=1, videos_done=rendering(progress), built=built)
    progress(stage="study", done=0, total=1, message="making the study's comparisons over the videos")
    with factory() as session:
        study = draft(session, study_id)
        show_design(session, study, media, settings.media_dir, place.clips_dir)
    progress(stage="study", done=1, total=1, message=f"the study shows {', '.join(design.animations)}")


# --- queueing a build ---------------------------------------------------------------------------------------------

def start_build(session: Session, settings: Settings, engine: Engine, study: Study) -> BuildJob:
    """Queue the build of the study's assets (or of the ``[clips]`` it was created with,
    :func:`server.uploads.service.study_clips`) and start its process (``python -m server.pipeline.jobs ID``); 409
    if the study has nothing to build or a build is running (:func:`server.jobs.control.check_build_slot`)."""
    if not list_assets(session, study) and not study_clips_path(settings, study.id).is_file():
        raise Conflict(f"study {study.slug!r} has no assets to build; upload a BVH or glTF file first")
    check_build_slot(session, settings, study.owner_id)
    return launch(session, settings, engine, study)


def create_building(session: Session, settings: Settings, engine: Engine, study_file: StudyFile,
                    owner: Researcher) -> tuple[Study, BuildJob]:
    """A draft study from a study file with inline ``[clips]`` and the build job that builds and renders its
    clips and then makes its comparisons (poll it as any build job).  What can be checked now is, as 422 naming
    the field: the clip set given inline (the motions must be files of the data directory), the design against
    it; 409 if a build is running or the slug is taken.  Nothing is created then."""
    from anim_core.clips.build import ConfigError
    from server.clipset.config import inline_config
    from server.studies import ladder
    from server.studies.service import new_draft

    clips = study_file.clips
    if clips is None:
        raise ValueError("create_building is for a study file with [clips]")
    if clips.set is not None:
        raise Unprocessable("clips.set: a clip-set file names files on the server; through the API give the "
                            "clip set inline ([[clips.conditions]] and/or [clips.animations.<name>], motions from "
                            "the server's data directory), or run `animstudy study create FILE` on the server")
    check_build_slot(session, settings, owner.id)
    try:
        config = inline_config(clips.animations, clips.conditions, "the study file", clips.ladders)
    except ConfigError as exc:
        raise Unprocessable(str(exc)) from None
    for name, animation in (clips.animations or {}).items():
        check_data_file(settings, animation.get("source"), f"clips.animations.{name}.source")
        check_data_file(settings, animation.get("mapping"), f"clips.animations.{name}.mapping")
    design = ladder.resolve(study_file.design, ladder.ladder_fields(config.conditions))
    study_file = study_file.model_copy(update={"design": design})
    pipeline.check_design(config, design)
    study = new_draft(session, study_file, owner)
    session.add(study)
    session.flush()  # its id names the folder of its [clips]
    path = study_clips_path(settings, study.id)
    try:  # the study and its [clips], both or neither
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_text(clips.model_dump_json(exclude_none=True), encoding="utf-8")
        tmp.replace(path)
        session.commit()
    except BaseException:
        session.rollback()
        path.unlink(missing_ok=True)
        raise
    return study, launch(session, settings, engine, study)

# --- the registry and the process --------------------------------------------------------------------------------

#: Every kind of job and what it runs: the one place a kind is registered.
KINDS: dict[str, runner.Kind] = {
    JobKind.upload: runner.Kind(build_job, for_researchers=True, lock=build_lock, started="reading the assets"),
    JobKind.render: runner.Kind(commands.render_job),
    JobKind.study: runner.Kind(commands.study_job),
    JobKind.archive: runner.Kind(commands.archive_job),
    JobKind.default: runner.Kind(commands.default_job),
}


def run(settings: Settings, factory: sessionmaker[Session], job_id: int,
        echo: Callable[[str], None] | None = None) -> None:
    """Run the job ``job_id`` to its end, whatever its kind (:func:`server.jobs.runner.run` over :data:`KINDS`)."""
    runner.run(settings, factory, job_id, KINDS, echo)


def run_in_this_process(settings: Settings, kind: JobKind, params: dict[str, Any],
                        echo: Callable[[str], None] = lambda m: print(m, flush=True)) -> BuildJob:
    """Make a command's job and run it here (its ``pid`` this process's); returns the finished row."""
    return runner.run_in_this_process(settings, kind, params, KINDS, echo)


def prepare_default(settings: Settings, factory: sessionmaker[Session],
                    echo: Callable[[str], None] = lambda m: print(m, flush=True)) -> BuildJob | None:
    """``animstudy serve``: when the database holds no study, the default study as a job (kind ``default``) run
    here; a default job whose process ended mid-job (a server stopped while rendering) is claimed and run again,
    rendering only what is missing.  None when there is a study already."""
    with factory() as session:
        if session.scalar(select(Study.id).limit(1)) is not None:
            return None
        claimed = next((job.id for job in lost_jobs(session, JobKind.default) if claim(session, job)), None)
    if claimed is None:
        return run_in_this_process(settings, JobKind.default, {}, echo)
    run(settings, factory, claimed, echo)
    with factory() as session:
        finished = session.get(BuildJob, claimed)
        session.expunge(finished)
        return finished


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if len(argv) != 1 or not argv[0].isdigit():
        print("usage: python -m server.pipeline.jobs JOB_ID", file=sys.stderr)
        return 2
    settings = Settings()
    runner.limit_memory(settings.build_memory_mb)
    engine = make_engine(settings.sqlalchemy_url)
    try:
        run(settings, session_factory(engine), int(argv[0]), echo=lambda m: print(m, flush=True))  # into its log
    finally:
        engine.dispose()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
