"""``animstudy`` command line."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from anim_core.clips.sources import MotionReport

from .config import Settings


def _fail(message: str) -> int:
    print(f"error: {message}", file=sys.stderr)
    return 2


#: The frames × joints ``clips inspect`` and ``clips convert`` read at least (about 600 MB at the 300 bytes per
#: frame·joint reading takes): more than any real recording of under 20,000 frames of 100 joints, and a larger real
#: file gets more from the upload's bound (its text or binary holds every frame·joint).  A 115 KB BVH of 969
#: joints without channels asked for 9.7 million (2.6 GiB) and is refused.
CLI_FRAME_JOINTS = 2_000_000


def _frame_joints(path: Path, flag: int | None) -> int:
    """The frames × joints a motion file given on the command line may hold: ``--max-frame-joints``, or the
    larger of :data:`CLI_FRAME_JOINTS` and what an upload of its size may hold."""
    from server.uploads.service import max_frame_joints

    return flag if flag is not None else max(CLI_FRAME_JOINTS, max_frame_joints(path.stat().st_size))


def _too_many(message: str) -> str:
    """A reader's message, with the way out when the frame·joint bound refused the file."""
    return message + ("; --max-frame-joints N allows more" if "frame-joints" in message else "")


def _source_options(parser: argparse.ArgumentParser) -> None:
    """--mapping, --units and --up of ``clips inspect`` and ``clips convert``."""
    parser.add_argument("--mapping", type=Path, default=None,
                        help="explicit joint mapping (.toml or .json: character joint = file joint)")
    parser.add_argument("--units", choices=["m", "cm", "mm", "inch", "cmu"], default=None,
                        help="length unit of the file (default: detected from the skeleton's height)")
    parser.add_argument("--up", choices=["y", "z"], default=None, help="up axis of the file (default: detected)")
    parser.add_argument("--max-frame-joints", type=int, default=None, metavar="N",
                        help=f"read at most N frames × joints (default: {CLI_FRAME_JOINTS}, or more for a large "
                        "file: a file of joints without channels can ask for gigabytes)")


def clips_inspect(data_dir: Path, path: Path, mapping: Path | None, units: str | None, up_axis: str | None,
                  max_frame_joints: int | None = None) -> int:
    """Print what a BVH or glTF file holds and how it maps onto the character (``animstudy clips inspect``); for a
    motion suggested as kind ``other``, a ``tolerance_mm`` measured by building it (:func:`_tolerance_line`)."""
    from anim_core.clips.sources import format_report, inspect_source, joint_table
    from anim_core.rig.rigmap import RigMapError, read_mapping_file

    if not path.is_file():
        return _fail(f"{path}: no such file")
    try:
        explicit = read_mapping_file(mapping) if mapping else None
        reports = inspect_source(path, explicit, units, up_axis, _frame_joints(path, max_frame_joints))
    except (ValueError, OSError) as exc:  # BvhError, GltfError and RigMapError name the file (and line)
        # A skeleton that does not map: its joints, to write a mapping file from.
        table = joint_table(path) if isinstance(exc, RigMapError) else None
        return _fail(_too_many(str(exc)) + (f"\n{table}" if table else ""))
    print(format_report(path, reports, [_tolerance_line(data_dir, path, r) if r.kind == "other" else None
                                        for r in reports]))
    return 0


def _tolerance_line(data_dir: Path, path: Path, report: MotionReport) -> str:
    """The suggested ``tolerance_mm`` of a kind-``other`` motion, with the key and byte ratio of the hybrid it
    builds on the clip set's character (:func:`anim_core.clips.build.suggest_tolerance`), or why there is none."""
    from anim_core.clips.build import AnimationConfig, source_from_bvh, suggest_tolerance
    from server.assets import AssetError
    from server.clipset.build import load_character
    from server.clipset.config import load_config

    n = report.normalized
    try:
        clip_set = load_config()
        character, _ = load_character(data_dir, clip_set.character)
        config = AnimationConfig(Path(report.name).stem or "motion", "other", str(path), report.frames,
                                 "loop" if report.playback == "loop" else "pingpong", False)
        source = source_from_bvh(n.bvh, character, config, clip_set.relocate, n.metres_per_unit, n.source_positions)
        return suggest_tolerance(source, clip_set.fps).describe()
    except (AssetError, ValueError) as exc:  # ConfigError (the gate, the key picking) names the animation
        return f"tolerance_mm: none suggested, building the motion failed: {exc}"


def clips_convert(data_dir: Path, path: Path, out: Path, mapping: Path | None, units: str | None,
                  up_axis: str | None, max_frame_joints: int | None = None) -> int:
    """Write a BVH/glTF motion retargeted onto the character as .glb/.gltf or .bvh (``animstudy clips convert``)."""
    from anim_core.clips.sources import export_on_character, inspect_source
    from anim_core.rig.rigmap import read_mapping_file
    from server.assets import character as load_character

    if not path.is_file():
        return _fail(f"{path}: no such file")
    try:
        explicit = read_mapping_file(mapping) if mapping else None
        report = inspect_source(path, explicit, units, up_axis, _frame_joints(path, max_frame_joints))[0]
        export_on_character(report.normalized, load_character(data_dir), out, report.name)
    except (ValueError, OSError) as exc:  # file, mapping and character errors are ValueErrors naming the file
        return _fail(_too_many(str(exc)))
    print(f"wrote {out} ({report.n_frames} frames at {report.fps:g} fps on the character)")
    return 0


def clips_export(data_dir: Path, clips_dir: Path, clip_id: str, out: Path) -> int:
    """Write one clip of a built clip set on the character as .glb/.gltf or .bvh (``animstudy clips export``)."""
    import numpy as np

    from anim_core.clips.sources import write_motion
    from anim_core.math.skeleton import Skeleton
    from anim_core.rig.character import bind_mesh
    from server.clipset.build import load_character, record_config
    from server.clipset.manifest import read_clip, read_clip_manifest

    try:
        entry, a = read_clip(clips_dir, clip_id)
        names = [str(n) for n in a["joint_names"]]
        skeleton = Skeleton(names, a["parents"], a["offsets"])
        # The body the clip was built for (MakeHuman or the clip set's glTF), its files checked as for rendering.
        record = read_clip_manifest(clips_dir).character
        character = load_character(data_dir, record_config(data_dir, None if record is None else
                                                           record.model_dump())[0])[0]
        mesh = bind_mesh(character, names, a["bind_rotations"], a["bind_positions"])
        # The clip stores no End Sites: each leaf's continues its last bone by half its length.
        leaves = np.setdiff1d(np.arange(len(names)), skeleton.parents)
        ends = {int(j): 0.5 * np.asarray(a["offsets"][j]) for j in leaves}
        write_motion(out, skeleton, mesh, character.faces, a["local_rotations"], a["root_positions"],
                     1.0 / entry.fps, ends, clip_id)
    except (ValueError, OSError) as exc:  # ManifestError, AssetError, GltfError name the file
        return _fail(str(exc))
    print(f"wrote {out} ({entry.frames} frames at {entry.fps} fps, {entry.playback}: clip {clip_id} on the "
          f"character)")
    return 0


