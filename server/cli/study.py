"""``animstudy render``, ``animstudy study ...`` and ``animstudy gc``: studies, their videos, and collecting what
nothing uses."""

from __future__ import annotations

import argparse
import json
import math
import sys
import tomllib
from pathlib import Path
from typing import Any

from sqlalchemy import select
from sqlalchemy.exc import OperationalError
from sqlalchemy.orm import Session

from anim_core.clips.build import ConfigError
from server.analysis import simulate as sim
from server.assets import AssetError
from server.clipset.manifest import MANIFEST, unreferenced_clip_files
from server.config import Settings
from server.db import make_engine, migrate, session_factory
from server.errors import MediaError, ServiceError
from server.jobs.control import running_jobs
from server.jobs.models import BuildState, JobKind
from server.pipeline import stimuli as pipeline
from server.pipeline.jobs import run_in_this_process
from server.pipeline.stimuli import clip_set_dirs, render_manifest_dirs
from server.research import export
from server.research.service import study_summary
from server.researchers.models import Researcher
from server.researchers.service import normalize_email
from server.stimuli.service import collect
from server.studies import service
from server.studies.archive import ArchiveLimits, export_archive
from server.studies.design import Design
from server.studies.models import Study, StudyState
from server.studies.studyfile import THESIS_FILE, StudyFile, StudyFileError, load_study_file

from . import thresholds as threshold_commands
from .common import fail


def render(settings: Settings, out: Path, clips_dir: Path, workers: int, studies: list[Path],
           width: int, height: int, shadows: bool, every_clip: bool = False) -> int:
    """Render the clip set's videos into ``out`` (building the clip set first if it is missing): the pairs the
    ``studies`` files show (default: the thesis study file for the server's clip set, none for another), the pairs
    of every study in the database, and the clips of those pairs (``every_clip``: every clip).  A job of the
    database (kind ``render``, :mod:`server.pipeline.commands`): resumed by ``animstudy serve`` if this process
    dies mid-job."""

    # The thesis study's pairs are the server's clip set's; another set (say `clips build --config`) has its own
    # animations, so without a study file over it only --every-clip says what to render.
    own_set = Path(clips_dir).resolve() == settings.clips_dir
    if not studies and not own_set and not every_clip:
        return fail(f"{clips_dir} is not the server's clip set ({settings.clips_dir}), so the default study "
                    f"(studies/thesis.toml) does not apply to it: give --study FILE (a study over that clip set), "
                    f"--every-clip (a video of each of its clips), or both")
    files = studies or ([THESIS_FILE] if own_set else [])
    try:
        for f in files:
            load_study_file(f)
    except StudyFileError as exc:
        return fail(f"{exc.source} is not a valid study file: {'; '.join(exc.errors)}")
    job = run_in_this_process(settings, JobKind.render, {
        "out": str(Path(out).resolve()), "clips_dir": str(Path(clips_dir).resolve()),
        "studies": [str(Path(f).resolve()) for f in files], "workers": workers, "every_clip": every_clip,
        "settings": {"width": width, "height": height, "shadows": shadows}})
    return 0 if job.state == BuildState.done else fail(f"{job.error} (job {job.id})")


def _study_session(settings: Settings) -> object:

    engine = make_engine(settings.sqlalchemy_url)
    migrate(engine, media_dir=settings.media_dir, clips_dir=settings.clips_dir)
    return session_factory(engine)()


