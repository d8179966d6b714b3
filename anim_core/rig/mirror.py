"""Left/right mirroring of poses.

A mirrored pose is the reflection of the original through a plane (for a humanoid: its sagittal plane).  The
reflection ``M = I - 2 n n^T`` (unit normal ``n``) maps a rotation ``R`` to ``M R M``; for a quaternion
``(w, v)`` that is ``(w, -M v)`` — with ``n = x`` it keeps the x component and negates y and z ("negate two of
the three axes").  Left and right joints then swap their values; joints without a partner (hips, spine, neck)
keep their own, mirrored.

Local rotations are only comparable across left and right after a **left/right-symmetric pose is removed**: each
local rotation ``L_j`` is first expressed as the world-aligned rotation ``A_j = B_p L_j B_j^-1`` (``B`` the global
rotations that put the skeleton in that symmetric pose, ``p`` the parent), which is the identity in that pose whatever
the rig's joint frames are; ``A`` is mirrored and swapped, then the symmetric pose is put back.  Skipping that step
on a rig whose joint frames are not world-aligned turns limbs around (the thesis saw the model turn by 180
degrees).

Which symmetric pose: a character's **bind pose** (its mesh as authored, left and right symmetric by
construction), given as ``bind``; then ``A_j`` is the rotation that joint's mesh has turned through, and the mirrored
pose is the mirror image of the mesh participants see.  Only when no bind pose is given is the skeleton's rest pose
used (``B = G0``, the global rest rotations), which is right only if that rest pose is itself symmetric: CMU's
T-pose is; a rig whose rest is a frame of the motion (a stride, one shin 38 degrees from the other's mirror image)
is not, and mirroring about it puts that asymmetry into every mirrored pose (issue 35: feet that never land).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..math.clip import Pose
from ..math.quat import identity, quat_conj, quat_mul
from ..math.skeleton import Skeleton
from .names import partner_name, split_side

Array = NDArray[np.float64]

def mirror_partners(names: Sequence[str], overrides: Mapping[str, str] | None = None) -> NDArray[np.intp]:
    """Index of each joint's left/right partner (its own index for central joints), shape ``(J,)``.

    Partners are found from the names as :func:`anim_core.rig.names.split_side` reads them: the same name with the
    other side marker (``LeftArm``/``RightArm``, ``mixamorig:LeftArm``, ``LHipJoint``/``RHipJoint``, ``lShin``/
    ``rShin``, ``L_Hip``/``R_Hip``, ``hand.L``/``hand.R``, ``foot_l``/``foot_r``, ``ThighLeft``/``ThighRight``);
    ``overrides`` maps names to partners explicitly (both directions are set) and wins over the names.  A name
    with a word or separated side marker (``Left``, ``_L``, ``L_``) but no partner raises ``ValueError``; one with
    only a glued letter (``LOD``) without a partner is central.
    """
    index = {n: i for i, n in enumerate(names)}
    perm = np.arange(len(names), dtype=np.intp)
    explicit: dict[str, str] = {}
    for a, b in (overrides or {}).items():
        for n in (a, b):
            if n not in index:
                raise ValueError(f"mirror override names unknown joint {n!r}")
        explicit[a], explicit[b] = b, a
    for i, name in enumerate(names):
        if name in explicit:
            perm[i] = index[explicit[name]]
            continue
        partner = partner_name(name)
        if partner is None:
            continue
        if partner in index:
            perm[i] = index[partner]
        elif split_side(name).strong:
            raise ValueError(f"joint {name!r} looks sided but has no partner {partner!r}; give the pair explicitly")
    if not np.array_equal(perm[perm], np.arange(len(names))):
        raise ValueError("mirror partners are not symmetric")
    return perm


@dataclass(frozen=True, eq=False)
class Mirror:
    """Mirrors poses of one skeleton through the plane ``dot(n, p) = offset`` (unit normal ``n``, world axes).

    ``bind``: ``(J, 4)`` global rotations (w, x, y, z) that put the skeleton in a left/right-symmetric pose (a
    character's bind pose, :attr:`anim_core.rig.character.RetargetedCharacter.bind_rotations`); default: the
    skeleton's rest rotations, which must then be symmetric.  Everything that depends only on the skeleton and
    that pose (partners, pose rotations) is computed once here.
    """

    skeleton: Skeleton
    normal: Array = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))
    offset: float = 0.0
    overrides: Mapping[str, str] | None = None
    bind: ArrayLike | None = field(default=None, repr=False)
    partners: NDArray[np.intp] = field(init=False, repr=False)
    _bind: Array = field(init=False, repr=False)
    _bind_parent: Array = field(init=False, repr=False)

    def __post_init__(self) -> None:
        n = np.asarray(self.normal, dtype=np.float64)
        if n.shape != (3,) or not np.linalg.norm(n) > 0:
            raise ValueError(f"mirror plane normal must be a non-zero 3-vector, got {self.normal!r}")
        if self.bind is None:
            bind, _ = self.skeleton.rest_global()
        else:
            bind = np.asarray(self.bind, dtype=np.float64)
            if bind.shape != (self.skeleton.n_joints, 4) or not np.all(np.isfinite(bind)):
                raise ValueError(f"bind must hold one finite quaternion per joint, shape ({self.skeleton.n_joints}, "
                                 f"4), got {bind.shape}")
        parents = self.skeleton.parents
        bind_parent = np.where((parents >= 0)[:, None], bind[np.maximum(parents, 0)], identity((len(parents),)))
        for name, value in (("normal", n / np.linalg.norm(n)),
                            ("partners", mirror_partners(self.skeleton.names, self.overrides)),
                            ("_bind", bind), ("_bind_parent", bind_parent)):
            object.__setattr__(self, name, value)

    def with_offset(self, offset: float) -> Mirror:
        """The same mirror through a parallel plane ``dot(n, p) = offset``."""
        return Mirror(self.skeleton, self.normal, offset, self.overrides, self._bind)

    def reflect_rotations(self, q: ArrayLike) -> Array:
        """``M R M`` for quaternions ``(..., 4)``: ``(w, v) -> (w, -v + 2 (v . n) n)``."""
        q = np.asarray(q, dtype=np.float64)
        v = q[..., 1:]
        vn = np.sum(v * self.normal, axis=-1, keepdims=True)
        return np.concatenate([q[..., :1], -v + 2.0 * vn * self.normal], axis=-1)

    def reflect_points(self, p: ArrayLike) -> Array:
        """Reflect points ``(..., 3)`` through the plane."""
        p = np.asarray(p, dtype=np.float64)
        d = np.sum(p * self.normal, axis=-1, keepdims=True) - self.offset
        return p - 2.0 * d * self.normal

    def __call__(self, pose: Pose) -> Pose:
        """Mirror a batch of poses: rotations ``(..., J, 4)``, root translation ``(..., 3)``."""
        rot = np.asarray(pose.rotations, dtype=np.float64)
        aligned = quat_mul(quat_mul(self._bind_parent, rot), quat_conj(self._bind))
        swapped = self.reflect_rotations(aligned)[..., self.partners, :]
        local = quat_mul(quat_mul(quat_conj(self._bind_parent), swapped), self._bind)
        root0 = self.skeleton.offsets[0]
        root = self.reflect_points(np.asarray(pose.root_translation, dtype=np.float64) + root0) - root0
        return Pose(local, root)
