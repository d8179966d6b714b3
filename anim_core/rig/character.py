"""The skinned character (MakeHuman base mesh on the 31-joint ``cmu_mb`` rig) and retargeting of mocap onto it.

Source files (:func:`load_character` takes their paths; the server finds and verifies them in its data directory,
``server.assets``): ``base.obj.gz`` (decimetres, Y up, A-pose;
only the group ``body`` is the character, the rest is helper geometry), ``rig.cmu_mb.json`` (bone heads and tails
in metres, Blender Z up) and ``weights.cmu_mb.json.gz`` (per bone ``[vertex, weight]`` lists, up to 8 bones per
vertex).  Everything here is converted to **metres, Y up**, the character facing +Z with its left at +X (the
orientation of the CMU motion capture).

Retargeting (:func:`retarget`) plays the local joint rotations of a BVH skeleton unchanged on a skeleton with the
character's bone lengths and the mocap's rest bone directions, so every bone of the character points exactly
where the mocap's bone points, at every frame.  The mesh is bound to that skeleton by one rotation per joint
(``bind_rotations``), the rotation that turns the joint's mocap rest direction into the direction the bone has in
the A-posed mesh; it is computed down each chain relative to the parent's, so twist carries over smoothly.  A
gait is mirrored about a bind made from the clip itself (:func:`mirror_bind`), so that its hybrid does not depend on
the rig the take came on.

Each take is bound on its own (its mocap's rest directions, its pelvis as it holds it), so two takes' skeletons
differ even on one character: a take's rotations played on another take's skeleton put its feet elsewhere (up to
0.3 m for CMU's run on its idle's).  :func:`rebind` re-expresses a motion on another binding so that every bone of
the mesh turns as it did (what a composite of several takes needs).
"""

from __future__ import annotations

import gzip
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from ..math.clip import Pose
from ..math.quat import identity, quat_between, quat_conj, quat_from_axis_angle, quat_mul, rotate
from ..math.skeleton import Skeleton
from ..math.skinning import MAX_INFLUENCES, SkinnedMesh, invert_transforms, transforms, vertex_normals

Array = NDArray[np.float64]

BODY_GROUP = "body"
#: The character's feet (each: ankle and toe joint), legs (IK chains hip, knee, ankle, as FEET) and up axis (Y).
FEET = (("LeftFoot", "LeftToeBase"), ("RightFoot", "RightToeBase"))  # each foot: ankle and toe joints
LEGS = (("LeftUpLeg", "LeftLeg", "LeftFoot"), ("RightUpLeg", "RightLeg", "RightFoot"))  # IK chains, as FEET
UP = 1


class CharacterError(ValueError):
    """A character file is unreadable or not what the loader expects; the message names the file."""

#: BVH joint name -> rig joint name where they differ.
CMU_TO_RIG = {"LeftHandIndex1": "LeftHandFinger1", "RightHandIndex1": "RightHandFinger1"}
#: Pelvis "bones" from the hip centre to each hip socket: the mocap and the rig disagree on where these point
#: (by about 45 degrees), and the pelvis is rigid, so these joints are moved rather than their mesh rotated.
DEFAULT_RELOCATE = ("LHipJoint", "RHipJoint")
#: Joints that carry a face: bound level over the take when they have no bone of their own (an End Site at the
#: joint, as the Bandai Namco rigs' heads).  Only these: a bone-less hand has no "level" to be bound at.
DEFAULT_LEVEL = ("Head",)


@dataclass(frozen=True, eq=False)
class Character:
    """The rigged mesh as authored (A-pose), metres, Y up.

    ``names``/``parents``: rig joints in topological order; ``heads``/``tails``: ``(J, 3)`` bone head (the joint)
    and tail positions; ``vertices``/``normals``: ``(V, 3)``; ``faces``: ``(F, 3)`` triangles; ``joints``/``weights``:
    ``(V, 8)`` influences, each row summing to 1.
    """

    names: tuple[str, ...]
    parents: NDArray[np.intp]
    heads: Array
    tails: Array
    vertices: Array
    normals: Array
    faces: NDArray[np.intp]
    joints: NDArray[np.intp]
    weights: Array

    def __post_init__(self) -> None:
        # Read-only, as Skeleton's: one loaded character is shared (server/assets.py loads it once per process).
        for name in ("parents", "heads", "tails", "vertices", "normals", "faces", "joints", "weights"):
            value = getattr(self, name)
            if isinstance(value, np.ndarray):
                value.flags.writeable = False

    def index(self, name: str) -> int:
        return self.names.index(name)

    @property
    def sole_height(self) -> float:
        """Lowest point of the mesh (the soles, feet flat in the A-pose)."""
        return float(self.vertices[:, 1].min())