def study_command(settings: Settings, args: argparse.Namespace) -> int:
    """``animstudy study ...``: schema, validate, create, list, open, close, export, export-archive,
    import-archive, simulate, plan; every failure as one line of error (a study file's, one line per error)."""
    command = args.study_command
    if command in ("threshold-plan", "frontier"):  # issue 38: server/threshold_commands.py
        return (threshold_commands.threshold_plan if command == "threshold-plan"
                else threshold_commands.frontier_command)(args)
    if command == "schema":
        print(json.dumps(StudyFile.model_json_schema(), indent=2))
        return 0
    try:
        if command in ("simulate", "plan"):
            study_file = load_study_file(args.file)
            design = study_file.design
            if getattr(design, "mode", None) in threshold_commands.THRESHOLD_MODES:
                # the levels are the clip set's: its [clips] file's conditions, or the server's clip manifest
                place = pipeline.study_place(settings, study_file, args.file)
                return threshold_commands.simulate_or_plan(args, pipeline.settled(place, design, str(args.file)))
            return _simulate_or_plan(args, design)
        if command == "validate":
            return _validate(settings, args)
        with _study_session(settings) as session:  # type: ignore[attr-defined]
            return {"create": _create, "import-archive": _import_archive, "list": _list, "open": _open,
                    "close": _close, "export-archive": _export_archive, "export": _export}[command](
                settings, session, args)
    except StudyFileError as exc:
        print(f"error: {exc.source} is not a valid study file:", file=sys.stderr)
        for line in exc.errors:
            print(f"  {line}", file=sys.stderr)
        return 2
    except ServiceError as exc:
        return fail(exc.detail)
    except (AssetError, ConfigError, MediaError, OSError) as exc:
        return fail(str(exc))
    except OperationalError as exc:  # e.g. another process holding SQLite's writers for longer than the timeout
        return fail(f"the database could not be used: {exc.orig}; try again when the other command has finished")
    return 0


def _validate(settings: Settings, args: argparse.Namespace) -> int:
    """``study validate``: the file, and its animations and conditions against its clip set."""
    study_file = load_study_file(args.file)
    design = study_file.design
    if study_file.clips is not None:
        place = pipeline.study_place(settings, study_file, args.file)
        config = place.config
        assert config is not None
        try:  # its levels, conditions and animations (takes and composites), each condition building a clip of each
            design = pipeline.settled(place, design, str(args.file))
            pipeline.check_design(config, design)
        except ServiceError as exc:
            return fail(f"{args.file}: {exc.detail}")
        checked = "; its animations and conditions are in its own clip set ([clips])"
    elif (settings.clips_dir / MANIFEST).is_file():
        design = service.settled(study_file.design, settings.clips_dir)
        service.check_known(design, service.clip_set_index(settings.clips_dir))
        checked = f"; its animations and conditions are in the clip set {settings.clips_dir}"
    else:
        checked = f" (no clip set in {settings.clips_dir}: animations and conditions not checked)"
    print(f"{args.file}: study {study_file.slug!r} is valid, {design.trials_total()} trials per "
          f"participant{checked}")
    return 0


def _create(settings: Settings, session: Session, args: argparse.Namespace) -> int:
    """``study create``: a job (kind ``study``) builds, renders and creates it; its notes printed."""
    study_file = load_study_file(args.file)
    owner = None
    if args.owner:
        owner = session.scalar(select(Researcher).where(Researcher.email == normalize_email(args.owner)))
        if owner is None:
            return fail(f"no researcher {args.owner!r} (create one with `animstudy researcher create`)")
    if session.scalar(select(Study.id).where(Study.slug == study_file.slug)) is not None:
        return fail(f"a study with slug {study_file.slug!r} exists already")
    size = None
    if args.width or args.height or args.no_shadows:
        size = {"width": args.width or 640, "height": args.height or 480, "shadows": not args.no_shadows}
    # The owner's id is read before the rollback: reading it after would load the expired row in a
    # new transaction, which on SQLite holds the writers' lock while the job writes ("database is
    # locked" after 30 s, issue 36).
    owner_id = owner.id if owner else None
    session.rollback()  # no transaction open while the job writes (SQLite would lock)
    job = run_in_this_process(settings, JobKind.study, {
        "file": str(Path(args.file).resolve()), "owner_id": owner_id,
        "open": bool(args.open), "settings": size})
    if job.state != BuildState.done or job.study_id is None:
        return fail(f"{job.error} (job {job.id})")
    study = session.get(Study, job.study_id)
    place = pipeline.study_place(settings, study_file, args.file, owner_id)
    print(f"created study {study.slug!r} ({study.state}, {service.trials_total(study)} trials per "
          f"participant); participant link: /s/{study.slug}")
    for test, ref in service.identical_comparisons(Design.model_validate(study.design), place.clips_dir):
        print(f"note: {test} is identical to {ref} (same arrays): that comparison shows one clip on "
              "both sides, like a catch trial")
    return 0


