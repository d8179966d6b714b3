"""Two-bone IK at run time (issue 39), ozz-animation style: one job over a crowd of characters (ozz's
``IKTwoBoneJob``), its buffers validated before the numba kernel touches them.

:class:`TwoBoneIKJob` holds legs (hip, knee, ankle chains), each knee's hinge in its own frame and the soft reach;
:meth:`TwoBoneIKJob.run` takes the crowd's model-space pose (rotations ``(N, J, 4)``, positions ``(N, J, 3)``
float32, e.g. from :func:`anim_core.runtime.blending.local_to_model`), per character and leg a model-space ankle
target ``(N, F, 3)`` and a weight ``(N, F)`` in 0..1 (float32), and solves every leg of weight > 0 in place: the
steps of the offline :func:`anim_core.methods.ik.two_bone_ik` with the hinge, no pole, the soft reach and the ankle
keeping its world orientation (the held feet of :mod:`anim_core.methods.transition_feet`), run by the same compiled
per-leg solve as the foot-locked hybrid's runtime (:func:`anim_core.runtime.kernels.solve_leg`, float64 on the
float32 pose).  The hip's and knee's model-space rotations turn and every joint under the hip is re-placed from its
parent, so the pose needs no second local-to-model pass (ozz's job returns the hip's and knee's corrections and
leaves that pass to the caller).  Weight 0 leaves a leg bit for bit as it was.

A crossfading character with held feet runs sample A, sample B, blend, local-to-model, then this job; its cost is
the ``crossfade_feet`` row of ``animstudy bench --stages blend`` (:mod:`anim_core.bench.blend`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..math.skeleton import Skeleton
from ..methods.ik import STRAIGHT
from .blending import buffer, need_numba, output, weights_buffer
from .crowd import numba
from .kinds import frozen, skeleton_arrays
from .offline import leg_arrays

F32 = NDArray[np.float32]
Array = NDArray[np.float64]

if numba is not None:
    from .kernels import ik_job


def _finite(name: str, buf: Any, shape: tuple[int, ...]) -> F32:
    out = buffer(name, buf, shape)
    if not np.all(np.isfinite(out)):
        raise ValueError(f"{name} must be finite (no NaN or infinity)")
    return out


@dataclass(frozen=True, eq=False)
class TwoBoneIKJob:
    """Legs ``F`` of ``skeleton``: ``chains (F, 3)`` int32 (hip, knee, ankle), ``hinges (F, 3)`` float32 each knee's
    unit hinge in its local frame (:func:`anim_core.methods.ik.hinge_axis`), ``below``/``turns (F, L)`` int32 the
    joints under each hip and what turns each (:func:`anim_core.runtime.offline.leg_arrays`), ``params (2,)``
    float64 = (soft reach in the skeleton's units, the IK's straight-knee threshold)."""

    skeleton: Skeleton
    chains: NDArray[np.int32]
    hinges: F32
    below: NDArray[np.int32]
    turns: NDArray[np.int32]
    params: Array

    @classmethod
    def for_legs(cls, skeleton: Skeleton, legs: Sequence[tuple[int, int, int]], hinges: ArrayLike,
                 soft: float = 0.0) -> TwoBoneIKJob:
        """The job of ``legs`` (``(hip, knee, ankle)`` joint indices, each parent-linked) with the knees'
        ``hinges (F, 3)`` (normalized here) and the soft reach ``soft`` (as :func:`two_bone_ik`'s, >= 0 and
        short of every leg's reach).  ``ValueError`` for a chain that is not start -> mid -> end, a zero-length
        bone, a hinge of zero length or not finite, or a bad ``soft``."""
        n, parents = skeleton.n_joints, skeleton.parents
        for s, m, e in legs:
            if not all(0 <= int(j) < n for j in (s, m, e)) or parents[m] != s or parents[e] != m:
                raise ValueError(f"leg {(s, m, e)} is not hip -> knee -> ankle joints of the skeleton")
            if min(np.linalg.norm(skeleton.offsets[m]), np.linalg.norm(skeleton.offsets[e])) <= 0:
                raise ValueError(f"leg {(s, m, e)} has a zero-length bone")
        h = np.asarray(hinges, np.float64)
        if h.shape != (len(legs), 3) or not np.all(np.isfinite(h)) or np.any(np.linalg.norm(h, axis=-1) <= 0):
            raise ValueError(f"hinges must be {len(legs)} finite non-zero 3-vectors, got shape {h.shape}")
        reach = min([np.inf, *(np.linalg.norm(skeleton.offsets[m]) + np.linalg.norm(skeleton.offsets[e])
                               for _, m, e in legs)])
        if not 0.0 <= soft < reach:
            raise ValueError(f"soft must be in [0, {reach:g}) (the shortest leg's reach), got {soft}")
        chains, below, turns = leg_arrays(skeleton, legs)
        return cls(skeleton, frozen(chains, np.int32), frozen(h / np.linalg.norm(h, axis=-1, keepdims=True),
                                                              np.float32),
                   frozen(below, np.int32), frozen(turns, np.int32), frozen([soft, STRAIGHT], np.float64))

    @property
    def runtime_bytes(self) -> int:
        return int(self.chains.nbytes + self.hinges.nbytes + self.below.nbytes + self.turns.nbytes
                   + self.params.nbytes)

    def run(self, model_rotations: F32, model_positions: F32, targets: F32, weights: F32) -> None:
        """Solve every leg of every character towards ``targets (N, F, 3)`` blended from its animated ankle by
        ``weights (N, F)``, in place in ``model_rotations (N, J, 4)`` / ``model_positions (N, J, 3)``.  Every
        buffer is validated first (float32, C-contiguous, its shape; targets finite, weights in 0..1):
        ``ValueError`` naming the buffer, and nothing written."""
        need_numba()
        j, legs = self.skeleton.n_joints, self.chains.shape[0]
        if not isinstance(model_rotations, np.ndarray) or model_rotations.ndim != 3:
            raise ValueError("model rotations must be an (N, J, 4) array")
        n = model_rotations.shape[0]
        rot = output("model rotations", model_rotations, (n, j, 4))
        pos = output("model positions", model_positions, (n, j, 3))
        if np.shares_memory(rot, pos):
            raise ValueError("model rotations and positions must not overlap")
        ik_job(self.chains, self.hinges, self.below, self.turns, self.params,
                   _finite("targets", targets, (n, legs, 3)), weights_buffer("weights", weights, (n, legs)),
                   *skeleton_arrays(self.skeleton), rot, pos)
