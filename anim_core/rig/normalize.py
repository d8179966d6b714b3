"""A source motion on any humanoid skeleton brought into the canonical form (:mod:`anim_core.rig.rigmap`): its
joints mapped, its units and up axis detected from the motion (or given), its rest pose a standing one, turned so
the character's left is +X (:func:`normalize_motion`), and a BVH file as tools write it read into that
(:func:`normalize_bvh`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from ..io.bvh import OFFSET_MATCH, Bvh, bvh_from_poses, still_translation
from ..math.quat import identity, quat_conj, quat_from_axis_angle, quat_from_euler, quat_mul, rotate
from ..math.skeleton import Skeleton
from .rigmap import (
    CANONICAL_NAMES,
    CANONICAL_PARENTS,
    MAX_FRAMES,
    MAX_JOINTS,
    UNITS,
    RigMapError,
    RigMapping,
    map_skeleton,
)
from .structure import joint_chain

Array = NDArray[np.float64]


# ---------------------------------------------------------------------------------------------------------------
# Units and up axis

def detect_up_axis(rest_positions: Array, head: int, hips: int) -> str:
    """``"y"`` or ``"z"``: the axis along which the head stands above the hips (most)."""
    d = rest_positions[head] - rest_positions[hips]
    return "y" if abs(d[1]) >= abs(d[2]) else "z"


def detect_units(height: float) -> str:
    """The unit in which ``height`` (rest-pose joint extent along up) is a plausible human height."""
    for unit, (_, (lo, hi)) in UNITS.items():
        if lo <= height <= hi:
            return unit
    raise RigMapError(f"a rest-pose height of {height:.4g} units is not a human height in m, cm, mm, inches or CMU "
                      f"units; give the units explicitly")


def units_from_height(height: float, what: str = "skinned mesh") -> str:
    """The unit in which a figure ``height`` tall (``what``: a skinned mesh's bounding box along up, head and feet
    included) is a plausible human height (the ranges of :data:`UNITS`)."""
    for unit, (_, (lo, hi)) in UNITS.items():
        if lo <= height <= hi:
            return unit
    raise RigMapError(f"a {what} {height:.4g} units tall is not a human height in m, cm, mm, inches or CMU units; "
                      f"give the units explicitly")


def canonical_frame(rest_positions: Array, source_index: NDArray[np.intp], up_axis: str | None = None,
                    units: str | None = None) -> tuple[Array, str, str, float]:
    """The turn that brings a source skeleton into the canonical world (Y up, its left at +X), and its units.

    ``rest_positions``: ``(J, 3)`` source joint positions at rest; ``source_index``: a :class:`RigMapping`'s
    ``source_index``; ``up_axis``/``units`` override the detection.  Returns ``(world, up_axis, units, facing)``:
    ``world`` the quaternion (w, x, y, z) to apply to source positions, ``facing`` the turn about up (radians).
    """
    idx = source_index
    hips, head = idx[0], idx[CANONICAL_NAMES.index("Head")]
    if up_axis is None:
        up_axis = detect_up_axis(rest_positions, head, hips)
    if up_axis not in ("y", "z"):
        raise RigMapError(f"up axis must be 'y' or 'z', got {up_axis!r}")
    facing, world = _facing_turn(_to_y_up(up_axis), rest_positions, idx)
    height = float(np.ptp(rotate(world, rest_positions)[:, 1]))
    if units is None:
        units = detect_units(height)
    if units not in UNITS:
        raise RigMapError(f"units must be one of {', '.join(UNITS)}, got {units!r}")
    return world, up_axis, units, facing


def _to_y_up(up_axis: str) -> Array:
    """The world change ``(4,)`` to Y up from ``up_axis`` ``"y"`` or ``"z"``."""
    # Z up (x, y, z) -> (x, z, -y) is a -90 degree turn about x.
    return identity() if up_axis == "y" else quat_from_axis_angle(np.array([1.0, 0.0, 0.0]), -np.pi / 2)


def _facing_turn(to_y: Array, rest_positions: Array, source_index: NDArray[np.intp]) -> tuple[float, Array]:
    """``(facing, world)``: the turn about up (radians) that puts the left hip of ``rest_positions`` ``(J, 3)``
    (Y up after ``to_y``) at +X, and ``world`` ``(4,)``, ``to_y`` followed by that turn."""
    p = rotate(to_y, rest_positions)
    left = p[source_index[CANONICAL_NAMES.index("LeftUpLeg")]] - p[source_index[CANONICAL_NAMES.index("RightUpLeg")]]
    # Rigs are authored facing along an axis: the turn is snapped to quarter turns so that a subject's slight
    # asymmetry does not turn the motion.
    facing = float(np.round(np.arctan2(left[2], left[0]) / (np.pi / 2)) * (np.pi / 2))
    return facing, quat_mul(quat_from_axis_angle(np.array([0.0, 1.0, 0.0]), facing), to_y)


#: Joint extent of a standing person (head joint to toe joints) per leg length (thigh + shin bone), as on the CMU
#: skeleton (23.9 / 14.65 units).  Units are detected from bone lengths, which no pose and no rest pose changes.
HEIGHT_PER_LEG = 1.63
#: A pose is standing if the trunk (hips to head) and both legs (hip socket to ankle) are within 30 degrees of up,
#: measured as the cosine ("uprightness") of the worst of the three.
STANDING_COS = float(np.cos(np.radians(30.0)))
_HEAD = CANONICAL_NAMES.index("Head")
_LEGS = tuple(tuple(CANONICAL_NAMES.index(f"{s}{p}") for p in ("UpLeg", "Foot")) for s in ("Left", "Right"))


def leg_length(skeleton: Skeleton, source_index: NDArray[np.intp]) -> float:
    """Mean length of the two legs (hip socket to ankle, along the bones) in the skeleton's units."""
    lengths = []
    for upleg, foot in _LEGS:
        chain = joint_chain(skeleton.parents, int(source_index[foot]), int(source_index[upleg]))
        lengths.append(float(sum(np.linalg.norm(skeleton.offsets[j]) for j in chain)))
    return float(np.mean(lengths))


