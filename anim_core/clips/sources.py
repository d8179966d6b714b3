"""What a motion file holds, for a user about to add it to a clip set (``animstudy clips inspect FILE``), and the
motion on the character as glTF or BVH (``animstudy clips convert FILE OUT``, :func:`write_motion`; a built clip:
``animstudy clips export``).

:func:`inspect_source` reads a BVH (``.bvh``, ``.bvh.gz``) or glTF (``.glb``, ``.gltf``) file, maps its skeleton
(:mod:`anim_core.rig.rigmap`, :mod:`anim_core.rig.normalize`) and reports, per motion: joints, convention and
mapping with reasons, units, up axis, fps, frames, duration, the foot-contact phases (frame intervals,
:mod:`anim_core.math.contacts` on the motion in metres) and a suggested ``kind`` and frame range.  Suggestions
are heuristics stated in :func:`suggest`; the user decides.  Every failure is a ``ValueError`` subclass naming the
file (:class:`~anim_core.io.bvh.BvhError` with its line, :class:`~anim_core.io.gltf.GltfError`,
:class:`~anim_core.rig.rigmap.RigMapError`).
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..io.bvh import MAX_FRAME_JOINTS, Bvh, bvh_from_poses, read_bvh, write_bvh
from ..io.gltf import GltfAnimation, GltfAsset, read_gltf, write_gltf
from ..math.contacts import contact_intervals, foot_down
from ..math.skeleton import Skeleton
from ..math.skinning import SkinnedMesh
from ..rig.character import Character, retarget
from ..rig.normalize import Normalized, detect_up_axis, normalize_bvh, normalize_motion, units_from_height
from ..rig.rigmap import CANONICAL_NAMES, RigMapError, map_skeleton

Array = NDArray[np.float64]

#: Root speed (m/s) above which a motion with alternating foot contacts is a gait; hip drop (share of the standing
#: hip height) above which a motion is a crouch; root travel (m) and joint motion below which it is an idle.
GAIT_SPEED = 0.3
CROUCH_DROP = 0.2
IDLE_TRAVEL = 0.3
MIN_PHASE = 0.1
#: A hand moving further than this (m) from its mean place against the hips: the motion is no idle sway.
ARM_MOTION = 0.2
#: Kind ``other``: a take whose root gets further than this (m, horizontally, in the file's own motion) from where
#: it starts travels: it is suggested to loop, and refused as ping-pong (which would move it backwards every second
#: half) by the build, which measures it the same way (:func:`root_travel`).
PINGPONG_TRAVEL_M = 0.3
_CANON = {n: i for i, n in enumerate(CANONICAL_NAMES)}


@dataclass(frozen=True)
class MotionReport:
    """One motion of a file: the normalized motion, contact phases per foot (``[start, stop)`` frames) and the
    suggestion with its reason; ``playback``: how the motion plays (:func:`suggest_playback`): a gait loops, a
    crouch or idle plays ping-pong, and an ``other`` loops if it travels (an upload switched to kind ``other`` keeps
    its suggested playback, so a walk so switched loops)."""

    name: str
    normalized: Normalized
    contacts: dict[str, list[tuple[int, int]]]
    kind: str
    frames: tuple[int, int]
    reason: str
    playback: str = "pingpong"

    @property
    def n_frames(self) -> int:
        return self.normalized.bvh.n_frames

    @property
    def fps(self) -> float:
        return self.normalized.bvh.fps

    @property
    def duration(self) -> float:
        return (self.n_frames - 1) / self.fps


def _t_pose(positions: Array) -> bool:
    """Is frame 0 a calibration T-pose (both hands level with the shoulders, far out to the sides)?"""
    ix = {n: i for i, n in enumerate(CANONICAL_NAMES)}
    p = positions[0]
    arm = np.linalg.norm(p[ix["LeftHand"]] - p[ix["LeftArm"]])
    return all(abs(p[ix[f"{s}Hand"], 1] - p[ix[f"{s}Arm"], 1]) < 0.15 * arm for s in ("Left", "Right"))


def suggest(positions: Array, fps: float, contacts: Mapping[str, NDArray[np.intp]]) -> tuple[str, tuple[int, int],
                                                                                               str]:
    """Kind (``gait``, ``crouch``, ``idle``, ``other``), inclusive frame range and why, from joint positions
    ``(F, 31, 3)`` in metres (Y up) of the canonical skeleton.

    A calibration T-pose in frame 0 is skipped.  ``crouch``: the hips drop by more than :data:`CROUCH_DROP` of
    their height in the first frame; ``gait``: the root moves faster than :data:`GAIT_SPEED` and both feet touch
    down; ``idle``: the root travels less than
    :data:`IDLE_TRAVEL` and no hand moves more than :data:`ARM_MOTION` against the hips; else ``other``.  A gait's
    range is the whole take: the build picks its cleanest whole cycle.
    """
    first = 1 if len(positions) > 2 and _t_pose(positions) else 0
    last = len(positions) - 1
    hips = positions[first:, 0]
    height = hips[:, 1] - positions[first:, :, 1].min()
    horizontal = hips[:, [0, 2]]
    travel = float(np.linalg.norm(horizontal[-1] - horizontal[0]))
    speed = travel / max((last - first) / fps, 1e-9)
    drop = 1.0 - float(height.min() / max(height[0], 1e-9))
    skip = " (frame 0 is a T-pose)" if first else ""
    if drop > CROUCH_DROP:
        return "crouch", (first, last), f"the hips drop by {drop:.0%} of their height{skip}"
    left = [int(s) for s, _ in contacts["left"] if s > first]
    if speed > GAIT_SPEED and len(contacts["left"]) and len(contacts["right"]):
        # The whole take: the builder picks its cleanest whole cycle (a range cut at touchdowns can miss the
        # cycle's ends, which are where the left foot leads most).
        cycles = f"; about {len(left) - 1} whole cycle(s) between left touchdowns" if len(left) >= 2 else ""
        return "gait", (first, last), (f"the root moves {speed:.2f} m/s with alternating foot contacts{cycles}; "
                                       f"the build picks the cleanest cycle{skip}")
    hands = positions[first:, [_CANON["LeftHand"], _CANON["RightHand"]]] - positions[first:, :1]
    arms = float(np.linalg.norm(hands - hands.mean(axis=0), axis=-1).max())
    if travel < IDLE_TRAVEL and arms > ARM_MOTION:
        return "other", (first, last), (f"the root travels {travel:.2f} m in all but a hand moves {arms:.2f} m "
                                        f"against the hips (arm motion, not an idle sway){skip}")
    if travel < IDLE_TRAVEL:
        return "idle", (first, last), f"the root travels {travel:.2f} m in all{skip}"
    return "other", (first, last), f"no gait, crouch or idle pattern (root travels {travel:.2f} m){skip}"


def root_travel(positions: Array) -> float:
    """The furthest the root of ``(F, J, 3)`` joint positions (or ``(F, 3)`` root positions; Y up) gets
    horizontally from where it starts, in their units."""
    hips = (positions[:, 0] if positions.ndim == 3 else positions)[:, [0, 2]]
    return float(np.linalg.norm(hips - hips[:1], axis=-1).max())


def suggest_playback(positions: Array, kind: str, frames: tuple[int, int]) -> str:
    """``loop`` or ``pingpong``: how a motion of ``kind`` over ``frames`` (inclusive) of ``(F, J, 3)`` positions in
    metres plays.  A gait loops and a crouch or idle plays ping-pong (their hybrids do); an ``other`` take loops when
    its root travels more than :data:`PINGPONG_TRAVEL_M`: played ping-pong, it would move backwards."""
    if kind == "gait":
        return "loop"
    if kind != "other":
        return "pingpong"
    return "loop" if root_travel(positions[frames[0]:frames[1] + 1]) > PINGPONG_TRAVEL_M else "pingpong"


def _report(name: str, out: Normalized) -> MotionReport:
    bvh = out.bvh
    rot, root = bvh.pose_arrays()
    skeleton = bvh.posed_skeleton()
    positions = skeleton.forward_kinematics(rot, root)[1] * out.metres_per_unit
    ix = {n: i for i, n in enumerate(CANONICAL_NAMES)}
    feet = positions[:, [[ix["LeftFoot"], ix["LeftToeBase"]], [ix["RightFoot"], ix["RightToeBase"]]]]
    contacts: dict[str, NDArray[np.intp]] = {}
    if len(positions) >= 2:
        down = foot_down(feet)
        # Blips shorter than MIN_PHASE seconds (a heel grazing the floor) are not phases; gaps as short are closed.
        short = max(1, round(MIN_PHASE * bvh.fps))
        for k in range(2):
            for s, e in contact_intervals(~down[:, k]):
                if e - s < short and s > 0 and e < len(down):
                    down[s:e, k] = True
            for s, e in contact_intervals(down[:, k]):
                if e - s < short:
                    down[s:e, k] = False
        contacts = {"left": contact_intervals(down[:, 0]), "right": contact_intervals(down[:, 1])}
    else:
        contacts = {"left": np.zeros((0, 2), np.intp), "right": np.zeros((0, 2), np.intp)}
    kind, frames, reason = suggest(positions, bvh.fps, contacts)
    playback = suggest_playback(positions, kind, frames)
    if kind == "other" and playback == "loop":
        reason += (f"; it travels {root_travel(positions[frames[0]:frames[1] + 1]):.2f} m, so it loops (ping-pong "
                   f"would move it backwards)")
    return MotionReport(name, out, {k: [(int(a), int(b)) for a, b in v] for k, v in contacts.items()}, kind, frames,
                        reason, playback)


def read_motions(path: str | os.PathLike[str], explicit: Mapping[str, str] | None = None,
                 units: str | None = None, up_axis: str | None = None,
                 max_frame_joints: int = MAX_FRAME_JOINTS) -> list[tuple[str, Normalized]]:
    """Every motion of a BVH (one) or glTF file (one per animation; one-joint animations as one, see
    :mod:`anim_core.io.gltf`), named and normalized (:func:`~anim_core.rig.normalize.normalize_bvh`; a glTF's units
    from its skinned mesh's height where that is a human's, :func:`_mesh_units`); errors are ``ValueError``
    subclasses naming the file.  A motion
    of more than ``max_frame_joints`` frames × joints fails before it is read (the memory spent on a motion grows
    with it; :func:`~anim_core.io.bvh.parse_bvh`, :func:`~anim_core.io.gltf.read_gltf`)."""
    path = Path(path)
    name = path.name.lower()
    if name.endswith((".bvh", ".bvh.gz")):
        bvh: Bvh = read_bvh(path, max_frame_joints)
        return [(path.name, normalize_bvh(bvh, explicit, units, up_axis))]
    if name.endswith((".glb", ".gltf")):
        asset = read_gltf(path, max_frame_joints=max_frame_joints)
        if not asset.animations:
            raise ValueError(f"{path.name}: the file holds a character but no animation")
        units = units or _mesh_units(asset, explicit, up_axis)
        sk = asset.skeleton
        return [(a.name, normalize_motion(sk if a.offsets is None else Skeleton(sk.names, sk.parents, a.offsets,
                                                                                sk.rest_rotations),
                                          a.rotations, a.root_translation, a.frame_time, {},
                                          f"{path.name} animation {a.name!r}", explicit, units, up_axis))
                for a in asset.animations]
    raise ValueError(f"{path.name}: not a motion file; expected .bvh, .bvh.gz, .glb or .gltf")


def _mesh_units(asset: GltfAsset, explicit: Mapping[str, str] | None, up_axis: str | None) -> str | None:
    """The unit in which the skinned mesh's height (its bounding box along up) is a human height, ``None`` where
    that cannot be told (the skeleton does not map, or the mesh is no human height): the skeleton's leg length
    decides then.  The mesh is the figure's whole height, head and feet included, where the joints stop short of
    both (a 1.51 m figure's joints span 1.3 m)."""
    try:
        mapping = map_skeleton(asset.skeleton, explicit)
    except RigMapError:
        return None
    rest = asset.skeleton.rest_global()[1]
    up = up_axis or detect_up_axis(rest, int(mapping.source_index[_CANON["Head"]]), int(mapping.source_index[0]))
    try:
        return units_from_height(float(np.ptp(asset.vertices[:, 1 if up == "y" else 2])), "skinned mesh")
    except RigMapError:
        return None


def inspect_source(path: str | os.PathLike[str], explicit: Mapping[str, str] | None = None,
                   units: str | None = None, up_axis: str | None = None,
                   max_frame_joints: int = MAX_FRAME_JOINTS) -> list[MotionReport]:
    """Reports of every motion in the file (one for a BVH, one per animation of a glTF); ``max_frame_joints`` as
    :func:`read_motions` takes it."""
    return [_report(name, out) for name, out in read_motions(path, explicit, units, up_axis, max_frame_joints)]


def joint_table(path: str | os.PathLike[str]) -> str | None:
    """The joints of a BVH or glTF file, one a line: index, name, parent and position in the bind pose (glTF: from
    the inverse bind matrices; BVH: the rest pose), in file units, so that a user whose file does not map can
    write a mapping file from them; ``None`` if the file's skeleton cannot be read.  Unnamed glTF joints are
    ``joint<k>``, ``k`` the index here (depth-first from the root joint, children in the file's order)."""
    path = Path(path)
    try:
        if path.name.lower().endswith((".glb", ".gltf")):
            asset = read_gltf(path, animations=False)
            skeleton = asset.skeleton
            ibm = np.asarray(asset.inverse_bind, np.float64)
            positions = np.linalg.inv(ibm)[:, :3, 3]
            where = "bind position (from the inverse bind matrices)"
        else:
            skeleton = read_bvh(path).skeleton
            positions = skeleton.rest_global()[1]
            where = "rest position"
    except (ValueError, OSError, np.linalg.LinAlgError):
        return None
    names = skeleton.names
    width = max(len(n) for n in names)
    lines = [f"joints of {path.name} (for a mapping file: character joint = \"file joint\"):",
             f"  {'index':>5}  {'name':<{width}}  {'parent':<{width}}  {where}, file units"]
    for j, name in enumerate(names):
        parent = names[skeleton.parents[j]] if skeleton.parents[j] >= 0 else "-"
        x, y, z = positions[j]
        lines.append(f"  {j:>5}  {name:<{width}}  {parent:<{width}}  ({x:.4g}, {y:.4g}, {z:.4g})")
    return "\n".join(lines)


def format_report(path: str | os.PathLike[str], reports: list[MotionReport],
                  tolerances: Sequence[str | None] | None = None) -> str:
    """Plain-text report of :func:`inspect_source` for the terminal; ``tolerances``: per report a line on the
    suggested ``tolerance_mm`` (kind ``other``) or ``None``."""
    lines = []
    for k, r in enumerate(reports):
        n = r.normalized
        m = n.mapping
        lines += [f"{Path(path).name}: {r.name}",
                  f"  joints      {len(m.source_names)}",
                  f"  convention  {m.convention}",
                  f"  units       {n.units} ({n.metres_per_unit:g} m per unit)",
                  f"  up axis     {n.up_axis.upper()}" + (f"; {'; '.join(n.notes)}" if n.notes else ""),
                  f"  fps         {r.fps:g}",
                  f"  frames      {r.n_frames}",
                  f"  duration    {r.duration:.3f} s",
                  "  foot contacts (frames [start, stop)):"]
        for foot, phases in r.contacts.items():
            lines.append(f"    {foot:<5} {', '.join(f'{a}-{b}' for a, b in phases) or 'none'}")
        playback = f', playback = "{r.playback}"' if r.kind == "other" else ""
        lines.append(f"  suggested   kind = \"{r.kind}\", frames {r.frames[0]}..{r.frames[1]}{playback}  ({r.reason})")
        if tolerances is not None and tolerances[k] is not None:
            lines.append(f"              {tolerances[k]}")
        lines.append("  mapping (character joint <- file joint: why):")
        for d in m.decisions:
            lines.append(f"    {d.canonical:<16} <- {d.source or '(none)'}: {d.reason}")
        if m.unmapped:
            lines.append(f"  unmapped (ignored): {', '.join(m.unmapped)}")
    return "\n".join(lines)


def write_motion(path: str | os.PathLike[str], skeleton: Skeleton, mesh: SkinnedMesh, faces: NDArray[np.intp],
                 rotations: Array, root_translation: Array, frame_time: float, end_sites: Mapping[int, Array],
                 name: str = "motion") -> None:
    """Write a motion on the character: ``.glb``/``.gltf`` (character mesh + skin + animation) or ``.bvh``/
    ``.bvh.gz`` (``skeleton`` with ``end_sites``), for a look in Blender or a web viewer.

    ``skeleton``: the character's bones (metres, Y up, identity rest rotations); ``mesh`` bound to it;
    ``rotations``: ``(F, J, 4)`` local (w, x, y, z); ``root_translation``: ``(F, 3)`` m; one frame per
    ``frame_time`` seconds.  Nothing is left behind on failure (both writers write to a temporary name)."""
    path = Path(path)
    lower = path.name.lower()
    if lower.endswith((".glb", ".gltf")):
        times = np.arange(len(rotations)) * frame_time
        write_gltf(path, skeleton, mesh.vertices, mesh.normals, faces, mesh.joints, mesh.weights, mesh.inverse_bind,
                   (GltfAnimation(name, times, rotations, root_translation),))
    elif lower.endswith((".bvh", ".bvh.gz")):
        write_bvh(bvh_from_poses(skeleton, rotations, root_translation, frame_time, dict(end_sites), path.name), path)
    else:
        raise ValueError(f"{path.name}: export writes .glb, .gltf, .bvh or .bvh.gz")


def export_on_character(normalized: Normalized, character: Character, path: str | os.PathLike[str],
                        name: str = "motion") -> None:
    """Write a normalized motion retargeted onto ``character`` (:func:`write_motion`)."""
    bvh = normalized.bvh
    rot, root = bvh.pose_arrays()
    rt = retarget(character, bvh.posed_skeleton(), bvh.end_sites, motion=rot)
    ends = {j: np.asarray(e) * rt.root_scale for j, e in bvh.end_sites.items()}
    write_motion(path, rt.skeleton, rt.mesh, rt.faces, rot, root * rt.root_scale, bvh.frame_time, ends, name)
