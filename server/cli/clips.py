"""``animstudy inspect`` and ``animstudy clips ...``: motion files and the clip set."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from anim_core.clips.build import METRES_PER_CMU_UNIT, AnimationConfig, ConfigError, source_from_bvh, suggest_tolerance
from anim_core.clips.composite import format_transitions
from anim_core.clips.measure import clip_warnings
from anim_core.clips.sources import (
    MotionReport,
    export_on_character,
    format_report,
    inspect_source,
    joint_table,
    write_motion,
)
from anim_core.io.bvh import BvhError, clip_from_bvh, read_bvh
from anim_core.math.skeleton import Skeleton
from anim_core.rig.character import bind_mesh
from anim_core.rig.rigmap import RigMapError, read_mapping_file
from server.assets import AssetError
from server.assets import character as data_character
from server.clipset.build import build_clip_set, load_character, record_config
from server.clipset.config import load_config
from server.clipset.manifest import read_clip, read_clip_manifest, write_clip_set
from server.config import Settings
from server.uploads.service import max_frame_joints

from .common import CLI_FRAME_JOINTS, fail


def _frame_joints(path: Path, flag: int | None) -> int:
    """The frames × joints a motion file given on the command line may hold: ``--max-frame-joints``, or the
    larger of :data:`CLI_FRAME_JOINTS` and what an upload of its size may hold."""

    return flag if flag is not None else max(CLI_FRAME_JOINTS, max_frame_joints(path.stat().st_size))


def _too_many(message: str) -> str:
    """A reader's message, with the way out when the frame·joint bound refused the file."""
    return message + ("; --max-frame-joints N allows more" if "frame-joints" in message else "")


def clips_inspect(data_dir: Path, path: Path, mapping: Path | None, units: str | None, up_axis: str | None,
                  max_frame_joints: int | None = None) -> int:
    """Print what a BVH or glTF file holds and how it maps onto the character (``animstudy clips inspect``); for a
    motion suggested as kind ``other``, a ``tolerance_mm`` measured by building it (:func:`_tolerance_line`)."""

    if not path.is_file():
        return fail(f"{path}: no such file")
    try:
        explicit = read_mapping_file(mapping) if mapping else None
        reports = inspect_source(path, explicit, units, up_axis, _frame_joints(path, max_frame_joints))
    except (ValueError, OSError) as exc:  # BvhError, GltfError and RigMapError name the file (and line)
        # A skeleton that does not map: its joints, to write a mapping file from.
        table = joint_table(path) if isinstance(exc, RigMapError) else None
        return fail(_too_many(str(exc)) + (f"\n{table}" if table else ""))
    print(format_report(path, reports, [_tolerance_line(data_dir, path, r) if r.kind == "other" else None
                                        for r in reports]))
    return 0


def _tolerance_line(data_dir: Path, path: Path, report: MotionReport) -> str:
    """The suggested ``tolerance_mm`` of a kind-``other`` motion, with the key and byte ratio of the hybrid it
    builds on the clip set's character (:func:`anim_core.clips.build.suggest_tolerance`), or why there is none."""

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

    if not path.is_file():
        return fail(f"{path}: no such file")
    try:
        explicit = read_mapping_file(mapping) if mapping else None
        report = inspect_source(path, explicit, units, up_axis, _frame_joints(path, max_frame_joints))[0]
        export_on_character(report.normalized, data_character(data_dir), out, report.name)
    except (ValueError, OSError) as exc:  # file, mapping and character errors are ValueErrors naming the file
        return fail(_too_many(str(exc)))
    print(f"wrote {out} ({report.n_frames} frames at {report.fps:g} fps on the character)")
    return 0


def clips_export(data_dir: Path, clips_dir: Path, clip_id: str, out: Path) -> int:
    """Write one clip of a built clip set on the character as .glb/.gltf or .bvh (``animstudy clips export``)."""


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
        return fail(str(exc))
    print(f"wrote {out} ({entry.frames} frames at {entry.fps} fps, {entry.playback}: clip {clip_id} on the "
          f"character)")
    return 0


def inspect(data_dir: Path) -> int:
    """Print what the motion-capture files in the data directory hold."""


    paths = sorted(data_dir.glob("mocap/**/*.bvh*"))
    if not paths:
        return fail(f"no BVH files under {data_dir / 'mocap'}; set ANIMSTUDY_DATA_DIR (see docs/reference/data.md)")
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

    started = time.perf_counter()
    try:
        cfg = load_config(config) if config else load_config()
        clips = build_clip_set(data_dir, cfg, progress=lambda msg: print(msg, flush=True), scheduler=scheduler,
                               workers=2)
        manifest = write_clip_set(clips, out)
    except (AssetError, ConfigError) as exc:
        return fail(str(exc))
    except OSError as exc:
        return fail(f"cannot write the clip set to {out}: {exc}")
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
        against = f.against or ("source" if c is clips[0] or c.animation != prev else "reference")
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
    print(format_transitions(clips), end="")  # issue 39: sequences' transition metrics
    for w in warnings:
        print(f"warning: {w}", flush=True)


def run(settings: Settings, args: argparse.Namespace) -> int:
    """``animstudy inspect`` and ``animstudy clips ...``."""
    if args.command == "inspect":
        return inspect(settings.data)
    if args.clips_command == "inspect":
        return clips_inspect(settings.data, args.file, args.mapping, args.units, args.up, args.max_frame_joints)
    if args.clips_command == "export":
        return clips_export(settings.data, args.clips or settings.var / "clips", args.clip, args.out)
    if args.clips_command == "convert":
        return clips_convert(settings.data, args.file, args.out, args.mapping, args.units, args.up,
                             args.max_frame_joints)
    return clips_build(settings.data, args.out or settings.var / "clips", args.config, settings.dask_scheduler)