def uprightness(positions: Array, source_index: NDArray[np.intp]) -> Array:
    """``(...)`` the cosine between up (+Y) and the least upright of trunk, left leg and right leg, for joint
    positions ``(..., J, 3)`` (Y up): 1 standing straight, 0 lying, negative upside down."""
    idx = source_index

    def up_share(v: Array) -> Array:
        return v[..., 1] / np.maximum(np.linalg.norm(v, axis=-1), 1e-12)
    trunk = up_share(positions[..., idx[_HEAD], :] - positions[..., idx[0], :])
    legs = [up_share(positions[..., idx[a], :] - positions[..., idx[b], :]) for a, b in _LEGS]
    return np.minimum(trunk, np.minimum(*legs))


def motion_up_axis(positions: Array, source_index: NDArray[np.intp]) -> str:
    """``"y"`` or ``"z"``: the axis along which the head is above the hips in most frames of ``(F, J, 3)``."""
    d = positions[:, source_index[_HEAD]] - positions[:, source_index[0]]
    d = np.median(d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12), axis=0)
    return "y" if abs(d[1]) >= abs(d[2]) else "z"


def units_from_legs(leg: float) -> str:
    """The unit in which legs of length ``leg`` (:func:`leg_length`) belong to a plausible human."""
    height = HEIGHT_PER_LEG * leg
    for unit, (_, (lo, hi)) in UNITS.items():
        if lo <= height <= hi:
            return unit
    raise RigMapError(f"legs of {leg:.4g} units (a standing height of about {height:.4g} units) are not a human "
                      f"height in m, cm, mm, inches or CMU units; give the units explicitly (--units, or the units "
                      f"field of the upload)")


@dataclass(frozen=True, eq=False)
class Normalized:
    """A source motion brought into the canonical form: ``bvh`` (CMU joints and channels, Y up, facing +Z), the
    ``mapping``, the detected or given ``units`` and ``up_axis``, ``metres_per_unit`` and ``facing_angle`` (radians
    about up that turned the source's left to +X).  ``reference_frame``: the source frame whose pose is the rest
    pose of ``bvh`` when the source's own rest (all-zero) pose is not a standing pose, else ``None``.
    ``source_positions``: ``(F, 31, 3)`` the mapped source joints by the source's own forward kinematics, turned
    into the canonical world, in source units (an unmapped joint at its canonical parent's place): what the
    fidelity gate (:mod:`anim_core.clips.fidelity`) holds the retargeted motion against."""

    bvh: Bvh
    mapping: RigMapping
    units: str
    up_axis: str
    metres_per_unit: float
    facing_angle: float
    notes: tuple[str, ...] = field(default=())
    reference_frame: int | None = None
    source_positions: Array | None = field(default=None, repr=False)