def _open_text(path: Path) -> str:
    try:
        data = path.read_bytes()
        return (gzip.decompress(data) if path.suffix == ".gz" else data).decode("utf-8")
    except UnicodeDecodeError as exc:
        raise CharacterError(f"{path} is not UTF-8 text: {exc}") from None
    except (OSError, EOFError) as exc:
        raise CharacterError(f"cannot read {path}: {exc} (corrupt file?)") from None


def _load_json(path: Path) -> dict:
    try:
        return json.loads(_open_text(path))
    except json.JSONDecodeError as exc:
        raise CharacterError(f"{path} is not valid JSON: {exc}") from None


def _yup(blender: Array) -> Array:
    """Blender Z-up (x, y, z) -> Y-up (x, z, -y); the rig faces -Y in Blender, +Z here."""
    b = np.asarray(blender, dtype=np.float64)
    return np.stack([b[..., 0], b[..., 2], -b[..., 1]], axis=-1)


def _parse_obj(text: str, path: Path) -> tuple[Array, NDArray[np.intp]]:
    """All vertices (decimetres) and the quad/triangle faces of group ``body`` as triangles (0-based, global)."""
    vertices: list[list[float]] = []
    faces: list[list[int]] = []
    group = None
    try:
        for number, line in enumerate(text.splitlines(), 1):  # noqa: B007 (number names the bad line)
            if line.startswith("v "):
                vertices.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("g "):
                group = line[2:].strip()
            elif line.startswith("f ") and group == BODY_GROUP:
                idx = [int(tok.split("/")[0]) - 1 for tok in line.split()[1:]]
                faces.extend([idx[0], idx[k], idx[k + 1]] for k in range(1, len(idx) - 1))
    except (ValueError, IndexError):
        raise CharacterError(f"{path}, line {number}: malformed OBJ line {line[:60]!r}") from None
    if not faces:
        raise CharacterError(f"{path} has no faces in group {BODY_GROUP!r}")
    v = np.array(vertices, dtype=np.float64)
    f = np.array(faces, dtype=np.intp)
    if f.min() < 0 or f.max() >= len(v):
        raise CharacterError(f"{path}: a face refers to a vertex that does not exist")
    return v, f


