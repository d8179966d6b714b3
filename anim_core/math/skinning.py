"""Linear blend skinning of positions and normals for a batch of characters.

``v' = sum_k w_k S_{j_k} v`` with skinning matrices ``S_j = W_j B_j^-1`` (``W_j`` the joint's current world
transform, ``B_j`` its world transform in the bind pose).  The influences (up to ``MAX_INFLUENCES`` per vertex)
are held as one sparse ``(V, J)`` weight matrix, so blending the matrices of a whole batch is one sparse
product instead of a ``(N, V, K, 3, 4)`` gather.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import sparse

from .quat import matrix_from_quat

Array = NDArray[np.float64]
MAX_INFLUENCES = 8


def vertex_normals(vertices: Array, faces: NDArray[np.intp]) -> Array:
    """Area-weighted unit vertex normals ``(V, 3)`` of a triangle mesh."""
    tri = vertices[faces]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2 * area
    normals = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(normals, faces[:, k], face_n)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-20)


def transforms(rotations: ArrayLike, positions: ArrayLike) -> Array:
    """Affine ``(..., 3, 4)`` matrices ``[R | p]`` from quaternions ``(..., 4)`` and positions ``(..., 3)``."""
    return np.concatenate([matrix_from_quat(rotations), np.asarray(positions, np.float64)[..., None]], axis=-1)


def invert_transforms(m: ArrayLike) -> Array:
    """Inverse of rigid ``(..., 3, 4)`` transforms (rotation part orthonormal)."""
    m = np.asarray(m, dtype=np.float64)
    rt = np.swapaxes(m[..., :3], -1, -2)
    return np.concatenate([rt, -rt @ m[..., 3:]], axis=-1)


def compose_transforms(a: ArrayLike, b: ArrayLike) -> Array:
    """``a @ b`` for affine ``(..., 3, 4)`` matrices."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return np.concatenate([a[..., :3] @ b[..., :3], a[..., :3] @ b[..., 3:] + a[..., 3:]], axis=-1)


@dataclass(frozen=True, eq=False)
class SkinnedMesh:
    """A mesh bound to a skeleton.

    ``vertices``: ``(V, 3)`` and ``normals``: ``(V, 3)`` in the bind pose; ``joints``: ``(V, K)`` joint indices and
    ``weights``: ``(V, K)`` weights (``K <= 8``; unused slots have weight 0; each row sums to 1);
    ``inverse_bind``: ``(J, 3, 4)`` inverse bind transforms, e.g. ``invert_transforms(transforms(*rest_global))``.
    """

    vertices: Array
    normals: Array
    joints: NDArray[np.intp]
    weights: Array
    inverse_bind: Array
    _w: sparse.csr_matrix = field(init=False, repr=False)

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices, np.float64)
        nv = v.shape[0]
        joints = np.asarray(self.joints)
        weights = np.asarray(self.weights, np.float64)
        inv_bind = np.asarray(self.inverse_bind, np.float64)
        if v.shape != (nv, 3) or np.shape(self.normals) != (nv, 3):
            raise ValueError(f"vertices and normals must both be ({nv}, 3)")
        if joints.shape != weights.shape or joints.ndim != 2 or joints.shape[0] != nv:
            raise ValueError(f"joints and weights must both be ({nv}, K), got {joints.shape} and {weights.shape}")
        if joints.shape[1] > MAX_INFLUENCES:
            raise ValueError(f"at most {MAX_INFLUENCES} influences per vertex, got {joints.shape[1]}")
        n_joints = inv_bind.shape[0]
        if inv_bind.shape != (n_joints, 3, 4):
            raise ValueError(f"inverse bind transforms must be (J, 3, 4), got {inv_bind.shape}")
        if np.any(weights < 0) or not np.allclose(weights.sum(axis=1), 1.0, atol=1e-6):
            bad = int(np.argmax(np.abs(weights.sum(axis=1) - 1.0)))
            raise ValueError(f"skin weights must be >= 0 and sum to 1 per vertex (vertex {bad} sums to "
                             f"{weights[bad].sum():.6f})")
        if np.any((joints < 0) | (joints >= n_joints)):
            raise ValueError(f"joint indices must lie in 0..{n_joints - 1}")
        w = sparse.csr_matrix((weights.ravel(), (np.repeat(np.arange(nv), joints.shape[1]), joints.ravel())),
                              shape=(nv, n_joints))
        w.sum_duplicates()
        w.eliminate_zeros()
        object.__setattr__(self, "_w", w)

    @property
    def n_vertices(self) -> int:
        return int(np.shape(self.vertices)[0])

    def skinning_matrices(self, global_rotations: ArrayLike, global_positions: ArrayLike) -> Array:
        """``(..., J, 3, 4)`` skinning matrices from forward-kinematics output ``(..., J, 4)``, ``(..., J, 3)``."""
        return compose_transforms(transforms(global_rotations, global_positions), self.inverse_bind)

    def skin(self, skinning_matrices: ArrayLike) -> tuple[Array, Array]:
        """Skinned positions and unit normals ``(..., V, 3)`` for skinning matrices ``(..., J, 3, 4)``."""
        s = np.asarray(skinning_matrices, dtype=np.float64)
        batch = s.shape[:-3]
        n_joints = s.shape[-3]
        # (J, N*12) -> sparse (V, J) @ -> (V, N*12): per-vertex blended matrices for every character at once,
        # then one contiguous (N, V) row per matrix entry: the arithmetic below on strided (V, 3, 4) views
        # (einsum, np.cross) took twice as long, and the renderer skins every frame.
        flat = np.moveaxis(s.reshape(-1, n_joints, 12), 1, 0).reshape(n_joints, -1)
        m = np.ascontiguousarray(np.asarray(self._w @ flat).reshape(self.n_vertices, -1, 12).transpose(2, 1, 0))
        x, y, z = np.asarray(self.vertices, np.float64).T
        pos = np.empty((*m.shape[1:], 3))
        for i in range(3):
            pos[..., i] = m[4 * i] * x + m[4 * i + 1] * y + m[4 * i + 2] * z + m[4 * i + 3]
        # Normals take the cofactor matrix (inverse transpose up to scale): correct for blended, non-rigid matrices.
        # Its rows are r1 x r2, r2 x r0, r0 x r1 for the rows r0, r1, r2 of the blended 3x3 part.
        (a, b, c), (d, e, f), (g, h, k) = m[0:3], m[4:7], m[8:11]
        nx, ny, nz = np.asarray(self.normals, np.float64).T
        nrm = np.empty_like(pos)
        nrm[..., 0] = (e * k - f * h) * nx + (f * g - d * k) * ny + (d * h - e * g) * nz
        nrm[..., 1] = (h * c - k * b) * nx + (k * a - g * c) * ny + (g * b - h * a) * nz
        nrm[..., 2] = (b * f - c * e) * nx + (c * d - a * f) * ny + (a * e - b * d) * nz
        nrm /= np.maximum(np.linalg.norm(nrm, axis=-1, keepdims=True), 1e-12)
        return pos.reshape(*batch, self.n_vertices, 3), nrm.reshape(*batch, self.n_vertices, 3)
