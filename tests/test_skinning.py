"""Linear blend skinning against a per-vertex reference loop."""

import numpy as np
import pytest

from anim_core.math import quat as Q
from anim_core.math.skinning import SkinnedMesh, invert_transforms, transforms
from tests.synthetic import random_rotations, random_tree_skeleton


def make_mesh(rng, skeleton, n_vertices=300, k=8):
    vertices = rng.normal(size=(n_vertices, 3))
    normals = rng.normal(size=(n_vertices, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    joints = np.stack([rng.choice(skeleton.n_joints, size=k, replace=False) for _ in range(n_vertices)])
    weights = rng.random((n_vertices, k)) ** 3
    weights[:20, 1:] = 0.0  # rigid vertices: one influence
    weights /= weights.sum(axis=1, keepdims=True)
    inverse_bind = invert_transforms(transforms(*skeleton.rest_global()))
    return SkinnedMesh(vertices, normals, joints, weights, inverse_bind)


def test_bind_pose_returns_the_mesh(rng):
    skeleton = random_tree_skeleton(rng, 31)
    mesh = make_mesh(rng, skeleton)
    pos, nrm = mesh.skin(mesh.skinning_matrices(*skeleton.rest_global()))
    np.testing.assert_allclose(pos, mesh.vertices, atol=1e-12)
    np.testing.assert_allclose(nrm, mesh.normals, atol=1e-12)


def test_batch_equals_per_vertex_reference(rng):
    skeleton = random_tree_skeleton(rng, 31)
    mesh = make_mesh(rng, skeleton)
    g_rot, g_pos = skeleton.forward_kinematics(random_rotations(rng, (3, 31)), rng.normal(size=(3, 3)))
    skin_m = mesh.skinning_matrices(g_rot, g_pos)
    pos, nrm = mesh.skin(skin_m)
    assert pos.shape == (3, 300, 3)
    for c in range(3):
        for v in range(0, 300, 7):
            ref = sum(w * (skin_m[c, j, :, :3] @ mesh.vertices[v] + skin_m[c, j, :, 3])
                      for j, w in zip(mesh.joints[v], mesh.weights[v], strict=True))
            np.testing.assert_allclose(pos[c, v], ref, atol=1e-12)
        # A rigid vertex's normal turns with its single joint.
        for v in range(20):
            expected = skin_m[c, mesh.joints[v, 0], :, :3] @ mesh.normals[v]
            np.testing.assert_allclose(nrm[c, v], expected, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=-1), 1.0, atol=1e-12)


def test_skinning_matrices_of_rigid_motion_move_every_vertex_rigidly(rng):
    skeleton = random_tree_skeleton(rng, 10)
    mesh = make_mesh(rng, skeleton, k=4)
    rest_rot, rest_pos = skeleton.rest_global()
    turn = Q.quat_from_axis_angle([0.0, 1.0, 0.0], 0.7)
    shift = np.array([1.0, 2.0, 3.0])
    pos, nrm = mesh.skin(mesh.skinning_matrices(Q.quat_mul(turn, rest_rot), Q.rotate(turn, rest_pos) + shift))
    np.testing.assert_allclose(pos, Q.rotate(turn, mesh.vertices) + shift, atol=1e-12)
    np.testing.assert_allclose(nrm, Q.rotate(turn, mesh.normals), atol=1e-12)


def test_invalid_skins_are_rejected(rng):
    skeleton = random_tree_skeleton(rng, 12)
    mesh = make_mesh(rng, skeleton, n_vertices=10, k=8)
    with pytest.raises(ValueError, match="at most 8 influences"):
        SkinnedMesh(mesh.vertices, mesh.normals, np.zeros((10, 9), int), np.full((10, 9), 1 / 9), mesh.inverse_bind)
    with pytest.raises(ValueError, match="sum to 1"):
        SkinnedMesh(mesh.vertices, mesh.normals, mesh.joints, mesh.weights * 0.5, mesh.inverse_bind)
    with pytest.raises(ValueError, match="joint indices"):
        SkinnedMesh(mesh.vertices, mesh.normals, mesh.joints + 12, mesh.weights, mesh.inverse_bind)