def load_character(rig_path: Path, weights_path: Path, obj_path: Path) -> Character:
    """Load the MakeHuman character from its rig, weights and mesh files (each may be gzip-compressed, ``.gz``):
    body only, metres, Y up, weights normalized per vertex."""
    rig_path, weights_path, obj_path = Path(rig_path), Path(weights_path), Path(obj_path)
    rig = _load_json(rig_path)
    weight_lists = _load_json(weights_path).get("weights")
    if not isinstance(weight_lists, dict):
        raise CharacterError(f"{weights_path} has no 'weights' table")
    all_vertices, faces = _parse_obj(_open_text(obj_path), obj_path)

    # Rig joints in topological order (parents first), names as in the file.
    try:
        order: list[str] = []
        pending = dict(rig)
        while pending:
            ready = [n for n, b in pending.items() if b["parent"] == "" or b["parent"] in order]
            if not ready:
                raise CharacterError(f"rig bones {sorted(pending)} have parents that are not in the rig")
            for n in sorted(ready):
                order.append(n)
                del pending[n]
        parents = np.array([order.index(rig[n]["parent"]) if rig[n]["parent"] else -1 for n in order])
        heads = _yup(np.array([rig[n]["head"]["default_position"] for n in order]))
        tails = _yup(np.array([rig[n]["tail"]["default_position"] for n in order]))
    except (KeyError, TypeError, ValueError) as exc:
        raise CharacterError(f"{rig_path} is not a rig file as expected: {exc!r}") from None

    # Keep the body's vertices only, re-indexed.
    used = np.unique(faces)
    remap = np.full(len(all_vertices), -1, dtype=np.intp)
    remap[used] = np.arange(len(used))
    vertices = all_vertices[used] * 0.1  # decimetres -> metres; the OBJ is already Y up
    faces = remap[faces]

    influences: list[list[tuple[int, float]]] = [[] for _ in range(len(used))]
    for bone, pairs in weight_lists.items():
        if bone not in order:
            raise CharacterError(f"skin weights name bone {bone!r}, which is not in the rig")
        j = order.index(bone)
        for vertex, weight in pairs:
            if 0 <= vertex < len(remap) and remap[vertex] >= 0 and weight > 0:
                influences[remap[vertex]].append((j, float(weight)))
    if any(len(inf) == 0 for inf in influences):
        raise CharacterError("some body vertices have no skin weights")
    if max(len(inf) for inf in influences) > MAX_INFLUENCES:
        raise CharacterError(f"some vertices have more than {MAX_INFLUENCES} influences")
    joints = np.zeros((len(used), MAX_INFLUENCES), dtype=np.intp)
    weights = np.zeros((len(used), MAX_INFLUENCES))
    for v, inf in enumerate(influences):  # once at load time
        joints[v, : len(inf)] = [j for j, _ in inf]
        weights[v, : len(inf)] = [w for _, w in inf]
    sums = weights.sum(axis=1)
    if np.abs(sums - 1.0).max() > 1e-3:
        raise CharacterError(f"skin weights of the body do not sum to 1 (worst vertex sums to {sums.min():.4f})")
    weights /= sums[:, None]
    return Character(tuple(order), parents, heads, tails, vertices, vertex_normals(vertices, faces), faces,
                     joints, weights)


def _arc(a: Array, b: Array) -> Array:
    """The smallest rotation (quaternion) turning direction ``a (3,)`` into direction ``b (3,)``."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis)
    if s < 1e-12:
        if a @ b > 0:
            return identity()
        ortho = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        return quat_from_axis_angle(ortho, np.pi)
    return quat_from_axis_angle(axis, np.arctan2(s, a @ b))


@dataclass(frozen=True, eq=False)
class RetargetedCharacter:
    """The character bound to one mocap skeleton.

    ``skeleton``: the mocap's joints (names, order, parents) with the character's bone lengths and the mocap's rest
    directions, metres, identity rest rotations; mocap local rotations play on it unchanged.  ``mesh``: the body
    bound to it (joint indices in the mocap's order).  ``bind_rotations``/``bind_positions``: ``(J, 4)``/``(J, 3)``
    joint frames in the A-posed mesh.  ``root_scale``: metres per mocap length unit (ratio of leg lengths).
    ``contact_heights``: ``(J,)`` height of each joint above the soles in the A-pose (feet flat on the floor).
    ``bones``: the joints ``bind_rotations`` turns by a bone, each with that bone's mocap rest direction (what
    :meth:`mirror_bind` needs).
    """

    skeleton: Skeleton
    mesh: SkinnedMesh
    faces: NDArray[np.intp]
    bind_rotations: Array
    bind_positions: Array
    root_scale: float
    contact_heights: Array
    bones: Mapping[int, Array] = field(default_factory=dict, repr=False)

    def pose(self, mocap: Pose) -> Pose:
        """The character's pose for a batch of mocap poses: same rotations, root translation scaled to metres."""
        return Pose(np.asarray(mocap.rotations), np.asarray(mocap.root_translation) * self.root_scale)

    def mirror_bind(self, motion: ArrayLike) -> Array:
        """The bind a clip is mirrored about (:func:`mirror_bind`): ``motion`` ``(F, J, 4)``, the local rotations
        of the clip as it is mirrored (its root's in the frame whose plane ``x = 0`` is the mirror)."""
        return mirror_bind(self.skeleton, self.bind_rotations, self.bones, motion)