def normalize_motion(skeleton: Skeleton, rotations: Array, root_translation: Array, frame_time: float,
                     end_sites: Mapping[int, Array], source: str, explicit: Mapping[str, str] | None = None,
                     units: str | None = None, up_axis: str | None = None,
                     rest: Literal["zero", "motion"] | None = None) -> Normalized:
    """Bring a motion on any humanoid skeleton into the canonical form (see :class:`Normalized`).

    ``skeleton``: source joints (any rest rotations, any local joint frames); ``rotations``: ``(F, J, 4)`` local
    (w, x, y, z); ``root_translation``: ``(F, 3)`` in source units; ``end_sites``: leaf offsets per joint index.
    ``units`` (a key of :data:`UNITS`) and ``up_axis`` (``"y"``/``"z"``) override the detection, which reads the
    motion: up is where the head is above the hips in most frames, units follow from the leg length.

    Method: the canonical joints' global rotations are the mapped source joints' global rotations taken relative
    to a **standing reference pose** and turned to the canonical world (Y up, left at +X); the reference pose's
    joint positions become the canonical rest offsets.  The reference is the source's rest pose when that pose
    stands (head above hips, legs down, :data:`STANDING_COS`), else the most upright frame of the motion
    (``rest``: force ``"zero"`` or ``"motion"``).  So every canonical bone points where the source's bone points in
    the world at every frame, whatever the source's rest pose and local joint frames are: rigs that differ only in
    those give the same canonical motion.
    """
    rotations = np.asarray(rotations, dtype=np.float64)
    _check_motion(rotations, root_translation, source, units, up_axis, rest)
    g_rot, g_pos = skeleton.forward_kinematics(rotations, root_translation)
    rest_rot, rest_pos = skeleton.rest_global()

    def mapped(positions: Array | None) -> RigMapping:
        try:
            return map_skeleton(skeleton, explicit, positions)
        except RigMapError as exc:
            raise RigMapError(f"{source}: {exc}") from None

    try:
        mapping = map_skeleton(skeleton, explicit)
    except RigMapError:
        mapping = mapped(g_pos[0])  # a rest pose that is no human pose: distances measured on the motion
    idx = mapping.source_index
    if up_axis is None:
        up_axis = motion_up_axis(g_pos, idx)
    to_y = _to_y_up(up_axis)
    reference: int | None = None
    if rest == "motion" or (rest is None and uprightness(rotate(to_y, rest_pos), idx) < STANDING_COS):
        reference = int(np.argmax(uprightness(rotate(to_y, g_pos), idx)))
        mapping = mapped(g_pos[reference])
        idx = mapping.source_index
        rest_rot, rest_pos = g_rot[reference], g_pos[reference]
    if units is None:
        try:
            units = units_from_legs(leg_length(skeleton, idx))
        except RigMapError as exc:
            raise RigMapError(f"{source}: {exc}") from None
    facing, world = _facing_turn(to_y, rest_pos, idx)
    p = rotate(world, rest_pos)
    offsets, local, own = _canonical_motion(world, g_rot, g_pos, rest_rot, p, idx)
    root = rotate(world, g_pos[:, idx[0]])
    ends = _canonical_end_sites(skeleton, idx, end_sites, world, rest_rot, p)
    bvh = bvh_from_poses(Skeleton(CANONICAL_NAMES, CANONICAL_PARENTS, offsets), local, root, frame_time, ends,
                         source)
    notes = []
    if reference is not None:
        notes.append(f"the rest (all-zero) pose is not a standing pose: the motion is taken relative to the pose "
                     f"of frame {reference}" if rest is None else f"rest pose taken from frame {reference}")
    if abs(facing) > 1e-9:
        notes.append(f"turned {np.degrees(facing):.1f} degrees about up so the character's left is +X")
    return Normalized(bvh, mapping, units, up_axis, UNITS[units][0], facing, tuple(notes), reference, own)


