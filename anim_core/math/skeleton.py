"""Skeletons and batched forward kinematics.

A pose is given by **local joint rotations** ``(..., J, 4)`` (unit quaternions ``(w, x, y, z)``, each relative
to the parent joint's frame) and a **root translation** ``(..., 3)``.  Forward kinematics gives the global
(model-space) rotation and position of every joint:

    R_j = R_parent(j) * L_j
    p_j = p_parent(j) + rotate(R_parent(j), offset_j)        (root: p_0 = offset_0 + root_translation)

Lengths are in the units of the skeleton's offsets (the source's units; BVH files of CMU use CMU units).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .quat import identity, quat_mul, rotate

Array = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class Skeleton:
    """Joint hierarchy with rest (bind) pose.

    ``names``: joint names ``(J,)``; ``parents``: parent index per joint, ``-1`` for the root, every parent before
    its children (topological order); ``offsets``: ``(J, 3)`` position of each joint in its parent's frame (for
    the root: its rest position); ``rest_rotations``: ``(J, 4)`` local rotations of the rest pose (identity for
    BVH skeletons, whose joint frames are aligned with the world at rest).
    """

    names: tuple[str, ...]
    parents: NDArray[np.intp]
    offsets: Array
    rest_rotations: Array = field(default=None)  # type: ignore[assignment]
    _levels: tuple[tuple[NDArray[np.intp], NDArray[np.intp]], ...] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        names = tuple(self.names)
        parents = np.asarray(self.parents, dtype=np.intp)
        offsets = np.asarray(self.offsets, dtype=np.float64)
        n = len(names)
        if parents.shape != (n,) or offsets.shape != (n, 3):
            raise ValueError(f"skeleton of {n} joints needs parents ({n},) and offsets ({n}, 3), "
                             f"got {parents.shape} and {offsets.shape}")
        if len(set(names)) != n:
            raise ValueError("joint names must be unique")
        if n == 0 or parents[0] != -1 or np.any(parents[1:] < 0) or np.any(parents[1:] >= np.arange(1, n)):
            raise ValueError("joints must be in topological order: joint 0 is the only root and every parent "
                             "index is smaller than its child's")
        rest = identity((n,)) if self.rest_rotations is None else np.asarray(self.rest_rotations, np.float64)
        if rest.shape != (n, 4):
            raise ValueError(f"rest_rotations must have shape ({n}, 4), got {rest.shape}")
        depth = np.zeros(n, dtype=np.intp)
        for j in range(1, n):  # once per skeleton, not per frame
            depth[j] = depth[parents[j]] + 1
        levels = tuple(
            (np.flatnonzero(depth == d), parents[depth == d]) for d in range(1, int(depth.max()) + 1)
        )
        for name, value in (("names", names), ("parents", parents), ("offsets", offsets),
                            ("rest_rotations", rest), ("_levels", levels)):
            object.__setattr__(self, name, value)
        parents.flags.writeable = False
        offsets.flags.writeable = False
        rest.flags.writeable = False

    @property
    def n_joints(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        """Index of the joint called ``name`` (``KeyError`` listing the joints if there is none)."""
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"no joint named {name!r}; joints are {', '.join(self.names)}") from None

    def indices(self, names: Sequence[str]) -> NDArray[np.intp]:
        return np.array([self.index(n) for n in names], dtype=np.intp)

    def children(self, j: int) -> list[int]:
        return [int(c) for c in np.flatnonzero(self.parents == j)]

    def rest_pose(self) -> tuple[Array, Array]:
        """Local rotations ``(J, 4)`` and root translation ``(3,)`` of the rest pose."""
        return self.rest_rotations.copy(), np.zeros(3)

    def forward_kinematics(self, local_rotations: ArrayLike, root_translation: ArrayLike | None = None
                           ) -> tuple[Array, Array]:
        """Global rotations ``(..., J, 4)`` and positions ``(..., J, 3)`` of a batch of poses.

        ``local_rotations``: ``(..., J, 4)``; ``root_translation``: ``(..., 3)`` or ``None`` (zero).  Vectorized over
        the batch and over all joints of the same depth: the Python loop runs once per depth level (about 10
        for a humanoid), never per joint or per character.
        """
        local = np.asarray(local_rotations, dtype=np.float64)
        if local.shape[-2:] != (self.n_joints, 4):
            raise ValueError(f"expected local rotations (..., {self.n_joints}, 4), got {local.shape}")
        batch = local.shape[:-2]
        g_rot = np.empty_like(local)
        g_pos = np.empty((*batch, self.n_joints, 3))
        g_rot[..., 0, :] = local[..., 0, :]
        g_pos[..., 0, :] = self.offsets[0]
        if root_translation is not None:
            g_pos[..., 0, :] += np.asarray(root_translation, dtype=np.float64)
        for joints, parents in self._levels:
            pr = g_rot[..., parents, :]
            g_rot[..., joints, :] = quat_mul(pr, local[..., joints, :])
            g_pos[..., joints, :] = g_pos[..., parents, :] + rotate(pr, self.offsets[joints])
        return g_rot, g_pos

    def rest_global(self) -> tuple[Array, Array]:
        """Global rotations ``(J, 4)`` and positions ``(J, 3)`` of the rest pose."""
        return self.forward_kinematics(self.rest_rotations)