def _list(settings: Settings, session: Session, args: argparse.Namespace) -> int:
    """``study list``."""
    rows = [study_summary(session, s) for s in session.scalars(select(Study).order_by(Study.id))]
    print(f"{'slug':24} {'state':7} {'started':>7} {'completed':>9} {'votes':>6}  title")
    for r in rows:
        print(f"{r.slug:24} {r.state:7} {r.started:7d} {r.completed:9d} {r.votes:6d}  {r.title}")
    return 0


def _open(settings: Settings, session: Session, args: argparse.Namespace) -> int:
    """``study open``."""
    study = service.open_study(session, service.get_study(session, args.slug), settings.media_dir)
    print(f"study {study.slug!r} is {study.state}; its stimulus set {study.stimulus_set.digest[:12]} "
          "is pinned")
    return 0


def _close(settings: Settings, session: Session, args: argparse.Namespace) -> int:
    """``study close``."""
    study = service.set_state(session, service.get_study(session, args.slug), StudyState.closed)
    print(f"study {study.slug!r} is {study.state}")
    return 0


def _export_archive(settings: Settings, session: Session, args: argparse.Namespace) -> int:
    """``study export-archive``."""

    study = service.get_study(session, args.slug)
    out = export_archive(study, settings.media_dir, args.out or Path(f"{study.slug}.animstudy.zip"))
    print(f"study {study.slug!r} with its stimulus set {study.stimulus_set.digest[:12]} "
          f"({len(study.stimulus_set.content['pairs'])} pair videos) -> {out} "
          f"({out.stat().st_size / 2**20:.1f} MiB)")
    return 0


def _import_archive(settings: Settings, session: Session, args: argparse.Namespace) -> int:
    """``study import-archive``: a job (kind ``archive``) imports it."""

    owner_id = None
    if args.owner:
        owner_id = session.scalar(select(Researcher.id).where(
            Researcher.email == normalize_email(args.owner)))
        if owner_id is None:
            return fail(f"no researcher {args.owner!r} (create one with `animstudy researcher create`)")
    limits = {}
    if args.max_mib is not None:
        limits = {"total_bytes": args.max_mib * 2**20,
                  "member_bytes": min(ArchiveLimits().member_bytes, args.max_mib * 2**20)}
    session.rollback()  # no transaction open while the job writes (SQLite would lock)
    job = run_in_this_process(settings, JobKind.archive, {
        "file": str(Path(args.file).resolve()), "owner_id": owner_id, "limits": limits,
        "open": bool(args.open)})
    if job.state != BuildState.done or job.study_id is None:
        return fail(f"{job.error} (job {job.id})")
    study = session.get(Study, job.study_id)
    print(f"imported study {study.slug!r} ({study.state}) with its stimulus set "
          f"{study.stimulus_set.digest[:12]}; participant link: /s/{study.slug}")
    return 0


def _export(settings: Settings, session: Session, args: argparse.Namespace) -> int:
    """``study export``: the votes in one of the formats, to a file or standard output."""
    study = service.get_study(session, args.slug)
    text = {"csv": lambda: export.export_csv(session, study),
            "json": lambda: json.dumps(export.export_document(session, study), indent=1) + "\n",
            "sureal": lambda: json.dumps(export.export_sureal(session, study), indent=1) + "\n",
            "pwcmp": lambda: export.export_pwcmp_csv(session, study)}[args.format]()
    if args.out:
        args.out.write_text(text, encoding="utf-8")
        rows = text.count(chr(10)) - 1 if args.format in ("csv", "pwcmp") else "the"
        print(f"{rows} rows of {study.slug!r} -> {args.out}", file=sys.stderr)
    else:
        sys.stdout.write(text)
    return 0