def _check_motion(rotations: Array, root_translation: Array, source: str, units: str | None, up_axis: str | None,
                  rest: str | None) -> None:
    """:func:`normalize_motion`'s arguments checked before any work: frames, finite values, the options."""
    n_frames = rotations.shape[0]
    if n_frames > MAX_FRAMES:
        raise RigMapError(f"{source}: {n_frames} frames; at most {MAX_FRAMES} are supported")
    if n_frames == 0:
        raise RigMapError(f"{source}: the motion has no frames")
    if not (np.all(np.isfinite(rotations)) and np.all(np.isfinite(root_translation))):
        raise RigMapError(f"{source}: the motion holds NaN or infinite values")
    if rest not in (None, "zero", "motion"):
        raise ValueError(f"rest must be None, 'zero' or 'motion', got {rest!r}")
    if up_axis not in (None, "y", "z"):
        raise RigMapError(f"up axis must be 'y' or 'z', got {up_axis!r}")
    if units is not None and units not in UNITS:
        raise RigMapError(f"units must be one of {', '.join(UNITS)}, got {units!r}")


def _canonical_motion(world: Array, g_rot: Array, g_pos: Array, rest_rot: Array, p: Array,
                      idx: NDArray[np.intp]) -> tuple[Array, Array, Array]:
    """The canonical skeleton's rest offsets ``(31, 3)``, local rotations ``(F, 31, 4)`` and joint positions by the
    source's own forward kinematics ``(F, 31, 3)`` (source units), from the source's global rotations and positions
    ``g_rot``/``g_pos``, its reference pose's global rotations ``rest_rot`` and positions ``p`` (in the new
    world), ``world`` the turn into the canonical world and ``idx`` the source joint per canonical joint (-1: none,
    the joint then sits on its canonical parent and turns with it)."""
    n_frames = g_rot.shape[0]
    # Source global rotation relative to the reference, in the new world: W G G_ref^-1 W^-1.
    aligned = quat_mul(quat_mul(world, quat_mul(g_rot, quat_conj(rest_rot))), quat_conj(world))
    n = len(CANONICAL_NAMES)
    c_rest = np.zeros((n, 3))
    c_glob = np.empty((n_frames, n, 4))
    for c in range(n):  # 31 canonical joints, vectorized over frames
        parent = CANONICAL_PARENTS[c]
        if idx[c] >= 0:
            c_rest[c] = p[idx[c]]
            c_glob[:, c] = aligned[:, idx[c]]
        else:
            c_rest[c] = c_rest[parent]
            c_glob[:, c] = c_glob[:, parent]
    own = np.empty((n_frames, n, 3))
    for c in range(n):
        own[:, c] = g_pos[:, idx[c]] if idx[c] >= 0 else own[:, CANONICAL_PARENTS[c]]
    own = rotate(world, own)
    offsets = c_rest.copy()
    offsets[1:] -= c_rest[CANONICAL_PARENTS[1:]]
    offsets[0] = 0.0  # the root translation is the hips' place, whatever pose the rest is
    local = c_glob.copy()
    local[:, 1:] = quat_mul(quat_conj(c_glob[:, CANONICAL_PARENTS[1:]]), c_glob[:, 1:])
    return offsets, local, own


def _canonical_end_sites(skeleton: Skeleton, idx: NDArray[np.intp], end_sites: Mapping[int, Array], world: Array,
                         rest_rot: Array, p: Array) -> dict[int, Array]:
    """End Site ``(3,)`` of each canonical leaf in the canonical world: the source joint's End Site, else the bone
    to its first child in the reference pose ``p`` (new world), else zero."""
    ends: dict[int, Array] = {}
    for c in range(len(CANONICAL_NAMES)):
        if c in CANONICAL_PARENTS:
            continue
        j = idx[c]
        if j >= 0 and j in end_sites:
            # The End Site offset is in the joint's frame; bring it to the world at rest, then to the new world.
            ends[c] = rotate(world, rotate(rest_rot[j], np.asarray(end_sites[j], np.float64)))
        elif j >= 0 and skeleton.children(j):
            ends[c] = p[skeleton.children(j)[0]] - p[j]
        else:
            ends[c] = np.zeros(3)
    return ends