def inspect(data_dir: Path) -> int:
    """Print what the motion-capture files in the data directory hold."""
    import numpy as np

    from anim_core.clips.build import METRES_PER_CMU_UNIT
    from anim_core.io.bvh import BvhError, clip_from_bvh, read_bvh

    paths = sorted(data_dir.glob("mocap/**/*.bvh*"))
    if not paths:
        return _fail(f"no BVH files under {data_dir / 'mocap'}; set ANIMSTUDY_DATA_DIR (see docs/reference/data.md)")
    print(f"motion capture in {data_dir}:")
    print(f"{'file':34} {'frames':>6} {'fps':>5} {'seconds':>7} {'joints':>6} {'travel m':>8} {'speed m/s':>9}")
    status = 0
    for path in paths:
        try:
            bvh = read_bvh(path)
        except (BvhError, OSError) as exc:
            print(f"{path.name:34} unreadable: {exc}", file=sys.stderr)
            status = 1
            continue
        clip = clip_from_bvh(bvh)
        travel = np.linalg.norm(clip.velocity) * clip.duration * METRES_PER_CMU_UNIT
        print(f"{path.name:34} {bvh.n_frames:6d} {bvh.fps:5.0f} {clip.duration:7.2f} "
              f"{clip.skeleton.n_joints:6d} {travel:8.2f} {travel / clip.duration:9.2f}")
    return status


def _fmt(value: float | None, digits: int) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def clips_build(data_dir: Path, out: Path, config: Path | None, scheduler: str | None = None) -> int:
    """Build the clip set, write it to ``out`` and print its metric table.  One Dask task per animation, on the
    cluster at ``scheduler`` or a local one of 2 workers (docs/cluster.md)."""
    from anim_core.clips.build import ConfigError
    from anim_core.clips.measure import clip_warnings
    from server.assets import AssetError
    from server.clipset.build import build_clip_set
    from server.clipset.config import load_config
    from server.clipset.manifest import write_clip_set

    started = time.perf_counter()
    try:
        cfg = load_config(config) if config else load_config()
        clips = build_clip_set(data_dir, cfg, progress=lambda msg: print(msg, flush=True), scheduler=scheduler,
                               workers=2)
        manifest = write_clip_set(clips, out)
    except (AssetError, ConfigError) as exc:
        return _fail(str(exc))
    except OSError as exc:
        return _fail(f"cannot write the clip set to {out}: {exc}")
    print(f"\n{len(clips)} clips in {time.perf_counter() - started:.1f} s -> {manifest}\n")
    width = max(16, *(len(c.id) for c in clips))
    print(f"{'clip':{width}} {'keys':>4} {'s':>5} {'skate':>6} {'slide mm':>8} {'pen mm':>6} {'float mm':>8} "
          f"{'MPJPE mm':>8} {'key jump rad/s':>14} {'accel jump rad/s2':>17} {'max err deg':>11} {'jerk m/s3':>9} "
          f"{'bytes':>6}")
    for c in clips:
        m = c.metrics
        print(f"{c.id:{width}} {c.key_times.size:4d} {c.duration_s:5.2f} {m['foot_skate_ratio']:6.3f} "
              f"{m['foot_slide_mm']:8.2f} {m['penetration_mm']:6.1f} {m['floating_mm']:8.1f} "
              f"{_fmt(m['mpjpe_mm'], 1):>8} {m['key_velocity_jump_rad_s']:14.3f} "
              f"{m['key_accel_jump_rad_s2']:17.3f} {_fmt(m['max_global_error_deg'], 3):>11} {m['jerk_mean']:9.1f} "
              f"{m['bytes']:6d}")
    _print_comparison(clips, clip_warnings(clips))
    _print_fidelity(clips)
    return 0


def _print_fidelity(clips: list) -> None:
    """The fidelity gate's figures (anim_core.clips.fidelity) of every clip: head over hips (smallest, m), the feet's
    lowest clearance (the higher foot's, mm), depth under the floor (mm), frames with the left hip on the left, the
    largest pose angle difference, the bones' directions (p95, deg), hip width against what the clip is held against,
    knees bending forward, the worst stance's landing (mm) and a gait hybrid's mirrored half (p95, deg): the
    reference's against the source, a condition's against the reference, with the angle and the frame where the pose
    difference is largest."""
    width = max(16, *(len(c.id) for c in clips))
    at_width = max(10, *(len(c.fidelity.pose_error_at or "") for c in clips if c.fidelity is not None))
    print(f"\n{'fidelity':{width}} {'head m':>6} {'feet mm':>7} {'under mm':>8} {'left':>5} {'pose deg':>8} "
          f"{'bones':>5} {'hips':>4} {'knees':>5} {'land mm':>7} {'mirror':>6} {'against':>9}  "
          f"{'largest at':{at_width}} verdict")
    prev = None
    for c in clips:
        f = c.fidelity
        if f is None:
            continue
        verdict = ("UNFAITHFUL (built anyway): " + "; ".join(f.problems) if not f.ok else
                   "UNFAITHFUL (its reference; built anyway)" if c.metrics.get("unfaithful") else "ok")
        against = "source" if c is clips[0] or c.animation != prev else "reference"
        prev = c.animation
        at = f.pose_error_at or "-"
        land = None if f.landing_m is None else f.landing_m * 1000
        print(f"{c.id:{width}} {f.upright_m:6.2f} {f.foot_reach_m * 1000:7.0f} {-f.under_floor_m * 1000:8.0f} "
              f"{f.handedness:5.0%} {_fmt(f.pose_error_deg, 1):>8} {_fmt(f.bone_error_deg, 1):>5} "
              f"{_fmt(f.hip_width_ratio, 2):>4} {_pct(f.knees_forward):>5} {_fmt(land, 0):>7} "
              f"{_fmt(f.mirror_error_deg, 1):>6} {against:>9}  {at:{at_width}} {verdict}", flush=True)