def rebind(motion: Pose, source: RetargetedCharacter, target: RetargetedCharacter) -> Pose:
    """The motion ``motion`` (local rotations ``(..., J, 4)``, root translation ``(..., 3)`` in metres) of the
    character bound by ``source``, re-expressed on the binding ``target`` of the same character and joints: the mesh
    turns exactly as before.  Each joint's global rotation becomes ``G_j C_j`` with ``C_j = B_j^-1 B'_j`` (``B``,
    ``B'``: the two bindings' ``bind_rotations``), so its local rotation is ``C_parent^-1 L_j C_j``; the root keeps
    its world position.  Joints then land where they were up to the bindings' own differences (CMU's zero-length hip
    joints, placed per take: about 2 cm); the feet exactly.  ``ValueError`` if the joints differ."""
    if source.skeleton.names != target.skeleton.names:
        raise ValueError("rebind: both bindings need the same joints in the same order")
    if source is target:
        return motion
    c = quat_mul(quat_conj(source.bind_rotations), target.bind_rotations)  # (J, 4)
    c_parent = c[np.maximum(target.skeleton.parents, 0)]
    c_parent[0] = identity()
    rotations = quat_mul(quat_mul(quat_conj(c_parent), np.asarray(motion.rotations)), c)
    root = np.asarray(motion.root_translation) + source.skeleton.offsets[0] - target.skeleton.offsets[0]
    return Pose(rotations, root)


def bind_mesh(character: Character, joint_names: Sequence[str], bind_rotations: Array, bind_positions: Array,
              name_map: Mapping[str, str] | None = None) -> SkinnedMesh:
    """The character's body bound to joints ``joint_names`` (in that order) with the given A-pose joint frames.

    ``bind_rotations``/``bind_positions``: ``(J, 4)``/``(J, 3)``, e.g. from :func:`retarget` or a clip file.
    """
    name_map = dict(CMU_TO_RIG if name_map is None else name_map)
    rig_to_joint = np.full(len(character.names), -1, dtype=np.intp)
    for j, name in enumerate(joint_names):
        rig = name_map.get(name, name)
        if rig not in character.names:
            raise CharacterError(f"the character has no joint for {name!r}")
        rig_to_joint[character.index(rig)] = j
    joints = rig_to_joint[character.joints]
    if np.any((joints < 0) & (character.weights > 0)):
        raise CharacterError("the mesh is weighted to rig joints that the skeleton does not have")
    weights = np.where(joints >= 0, character.weights, 0.0)
    inverse_bind = invert_transforms(transforms(bind_rotations, bind_positions))
    return SkinnedMesh(character.vertices, character.normals, np.maximum(joints, 0), weights, inverse_bind)


def retarget(character: Character, mocap: Skeleton, end_sites: Mapping[int, Array],
             name_map: Mapping[str, str] | None = None,
             relocate: Sequence[str] = DEFAULT_RELOCATE, motion: ArrayLike | None = None,
             level: Sequence[str] = DEFAULT_LEVEL) -> RetargetedCharacter:
    """Bind ``character`` to the mocap skeleton ``mocap`` (identity rest rotations, e.g. from a BVH file).

    ``end_sites``: mocap End Site offsets per leaf joint (they give the direction of the last bones);
    ``name_map``: mocap -> rig joint names where they differ (default :data:`CMU_TO_RIG`); ``relocate``: mocap
    joints with a zero-length bone to their parent whose mesh keeps its parent's orientation; the joint itself is
    moved instead so that its child bone gets the mocap's direction while the child stays where the mesh has it
    (joints of ``relocate`` without such a bone are bound as the others); ``motion``: ``(F, J, 4)`` local rotations
    of the take that will play on it (w, x, y, z).  Given the take, the pelvis is bound as the take holds it, not as
    the rig's rest pose happens to: the root by its mean hip line and up direction (:func:`_symmetric_root`), the
    hip joints of ``relocate`` at their mean turn against it; so the same world motion on rigs with other rest
    poses binds the same pelvis, and the joints the character places from it (CMU's zero-length hip joints and
    lower back) land in the same places (issue 35); the joints of ``level`` without a bone of their own are bound
    level over the take (their mean up direction onto the mesh's).
    """
    name_map = dict(CMU_TO_RIG if name_map is None else name_map)
    if not np.allclose(mocap.rest_rotations, identity((mocap.n_joints,))):
        raise ValueError("retargeting expects a mocap skeleton with identity rest rotations (as read from BVH)")
    rig_index = _rig_index(character, mocap, name_map)
    heads = character.heads[rig_index]
    zero = np.linalg.norm(mocap.offsets, axis=1) < 1e-9
    q_bind = identity((mocap.n_joints,))  # mocap rest frame -> A-pose frame, per joint
    frames = world = None
    if motion is not None:
        frames = _frames(motion)
        world, positions = mocap.forward_kinematics(frames)
        # The pelvis as the take holds it, facing along its own sagittal plane, not as the rig's rest pose happens
        # to (with it, the zero-length CMU hip joints and lower back are placed; :func:`mirror_bind`).
        q_bind[0] = _symmetric_root(mocap, world, positions)
    p_bind, bones = _bind_joints(mocap, end_sites, heads, character.tails[rig_index], zero, q_bind, relocate, level,
                                 frames, world)
    offsets = _bound_offsets(mocap, heads, zero, q_bind, p_bind)
    skeleton = Skeleton(mocap.names, mocap.parents, offsets)

    mesh = bind_mesh(character, mocap.names, q_bind, p_bind, name_map)

    root_scale = _leg_ratio(mocap, offsets)
    contact = p_bind[:, 1] - character.sole_height
    return RetargetedCharacter(skeleton, mesh, character.faces, q_bind, p_bind, root_scale, contact, bones)


