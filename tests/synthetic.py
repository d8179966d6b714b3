"""Small synthetic skeletons, clips and meshes built by the tests themselves."""

from __future__ import annotations

import numpy as np

from anim_core.math import quat as Q
from anim_core.math.skeleton import Skeleton

# A 9-joint biped: hips, a spine chain and two 3-joint legs, Y up, X to the character's left, Z forward.
BIPED_NAMES = ("Hips", "Spine", "Head", "LeftUpLeg", "LeftLeg", "LeftFoot", "RightUpLeg", "RightLeg", "RightFoot")
BIPED_PARENTS = (-1, 0, 1, 0, 3, 4, 0, 6, 7)
BIPED_OFFSETS = np.array([
    [0.0, 1.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.4, 0.0],
    [0.1, -0.05, 0.0], [0.0, -0.45, 0.0], [0.0, -0.45, 0.0],
    [-0.1, -0.05, 0.0], [0.0, -0.45, 0.0], [0.0, -0.45, 0.0],
])


def biped(rest_rotations: np.ndarray | None = None) -> Skeleton:
    return Skeleton(BIPED_NAMES, BIPED_PARENTS, BIPED_OFFSETS, rest_rotations)


def random_tree_skeleton(rng: np.random.Generator, n_joints: int) -> Skeleton:
    """A random tree in topological order with random offsets and rest rotations."""
    parents = [-1] + [int(rng.integers(0, j)) for j in range(1, n_joints)]
    rest = Q.quat_normalize(rng.normal(size=(n_joints, 4)))
    return Skeleton(tuple(f"j{i}" for i in range(n_joints)), parents, rng.normal(size=(n_joints, 3)), rest)


def random_rotations(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    return Q.quat_normalize(rng.normal(size=(*shape, 4)))