def gc(settings: Settings, dry_run: bool) -> int:
    """``animstudy gc``: delete the videos and posters that neither a study's stimulus set nor a render manifest
    uses, and the clip files no clip set's manifest names (``--dry-run``: list them).  Refused while a job runs:
    what it has made is named by nothing until it ends."""

    with _study_session(settings) as session:  # type: ignore[attr-defined]
        if running := running_jobs(session):
            listed = ", ".join(f"{j.kind} job {j.id}" for j in running)
            return fail(f"a job is running ({listed}); run gc when it has finished (what a running job has made "
                         "is not yet named by any manifest)")
        found = collect(session, settings.media_dir, render_manifest_dirs(settings), dry_run=dry_run)
    clip_files = [f for d in clip_set_dirs(settings) if d.is_dir() for f in unreferenced_clip_files(d)]
    clip_bytes = sum(f.stat().st_size for f in clip_files)
    if not dry_run:
        for f in clip_files:
            f.unlink(missing_ok=True)
    for f in found.files:
        print(f.name)
    for f in clip_files:
        print(f.relative_to(settings.var) if f.is_relative_to(settings.var) else f.name)
    verb = "would delete" if dry_run else "deleted"
    print(f"{verb} {len(found.files)} unreferenced files ({found.size_bytes / 2**20:.1f} MiB); kept {found.kept} "
          "that a study's stimulus set or the render manifest uses", file=sys.stderr)
    print(f"{verb} {len(clip_files)} clip files no clip set's manifest names ({clip_bytes / 2**20:.1f} MiB)",
          file=sys.stderr)
    return 0


def _read_truth(path: Path, conditions: list[str]) -> dict[str, float]:
    """condition -> value from a TOML or JSON table; every condition of the design must have a number."""

    text = path.read_text(encoding="utf-8")
    try:
        raw = json.loads(text) if path.suffix == ".json" else tomllib.loads(text)
    except (ValueError, tomllib.TOMLDecodeError) as exc:
        raise ValueError(f"{path}: not valid {'JSON' if path.suffix == '.json' else 'TOML'}: {exc}") from None
    missing = [c for c in conditions if c not in raw]
    wrong = [c for c in conditions if c in raw and (isinstance(raw[c], bool) or not isinstance(raw[c], int | float)
                                                    or not math.isfinite(raw[c]))]
    if missing or wrong:
        raise ValueError(f"{path}: needs a number for every condition of the design "
                         f"({', '.join(conditions)}); missing: {', '.join(missing) or '-'}; not a number: "
                         f"{', '.join(wrong) or '-'}")
    return {c: float(raw[c]) for c in conditions}


def _simulate_or_plan(args: argparse.Namespace, design: Any) -> int:

    if args.study_command == "simulate":
        try:
            truth = (_read_truth(args.truth, design.all_conditions()) if args.truth else sim.even_truth(design))
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            return fail(str(exc))
        print(f"{design.mode} design, {len(design.all_conditions())} conditions, {len(design.animations)} "
              f"animation(s); truth: " + ", ".join(f"{c} {v:g}" for c, v in truth.items()), flush=True)
        summary = sim.summarise(design, truth, args.participants, args.seeds, progress=lambda done: print(
            f"  simulated study {done} of {args.seeds}", file=sys.stderr, flush=True))
        print(f"{args.participants} participants x {args.seeds} simulated studies: {summary.trials_per_study} "
              f"trials per study; scale error (RMSE, logit units) {summary.rmse:.3f}; Kendall tau "
              f"{summary.kendall_tau:.3f} (>= 0.9 in {100 * summary.tau_at_least_09:.0f} % of studies)"
              + (f"; {summary.failed} condition values infinite (one-sided answers)" if summary.failed else ""))
        return 0
    if args.effect is None or not 0 < args.power < 1 or not math.isfinite(args.effect) or args.effect == 0:
        return fail("--power must be between 0 and 1 and --effect a non-zero number")
    print(f"{design.mode} design: simulating {args.seeds} studies per participant count "
          f"(effect {args.effect:g} logit units, power {args.power:g}) ...", flush=True)
    needed, achieved = sim.plan(design, args.effect, args.power, args.seeds, progress=lambda n, value: print(
        f"  {n} participants: power {100 * value:.0f} %", file=sys.stderr, flush=True))
    if needed is None:
        return fail(f"even 1000 participants give only {100 * achieved:.0f} % power")
    trials = needed * design.trials_total()
    print(f"{needed} participants ({trials} trials; simulated power {100 * achieved:.0f} %)")
    return 0


def run(settings: Settings, args: argparse.Namespace) -> int:
    """``animstudy study ...``, ``gc`` and ``render``."""
    if args.command == "study":
        return study_command(settings, args)
    if args.command == "gc":
        return gc(settings, args.dry_run)
    return render(settings, args.out or settings.var / "media", args.clips or settings.var / "clips",
                  max(1, args.workers), args.study or [], args.width, args.height, not args.no_shadows,
                  args.every_clip)