def _rig_index(character: Character, mocap: Skeleton, name_map: Mapping[str, str]) -> NDArray[np.intp]:
    """The character's joint ``(J,)`` for each mocap joint, checked to form the same hierarchy."""
    try:
        rig_index = np.array([character.index(name_map.get(n, n)) for n in mocap.names])
    except ValueError:
        missing = [n for n in mocap.names if name_map.get(n, n) not in character.names]
        raise CharacterError(f"the character has no joints for mocap joints {missing}") from None
    rig_parents = character.parents[rig_index]
    expected = np.where(mocap.parents >= 0, rig_index[np.maximum(mocap.parents, 0)], -1)
    if not np.array_equal(rig_parents, expected):
        raise CharacterError("the character's joint hierarchy differs from the mocap skeleton's")
    return rig_index


def _bind_joints(mocap: Skeleton, end_sites: Mapping[int, Array], heads: Array, tails: Array, zero: NDArray[np.bool_],
                 q_bind: Array, relocate: Sequence[str], level: Sequence[str], frames: Array | None,
                 world: Array | None) -> tuple[Array, dict[int, Array]]:
    """Bind every joint down the tree: ``q_bind`` ``(J, 4)`` filled in place (its root already, given the take
    ``frames``, with ``world`` its forward kinematics); returns the bind positions ``(J, 3)`` and the joints bound
    by a bone with its mocap rest direction (see :func:`retarget`)."""
    children = [mocap.children(j) for j in range(mocap.n_joints)]
    p_bind = heads.copy()
    bones: dict[int, Array] = {}  # joints bound by a bone: its mocap rest direction
    for j in range(mocap.n_joints):  # once per skeleton
        p = mocap.parents[j]
        if p < 0 and frames is not None:
            continue  # bound above
        q_parent = q_bind[p] if p >= 0 else identity()
        # The bone that orients this joint's segment: its (single) child with a mocap direction, or its End Site.
        # (A bone the mesh's rig has no length for, e.g. a palm bone of another rig, says nothing either.)
        defining = [c for c in children[j] if not zero[c] and np.linalg.norm(heads[c] - heads[j]) > 1e-9]
        if defining:
            c = max(defining, key=lambda c: np.linalg.norm(mocap.offsets[c]))
            mocap_dir, rig_vec = mocap.offsets[c], heads[c] - heads[j]
        elif j in end_sites and np.linalg.norm(end_sites[j]) > 1e-9:
            mocap_dir, rig_vec = np.asarray(end_sites[j], np.float64), tails[j] - heads[j]
        else:
            mocap_dir = rig_vec = None
        # Only a joint with a zero-length bone to its parent and a child bone can move instead of turning its mesh
        # (the CMU pelvis); on rigs built otherwise (Mixamo: thighs straight under the hips) it is bound as usual.
        if mocap.names[j] in relocate and zero[j] and defining and p >= 0:
            # As the take holds it on average, not as the rig's rest pose happens to (CMU hip joints turn against
            # the pelvis: a rest pose taken from a frame of the take would make the pelvis lopsided).
            q_bind[j] = q_parent if frames is None else quat_mul(q_parent, _chordal_mean(frames[:, j]))
            direction = rotate(q_bind[j], mocap_dir / np.linalg.norm(mocap_dir))
            p_bind[j] = heads[c] - np.linalg.norm(rig_vec) * direction
        elif mocap_dir is not None:
            q_bind[j] = quat_mul(_arc(rotate(q_parent, mocap_dir), rig_vec), q_parent)
            bones[j] = np.asarray(mocap_dir, np.float64)
        elif mocap.names[j] in level and world is not None:
            # A head without a bone of its own (an End Site at the joint: the Bandai Namco rigs) says nothing of
            # where the face points.  Bound as the rest pose holds it on its neck, it tilts with whatever the rest
            # pose's neck does against the character's (the Bandai walk: the face turned up to the sky); so it is
            # bound level instead: the world's up, averaged over the take in its frame, onto the mesh's up.
            up = rotate(quat_conj(world[:, j]), np.array([0.0, 1.0, 0.0])).mean(axis=0)
            q_bind[j] = quat_mul(_arc(rotate(q_parent, up), np.array([0.0, 1.0, 0.0])), q_parent)
        else:
            q_bind[j] = q_parent
    return p_bind, bones


