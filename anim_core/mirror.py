"""Left/right mirroring of poses.

A mirrored pose is the reflection of the original through a plane (for a humanoid: its sagittal plane).  The
reflection ``M = I - 2 n n^T`` (unit normal ``n``) maps a rotation ``R`` to ``M R M``; for a quaternion
``(w, v)`` that is ``(w, -M v)`` — with ``n = x`` it keeps the x component and negates y and z ("negate two of
the three axes").  Left and right joints then swap their values; joints without a partner (hips, spine, neck)
keep their own, mirrored.

Local rotations are only comparable across left and right after the **bind (rest) pose is removed**: each
local rotation ``L_j`` is first expressed as the world-aligned rotation ``A_j = G0_p L_j G0_j^-1`` (``G0`` the
global rest rotations, ``p`` the parent), which is the identity at rest whatever the rig's joint frames are;
``A`` is mirrored and swapped, then the rest pose is put back.  Skipping that step on a rig whose joint frames
are not world-aligned turns limbs around (the thesis saw the model turn by 180 degrees).  For BVH skeletons,
whose rest rotations are the identity, ``A = L``.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .clip import Pose
from .quat import identity, quat_conj, quat_mul
from .skeleton import Skeleton

Array = NDArray[np.float64]

# (pattern, replacement) pairs tried in order; each maps a left name to its right partner and back.
_SIDE_RULES: tuple[tuple[str, str], ...] = (
    (r"^Left(?=[A-Z_\d]|$)", "Right"), (r"^Right(?=[A-Z_\d]|$)", "Left"),
    (r"^left(?=[A-Z_\d]|$)", "right"), (r"^right(?=[A-Z_\d]|$)", "left"),
    (r"^L(?=[A-Z_\d])", "R"), (r"^R(?=[A-Z_\d])", "L"),
    (r"([._])L$", r"\1R"), (r"([._])R$", r"\1L"), (r"([._])l$", r"\1r"), (r"([._])r$", r"\1l"),
)


def mirror_partners(names: Sequence[str], overrides: Mapping[str, str] | None = None) -> NDArray[np.intp]:
    """Index of each joint's left/right partner (its own index for central joints), shape ``(J,)``.

    Partners are found from the names (``LeftArm``/``RightArm``, ``LHipJoint``/``RHipJoint``, ``hand.L``/
    ``hand.R``, ``foot_l``/``foot_r``); ``overrides`` maps names to partners explicitly (both directions are set)
    and wins over the rules.  A name that looks sided but has no partner raises ``ValueError``.
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
        for pattern, repl in _SIDE_RULES:
            partner, hits = re.subn(pattern, repl, name)
            if hits:
                if partner not in index:
                    raise ValueError(f"joint {name!r} looks sided but has no partner {partner!r}; "
                                     f"give the pair explicitly")
                perm[i] = index[partner]
                break
    if not np.array_equal(perm[perm], np.arange(len(names))):
        raise ValueError("mirror partners are not symmetric")
    return perm


@dataclass(frozen=True, eq=False)
class Mirror:
    """Mirrors poses of one skeleton through the plane ``dot(n, p) = offset`` (unit normal ``n``, world axes).

    Everything that depends only on the skeleton (partners, rest rotations) is computed once here.
    """

    skeleton: Skeleton
    normal: Array = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))
    offset: float = 0.0
    overrides: Mapping[str, str] | None = None
    partners: NDArray[np.intp] = field(init=False, repr=False)
    _rest: Array = field(init=False, repr=False)
    _rest_parent: Array = field(init=False, repr=False)

    def __post_init__(self) -> None:
        n = np.asarray(self.normal, dtype=np.float64)
        if n.shape != (3,) or not np.linalg.norm(n) > 0:
            raise ValueError(f"mirror plane normal must be a non-zero 3-vector, got {self.normal!r}")
        rest, _ = self.skeleton.rest_global()
        parents = self.skeleton.parents
        rest_parent = np.where((parents >= 0)[:, None], rest[np.maximum(parents, 0)], identity((len(parents),)))
        for name, value in (("normal", n / np.linalg.norm(n)),
                            ("partners", mirror_partners(self.skeleton.names, self.overrides)),
                            ("_rest", rest), ("_rest_parent", rest_parent)):
            object.__setattr__(self, name, value)

    def with_offset(self, offset: float) -> Mirror:
        """The same mirror through a parallel plane ``dot(n, p) = offset``."""
        return Mirror(self.skeleton, self.normal, offset, self.overrides)

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
        aligned = quat_mul(quat_mul(self._rest_parent, rot), quat_conj(self._rest))
        swapped = self.reflect_rotations(aligned)[..., self.partners, :]
        local = quat_mul(quat_mul(quat_conj(self._rest_parent), swapped), self._rest)
        root0 = self.skeleton.offsets[0]
        root = self.reflect_points(np.asarray(pose.root_translation, dtype=np.float64) + root0) - root0
        return Pose(local, root)
