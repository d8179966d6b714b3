"""Analytic two-bone IK (hip-knee-ankle, shoulder-elbow-wrist) over batches of poses.

Conventions as in :mod:`anim_core.math.skeleton`: local rotations ``(..., J, 4)`` (w, x, y, z), root translation
``(..., 3)``, positions in the skeleton's units.  A chain is three joint indices ``(start, mid, end)`` with
``parent(mid) == start`` and ``parent(end) == mid``; any skeleton works.

The solve (position form of ozz-animation's ``IKTwoBoneJob``, research notes 8.3), per pose:

1. the target distance ``d = |target - start|`` is clamped to ``[|a - b|, a + b]`` (bone lengths ``a``, ``b``)
   shrunk by a relative ``1e-9``, so unreachable targets give the nearest reachable pose, never NaN (optionally
   softened near full reach first, ``soft``);
2. the mid joint bends about its current hinge axis (the normal of the start-mid-end plane) until the law of
   cosines gives ``d``; given the joint's own hinge (:func:`hinge_axis`), that normal is turned to the hinge's
   side, so the bend is always positive about it (a knee never bends backwards);
3. the start joint swings the chain's end onto the target, then turns it about the start -> target axis so the
   mid joint lies in the plane through start, target and the *pole* (default: the mid joint's animated
   position, which keeps the knee pointing where the animation points it); given the hinge and no pole, so
   that the chain's plane normal stays as close as it gets to the animated one (the hinge's where the chain is
   straight, and the animated knee, on the leg's line, points nowhere in particular); given both, the pole's
   plane where it is well defined and near the animated one, the animated one elsewhere.  The turn is computed
   from the chain's plane normal, carried along by the swing, which stays defined when the chain is straight;
4. the end joint keeps its animated world orientation (a planted foot stays flat), optionally re-aimed so its
   child points at a given position (toe levelling).

Only the three chain joints' local rotations change; bone lengths are those of the skeleton, so they are kept.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..math.quat import quat_between, quat_conj, quat_from_axis_angle, quat_mul, rotate
from ..math.skeleton import Skeleton

Array = NDArray[np.float64]

_SHRINK = 1e-9  # relative margin inside the reachable range: acos stays finite, targets are met to ~1e-9


def _unit(v: Array, fallback: Array) -> Array:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(n > 1e-12, v / np.maximum(n, 1e-300), fallback)


def smoothstep(x: ArrayLike) -> Array:
    """``3x² - 2x³`` of ``x`` clipped to 0..1: an ease from 0 to 1 with zero slope at both ends (the blend weight of
    this module's soft switches and of :mod:`anim_core.methods.footplant` / :mod:`anim_core.methods.footlock`)."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _perpendicular(v: Array) -> Array:
    helper = np.where(np.abs(v[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    c = np.cross(v, helper)
    return c / np.linalg.norm(c, axis=-1, keepdims=True)


STRAIGHT = 0.05  # sin of the hip angle below which the pole gives way to the hinge (knee bent < ~6 degrees)
_TRUSTED = np.radians(30.0)  # a pole's plane further than this from the animated plane gives way to it (fully at 2x)


def hinge_axis(skeleton: Skeleton, local_rotations: ArrayLike, root_translation: ArrayLike | None,
               chain: tuple[int, int, int]) -> Array:
    """``(3,)`` unit hinge of the chain's mid joint in its own local frame (the axis it bends about, oriented so
    that its bends are positive), estimated from poses ``(..., J, 4)``: the start-mid-end plane normal
    ``thigh x shin`` of every pose in the mid joint's frame, summed (its length ``a b sin(bend)`` weights the
    well-bent poses most).  Raises ``ValueError`` when no pose bends the chain."""
    s, m, e = (int(j) for j in chain)
    g_rot, g_pos = skeleton.forward_kinematics(np.asarray(local_rotations, dtype=np.float64), root_translation)
    normal = np.cross(g_pos[..., m, :] - g_pos[..., s, :], g_pos[..., e, :] - g_pos[..., m, :])
    total = rotate(quat_conj(g_rot[..., m, :]), normal).reshape(-1, 3).sum(axis=0)
    length = float(np.linalg.norm(total))
    if length <= 1e-9 * float(np.linalg.norm(skeleton.offsets[m]) * np.linalg.norm(skeleton.offsets[e])):
        raise ValueError(f"chain {chain} is straight in every pose: its hinge cannot be estimated")
    return total / length


def two_bone_ik(skeleton: Skeleton, local_rotations: ArrayLike, root_translation: ArrayLike | None,
                chain: tuple[int, int, int], target: ArrayLike, pole: ArrayLike | None = None,
                weight: ArrayLike | None = None, aim: tuple[int, ArrayLike] | None = None,
                hinge: ArrayLike | None = None, soft: float = 0.0) -> Array:
    """Local rotations ``(..., J, 4)`` with the chain's end joint at ``target (..., 3)`` (model space).

    ``pole (..., 3)``: a point the mid joint bends towards (default: its animated position); ``weight (...)``
    in 0..1 blends the target from the animated end position (0: unchanged pose, 1: on the target);
    ``aim = (child, position (..., 3))``: turn the end joint (minimally) so that joint ``child`` of it points at
    ``position`` — e.g. the toe at its planted place; ``hinge (3,)`` or ``(..., 3)``: the mid joint's hinge in
    its local frame (:func:`hinge_axis`), which makes the solve safe near a straight chain: the mid joint always
    bends positively about it (a knee never bends backwards, even from a slightly hyper-extended or straight
    animated pose), and without a pole the chain's plane keeps the animated plane's normal as far as the target
    allows (the hinge's while the animated chain is straight); with a pole, the plane turns towards the
    hinge's where the pole is (nearly) on the start -> target line, and towards the animated plane (as without a
    pole) where the pole's plane is more than 30 degrees from it (fully at 60): near a straight chain a target
    moved off the animated end turns the plane through a pole at the animated mid joint anywhere.
    Without it the animated plane stands in for the hinge, which is only defined while the chain is bent.
    ``soft`` (units, >= 0): soft IK near full reach ``L = a + b`` — a target further than ``L - soft`` is reached
    only to ``L - soft exp(-(d - L + soft) / soft)`` (short of it by at most ``soft / e`` at ``d = L``), so the
    bend stays smooth where a target passes full reach or touches it (with ``soft = 0`` the bend goes as
    ``sqrt(L - d)`` there: its angular velocity jumps or is unbounded).
    Raises ``ValueError`` for a chain that is not parent-linked or for mismatched shapes.
    """
    s, m, e = _chain_joints(skeleton, chain)
    parents = skeleton.parents
    local = np.array(local_rotations, dtype=np.float64)
    g_rot, g_pos = skeleton.forward_kinematics(local, root_translation)
    batch = local.shape[:-2]
    target = np.broadcast_to(np.asarray(target, dtype=np.float64), (*batch, 3))
    S, M, E = g_pos[..., s, :], g_pos[..., m, :], g_pos[..., e, :]
    if weight is not None:
        w = np.clip(np.broadcast_to(np.asarray(weight, dtype=np.float64), batch), 0.0, 1.0)[..., None]
        target = E + w * (target - E)
    a, b = _bone_lengths(skeleton, chain, soft)
    d_hat, d = _target_distance(target - S, S, M, E, a, b, soft)
    thigh, shin = M - S, E - M
    side, h, h_thigh = _bend_plane(thigh, shin, a, b, g_rot[..., m, :], hinge, batch)
    shin_1 = _bent_shin(thigh / a, side, a, b, d)
    r_mid = quat_between(shin, shin_1)
    end_1 = M + shin_1
    r_start = _swing_and_twist(S, M, end_1, d_hat, side, pole, h, h_thigh, a, batch)

    g_start = quat_mul(r_start, g_rot[..., s, :])
    g_mid = quat_mul(r_start, quat_mul(r_mid, g_rot[..., m, :]))
    g_end = g_rot[..., e, :]  # 4. the end keeps its world orientation
    if aim is not None:
        g_end = _aimed_end(skeleton, e, g_end, S + rotate(r_start, end_1 - S), aim, batch)

    ps = parents[s]
    local[..., s, :] = g_start if ps < 0 else quat_mul(quat_conj(g_rot[..., ps, :]), g_start)
    local[..., m, :] = quat_mul(quat_conj(g_start), g_mid)
    local[..., e, :] = quat_mul(quat_conj(g_mid), g_end)
    return local


def _chain_joints(skeleton: Skeleton, chain: tuple[int, int, int]) -> tuple[int, int, int]:
    """``(start, mid, end)`` joint indices of ``chain``, checked to be parent-linked joints of ``skeleton``."""
    s, m, e = (int(j) for j in chain)
    parents = skeleton.parents
    if not (0 <= s < skeleton.n_joints and 0 <= m < skeleton.n_joints and 0 <= e < skeleton.n_joints):
        raise ValueError(f"chain {chain} has joints outside the skeleton's {skeleton.n_joints}")
    if parents[m] != s or parents[e] != m:
        raise ValueError(f"chain {chain} is not start -> mid -> end: parents are {parents[m]}, {parents[e]}")
    return s, m, e


def _bone_lengths(skeleton: Skeleton, chain: tuple[int, int, int], soft: float) -> tuple[float, float]:
    """Lengths ``a`` (start-mid) and ``b`` (mid-end) of the chain's bones; ``soft`` checked against the reach."""
    a = float(np.linalg.norm(skeleton.offsets[int(chain[1])]))
    b = float(np.linalg.norm(skeleton.offsets[int(chain[2])]))
    if a <= 0 or b <= 0:
        raise ValueError(f"chain {chain} has a zero-length bone")
    if not 0.0 <= soft < a + b:
        raise ValueError(f"soft must be in [0, {a + b:g}) (the chain's reach), got {soft}")
    return a, b


def _target_distance(to_target: Array, S: Array, M: Array, E: Array, a: float, b: float,
                     soft: float) -> tuple[Array, Array]:
    """Step 1: unit direction ``(..., 3)`` and clamped (and softened) distance ``(...)`` from start to target."""
    # A target on the start joint has no direction: the animated end's stands in, then any perpendicular.
    d_hat = _unit(to_target, _unit(E - S, _perpendicular(M - S)))
    d = np.linalg.norm(to_target, axis=-1)
    if soft > 0.0:
        d_soft = a + b - soft
        d = np.where(d > d_soft, d_soft - soft * np.expm1(-(d - d_soft) / soft), d)
    return d_hat, np.clip(d, abs(a - b) + _SHRINK * (a + b), (a + b) * (1.0 - _SHRINK))


def _bend_plane(thigh: Array, shin: Array, a: float, b: float, g_mid: Array, hinge: ArrayLike | None,
                batch: tuple[int, ...]) -> tuple[Array, Array | None, Array | None]:
    """Step 2's plane: its unit normal ``side (..., 3)``; with a ``hinge``, also the hinge in world space ``h`` and
    made perpendicular to the thigh ``h_thigh`` (``(..., 3)``, else ``None``), which step 3 turns towards."""
    normal = np.cross(thigh, shin)
    if hinge is None:
        return _unit(normal, _perpendicular(thigh)), None, None
    # The animated plane turned to the hinge's side (a hyper-extended pose bends forwards through straight,
    # not further back), easing into the hinge's own plane as the animated chain straightens and its plane
    # is lost in noise.
    t_hat = thigh / a
    h = rotate(g_mid, np.broadcast_to(np.asarray(hinge, dtype=np.float64), (*batch, 3)))
    h_thigh = _unit(h - np.sum(h * t_hat, axis=-1, keepdims=True) * t_hat, _perpendicular(thigh))
    flip = np.where(np.sum(normal * h, axis=-1, keepdims=True) < 0.0, -1.0, 1.0)
    ease = smoothstep(np.linalg.norm(normal, axis=-1, keepdims=True) / (STRAIGHT * a * b))
    return _unit(ease * flip * _unit(normal, h_thigh) + (1.0 - ease) * h_thigh, h_thigh), h, h_thigh


def _bent_shin(t_hat: Array, side: Array, a: float, b: float, d: Array) -> Array:
    """Step 2: the shin ``(..., 3)`` at the angle from the thigh (unit ``t_hat``) in the plane of normal ``side``
    at which the law of cosines gives the distance ``d``: exact for any ``side``."""
    cos_inner = np.clip((a * a + b * b - d * d) / (2.0 * a * b), -1.0, 1.0)
    bend = (np.pi - np.arccos(cos_inner))[..., None]  # 0 = straight
    return b * (np.cos(bend) * t_hat + np.sin(bend) * np.cross(side, t_hat))


def _swing_and_twist(S: Array, M: Array, end_1: Array, d_hat: Array, side: Array, pole: ArrayLike | None,
                     h: Array | None, h_thigh: Array | None, a: float, batch: tuple[int, ...]) -> Array:
    """Step 3: the start joint's turn ``(..., 4)`` that swings the bent chain's end ``end_1`` onto the target
    direction ``d_hat``, then twists about it to put the chain's plane (normal ``side``, carried along by the
    swing) where it is wanted: through start, target and pole; with the hinge (``h``) and no pole, as close as it
    gets to the animated plane (``side``, which is the hinge's where the chain is straight and a pole on the leg's
    line would point nowhere in particular)."""
    r_swing = quat_between(end_1 - S, d_hat)
    plane = rotate(r_swing, side)
    if h is not None:
        kept = side - np.sum(side * d_hat, axis=-1, keepdims=True) * d_hat  # the animated plane's normal, kept
    if h is not None and pole is None:
        wanted = kept
    else:
        p = (M if pole is None else np.broadcast_to(np.asarray(pole, dtype=np.float64), (*batch, 3))) - S
        wanted = np.cross(p, d_hat)
    if h is not None and pole is not None:
        wanted = _trusted_pole_plane(wanted, kept, p, d_hat, h, h_thigh)
    ok = np.linalg.norm(wanted, axis=-1) > 1e-9 * a  # a pole on the line (no hinge given): no twist
    angle = np.where(ok, np.arctan2(np.sum(d_hat * np.cross(plane, wanted), axis=-1),
                                    np.sum(plane * wanted, axis=-1)), 0.0)
    return quat_mul(quat_from_axis_angle(d_hat, angle), r_swing)


def _trusted_pole_plane(wanted: Array, kept: Array, p: Array, d_hat: Array, h: Array, h_thigh: Array) -> Array:
    """The normal ``(..., 3)`` wanted of the chain's plane given a pole (at ``p`` from the start) and the hinge:
    the pole's plane ``wanted`` while the pole is well off the line and that plane within _TRUSTED of the animated
    one ``kept``, easing into the animated plane (the no-pole solve) otherwise."""
    # Near a straight leg a pole at the animated knee lies almost on the line, and a target moved off the animated
    # ankle turns its plane anywhere (a one-frame twist of the thigh by up to 180 degrees).
    wanted = _unit(wanted * np.where(np.sum(wanted * h, axis=-1, keepdims=True) < 0.0, -1.0, 1.0), kept)
    kept = _unit(kept, h_thigh)
    reach = np.maximum(STRAIGHT * np.linalg.norm(p, axis=-1, keepdims=True), 1e-300)
    off_line = smoothstep(np.linalg.norm(np.cross(p, d_hat), axis=-1, keepdims=True) / reach)
    cos_lo, cos_hi = np.cos(2.0 * _TRUSTED), np.cos(_TRUSTED)
    agrees = smoothstep((np.sum(wanted * kept, axis=-1, keepdims=True) - cos_lo) / (cos_hi - cos_lo))
    trust = off_line * agrees
    return trust * wanted + (1.0 - trust) * kept


def _aimed_end(skeleton: Skeleton, e: int, g_end: Array, end_pos: Array, aim: tuple[int, ArrayLike],
               batch: tuple[int, ...]) -> Array:
    """Step 4: the end joint's world rotation ``g_end (..., 4)`` turned (minimally) so that its child ``aim[0]``
    points from the end's solved position ``end_pos`` at ``aim[1] (..., 3)``."""
    child, position = aim
    child = int(child)
    if skeleton.parents[child] != e:
        raise ValueError(f"aim joint {child} is not a child of the chain's end {e}")
    current = rotate(g_end, skeleton.offsets[child])
    wanted = np.broadcast_to(np.asarray(position, dtype=np.float64), (*batch, 3)) - end_pos
    return quat_mul(quat_between(current, wanted), g_end)