def _bound_offsets(mocap: Skeleton, heads: Array, zero: NDArray[np.bool_], q_bind: Array, p_bind: Array) -> Array:
    """Offsets ``(J, 3)`` of the bound skeleton: the mocap's bone directions at the character's bone lengths; a
    zero-length mocap bone where the bind put the joint (in its parent's bind frame)."""
    offsets = np.zeros((mocap.n_joints, 3))
    for j in range(1, mocap.n_joints):
        p = mocap.parents[j]
        if zero[j]:
            offsets[j] = rotate(quat_conj(q_bind[p]), p_bind[j] - p_bind[p])
        else:
            length = np.linalg.norm(heads[j] - heads[p])
            offsets[j] = mocap.offsets[j] / np.linalg.norm(mocap.offsets[j]) * length
    return offsets


def _leg_ratio(mocap: Skeleton, offsets: Array) -> float:
    """The character's leg length (thigh + shin, both sides) over the mocap's: the scale of the root's motion."""
    leg = ("LeftUpLeg", "LeftLeg", "LeftFoot", "RightUpLeg", "RightLeg", "RightFoot")
    try:
        chain = [mocap.index(name) for name in leg]
    except KeyError as exc:
        raise CharacterError(f"cannot scale the root: {exc}") from None
    mocap_leg = sum(np.linalg.norm(mocap.offsets[j]) for k, j in enumerate(chain) if k % 3)
    character_leg = sum(np.linalg.norm(offsets[j]) for k, j in enumerate(chain) if k % 3)
    return character_leg / mocap_leg


def _symmetric_root(skeleton: Skeleton, world: Array, positions: Array) -> Array:
    """The root's symmetric frame (quaternion, rest frame -> A-pose frame) from poses ``world``/``positions``
    (``(F, J, 4)``/``(F, J, 3)``): the mean line from the right thigh's head to the left's in the root's frame turned
    onto +x exactly, the mean up direction as near +y as that leaves; for a skeleton without two thighs apart (the
    gate refuses stacked ones), the root's mean orientation."""
    inverse = quat_conj(world[:, 0])
    up = rotate(inverse, np.array([0.0, 1.0, 0.0])).mean(axis=0)
    try:
        left, right = skeleton.index("LeftUpLeg"), skeleton.index("RightUpLeg")
    except KeyError:
        return _chordal_mean(world[:, 0])
    across = rotate(inverse, positions[:, left] - positions[:, right]).mean(axis=0)
    if min(np.linalg.norm(across), np.linalg.norm(up)) < 1e-9 or np.linalg.norm(
            np.cross(across / np.linalg.norm(across), up / np.linalg.norm(up))) < 1e-3:
        return _chordal_mean(world[:, 0])
    fit, _ = Rotation.align_vectors(np.eye(3)[:2], np.stack([across / np.linalg.norm(across),
                                                             up / np.linalg.norm(up)]), weights=[np.inf, 1.0])
    return fit.as_quat(scalar_first=True)