def _pct(share: float | None) -> str:
    return "-" if share is None else f"{share:.0%}"


def _print_comparison(clips: list, warnings: list[str]) -> None:
    """What else than the method the two sides of a pair differ in: feet, phase, seams (issue 14)."""
    width = max(16, *(len(c.id) for c in clips))
    print(f"\n{'clip':{width}} {'skate':>6} {'source':>6} {'seam mm':>7} {'step mm':>7} {'hips r':>6} {'lag':>4} "
          f"{'knee r':>6} {'lag':>4}")
    for c in clips:
        m = c.metrics
        print(f"{c.id:{width}} {m['foot_skate_ratio']:6.3f} {m['source_foot_skate_ratio']:6.3f} "
              f"{m['seam_jump_mm']:7.1f} {m['median_step_mm']:7.1f} {_fmt(m['phase_hips_r'], 2):>6} "
              f"{_fmt(m['phase_hips_lag'], 0):>4} {_fmt(m['phase_knee_r'], 2):>6} {_fmt(m['phase_knee_lag'], 0):>4}")
    from anim_core.clips.composite import format_transitions  # issue 39: sequences' transition metrics

    print(format_transitions(clips), end="")
    for w in warnings:
        print(f"warning: {w}", flush=True)


def render(settings: Settings, out: Path, clips_dir: Path, workers: int, studies: list[Path],
           width: int, height: int, shadows: bool, every_clip: bool = False) -> int:
    """Render the clip set's videos into ``out`` (building the clip set first if it is missing): the pairs the
    ``studies`` files (default: the thesis study file) show, the pairs of every study in the database, and the
    clips of those pairs (``every_clip``: every clip).  A job of the database (kind ``render``,
    :mod:`server.uploads.commands`): resumed by ``animstudy serve`` if this process dies mid-job."""
    from server.studies.studyfile import THESIS_FILE, StudyFileError, load_study_file
    from server.uploads.job import run_in_this_process
    from server.uploads.models import BuildState, JobKind

    files = studies or [THESIS_FILE]
    try:
        for f in files:
            load_study_file(f)
    except StudyFileError as exc:
        return _fail(f"{exc.source} is not a valid study file: {'; '.join(exc.errors)}")
    job = run_in_this_process(settings, JobKind.render, {
        "out": str(Path(out).resolve()), "clips_dir": str(Path(clips_dir).resolve()),
        "studies": [str(Path(f).resolve()) for f in files], "workers": workers, "every_clip": every_clip,
        "settings": {"width": width, "height": height, "shadows": shadows}})
    return 0 if job.state == BuildState.done else _fail(f"{job.error} (job {job.id})")


def prepare_study(settings: Settings, session_factory: object) -> None:
    """When the database holds no study: build the clip set and the videos the thesis study
    (studies/thesis.toml) needs (what is missing), then create and open it."""
    from sqlalchemy import select

    from server.studies import pipeline
    from server.studies.models import Study
    from server.studies.service import create_study, open_study
    from server.studies.studyfile import thesis_study

    with session_factory() as session:  # type: ignore[operator]
        if session.scalar(select(Study.id).limit(1)) is not None:
            return
        study_file = thesis_study()
        media, place = pipeline.prepare(settings, session, study_file, progress=lambda m: print(m, flush=True))
        study = create_study(session, media, study_file, media_dir=settings.media_dir, clips_dir=place.clips_dir)
        open_study(session, study, settings.media_dir)
        print(f"created and opened study {study.slug!r} ({len(study.comparisons)} comparisons)", flush=True)


def _study_session(settings: Settings) -> object:
    from server.db import make_engine, migrate, session_factory

    engine = make_engine(settings.sqlalchemy_url)
    migrate(engine, media_dir=settings.media_dir, clips_dir=settings.clips_dir)
    return session_factory(engine)()