def _bvh_motion(bvh: Bvh) -> tuple[Skeleton, Array, Array, dict[int, Array], list[str]]:
    """The skeleton (constant position channels folded into the offsets), local rotations ``(F, J, 4)``, root
    translation ``(F, 3)`` and End Sites of a BVH as tools write it, with notes on what was done.

    A static reference root above the joint that carries the motion's translation (the Bandai Namco and
    MotionBuilder layout: ``joint_Root`` above ``Hips``) is left out: its constant transform moves into the
    translation and rotation of the new root.  Position channels on other joints must be constant (those equal
    to the OFFSET restate the bone); animated ones that stay within 1 % of the bone's length are averaged, others
    are refused with the joint named.
    """
    s = bvh.skeleton
    names = s.names
    groups, columns = bvh._columns()
    padded = bvh._padded_motion()
    n_frames, n_joints = bvh.n_frames, s.n_joints
    rot = np.empty((n_frames, n_joints, 4))
    for order, (joints, cols) in groups.items():
        rot[:, joints] = quat_from_euler(np.radians(padded[:, cols]), order)
    has = columns >= 0  # (J, 3)
    values = padded[:, columns]  # (F, J, 3), 0 where a channel is missing
    scale = np.maximum(np.linalg.norm(s.offsets, axis=1), 1.0)
    varying = np.any(np.abs(values - values[:1]) > 1e-6 * scale[None, :, None], axis=(0, 2))  # rounding is not motion
    # Files that restate every bone in position channels (values equal to the OFFSET) mean the channel value *is*
    # the joint's translation; the moving root of such a file is placed by its channel values alone.
    restated = has.any(axis=1) & np.all(~has | (np.abs(values[0] - s.offsets) <= OFFSET_MATCH * np.maximum(
        np.abs(s.offsets), 1.0)), axis=1)
    restated[0] = False
    replace = bool(np.any(restated[1:] & ~varying[1:]))

    def translation(j: int) -> Array:  # (F, 3) joint j's translation in its parent's frame
        if j == 0:
            return s.offsets[0] + values[:, 0]
        if replace:
            return np.where(has[j], values[:, j], s.offsets[j])
        return s.offsets[j] + np.where(restated[j], 0.0, values[:, j])

    static = s.offsets + np.where(restated[:, None], 0.0, values[0])  # translation of joints with constant channels
    static[0] = s.offsets[0]
    moving = [j for j in range(1, n_joints) if varying[j]]
    top = _body_root(s, moving, varying, rot, values, scale)
    notes: list[str] = []
    for j in moving:
        if j == top or joint_chain(s.parents, top, j):
            continue
        mean, spread, still = still_translation(translation(j))
        if not still:
            raise RigMapError(f"{bvh.source}: joint {names[j]!r} has animated position channels (it moves up to "
                              f"{spread:.3g} units against its parent); only the body's root "
                              f"({names[top]!r}) may translate: export the motion without translation keys on "
                              f"{names[j]!r} (bake them into rotations)")
        static[j] = mean
        notes.append(f"the position channels of {names[j]!r} vary by at most {spread:.3g} units: their mean is "
                     f"used")
    if top == 0:
        skeleton = Skeleton(names, s.parents, static)
        return skeleton, rot, padded[:, columns[0]], dict(bvh.end_sites), notes
    sub, rotations, root, ends, dropped = _reroot(s, bvh.end_sites, top, rot, static, translation)
    notes.append(f"{', '.join(repr(d) for d in dropped)} above {names[top]!r} left out (its motion moved into "
                 f"{names[top]!r}, the new root)")
    return sub, rotations, root, ends, notes


