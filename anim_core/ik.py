"""Analytic two-bone IK (hip-knee-ankle, shoulder-elbow-wrist) over batches of poses.

Conventions as in :mod:`anim_core.skeleton`: local rotations ``(..., J, 4)`` (w, x, y, z), root translation
``(..., 3)``, positions in the skeleton's units.  A chain is three joint indices ``(start, mid, end)`` with
``parent(mid) == start`` and ``parent(end) == mid``; any skeleton works.

The solve (position form of ozz-animation's ``IKTwoBoneJob``, research notes 8.3), per pose:

1. the target distance ``d = |target - start|`` is clamped to ``[|a - b|, a + b]`` (bone lengths ``a``, ``b``)
   shrunk by a relative ``1e-9``, so unreachable targets give the nearest reachable pose, never NaN;
2. the mid joint bends about its current hinge axis (the normal of the start-mid-end plane) until the law of
   cosines gives ``d``;
3. the start joint swings the chain's end onto the target, then turns it about the start -> target axis so the
   mid joint lies in the plane through start, target and the *pole* (default: the mid joint's animated
   position, which keeps the knee pointing where the animation points it);
4. the end joint keeps its animated world orientation (a planted foot stays flat), optionally re-aimed so its
   child points at a given position (toe levelling).

Only the three chain joints' local rotations change; bone lengths are those of the skeleton, so they are kept.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .quat import quat_between, quat_conj, quat_from_axis_angle, quat_mul, rotate
from .skeleton import Skeleton

Array = NDArray[np.float64]

_SHRINK = 1e-9  # relative margin inside the reachable range: acos stays finite, targets are met to ~1e-9


def _unit(v: Array, fallback: Array) -> Array:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(n > 1e-12, v / np.maximum(n, 1e-300), fallback)


def _perpendicular(v: Array) -> Array:
    helper = np.where(np.abs(v[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    c = np.cross(v, helper)
    return c / np.linalg.norm(c, axis=-1, keepdims=True)


def two_bone_ik(skeleton: Skeleton, local_rotations: ArrayLike, root_translation: ArrayLike | None,
                chain: tuple[int, int, int], target: ArrayLike, pole: ArrayLike | None = None,
                weight: ArrayLike | None = None, aim: tuple[int, ArrayLike] | None = None) -> Array:
    """Local rotations ``(..., J, 4)`` with the chain's end joint at ``target (..., 3)`` (model space).

    ``pole (..., 3)``: a point the mid joint bends towards (default: its animated position); ``weight (...)``
    in 0..1 blends the target from the animated end position (0: unchanged pose, 1: on the target);
    ``aim = (child, position (..., 3))``: turn the end joint (minimally) so that joint ``child`` of it points at
    ``position`` — e.g. the toe at its planted place.  Raises ``ValueError`` for a chain that is not
    parent-linked or for mismatched shapes.
    """
    s, m, e = (int(j) for j in chain)
    parents = skeleton.parents
    if not (0 <= s < skeleton.n_joints and 0 <= m < skeleton.n_joints and 0 <= e < skeleton.n_joints):
        raise ValueError(f"chain {chain} has joints outside the skeleton's {skeleton.n_joints}")
    if parents[m] != s or parents[e] != m:
        raise ValueError(f"chain {chain} is not start -> mid -> end: parents are {parents[m]}, {parents[e]}")
    local = np.array(local_rotations, dtype=np.float64)
    g_rot, g_pos = skeleton.forward_kinematics(local, root_translation)
    batch = local.shape[:-2]
    target = np.broadcast_to(np.asarray(target, dtype=np.float64), (*batch, 3))
    S, M, E = g_pos[..., s, :], g_pos[..., m, :], g_pos[..., e, :]
    if weight is not None:
        w = np.clip(np.broadcast_to(np.asarray(weight, dtype=np.float64), batch), 0.0, 1.0)[..., None]
        target = E + w * (target - E)
    a = float(np.linalg.norm(skeleton.offsets[m]))
    b = float(np.linalg.norm(skeleton.offsets[e]))
    if a <= 0 or b <= 0:
        raise ValueError(f"chain {chain} has a zero-length bone")

    # 1. Clamped distance and direction to the target.
    to_target = target - S
    d_hat = _unit(to_target, _unit(E - S, _perpendicular(M - S)))
    d = np.clip(np.linalg.norm(to_target, axis=-1), abs(a - b) + _SHRINK * (a + b), (a + b) * (1.0 - _SHRINK))

    # 2. Bend the mid joint about its hinge (current plane normal; any perpendicular if the chain is straight).
    thigh, shin = M - S, E - M
    hinge = _unit(np.cross(thigh, shin), _perpendicular(thigh))
    bend = np.arctan2(np.linalg.norm(np.cross(thigh, shin), axis=-1), np.sum(thigh * shin, axis=-1))
    cos_inner = np.clip((a * a + b * b - d * d) / (2.0 * a * b), -1.0, 1.0)
    r_mid = quat_from_axis_angle(hinge, (np.pi - np.arccos(cos_inner)) - bend)
    end_1 = M + rotate(r_mid, shin)

    # 3. Swing the end onto the target, then twist about start -> target towards the pole.
    r_swing = quat_between(end_1 - S, d_hat)
    knee = rotate(r_swing, thigh)
    p = (M if pole is None else np.broadcast_to(np.asarray(pole, dtype=np.float64), (*batch, 3))) - S
    k_perp = knee - np.sum(knee * d_hat, axis=-1, keepdims=True) * d_hat
    p_perp = p - np.sum(p * d_hat, axis=-1, keepdims=True) * d_hat
    ok = (np.linalg.norm(k_perp, axis=-1) > 1e-9 * a) & (np.linalg.norm(p_perp, axis=-1) > 1e-9 * a)
    angle = np.where(ok, np.arctan2(np.sum(d_hat * np.cross(k_perp, p_perp), axis=-1),
                                    np.sum(k_perp * p_perp, axis=-1)), 0.0)
    r_start = quat_mul(quat_from_axis_angle(d_hat, angle), r_swing)

    g_start = quat_mul(r_start, g_rot[..., s, :])
    g_mid = quat_mul(r_start, quat_mul(r_mid, g_rot[..., m, :]))
    g_end = g_rot[..., e, :]  # 4. the end keeps its world orientation
    if aim is not None:
        child, position = aim
        child = int(child)
        if parents[child] != e:
            raise ValueError(f"aim joint {child} is not a child of the chain's end {e}")
        end_pos = S + rotate(r_start, end_1 - S)
        current = rotate(g_end, skeleton.offsets[child])
        wanted = np.broadcast_to(np.asarray(position, dtype=np.float64), (*batch, 3)) - end_pos
        g_end = quat_mul(quat_between(current, wanted), g_end)

    ps = parents[s]
    local[..., s, :] = g_start if ps < 0 else quat_mul(quat_conj(g_rot[..., ps, :]), g_start)
    local[..., m, :] = quat_mul(quat_conj(g_start), g_mid)
    local[..., e, :] = quat_mul(quat_conj(g_mid), g_end)
    return local