def study_command(settings: Settings, args: argparse.Namespace) -> int:
    """``animstudy study ...``: schema, validate, create, list, open, close, export."""
    from sqlalchemy import select
    from sqlalchemy.exc import OperationalError

    from anim_core.clips.build import ConfigError
    from server.assets import AssetError
    from server.clipset.manifest import MANIFEST
    from server.errors import MediaError, ServiceError
    from server.research import export
    from server.research.service import study_summary
    from server.researchers.models import Researcher
    from server.researchers.service import normalize_email
    from server.studies import pipeline, service
    from server.studies.models import Study, StudyState
    from server.studies.studyfile import StudyFile, StudyFileError, load_study_file
    from server.uploads.job import run_in_this_process
    from server.uploads.models import BuildState, JobKind

    command = args.study_command
    if command in ("threshold-plan", "frontier"):  # issue 38: server/threshold_commands.py
        from server import threshold_commands

        return (threshold_commands.threshold_plan if command == "threshold-plan"
                else threshold_commands.frontier_command)(args)
    if command == "schema":
        print(json.dumps(StudyFile.model_json_schema(), indent=2))
        return 0
    try:
        if command in ("simulate", "plan"):
            from server import threshold_commands  # issue 38: threshold designs

            design = load_study_file(args.file).design
            if getattr(design, "mode", None) in threshold_commands.THRESHOLD_MODES:
                return threshold_commands.simulate_or_plan(args, design)
            return _simulate_or_plan(args, design)
        if command == "validate":
            study_file = load_study_file(args.file)
            if study_file.clips is not None:
                config = pipeline.study_place(settings, study_file, args.file).config
                assert config is not None
                ids = {c.id for c in config.conditions}
                lacking = [c for c in pipeline.needed_conditions(study_file.design) if c not in ids] + [
                    a for a in study_file.design.animations if a not in config.animations]
                if lacking:
                    return _fail(f"{args.file}: {', '.join(lacking)} not in its clip set")
                checked = "; its animations and conditions are in its own clip set ([clips])"
            elif (settings.clips_dir / MANIFEST).is_file():
                service.check_known(study_file.design, service.clip_set_index(settings.clips_dir))
                checked = f"; its animations and conditions are in the clip set {settings.clips_dir}"
            else:
                checked = f" (no clip set in {settings.clips_dir}: animations and conditions not checked)"
            print(f"{args.file}: study {study_file.slug!r} is valid, {study_file.design.trials_total()} trials per "
                  f"participant{checked}")
            return 0
        with _study_session(settings) as session:  # type: ignore[attr-defined]
            if command == "create":
                study_file = load_study_file(args.file)
                owner = None
                if args.owner:
                    owner = session.scalar(select(Researcher).where(Researcher.email == normalize_email(args.owner)))
                    if owner is None:
                        return _fail(f"no researcher {args.owner!r} (create one with `animstudy researcher create`)")
                if session.scalar(select(Study.id).where(Study.slug == study_file.slug)) is not None:
                    return _fail(f"a study with slug {study_file.slug!r} exists already")
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
                    return _fail(f"{job.error} (job {job.id})")
                study = session.get(Study, job.study_id)
                place = pipeline.study_place(settings, study_file, args.file, owner_id)
                print(f"created study {study.slug!r} ({study.state}, {service.trials_total(study)} trials per "
                      f"participant); participant link: /s/{study.slug}")
                for test, ref in service.identical_comparisons(study_file.design, place.clips_dir):
                    print(f"note: {test} is identical to {ref} (same arrays): that comparison shows one clip on "
                          "both sides, like a catch trial")
            elif command == "list":
                rows = [study_summary(session, s) for s in session.scalars(select(Study).order_by(Study.id))]
                print(f"{'slug':24} {'state':7} {'started':>7} {'completed':>9} {'votes':>6}  title")
                for r in rows:
                    print(f"{r.slug:24} {r.state:7} {r.started:7d} {r.completed:9d} {r.votes:6d}  {r.title}")
            elif command == "open":
                study = service.open_study(session, service.get_study(session, args.slug), settings.media_dir)
                print(f"study {study.slug!r} is {study.state}; its stimulus set {study.stimulus_set.digest[:12]} "
                      "is pinned")
            elif command == "close":
                study = service.set_state(session, service.get_study(session, args.slug), StudyState.closed)
                print(f"study {study.slug!r} is {study.state}")
            elif command == "export-archive":
                from server.studies.archive import export_archive

                study = service.get_study(session, args.slug)
                out = export_archive(study, settings.media_dir, args.out or Path(f"{study.slug}.animstudy.zip"))
                print(f"study {study.slug!r} with its stimulus set {study.stimulus_set.digest[:12]} "
                      f"({len(study.stimulus_set.content['pairs'])} pair videos) -> {out} "
                      f"({out.stat().st_size / 2**20:.1f} MiB)")
            elif command == "import-archive":
                from server.studies.archive import ArchiveLimits, import_archive

                owner = None
                if args.owner:
                    owner = session.scalar(select(Researcher).where(Researcher.email == normalize_email(args.owner)))
                    if owner is None:
                        return _fail(f"no researcher {args.owner!r} (create one with `animstudy researcher create`)")
                limits = ArchiveLimits()
                if args.max_mib is not None:
                    limits = ArchiveLimits(total_bytes=args.max_mib * 2**20,
                                           member_bytes=min(limits.member_bytes, args.max_mib * 2**20))
                study = import_archive(session, args.file, settings.media_dir, owner, limits)
                if args.open:
                    service.open_study(session, study, settings.media_dir)
                print(f"imported study {study.slug!r} ({study.state}) with its stimulus set "
                      f"{study.stimulus_set.digest[:12]}; participant link: /s/{study.slug}")
            elif command == "export":
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
    except StudyFileError as exc:
        print(f"error: {exc.source} is not a valid study file:", file=sys.stderr)
        for line in exc.errors:
            print(f"  {line}", file=sys.stderr)
        return 2
    except ServiceError as exc:
        return _fail(exc.detail)
    except (AssetError, ConfigError, MediaError, OSError) as exc:
        return _fail(str(exc))
    except OperationalError as exc:  # e.g. another process holding SQLite's writers for longer than the timeout
        return _fail(f"the database could not be used: {exc.orig}; try again when the other command has finished")
    return 0