def _body_root(s: Skeleton, moving: list[int], varying: NDArray[np.bool_], rot: Array, values: Array,
               scale: Array) -> int:
    """The joint that carries the body: the first one that translates (``moving``: joints below the root whose
    position channels ``values`` ``(F, J, 3)`` vary), if everything above it is still (a static reference root);
    else the first branching joint (the hips) below a chain of single joints whose motion, whatever it is,
    becomes the root's.  ``rot``: local rotations ``(F, J, 4)``; ``scale``: ``(J,)`` the rounding scale per joint."""
    if not moving:
        return 0
    first = moving[0]
    ancestors = joint_chain(s.parents, first, -1)[:-1]
    still = [not varying[a] and np.allclose(rot[:, a], rot[:1, a], atol=1e-12) for a in ancestors]
    still[0] = still[0] and not np.any(np.abs(values[:, 0] - values[:1, 0]) > 1e-6 * scale[0])
    if all(still):
        return first
    children = [s.children(j) for j in range(s.n_joints)]
    top = 0
    while len(children[top]) == 1:
        top = children[top][0]
    return top


def _reroot(s: Skeleton, end_sites: Mapping[int, Array], top: int, rot: Array, static: Array,
            translation: Callable[[int], Array]) -> tuple[Skeleton, Array, Array, dict[int, Array], list[str]]:
    """The motion re-rooted at joint ``top``: the joints above it become one transform per frame, folded into
    ``top``'s rotation and translation.  Returns the skeleton of ``top`` and the joints below it (``static``
    ``(J, 3)`` their offsets), its local rotations ``(F, J', 4)`` (of ``rot`` ``(F, J, 4)``), root translation
    ``(F, 3)``, End Sites, and the names of the joints left out; ``translation(j)`` ``(F, 3)`` is joint ``j``'s in
    its parent's frame."""
    names, n_joints = s.names, s.n_joints
    q, t = identity((rot.shape[0],)), np.zeros((rot.shape[0], 3))
    for a in joint_chain(s.parents, top, -1)[:-1]:
        t = t + rotate(q, translation(a))
        q = quat_mul(q, rot[:, a])
    own = translation(top)
    keep = [top] + [j for j in range(top + 1, n_joints) if joint_chain(s.parents, j, top)]
    new = {j: k for k, j in enumerate(keep)}
    offsets = static[keep]
    offsets[0] = 0.0
    sub = Skeleton([names[j] for j in keep], [new.get(int(s.parents[j]), -1) for j in keep], offsets)
    rotations = rot[:, keep]
    rotations[:, 0] = quat_mul(q, rot[:, top])
    root = t + rotate(q, own)
    dropped = [names[j] for j in range(n_joints) if j not in new]
    return sub, rotations, root, {new[j]: e for j, e in end_sites.items() if j in new}, dropped


def normalize_bvh(bvh: Bvh, explicit: Mapping[str, str] | None = None, units: str | None = None,
                  up_axis: str | None = None, rest: Literal["zero", "motion"] | None = None) -> Normalized:
    """:func:`normalize_motion` of a BVH file as tools write it (:func:`_bvh_motion`: a static reference root
    above the hips, position channels on every joint, any Euler order)."""
    if bvh.skeleton.n_joints > MAX_JOINTS:
        raise RigMapError(f"{bvh.source}: {bvh.skeleton.n_joints} joints; at most {MAX_JOINTS} are supported")
    if bvh.n_frames == 0:
        raise RigMapError(f"{bvh.source}: the MOTION section has no frames ('Frames: 0')")
    zero = [bvh.skeleton.names[j] for j in range(1, bvh.skeleton.n_joints)
            if np.linalg.norm(bvh.skeleton.offsets[j]) < 1e-12 and not bvh.skeleton.children(j)
            and np.linalg.norm(bvh.end_sites.get(j, np.zeros(3))) < 1e-12]
    skeleton, rotations, root, end_sites, read_notes = _bvh_motion(bvh)
    out = normalize_motion(skeleton, rotations, root, bvh.frame_time, end_sites, bvh.source, explicit, units,
                           up_axis, rest)
    s = bvh.skeleton
    if (s.names == CANONICAL_NAMES and np.array_equal(s.parents, CANONICAL_PARENTS) and out.up_axis == "y"
            and out.facing_angle == 0 and out.reference_frame is None
            and np.array_equal(out.mapping.source_index, np.arange(len(CANONICAL_NAMES)))):
        # Already canonical (a CMU file): the file itself, bit for bit; the computation would only add rounding.
        out = dataclasses.replace(out, bvh=bvh)
    notes = (*read_notes, *out.notes) + ((f"zero-length leaf bones ignored: {', '.join(zero)}",) if zero else ())
    return dataclasses.replace(out, notes=notes)
