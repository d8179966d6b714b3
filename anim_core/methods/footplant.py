"""Keep planted feet planted: contact phases given per frame, legs pinned there with two-bone IK.

Offline (a clip builder's step, not a runtime job).  Conventions as in :mod:`anim_core.math.contacts` and
:mod:`anim_core.methods.ik`: frames along axis 0 at ``fps``, positions in metres, ``up_axis`` vertical.  For each
foot and each contact phase (an interval of frames in which the foot is down, typically detected on the source
motion before retargeting), the foot follows its animated path on the ground from the phase's slowest frame on,
shifted horizontally by whatever its slowest joint (heel or toe) moves beyond ``max_speed``: it can roll, not
slide.  Heights stay the animated ones, the foot keeps its animated world orientation, and two-bone IK on
hip-knee-ankle moves the leg, the knee bending about its hinge estimated on the given poses
(:func:`anim_core.methods.ik.hinge_axis`): towards its animated position while the leg is well bent, in its animated
plane where the leg is (nearly) straight and that position says nothing about where the knee points.  Over
``blend_frames`` frames on each side of a phase the IK weight eases in and out (smoothstep), so the leg never jumps.

With ``max_leg_change_deg`` the hold gives way where it would turn a thigh or change a knee's bend by more than
that: the ankle's target moves from the animated ankle towards the held place only as far as the leg stays within
that angle of its animated pose (:func:`leg_limited_targets`).  A take whose feet still slide as they land (a 30 fps
run) would otherwise have its leg pulled straight to reach a foothold the motion never had.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import minimum_filter1d, uniform_filter1d

from ..math.contacts import contact_intervals
from ..math.skeleton import Skeleton
from .ik import hinge_axis, smoothstep, two_bone_ik

Array = NDArray[np.float64]


def _held_offsets(points: Array, k: int, max_step: float, horizontal: list[int]) -> Array:
    """``(N, 3)`` horizontal offsets for a foot tracked by ``points (N, P, 3)`` on the ground over one contact
    phase: 0 at frame ``k``, and from there (forwards and backwards) the offset grows by exactly what the foot's
    slowest point moves beyond ``max_step`` per frame, so that point never moves faster — the foot may roll over
    its heel or toe, but it does not slide."""
    out = np.zeros((len(points), 3))

    def step(i: int, j: int) -> None:
        d = points[j][:, horizontal] - points[i][:, horizontal]  # (P, 2)
        slowest = d[int(np.argmin(np.linalg.norm(d, axis=1)))]
        length = float(np.linalg.norm(slowest))
        excess = slowest * (1.0 - max_step / length) if length > max_step else 0.0 * slowest
        out[j, horizontal] = out[i, horizontal] - excess

    for i in range(k, len(points) - 1):  # frames of one contact phase
        step(i, i + 1)
    for i in range(k, 0, -1):
        step(i, i - 1)
    return out


def foot_targets(skeleton: Skeleton, local_rotations: ArrayLike, root_translation: ArrayLike,
               legs: Sequence[tuple[int, int, int]], down: ArrayLike, fps: float,
               feet: Sequence[Sequence[int]] | None = None, periodic: bool = False,
               ground_velocity: ArrayLike | None = None, up_axis: int = 1, blend_frames: int = 5,
               max_speed: float = 0.4, rest_speed: float = 0.5) -> tuple[Array, Array]:
    """Where :func:`plant_feet` puts each ankle: targets ``(T, F, 3)`` (model space, the root as given) and IK
    weights ``(T, F)`` in 0..1 (0: the leg as animated).  Parameters as for :func:`plant_feet`.
    """
    rot = np.array(local_rotations, dtype=np.float64)
    root = np.asarray(root_translation, dtype=np.float64)
    contact = np.asarray(down, dtype=bool)
    n = rot.shape[0]
    if rot.ndim != 3 or root.shape != (n, 3) or contact.shape != (n, len(legs)):
        raise ValueError(f"expected rotations (T, J, 4), root (T, 3) and contacts (T, {len(legs)}), got "
                         f"{rot.shape}, {root.shape}, {contact.shape}")
    g = np.zeros(3) if ground_velocity is None else np.asarray(ground_velocity, dtype=np.float64)
    horizontal = [a for a in range(3) if a != up_axis]
    _, pos = skeleton.forward_kinematics(rot, root)  # legs are separate chains: one pass serves every leg
    targets = np.zeros((n, len(legs), 3))
    weights = np.zeros((n, len(legs)))
    for f, chain in enumerate(legs):  # one target track per leg over all frames
        points = [chain[2]] if feet is None else [int(j) for j in feet[f]]
        ankle = pos[:, chain[2]]
        foot = pos[:, points]
        speed = np.linalg.norm(np.gradient(foot, axis=0)[..., horizontal] * fps + g[horizontal], axis=-1).min(axis=1)
        target = ankle.copy()
        weight = np.zeros(n)
        for start, stop in contact_intervals(contact[:, f], periodic):  # one per contact phase
            inside = np.arange(start, stop)
            if speed[inside % n].min() > rest_speed:
                continue  # a swing passing low over the ground, not a step: left as animated
            ground = foot[inside % n] + g * (inside / fps)[:, None, None]  # the foot on the ground
            offset = _held_offsets(ground, int(np.argmin(speed[inside % n])), max_speed / fps, horizontal)
            # Beside the phase the edge's offset fades out, so a foot arriving or leaving fast is not dragged.
            offset = np.concatenate([np.repeat(offset[:1], blend_frames, 0), offset,
                                     np.repeat(offset[-1:], blend_frames, 0)])
            span = np.arange(start - blend_frames, stop + blend_frames)
            w = np.where(span < start, smoothstep((span - start + blend_frames + 1) / (blend_frames + 1)),
                         np.where(span >= stop, smoothstep((stop + blend_frames - span) / (blend_frames + 1)), 1.0))
            if not periodic:
                keep = (span >= 0) & (span < n)
                span, w, offset = span[keep], w[keep], offset[keep]
            idx = span % n
            better = w > weight[idx]
            target[idx[better]] = ankle[idx[better]] + offset[better]
            weight[idx[better]] = w[better]
        targets[:, f], weights[:, f] = target, weight
    return targets, weights


def plant_feet(skeleton: Skeleton, local_rotations: ArrayLike, root_translation: ArrayLike,
               legs: Sequence[tuple[int, int, int]], down: ArrayLike, fps: float,
               feet: Sequence[Sequence[int]] | None = None, periodic: bool = False,
               ground_velocity: ArrayLike | None = None, up_axis: int = 1, blend_frames: int = 5,
               max_speed: float = 0.4, rest_speed: float = 0.5, max_leg_change_deg: float | None = None) -> Array:
    """Local rotations ``(T, J, 4)`` with each leg's ankle held in place while its foot is down.

    ``legs``: per foot the chain ``(hip, knee, ankle)`` (joint indices); ``down``: ``(T, F)`` contact per frame
    and foot; ``feet``: per foot the joints that touch the ground (default: the ankle), e.g. ankle and toe;
    ``periodic``: the ``T`` frames are one loop (phases may wrap); ``ground_velocity (3,)`` m/s: for
    clips played in place, the ground moves at minus this under the character, so a pinned ankle follows it.
    ``max_speed`` m/s: inside a phase the foot follows its animated ground path, shifted so that its slowest
    joint never moves faster than this (by default 0.4 m/s, below the skate threshold of
    :mod:`anim_core.math.contacts`); the foot keeps its world orientation, so heel and toe still roll.
    ``rest_speed`` m/s: a phase in which the foot's slowest joint never gets slower than this is a swing that
    skims the floor, not a step, and is left alone (holding it would drag the swinging foot back).
    Each knee bends about its hinge estimated on ``local_rotations`` (:func:`anim_core.methods.ik.hinge_axis`; a leg
    straight in every pose has none and is solved without), so it never flips or bends backwards near full reach.
    ``max_leg_change_deg``: no thigh turns by more than this, no knee bends more or less than its animated bend by
    more than this; where holding the foot would need more, it is held only part of the way
    (:func:`leg_limited_targets`; ``None``: no limit).
    """
    rot = np.array(local_rotations, dtype=np.float64)
    targets, weights = foot_targets(skeleton, rot, root_translation, legs, down, fps, feet, periodic,
                                    ground_velocity, up_axis, blend_frames, max_speed, rest_speed)
    root = np.asarray(root_translation, dtype=np.float64)
    frames = np.arange(rot.shape[0])
    _, pos = skeleton.forward_kinematics(rot, root)
    for f, chain in enumerate(legs):  # one solve per leg over all frames
        active = frames[weights[:, f] > 0]
        if active.size:
            pole, hinge = pos[active, chain[1]], leg_hinge(skeleton, local_rotations, root, chain)
            target = targets[active, f]
            if max_leg_change_deg is not None:
                target = leg_limited_targets(skeleton, rot[active], root[active], chain, target, weights[active, f],
                                             np.radians(max_leg_change_deg), pole, hinge)
            rot[active] = two_bone_ik(skeleton, rot[active], root[active], chain, target, pole=pole,
                                      weight=weights[active, f], hinge=hinge)
    return rot


def leg_angles(skeleton: Skeleton, rot: Array, root: Array, chain: tuple[int, int, int]) -> tuple[Array, Array]:
    """``(T, 3)`` the thigh's unit direction and ``(T,)`` the knee's bend (radians, 0: straight) of poses ``rot``
    (the leg angles :func:`leg_limited_targets` and :func:`anim_core.methods.footlock.standing` keep)."""
    pos = skeleton.forward_kinematics(rot, root)[1]
    thigh, shin = pos[:, chain[1]] - pos[:, chain[0]], pos[:, chain[2]] - pos[:, chain[1]]
    thigh /= np.linalg.norm(thigh, axis=-1, keepdims=True)
    shin /= np.linalg.norm(shin, axis=-1, keepdims=True)
    return thigh, np.arccos(np.clip(np.sum(thigh * shin, axis=-1), -1.0, 1.0))


def leg_limited_targets(skeleton: Skeleton, rot: Array, root: Array, chain: tuple[int, int, int], targets: Array,
                        weights: Array, tolerance: float, pole: Array | None, hinge: Array | None,
                        soft: float = 0.0, smooth_frames: int = 0, periodic: bool = False) -> Array:
    """``(T, 3)`` ankle targets for :func:`anim_core.methods.ik.two_bone_ik` (with ``weights``, ``pole (T, 3)``
    or None, ``hinge`` and ``soft``, as :func:`plant_feet` or :meth:`anim_core.methods.footlock.FootLockedClip.sample`
    solves) on the poses ``rot``/``root`` such that the solved leg's thigh turns by at most ``tolerance`` radians
    and its knee bends within ``tolerance`` of the animated bend: each target moves from the animated ankle
    towards the given one as far as that holds (bisection on the solve; the thigh and the knee are the leg's
    angles that the fidelity gate compares with the source, :mod:`anim_core.clips.fidelity`).  Targets the leg
    reaches within the tolerance are returned unchanged.

    ``smooth_frames`` > 0: how far each target goes is also made to change gradually from frame to frame (the least
    over ``2 * smooth_frames + 1`` frames, then averaged over as many; ``periodic`` for a loop), never further than
    the frame itself allows: where the allowed way jumps between two frames, a target following it would move the
    knee by several centimetres in one frame (a pop; the walk's hybrid_ik 0: 9 cm).  The leg then fits at least
    as well where the solve is monotonic in the way, as a two-bone leg's is."""
    thigh0, bend0 = leg_angles(skeleton, rot, root, chain)
    ankle = skeleton.forward_kinematics(rot, root)[1][:, chain[2]]
    way = targets - ankle

    def fits(s: Array, frames: NDArray[np.intp]) -> NDArray[np.bool_]:
        solved = two_bone_ik(skeleton, rot[frames], root[frames], chain, ankle[frames] + s[:, None] * way[frames],
                             pole=None if pole is None else pole[frames], weight=weights[frames], hinge=hinge,
                             soft=soft)
        thigh, bend = leg_angles(skeleton, solved, root[frames], chain)
        turn = np.arccos(np.clip(np.sum(thigh * thigh0[frames], axis=-1), -1.0, 1.0))
        return (turn <= tolerance) & (np.abs(bend - bend0[frames]) <= tolerance)

    bad = np.flatnonzero(~fits(np.ones(len(targets)), np.arange(len(targets))))
    if bad.size == 0:
        return np.array(targets, dtype=np.float64)
    lo, hi = np.zeros(bad.size), np.ones(bad.size)
    for _ in range(16):  # to 1/65536 of the way
        mid = 0.5 * (lo + hi)
        ok = fits(mid, bad)
        lo, hi = np.where(ok, mid, lo), np.where(ok, hi, mid)
    share = np.ones(len(targets))
    share[bad] = lo
    if smooth_frames > 0:
        k = 2 * smooth_frames + 1
        mode = "wrap" if periodic else "nearest"
        share = uniform_filter1d(minimum_filter1d(share, k, mode=mode), k, mode=mode)
    return ankle + share[:, None] * way


def leg_hinge(skeleton: Skeleton, local_rotations: ArrayLike, root: Array,
              chain: tuple[int, int, int]) -> Array | None:
    """The knee's hinge (:func:`anim_core.methods.ik.hinge_axis`) on the animated poses, or ``None`` for a leg
    straight in
    every pose: its plane is nowhere defined, and the plain solve (knee towards its animated position) is all
    there is — a motion file is not refused for it."""
    try:
        return hinge_axis(skeleton, local_rotations, root, chain)
    except ValueError:
        return None