def gc(settings: Settings, dry_run: bool) -> int:
    """``animstudy gc``: delete the videos and posters that neither a study's stimulus set nor a render manifest
    uses, and the clip files no clip set's manifest names (``--dry-run``: list them).  Refused while a job runs:
    what it has made is named by nothing until it ends."""
    from server.clipset.manifest import unreferenced_clip_files
    from server.stimuli.service import collect
    from server.studies.pipeline import clip_set_dirs, render_manifest_dirs
    from server.uploads.service import running_jobs

    with _study_session(settings) as session:  # type: ignore[attr-defined]
        if running := running_jobs(session):
            listed = ", ".join(f"{j.kind} job {j.id}" for j in running)
            return _fail(f"a job is running ({listed}); run gc when it has finished (what a running job has made "
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
    import tomllib

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
    from server.analysis import simulate as sim

    if args.study_command == "simulate":
        try:
            truth = (_read_truth(args.truth, design.all_conditions()) if args.truth else sim.even_truth(design))
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            return _fail(str(exc))
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
        return _fail("--power must be between 0 and 1 and --effect a non-zero number")
    print(f"{design.mode} design: simulating {args.seeds} studies per participant count "
          f"(effect {args.effect:g} logit units, power {args.power:g}) ...", flush=True)
    needed, achieved = sim.plan(design, args.effect, args.power, args.seeds, progress=lambda n, value: print(
        f"  {n} participants: power {100 * value:.0f} %", file=sys.stderr, flush=True))
    if needed is None:
        return _fail(f"even 1000 participants give only {100 * achieved:.0f} % power")
    trials = needed * design.trials_total()
    print(f"{needed} participants ({trials} trials; simulated power {100 * achieved:.0f} %)")
    return 0


def ensure_researcher(settings: Settings, session_factory: object) -> None:
    """The first researcher account: from ANIMSTUDY_ADMIN_EMAIL/PASSWORD, or made up and printed once."""
    import secrets

    from sqlalchemy import select

    from server.researchers.models import Researcher
    from server.researchers.service import create_researcher

    with session_factory() as session:  # type: ignore[operator]
        if session.scalar(select(Researcher.id).limit(1)) is not None:
            return
        email = settings.admin_email or "admin@localhost"
        password = settings.admin_password or secrets.token_urlsafe(12)
        create_researcher(session, email, password, admin=True)  # manages every study, the default one too
        shown = password if not settings.admin_password else "(from ANIMSTUDY_ADMIN_PASSWORD)"
        print(f"researcher account created (admin): e-mail {email}, password {shown}", flush=True)


def serve(settings: Settings, host: str, port: int, workers: int) -> int:
    """Migrate, prepare the default study if there is none, and serve."""
    import uvicorn

    from anim_core.clips.build import ConfigError
    from server.assets import AssetError
    from server.db import make_engine, migrate, session_factory
    from server.errors import MediaError, ServiceError
    from server.uploads.service import resume_lost_jobs

    engine = make_engine(settings.sqlalchemy_url)
    try:
        migrate(engine, media_dir=settings.media_dir, clips_dir=settings.clips_dir)
        factory = session_factory(engine)
        prepare_study(settings, factory)
        ensure_researcher(settings, factory)
        with factory() as session:  # jobs whose process ended mid-job (this server's, a command's) go on
            for job in resume_lost_jobs(session, settings, engine):
                print(f"resumed {job.kind} job {job.id} (pid {job.pid}): it renders what is still missing",
                      flush=True)
    except (AssetError, ConfigError, MediaError, ServiceError) as exc:
        return _fail(str(exc))
    finally:
        engine.dispose()
    print(f"serving on http://{host}:{port} (database {engine.url.render_as_string(hide_password=True)})",
          flush=True)
    # The app reads X-Forwarded-For itself, from ANIMSTUDY_TRUSTED_PROXIES only (server.deps.client_address);
    # uvicorn would otherwise trust it from 127.0.0.1 by default.
    uvicorn.run("server.app:app_from_env", factory=True, host=host, port=port, workers=workers,
                log_level="info", proxy_headers=False)
    return 0


def read_password(given: str | None, from_stdin: bool) -> str | None:
    """The new account's password: ``--password`` (with a warning: every user of the machine sees a command's
    arguments), the first line of standard input (``--password-stdin``), or typed twice at a prompt that does not
    echo it (a terminal only).  None if there is none."""
    import getpass

    if given is not None:
        print("warning: --password shows the password to every user of this machine (process list, shell "
              "history); use the prompt or --password-stdin", file=sys.stderr)
        return given
    if from_stdin:
        line = sys.stdin.readline().rstrip("\r\n")
        return line or None
    if not sys.stdin.isatty():
        return None
    first = getpass.getpass("password: ")
    if first != getpass.getpass("password again: "):
        print("the two passwords differ", file=sys.stderr)
        return None
    return first or None


def researcher_create(settings: Settings, email: str, password: str, admin: bool = False) -> int:
    from server.db import make_engine, migrate, session_factory
    from server.errors import ServiceError
    from server.researchers.service import create_researcher

    engine = make_engine(settings.sqlalchemy_url)
    migrate(engine, media_dir=settings.media_dir, clips_dir=settings.clips_dir)
    try:
        with session_factory(engine)() as session:
            researcher = create_researcher(session, email, password, admin=admin)
    except ServiceError as exc:
        return _fail(exc.detail)
    print(f"researcher {researcher.email} created{' (admin: sees and manages every study)' if admin else ''}")
    return 0


def bench_render(settings: Settings, width: int, height: int, animations: list[str] | None) -> int:
    """Frames per second of rendering the default study's videos on a real Dask cluster (a local scheduler and
    worker processes) of 1 and then 2 workers, the same work each time, and the ratio."""
    import tempfile

    from server.assets import AssetError
    from server.clipset.build import build_clip_set
    from server.clipset.manifest import write_clip_set
    from server.errors import MediaError
    from server.media.build import plan, render_tasks, run_on_dask
    from server.media.scene import RenderSettings
    from server.studies.service import clip_set_index, required_pairs
    from server.studies.studyfile import thesis_study

    render_settings = RenderSettings(width=width, height=height)
    with tempfile.TemporaryDirectory(prefix="animstudy-bench-render-") as tmp:
        clips_dir = Path(tmp) / "clips"
        try:
            if (settings.clips_dir / "manifest.json").is_file():
                clips_dir = settings.clips_dir
            else:
                print("building the clip set", flush=True)
                write_clip_set(build_clip_set(settings.data), clips_dir)
            pairs = required_pairs(thesis_study().design, clip_set_index(clips_dir))
            fps = {}
            for workers in (1, 2):
                out = Path(tmp) / f"media-{workers}"
                out.mkdir()
                p = plan(settings.data, clips_dir, out, render_settings, settings.secret, pairs, animations)
                frames = sum(j.n_frames for j in p.jobs)
                tasks = render_tasks(p, workers)  # as run_on_dask cuts it on a local cluster of `workers`
                # A per-video task renders its clips itself: the clip shown in several pairs once per pair.
                print(f"{workers} worker(s): {sum(len(j.outputs) for j in p.jobs)} videos in {len(tasks)} tasks, "
                      f"{frames} frames of the study, {sum(t.n_frames for t in tasks)} frames rendered by the "
                      f"tasks, at {width}x{height}", flush=True)
                started = time.perf_counter()
                run_on_dask(p, out, None, workers, lambda m: print(m, flush=True))
                seconds = time.perf_counter() - started
                fps[workers] = frames / seconds
                print(f"{workers} worker(s): {seconds:.1f} s, {fps[workers]:.1f} frames/s (cluster start "
                      "included)", flush=True)
        except (AssetError, MediaError) as exc:
            return _fail(str(exc))
    print(f"render: 1 worker {fps[1]:.1f} frames/s, 2 workers {fps[2]:.1f} frames/s, ratio {fps[2] / fps[1]:.2f} "
          f"(on {os.cpu_count()} cores; load average {os.getloadavg()[0]:.1f})", flush=True)
    return 0


def bench(settings: Settings, json_path: Path, characters: list[int], stages: list[str], frames: int,
          variants: list[str], config: Path | None = None) -> int:
    """Run the performance benchmark on the clip set of ``config`` (default: the built-in one); write JSON (for
    the dashboard too) and the plots beside it."""
    # One thread for numpy/BLAS in the main figures (the compiled kernel's threads are a separate figure).
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"
    from anim_core.bench import suite as benchmark
    from anim_core.clips.build import ConfigError
    from server.assets import AssetError
    from server.clipset.build import build_clip_set
    from server.clipset.config import load_config

    started = time.perf_counter()
    try:
        print(f"building the clip set{f' of {config}' if config else ''}", flush=True)
        clips = build_clip_set(settings.data, load_config(config) if config else None)
    except (AssetError, ConfigError) as exc:
        return _fail(str(exc))
    print(f"building the runtimes and measuring memory and accuracy ({', '.join(variants)})", flush=True)
    doc = benchmark.run(clips, characters, stages, frames=frames, variants=variants,
                        progress=lambda m: print(m, flush=True))
    doc["series"] = benchmark.series(doc["results"])
    doc["x_label"], doc["y_label"] = "characters", "ms per frame (pose, one thread)"
    try:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
        plots = benchmark.write_plots(doc, json_path.parent)
    except OSError as exc:
        return _fail(f"cannot write the results: {exc}")
    _print_bench(doc)
    from anim_core.bench.blend import format_blend

    print(format_blend(doc["results"]), end="")
    print(f"results: {json_path}; plots: {', '.join(p.name for p in plots)}; "
          f"{time.perf_counter() - started:.0f} s in all")
    return 0


def _print_bench(doc: dict[str, Any]) -> None:
    """Per clip (every condition) and crowd size the median ms per frame and its ratio to the keyframe clip of the
    same animation, then bytes and errors per clip, then the goals' figures."""
    variant = "keys" if "keys" in doc["settings"]["variants"] else doc["settings"]["variants"][0]
    rows = [r for r in doc["results"] if r["stage"] == "pose" and r["variant"] == variant and r["threads"] == 1]
    width = max([16, *(len(m["clip"]) + 1 for m in doc["memory"])])
    if rows:
        ns = sorted({r["characters"] for r in rows})
        keyframe = {(r["animation"], r["characters"]): r["median_ms"] for r in rows if r["method"] == "keyframe"}
        print(f"\nmedian ms per frame (÷ the keyframe clip's, same rounds), variant {variant}, pose, one thread")
        print(f"{'clip':{width}}" + "".join(f"{n:>15}" for n in ns))
        for clip in dict.fromkeys((r["animation"], r["condition"]) for r in rows):
            by_n = {r["characters"]: r["median_ms"] for r in rows if (r["animation"], r["condition"]) == clip}
            cells = [(f"{by_n[n]:.4g}" + ("" if (clip[0], n) not in keyframe else
                                          f" ({by_n[n] / keyframe[(clip[0], n)]:.2f})")) if n in by_n else ""
                     for n in ns]
            print(f"{clip[0] + '-' + clip[1]:{width}}" + "".join(f"{c:>15}" for c in cells))
    variants = list(dict.fromkeys(m["variant"] for m in doc["memory"]))
    mem = {(m["clip"], m["variant"]): m["runtime_bytes"] for m in doc["memory"]}
    err = {(a["clip"], a["variant"]): a["max_error_deg"] for a in doc["accuracy"]}
    stored = {m["clip"]: m["stored_bytes"] for m in doc["memory"]}
    main = [v for v in variants if not v.startswith("keys-")]
    print("\nruntime bytes (stored keys first) and largest global-rotation error in degrees, per clip and variant")
    print(f"{'clip':{width}}{'stored':>8}" + "".join(f"{v:>10}" for v in main)
          + "".join(f"{'err ' + v:>14}" for v in main))
    for clip in stored:
        print(f"{clip:{width}}{stored[clip]:>8}" + "".join(f"{mem.get((clip, v), ''):>10}" for v in main)
              + "".join(f"{err[(clip, v)]:>14.4f}" if (clip, v) in err else f"{'':>14}" for v in main))
    lods = [v for v in variants if v.startswith("keys-")]
    if lods:
        print("\nLOD variants of keys: largest error in degrees per clip")
        print(f"{'clip':{width}}" + "".join(f"{v:>18}" for v in lods))
        for clip in stored:
            print(f"{clip:{width}}" + "".join(f"{err.get((clip, v), float('nan')):>18.3f}" for v in lods))
    s = doc["summary"]
    print()
    for label, value, unit in (
        ("worst hybrid/keyframe ratio at >= 10 characters (keys)", s["max_ratio_at_10_or_more"], ""),
        ("median hybrid/keyframe ratio at >= 10 characters (keys)", s["median_ratio_at_10_or_more"], ""),
        (f"{s['largest_crowd']} characters, worst median (keys, one thread)", s["largest_crowd_worst_ms"], " ms"),
        (f"speed-up on {s['parallel_threads']} threads at {s['largest_crowd']} characters, min / median",
         None if s["parallel_speedup_min"] is None else f"{s['parallel_speedup_min']:.2f} / "
         f"{s['parallel_speedup_median']:.2f}", ""),
        ("largest increment-0 hybrid runtime bytes / keyframe's (keys)", s["max_memory_ratio_increment_0"], ""),
        ("largest hybrid error (keys), degrees", s["max_hybrid_error_deg"], ""),
    ):
        shown = "n/a" if value is None else (f"{value:.3f}" if isinstance(value, float) else value)
        print(f"{label}: {shown}{unit}")


QUICK_BENCH = "--characters 10,1000 --stages pose --frames 50 --variants keys"


def _variants(text: str) -> list[str]:
    from anim_core.bench.suite import VARIANTS

    chosen = [v.strip() for v in text.split(",") if v.strip()]
    if not chosen or any(v not in VARIANTS for v in chosen):
        raise argparse.ArgumentTypeError(f"variants are {', '.join(VARIANTS)} (comma-separated), got {text!r}")
    return list(dict.fromkeys(chosen))


def _int_list(minimum: int, example: str) -> Callable[[str], list[int]]:
    """An argparse type: comma-separated integers, each at least ``minimum``."""
    def parse(text: str) -> list[int]:
        try:
            values = [int(v) for v in text.split(",") if v.strip()]
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected comma-separated numbers like {example}, got {text!r}") from None
        if not values or any(v < minimum for v in values):
            raise argparse.ArgumentTypeError(f"expected comma-separated numbers ≥ {minimum} like {example}, "
                                             f"got {text!r}")
        return values
    return parse


def _stages(text: str) -> list[str]:
    stages = [s.strip() for s in text.split(",") if s.strip()]
    if not stages or any(s not in ("pose", "skin", "blend") for s in stages):
        raise argparse.ArgumentTypeError(f"stages are pose, skin and blend, got {text!r}")
    return stages


def _positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if not 1 <= value <= 100_000:
        raise argparse.ArgumentTypeError(f"must be 1..100000, got {value}")
    return value


def _even(text: str) -> int:
    value = int(text)
    if value < 16 or value % 2:
        raise argparse.ArgumentTypeError(f"video sizes must be even and at least 16, got {value}")
    return value


def loadtest_parser(add_help: bool = True) -> argparse.ArgumentParser:
    """The options of ``animstudy loadtest`` (defined here, not in server/loadtest.py, whose imports would slow
    every command's start)."""
    p = argparse.ArgumentParser(prog="animstudy loadtest", add_help=add_help,
                                description="Load, crash and outage test of the participant API: N simulated "
                                "participants against a fresh server and database; exits non-zero if any "
                                "acknowledged vote was lost or doubled.")
    p.add_argument("--database", choices=["sqlite", "postgresql"], default="sqlite",
                   help="a fresh database of this kind (PostgreSQL: the one of --pg-url, emptied first)")
    p.add_argument("--participants", type=int, default=200, help="simulated participants, 16 votes each")
    p.add_argument("--workers", type=int, default=2, help="uvicorn worker processes of the server")
    p.add_argument("--concurrency", type=int, default=100, help="participants in progress at a time")
    p.add_argument("--pause-ms", type=float, default=0.0, help="mean think time before each vote")
    p.add_argument("--ramp-s", type=float, default=0.0,
                   help="spread the participants' arrivals over this many seconds (default: all at once)")
    p.add_argument("--crash-at", type=float, default=None, help="SIGKILL the server at this share of the votes")
    p.add_argument("--outage-at", type=float, default=None, help="stop PostgreSQL at this share of the votes")
    p.add_argument("--outage-s", type=float, default=5.0, help="seconds PostgreSQL stays stopped")
    p.add_argument("--time-limit", type=float, default=300.0, help="seconds before the run gives up")
    p.add_argument("--pg-url", default=None, help="PostgreSQL database to use, its schema dropped (default: "
                   "database animstudy_load of the local server, as user postgres)")
    p.add_argument("--json", type=Path, default=None, help="also write the report as JSON to this file")
    return p


def build_parser() -> argparse.ArgumentParser:
    """The whole command line, every subcommand and option (the docs site's CLI reference is generated from it)."""
    parser = argparse.ArgumentParser(prog="animstudy", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("inspect", help="summarize the motion-capture files of the data directory")
    loadtest = loadtest_parser(add_help=False)
    sub.add_parser("loadtest", help="load, crash and outage test of the participant API", parents=[loadtest],
                   description=loadtest.description)
    clips = sub.add_parser("clips", help="the clip set (keyframe and hybrid clips with motion metrics)")
    clips_sub = clips.add_subparsers(dest="clips_command", required=True)
    build = clips_sub.add_parser("build", help="build the clip set from the data directory")
    build.add_argument("--out", type=Path, default=None, help="output folder (default: <var dir>/clips)")
    build.add_argument("--config", type=Path, default=None, help="clip set TOML (default: the built-in one)")
    cinspect = clips_sub.add_parser("inspect", help="what a BVH/glTF motion file holds and how it maps onto the "
                                                   "character (joints, mapping, units, contacts, suggested kind)")
    cinspect.add_argument("file", type=Path, help=".bvh, .bvh.gz, .glb or .gltf file")
    _source_options(cinspect)
    convert = clips_sub.add_parser("convert", help="a BVH/glTF motion retargeted onto the character, written as "
                                                   ".glb/.gltf (character + animation) or .bvh")
    convert.add_argument("file", type=Path, help=".bvh, .bvh.gz, .glb or .gltf file (a glTF's first animation)")
    convert.add_argument("out", type=Path, help="output .glb, .gltf, .bvh or .bvh.gz")
    _source_options(convert)
    export = clips_sub.add_parser("export", help="one clip of a built clip set on the character, written as "
                                                 ".glb/.gltf (character + animation) or .bvh")
    export.add_argument("clip", help="clip id, <animation>-<condition> (see the clip set's manifest.json)")
    export.add_argument("--clips", type=Path, default=None, help="clip set folder (default: <var dir>/clips)")
    export.add_argument("--out", type=Path, required=True, help="output .glb, .gltf, .bvh or .bvh.gz")
    rend = sub.add_parser("render", help="pre-render the compared pairs (and their clips) into blind videos")
    rend.add_argument("--out", type=Path, default=None, help="video folder (default: <var dir>/media)")
    rend.add_argument("--clips", type=Path, default=None, help="clip set folder (default: <var dir>/clips)")
    rend.add_argument("--workers", type=int, default=2, help="worker processes (default: 2)")
    rend.add_argument("--study", type=Path, action="append", default=None,
                      help="study file whose pairs to render, may be repeated (default: studies/thesis.toml); the "
                           "pairs of the studies in the database are kept too")
    rend.add_argument("--every-clip", action="store_true",
                      help="also a video of every clip of the clip set (default: of the clips the pairs show)")
    rend.add_argument("--width", type=_even, default=640)
    rend.add_argument("--height", type=_even, default=480)
    rend.add_argument("--no-shadows", action="store_true")
    srv = sub.add_parser("serve", help="migrate the database, prepare the default study if needed, and serve")
    srv.add_argument("--host", default="127.0.0.1")
    srv.add_argument("--port", type=int, default=8000)
    srv.add_argument("--workers", type=int, default=1, help="uvicorn worker processes (default: 1)")
    researcher = sub.add_parser("researcher", help="researcher accounts")
    researcher_sub = researcher.add_subparsers(dest="researcher_command", required=True)
    rc = researcher_sub.add_parser("create", help="create a researcher account")
    rc.add_argument("--email", required=True)
    given = rc.add_mutually_exclusive_group()
    given.add_argument("--password-stdin", action="store_true",
                       help="read the password from standard input (its first line), e.g. from a password manager")
    given.add_argument("--password", default=None, help="the password (visible to every user of the machine in the "
                       "process list: prefer the prompt or --password-stdin)")
    rc.add_argument("--admin", action="store_true", help="may see and manage every study, not only their own")
    st = sub.add_parser("study", help="study files and studies: schema, validate, create, list, open, close, export")
    st_sub = st.add_subparsers(dest="study_command", required=True)
    st_sub.add_parser("schema", help="print the JSON Schema of study files")
    sv = st_sub.add_parser("validate", help="check a study file (every error with its field and line)")
    sv.add_argument("file", type=Path)
    sc = st_sub.add_parser("create", help="build the clips and render the videos a study file needs (what is "
                           "missing; its [clips] set or the server's clip set) and create it as a draft")
    sc.add_argument("file", type=Path)
    sc.add_argument("--open", action="store_true", help="open it for participants at once")
    sc.add_argument("--owner", default=None, help="e-mail of the researcher who owns it (default: none; admins "
                    "manage it)")
    sc.add_argument("--width", type=_even, default=None, help="video width when none were rendered before (640)")
    sc.add_argument("--height", type=_even, default=None, help="video height (480)")
    sc.add_argument("--no-shadows", action="store_true")
    st_sub.add_parser("list", help="every study with its state and counts")
    for name in ("open", "close"):
        so = st_sub.add_parser(name, help=f"{name} a study for participants")
        so.add_argument("slug")
    sa = st_sub.add_parser("export-archive", help="one file with the study file, its pinned stimulus set and its "
                           "videos, to rerun the study on another server")
    sa.add_argument("slug")
    sa.add_argument("--out", type=Path, default=None, help="archive file (default: <slug>.animstudy.zip)")
    si = st_sub.add_parser("import-archive", help="recreate a study from its archive (same stimuli, byte for byte)")
    si.add_argument("file", type=Path)
    si.add_argument("--owner", default=None, help="e-mail of the researcher who owns it (default: none)")
    si.add_argument("--open", action="store_true", help="open it for participants at once")
    si.add_argument("--max-mib", type=_positive, default=None, help="the most its files may take in all, in MiB "
                    "(default 8192; each file at most 512)")
    sm = st_sub.add_parser("simulate", help="simulated observers through a study file's design: scale error and "
                           "rank correlation (docs/designs.md)")
    sm.add_argument("file", type=Path)
    sm.add_argument("--participants", type=_positive, required=True)
    sm.add_argument("--truth", type=Path, default=None, help="TOML or JSON table: condition = true scale value "
                    "(logit units); default: the design's conditions evenly spaced over 0..2.5 in their order")
    sm.add_argument("--seeds", type=_positive, default=20, help="simulated studies (default 20)")
    sp = st_sub.add_parser("plan", help="participants needed to detect a difference from the reference, by "
                           "simulation (docs/designs.md)")
    sp.add_argument("file", type=Path)
    sp.add_argument("--effect", type=float, default=None, help="the difference to detect, logit units of the "
                    "scale (every condition that far above the reference); required but for threshold designs")
    sp.add_argument("--power", type=float, default=0.8)
    sp.add_argument("--seeds", type=_positive, default=100, help="simulated studies per participant count")
    from server import threshold_commands  # issue 38: threshold designs' options and commands

    threshold_commands.extend_simulate_plan(sm, sp)
    threshold_commands.add_parsers(st_sub, _positive)
    se = st_sub.add_parser("export", help="a study's votes, one row per vote (see the data dictionary)")
    se.add_argument("slug")
    se.add_argument("--format", choices=("csv", "json", "sureal", "pwcmp"), default="csv",
                    help="csv/json: one row per vote; sureal: a sureal dataset (JSON); pwcmp: pairwise CSV")
    se.add_argument("--out", type=Path, default=None, help="file to write (default: standard output)")
    gcp = sub.add_parser("gc", help="delete the videos no study's stimulus set (and no render manifest) uses and "
                                    "the clip files no clip set's manifest names")
    gcp.add_argument("--dry-run", action="store_true", help="list them, delete nothing")
    bn = sub.add_parser("bench", help="time pose evaluation of crowds, keyframe against every other condition "
                                      "(`bench render`: render frames per second on 1 and 2 Dask workers)")
    bn.add_argument("what", nargs="?", choices=["crowd", "render"], default="crowd",
                    help="crowd (default): pose evaluation; render: the default study's videos on a local Dask "
                         "cluster of 1 and then 2 workers")
    bn.add_argument("--width", type=int, default=160, help="bench render: video width (default: 160)")
    bn.add_argument("--height", type=int, default=120, help="bench render: video height (default: 120)")
    bn.add_argument("--animations", type=lambda v: [a for a in v.split(",") if a], default=None,
                    help="bench render: only these animations, comma-separated (default: all)")
    bn.add_argument("--json", type=Path, default=None, help="results file (default: <var dir>/benchmark/results.json)")
    bn.add_argument("--config", type=Path, default=None,
                    help="clip-set TOML whose clips to time (default: the built-in one), e.g. "
                         "server/clipset/conditions16.toml")
    bn.add_argument("--quick", action="store_true",
                    help=f"short run: {QUICK_BENCH} unless given")
    bn.add_argument("--characters", type=_int_list(1, "10,200"), default=None, help="crowd sizes, e.g. 10,200,10000")
    bn.add_argument("--stages", type=_stages, default=None, help="pose, skin (default: both), blend (blending jobs)")
    bn.add_argument("--frames", type=int, default=None, help="timed frames per measurement (default: 200)")
    bn.add_argument("--variants", type=_variants, default=None,
                    help="comma-separated: keys, baked, reference, naive (default: all)")
    return parser


def _main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "loadtest":
        from server import loadtest

        return loadtest.main(args)
    settings = Settings.from_env()
    if args.command == "bench" and args.what == "render":
        return bench_render(settings, max(16, args.width), max(16, args.height), args.animations)
    if args.command == "bench":
        from anim_core.bench.suite import DEFAULT_CHARACTERS, VARIANTS

        quick = args.quick
        return bench(settings, args.json or settings.benchmark_path,
                     args.characters or ([10, 1000] if quick else list(DEFAULT_CHARACTERS)),
                     args.stages or (["pose"] if quick else ["pose", "skin"]),
                     max(1, args.frames or (50 if quick else 200)),
                     args.variants or (["keys"] if quick else list(VARIANTS)), args.config)
    if args.command == "serve":
        return serve(settings, args.host, args.port, max(1, args.workers))
    if args.command == "researcher":
        password = read_password(args.password, args.password_stdin)
        if password is None:
            return _fail("no password: give it at the prompt, or on standard input with --password-stdin")
        return researcher_create(settings, args.email, password, args.admin)
    if args.command == "study":
        return study_command(settings, args)
    if args.command == "gc":
        return gc(settings, args.dry_run)
    if args.command == "inspect":
        return inspect(settings.data)
    if args.command == "render":
        return render(settings, args.out or settings.var / "media", args.clips or settings.var / "clips",
                      max(1, args.workers), args.study or [], args.width, args.height, not args.no_shadows,
                      args.every_clip)
    if args.clips_command == "inspect":
        return clips_inspect(settings.data, args.file, args.mapping, args.units, args.up, args.max_frame_joints)
    if args.clips_command == "export":
        return clips_export(settings.data, args.clips or settings.var / "clips", args.clip, args.out)
    if args.clips_command == "convert":
        return clips_convert(settings.data, args.file, args.out, args.mapping, args.units, args.up,
                             args.max_frame_joints)
    return clips_build(settings.data, args.out or settings.var / "clips", args.config, settings.dask_scheduler)


def main(argv: Sequence[str] | None = None) -> int:
    try:
        return _main(argv)
    except BrokenPipeError:
        # The reader went away (`animstudy inspect | head`): not an error of ours.  Python would otherwise report
        # the broken pipe again when it flushes stdout at exit (the recipe of the signal module's docs).
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1


if __name__ == "__main__":
    raise SystemExit(main())
