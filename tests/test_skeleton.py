"""Forward kinematics: the batched implementation against a plain per-joint reference loop."""

import numpy as np
import pytest

from anim_core.math import quat as Q
from anim_core.math.skeleton import Skeleton
from tests.synthetic import biped, random_rotations, random_tree_skeleton


def reference_fk(skeleton, local, root):
    """One character, one joint at a time, with 4x4 matrices: deliberately the simplest possible code."""
    world = []
    for j in range(skeleton.n_joints):
        m = np.eye(4)
        m[:3, :3] = Q.matrix_from_quat(local[j])
        m[:3, 3] = skeleton.offsets[j] + (root if j == 0 else 0.0)
        world.append(m if skeleton.parents[j] < 0 else world[skeleton.parents[j]] @ m)
    world = np.array(world)
    return world[:, :3, :3], world[:, :3, 3]


def test_batched_fk_equals_reference_loop(rng):
    skeleton = random_tree_skeleton(rng, 31)
    local = random_rotations(rng, (7, 5, 31))  # a (7, 5) batch of characters
    root = rng.normal(size=(7, 5, 3))
    g_rot, g_pos = skeleton.forward_kinematics(local, root)
    assert g_rot.shape == (7, 5, 31, 4) and g_pos.shape == (7, 5, 31, 3)
    for idx in [(0, 0), (3, 2), (6, 4)]:
        ref_m, ref_p = reference_fk(skeleton, local[idx], root[idx])
        np.testing.assert_allclose(Q.matrix_from_quat(g_rot[idx]), ref_m, atol=1e-12)
        np.testing.assert_allclose(g_pos[idx], ref_p, atol=1e-12)


def test_rest_pose_of_a_bvh_style_skeleton_sums_offsets():
    skeleton = biped()
    _, pos = skeleton.rest_global()
    np.testing.assert_allclose(pos[skeleton.index("LeftFoot")], [0.1, 1.0 - 0.05 - 0.9, 0.0], atol=1e-15)
    np.testing.assert_allclose(pos[skeleton.index("Head")], [0.0, 1.6, 0.0], atol=1e-15)


def test_skeleton_validation():
    with pytest.raises(ValueError, match="topological order"):
        Skeleton(("a", "b"), (-1, 1), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="unique"):
        Skeleton(("a", "a"), (-1, 0), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="offsets"):
        Skeleton(("a", "b"), (-1, 0), np.zeros((3, 3)))
    with pytest.raises(KeyError, match="no joint named 'Tail'"):
        biped().index("Tail")
    with pytest.raises(ValueError, match="expected local rotations"):
        biped().forward_kinematics(np.zeros((3, 4)))
