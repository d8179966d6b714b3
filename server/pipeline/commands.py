"""The jobs of the commands ``animstudy render``, ``animstudy study create``, ``animstudy study import-archive``
and of the default study ``animstudy serve`` prepares (:class:`server.jobs.models.JobKind` ``render``, ``study``,
``archive``, ``default``): rows of ``build_jobs`` like an upload's build, run by :func:`server.pipeline.jobs.run`
(:func:`server.pipeline.jobs.run_in_this_process` for the command itself).

The command checks what it is given, makes the job's row (``params``: everything the job needs, paths absolute)
and runs it in its own process, printing the messages; the row has its progress (one step per video rendered),
and ``done`` or ``failed`` with the reason.  When the command's process dies mid-job, ``animstudy serve`` resumes
the job at start-up (:func:`server.jobs.control.resume_lost_jobs`): it runs again from the start, and since
every video's name says what it shows, only the videos still missing are rendered.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from server.config import Settings
from server.jobs.progress import BuildError, Progress, rendering


def _study_file(path: Path) -> Any:
    from server.studies.studyfile import StudyFileError, load_study_file

    try:
        return load_study_file(path)
    except StudyFileError as exc:
        raise BuildError(f"{exc.source} is not a valid study file: {'; '.join(exc.errors)}") from None


def render_job(settings: Settings, factory: sessionmaker[Session], job_id: int, params: dict[str, Any],
               progress: Progress) -> None:
    """``animstudy render``: the clip set (built first if it is missing), the pairs of the study files and of
    every study in the database, the clips of those pairs (``every_clip``: every clip), into ``out``
    (:func:`server.pipeline.stimuli.make_stimuli` over the command's own folders)."""
    from server.media.scene import RenderSettings

    from . import stimuli as pipeline

    clips_dir, out = Path(params["clips_dir"]), Path(params["out"])
    # The render manifest lists what was asked for (and the studies' own pairs, so that new studies can be made
    # over it), not what the folder held before.
    place = pipeline.Place(clips_dir, out, media_dir=out, keep_rendered=False)
    designs = {path: _study_file(Path(path)).design for path in params["studies"]}
    with factory() as session:
        try:
            pipeline.make_stimuli(settings, session, place, designs, RenderSettings(**params["settings"]),
                                  progress=lambda m: progress(message=m), workers=params["workers"],
                                  every_clip=params["every_clip"], videos_done=rendering(progress))
        except OSError as exc:
            raise BuildError(f"cannot write videos to {out}: {exc}") from None


def study_job(settings: Settings, factory: sessionmaker[Session], job_id: int, params: dict[str, Any],
              progress: Progress) -> None:
    """``animstudy study create``: the clips and videos the study file needs (what is missing), then the study
    (``study_id`` of the job), opened if asked."""
    from server.media.scene import RenderSettings
    from server.researchers.models import Researcher
    from server.studies import service
    from server.studies.models import Study

    from . import stimuli as pipeline

    path = Path(params["file"])
    study_file = _study_file(path)
    size = RenderSettings(**params["settings"]) if params.get("settings") else None
    with factory() as session:
        if session.scalar(select(Study.id).where(Study.slug == study_file.slug)) is not None:
            raise BuildError(f"a study with slug {study_file.slug!r} exists already")
        owner = session.get(Researcher, params["owner_id"]) if params.get("owner_id") is not None else None
        session.commit()  # no transaction held while building: the job's progress is written meanwhile
        media, place = pipeline.prepare(settings, session, study_file, path, size,
                                        progress=lambda m: progress(message=m), videos_done=rendering(progress),
                                        owner_id=params.get("owner_id"))
        progress(stage="study", done=0, total=1, message=f"creating study {study_file.slug!r}")
        study = service.create_study(session, media, study_file, owner, media_dir=settings.media_dir,
                                     clips_dir=place.clips_dir)
        if params.get("open"):
            service.open_study(session, study, settings.media_dir)
        progress(stage="study", done=1, total=1, study_id=study.id)


def archive_job(settings: Settings, factory: sessionmaker[Session], job_id: int, params: dict[str, Any],
                progress: Progress) -> None:
    """``animstudy study import-archive``: the study of the archive ``file`` with its stimulus set (``study_id`` of
    the job), owned by ``owner_id``, within ``limits`` (:class:`server.studies.archive.ArchiveLimits` fields), opened
    if asked."""
    from server.researchers.models import Researcher
    from server.studies import service
    from server.studies.archive import ArchiveLimits, import_archive

    progress(stage="study", done=0, total=1, message=f"importing {Path(params['file']).name}")
    with factory() as session:
        owner = session.get(Researcher, params["owner_id"]) if params.get("owner_id") is not None else None
        try:
            study = import_archive(session, Path(params["file"]), settings.media_dir, owner,
                                   ArchiveLimits(**params.get("limits") or {}))
        except OSError as exc:  # a file that cannot be read: its message, not a traceback
            raise BuildError(str(exc)) from None
        if params.get("open"):
            service.open_study(session, study, settings.media_dir)
        progress(stage="study", done=1, total=1, study_id=study.id)


def default_job(settings: Settings, factory: sessionmaker[Session], job_id: int, params: dict[str, Any],
                progress: Progress) -> None:
    """The default study of ``animstudy serve`` (the thesis study, studies/thesis.toml) when the database holds
    none: its clips and videos (what is missing), then the study, created and opened."""
    from server.studies import service
    from server.studies.models import Study
    from server.studies.studyfile import thesis_study

    from . import stimuli as pipeline

    with factory() as session:
        if session.scalar(select(Study.id).limit(1)) is not None:
            progress(message="the database holds a study already: no default study made")
            return
        study_file = thesis_study()
        media, place = pipeline.prepare(settings, session, study_file, progress=lambda m: progress(message=m),
                                        videos_done=rendering(progress))
        progress(stage="study", done=0, total=1, message=f"creating study {study_file.slug!r}")
        study = service.create_study(session, media, study_file, media_dir=settings.media_dir,
                                     clips_dir=place.clips_dir)
        service.open_study(session, study, settings.media_dir)
        progress(stage="study", done=1, total=1, study_id=study.id,
                 message=f"created and opened study {study.slug!r} ({len(study.comparisons)} comparisons)")
