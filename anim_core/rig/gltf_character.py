"""A skinned glTF character (:class:`~anim_core.io.gltf.GltfAsset`) as the :class:`~anim_core.rig.character.Character`
the pipeline drives: its skeleton mapped onto the canonical CMU skeleton, metres, Y up, facing +Z, left at +X.

Nothing here opens a file (``server.assets`` finds and reads it); every failure is a
:class:`~anim_core.rig.character.CharacterError` whose message starts with the asset's file name.

- **Bind pose.**  The mesh is authored in its bind pose, so the joints' positions are those of their bind
  transforms (the inverses of the inverse bind matrices), not the nodes' rest pose; the two may differ.
- **Mapping.**  :func:`~anim_core.rig.rigmap.map_skeleton` maps the skin's joints (at the bind pose) onto the 31
  canonical
  joints; an explicit ``{canonical: source}`` mapping overrides or completes it.  A skeleton without hips, spine,
  head, legs or arms is an error naming the missing parts.
- **Units and up axis**: detected from the mesh's height (its bounding box along up; the joints' extent where
  the mesh is no human height in any unit) and the head-over-hips axis
  (:func:`~anim_core.rig.normalize.canonical_frame`), or given; the character is turned (quarter turns) so its left
  is +X.
- **Joints the canonical skeleton has and the rig lacks** (``LHipJoint``, ``LowerBack``, finger bases, ...) are
  placed where the CMU skeleton has them: on their parent for those with a zero offset there (:data:`ON_PARENT`),
  else evenly on the segment between their mapped neighbours (a missing leaf: towards the parent's tail, see
  below); nothing is weighted to them.
- **Leaf joints' tails** (their bone direction, which the mocap's End Sites give): the farthest child joint of the
  mapped source joint (``HeadTop_End``, ``LeftToe_End``, the next finger joint); for a joint without children,
  the farthest vertex whose largest weight is on it (the top of the head, the tip of the toes); for one without
  either, its parent's bone continued by half that bone's length.
- **Skin weights** of joints that map to nothing (helpers, twist bones, fingers beyond the canonical ones, joints
  above the hips) fold into their nearest mapped ancestor (the hips for joints above them); influences on the same
  canonical joint are summed, at most 8 per vertex remain, renormalized.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..io.gltf import GltfAsset
from ..math.quat import rotate
from ..math.skeleton import Skeleton
from ..math.skinning import MAX_INFLUENCES
from .character import CMU_TO_RIG, Character, CharacterError
from .normalize import canonical_frame, units_from_height
from .rigmap import CANONICAL_NAMES, CANONICAL_PARENTS, UNITS, RigMapError, RigMapping, map_skeleton

Array = NDArray[np.float64]

#: The character's joint names: the canonical ones, spelt as the MakeHuman rig spells them (what
#: :func:`~anim_core.rig.character.retarget` and :func:`~anim_core.rig.character.bind_mesh` look up by default).
RIG_NAMES: tuple[str, ...] = tuple(CMU_TO_RIG.get(n, n) for n in CANONICAL_NAMES)
#: Joints that sit on their parent in the CMU skeleton (zero offset; the bone below them carries the length): a rig
#: without them gets them there, as the motion has them.
ON_PARENT = frozenset(("LHipJoint", "RHipJoint", "LowerBack", "Neck", "LeftShoulder", "RightShoulder",
                       "LeftFingerBase", "RightFingerBase", "LThumb", "RThumb"))
LEAF_EXTENSION = 0.5  # a childless leaf's bone: this share of its parent bone's length, continuing it


@dataclass(frozen=True, eq=False)
class MappedCharacter:
    """A glTF character as the pipeline's :class:`Character` and how it was made: the ``mapping`` (source joint
    per canonical joint, with reasons), ``units``/``up_axis`` (detected or given), ``metres_per_unit`` and
    ``folded`` (``{source joint: canonical joint}`` for each unmapped joint whose weights went to that joint)."""

    character: Character
    mapping: RigMapping
    units: str
    up_axis: str
    metres_per_unit: float
    folded: dict[str, str]


def _bind_positions(asset: GltfAsset) -> Array:
    """``(J, 3)`` joint positions of the bind pose: translations of the inverse bind matrices' inverses."""
    ibm = np.asarray(asset.inverse_bind, np.float64)
    if not np.all(np.isfinite(ibm)):
        raise CharacterError(f"{asset.source}: its inverse bind matrices hold NaN or infinite values")
    if np.abs(ibm[:, 3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-6:
        raise CharacterError(f"{asset.source}: an inverse bind matrix is not affine (last row is not 0 0 0 1)")
    det = np.linalg.det(ibm[:, :3, :3])
    if np.any(np.abs(det) < 1e-12):
        bad = asset.skeleton.names[int(np.argmin(np.abs(det)))]
        raise CharacterError(f"{asset.source}: the inverse bind matrix of joint {bad!r} is singular")
    return np.linalg.inv(ibm)[:, :3, 3]


def _mesh_units(asset: GltfAsset, bind: Array, source_index: NDArray[np.intp], up_axis: str | None) -> str | None:
    """The unit in which the mesh's height (bounding box along up) is a human height, or ``None`` (the joints'
    extent decides, :func:`~anim_core.rig.normalize.canonical_frame`): the mesh is the whole figure, head and feet
    included, where the joints stop short of both."""
    world = canonical_frame(bind, source_index, up_axis, "m")[0]
    try:
        return units_from_height(float(np.ptp(rotate(world, asset.vertices)[:, 1])), "skinned mesh")
    except RigMapError:
        return None


def _fill_missing(heads: Array, tails: Array, mapped: NDArray[np.bool_]) -> None:
    """Place canonical joints with no source joint (in place), down each chain of missing joints from its mapped
    ancestor: joints that sit on their parent in the CMU skeleton (:data:`ON_PARENT`) on the joint above, the
    others evenly on the segment to the mapped joint below them, or, for a chain ending in a leaf, to the
    ancestor's tail."""
    children = [np.flatnonzero(CANONICAL_PARENTS == c) for c in range(len(CANONICAL_NAMES))]
    for c in range(len(CANONICAL_NAMES)):  # 31 joints, once per character
        if mapped[c] or not mapped[CANONICAL_PARENTS[c]]:
            continue  # handled from the top of its missing chain
        a = int(CANONICAL_PARENTS[c])
        chain = [c]
        while len(children[chain[-1]]) == 1 and not mapped[children[chain[-1]][0]]:
            chain.append(int(children[chain[-1]][0]))
        below = children[chain[-1]]
        end = heads[below[0]] if len(below) else tails[a]
        on_parent = np.array([CANONICAL_NAMES[j] in ON_PARENT for j in chain])
        steps = np.cumsum(~on_parent)
        for j, k in zip(chain, steps, strict=True):
            heads[j] = heads[a] + (end - heads[a]) * k / (steps[-1] + 1)
        for j in chain:
            tails[j] = end if not len(children[j]) else heads[children[j][0]]
        mapped[chain] = True


def character_from_gltf(asset: GltfAsset, explicit: Mapping[str, str] | None = None, units: str | None = None,
                        up_axis: str | None = None) -> MappedCharacter:
    """The glTF character ``asset`` as the pipeline's character (see the module docstring).

    ``explicit``: ``{canonical joint: source joint}`` (e.g. from :func:`~anim_core.rig.rigmap.read_mapping_file`);
    ``units`` (a key of :data:`~anim_core.rig.rigmap.UNITS`) and ``up_axis`` (``"y"``/``"z"``) override the detection.
    The result's ``vertices`` are the asset's in the same order, converted; ``joints``/``weights`` ``(V, 8)``.
    """
    src = asset.source
    sk = asset.skeleton
    for what, values in (("vertices", asset.vertices), ("normals", asset.normals), ("skin weights", asset.weights),
                         ("joint offsets", sk.offsets), ("joint rotations", sk.rest_rotations)):
        if not np.all(np.isfinite(values)):
            raise CharacterError(f"{src}: its {what} hold NaN or infinite values")
    if asset.joints.shape[1] > MAX_INFLUENCES:
        raise CharacterError(f"{src}: {asset.joints.shape[1]} influences per vertex; at most {MAX_INFLUENCES} are "
                             f"supported")
    bind = _bind_positions(asset)
    offsets = bind.copy()
    offsets[1:] -= bind[sk.parents[1:]]
    try:
        mapping = map_skeleton(Skeleton(sk.names, sk.parents, offsets), explicit)
        world, up_axis, units, _ = canonical_frame(bind, mapping.source_index, up_axis, units or _mesh_units(
            asset, bind, mapping.source_index, up_axis))
    except RigMapError as exc:
        raise CharacterError(f"{src}: {exc}") from None
    scale = UNITS[units][0]
    pos = rotate(world, bind) * scale
    idx = mapping.source_index
    mapped = idx >= 0
    n = len(CANONICAL_NAMES)
    joints, weights, folded = _folded_weights(asset, idx)

    vertices = rotate(world, asset.vertices) * scale
    heads = np.where(mapped[:, None], pos[np.maximum(idx, 0)], 0.0)
    tails = _mapped_tails(sk, idx, pos, heads, vertices, joints[:, 0])
    _fill_missing(heads, tails, mapped.copy())
    short = [RIG_NAMES[c] for c in range(n) if np.linalg.norm(tails[c] - heads[c]) < 1e-9
             and not np.any(CANONICAL_PARENTS == c)]
    if short:
        raise CharacterError(f"{src}: the leaf joints {short} have no length (their parent joint is at the same "
                             f"place); give them a child joint (an end joint) where the bone ends")

    normals = rotate(world, asset.normals)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    character = Character(RIG_NAMES, CANONICAL_PARENTS.copy(), heads, tails, vertices, normals,
                          np.asarray(asset.faces, np.intp), joints.astype(np.intp), weights)
    return MappedCharacter(character, mapping, units, up_axis, scale, folded)


def _folded_weights(asset: GltfAsset, idx: NDArray[np.intp]) -> tuple[NDArray[np.intp], Array, dict[str, str]]:
    """Skin weights on the canonical joints (source joint per canonical joint ``idx``, -1 unmapped): every source
    joint's onto its nearest mapped ancestor (or itself), summed per vertex, the largest :data:`MAX_INFLUENCES`
    kept and renormalised: ``joints``, ``weights`` ``(V, 8)`` and ``{source joint: canonical joint}`` of each
    weighted source joint that went to an ancestor."""
    sk = asset.skeleton
    fold = np.zeros(sk.n_joints, dtype=np.intp)
    canonical_of = {int(j): c for c, j in enumerate(idx) if j >= 0}
    for j in range(sk.n_joints):  # topological order: parents first
        fold[j] = canonical_of.get(j, fold[sk.parents[j]] if sk.parents[j] >= 0 else 0)
    n_v = len(asset.vertices)
    dense = np.zeros((n_v, len(CANONICAL_NAMES)))
    np.add.at(dense, (np.repeat(np.arange(n_v), asset.joints.shape[1]), fold[asset.joints].ravel()),
              asset.weights.ravel())
    order = np.argsort(-dense, axis=1, kind="stable")[:, :MAX_INFLUENCES]
    weights = np.take_along_axis(dense, order, axis=1)
    totals = weights.sum(axis=1)
    if np.any(totals <= 0):
        raise CharacterError(f"{asset.source}: {int(np.sum(totals <= 0))} vertices have no skin weight")
    weights /= totals[:, None]
    joints = np.where(weights > 0, order, 0)
    weighted = np.unique(asset.joints[asset.weights > 0])
    folded = {sk.names[j]: RIG_NAMES[fold[j]] for j in weighted if j not in canonical_of}
    return joints, weights, folded


def _mapped_tails(sk: Skeleton, idx: NDArray[np.intp], pos: Array, heads: Array, vertices: Array,
                  dominant: NDArray[np.intp]) -> Array:
    """Tails ``(31, 3)`` of the mapped canonical joints (the others: their heads, for :func:`_fill_missing`): the
    farthest source child, else the farthest vertex whose largest weight (``dominant`` joint per vertex) is on the
    joint, else the parent bone continued; ``pos`` the source joints' positions, ``heads`` the canonical ones'."""
    mapped = idx >= 0
    tails = heads.copy()
    source_children = [np.flatnonzero(sk.parents == j) for j in range(sk.n_joints)]
    for c in range(len(CANONICAL_NAMES)):  # 31 joints, once per character
        if not mapped[c]:
            continue
        kids = source_children[idx[c]]
        own = vertices[dominant == c]
        if len(kids):
            tails[c] = pos[kids[np.argmax(np.linalg.norm(pos[kids] - heads[c], axis=1))]]
        elif len(own):
            tails[c] = own[np.argmax(np.linalg.norm(own - heads[c], axis=1))]
        elif c > 0:
            p = int(CANONICAL_PARENTS[c])
            while not mapped[p]:
                p = int(CANONICAL_PARENTS[p])
            tails[c] = heads[c] + LEAF_EXTENSION * (heads[c] - heads[p])
    return tails