def _chordal_mean(q: Array) -> Array:
    """The mean rotation of quaternions ``(N, 4)`` (w, x, y, z): scipy's chordal mean (Markley et al. 2007; sign-free,
    so ``q`` and ``-q`` count alike)."""
    return Rotation.from_quat(q, scalar_first=True).mean().as_quat(scalar_first=True)


def _frames(motion: ArrayLike) -> Array:
    """A few hundred frames of ``motion``, evenly spaced: enough to fix the means below to well under 0.1 degree."""
    rot = np.asarray(motion, dtype=np.float64)
    return rot[:: max(1, len(rot) // 256)]


def mirror_bind(skeleton: Skeleton, bind: Array, bones: Mapping[int, Array], motion: ArrayLike) -> Array:
    """The bind ``bind`` (``(J, 4)``, rest frame -> A-pose frame per joint of ``skeleton``) with what the mocap rig's
    rest pose put into it taken out, from the clip ``motion`` (``(F, J, 4)`` local rotations, the root's in the frame
    whose plane ``x = 0`` it is mirrored through): the pose a gait is mirrored about
    (:class:`anim_core.rig.mirror.Mirror`).  ``bones``: the joints ``bind`` turns by a bone, each with that bone's
    rest direction (:attr:`RetargetedCharacter.bones`).

    Which way each bone's mesh is twisted about the bone is not in the bone directions, and what a rig's rest pose
    says about it (and about joints without a bone of their own: the CMU root, hip joints and chest) is an accident
    of that rig: mirrored about such a bind, a gait's mirrored keys carry the rest pose's twists, and the frames
    between the keys differ from rig to rig.  Here every joint is set from the clip alone, parents first:

    * the root: its line from the right thigh's head to the left's, averaged over the clip in the root's frame, along
      the A-pose's left (+x), and the up direction as near the A-pose's as that leaves (:func:`_symmetric_root`, as
      :func:`retarget` binds it when given the take); the pelvis's own sagittal plane is then the plane a gait is
      mirrored through.  Bound otherwise (at its mean orientation, or as a rest pose turned against the pelvis
      has it), the root is mirrored about a turned plane and the joints below it make up the difference at the
      keys but not between them (measured: the Bandai run's hybrid 0 28.3 degrees from its reference, p95,
      against 25.4; its walk's 49.9 against 42.5);
    * a joint bound by a bone: turned about the bone so that its twist relative to its parent is zero on average (a
      circular mean, each frame weighted by how far the bone is from pointing against its bind direction, where the
      twist is least defined); only the twist changes, so the bone still points where the mocap's does;
    * any other (a hip joint the character moves instead of turning, a joint without a bone): turned so that its
      rotation relative to its parent is the identity on average (the chordal mean).

    A rig's rest pose and joint frames change every local rotation of the clip by constant rotations on either side,
    and each of these means follows such a change, so the result is the same on every rig of the same world motion
    (tests/test_mirror_on_the_character.py: to 1e-6 degrees in every bone of the hybrid, at and between the keys).
    The mesh stays bound by ``bind``: for a left/right-symmetric gait the two differ by left/right-symmetric turns,
    which a mirror carries over unchanged.
    """
    world, positions = skeleton.forward_kinematics(_frames(motion))
    out = np.asarray(bind, dtype=np.float64).copy()
    out[0] = _symmetric_root(skeleton, world, positions)
    for j in range(1, skeleton.n_joints):
        p = skeleton.parents[j]
        parent_mesh = quat_mul(world[:, p], quat_conj(out[p]))
        local = quat_mul(quat_conj(parent_mesh), quat_mul(world[:, j], quat_conj(out[j])))
        if j in bones:
            bone = rotate(out[j], bones[j] / np.linalg.norm(bones[j]))
            now = rotate(local, bone)
            twist = quat_mul(quat_conj(quat_between(bone, now)), local)
            angle = 2.0 * np.arctan2(twist[:, 1:] @ bone, twist[:, 0])
            weight = 1.0 + now @ bone
            mean = quat_from_axis_angle(bone, np.arctan2(weight @ np.sin(angle), weight @ np.cos(angle)))
        else:
            mean = _chordal_mean(local)
        out[j] = quat_mul(mean, out[j])
    return out
