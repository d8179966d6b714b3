"""Keep planted feet planted: contact phases given per frame, legs pinned there with two-bone IK.

Offline (a clip builder's step, not a runtime job).  Conventions as in :mod:`anim_core.contacts` and
:mod:`anim_core.ik`: frames along axis 0 at ``fps``, positions in metres, ``up_axis`` vertical.  For each
foot and each contact phase (an interval of frames in which the foot is down, typically detected on the source
motion before retargeting), the ankle is held at one place on the ground — horizontally; its height stays the
animated one, so heel and toe still roll — and two-bone IK on hip-knee-ankle moves the leg there, the foot keeping
its animated world orientation.  The pin is where the ankle is in the phase's frame of least horizontal speed.
Over ``blend_frames`` frames on each side of a phase the IK weight eases in and out (smoothstep), so the leg never
jumps.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .contacts import contact_intervals
from .ik import two_bone_ik
from .skeleton import Skeleton

Array = NDArray[np.float64]


def _smoothstep(x: Array) -> Array:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _creep(ground: Array, k: int, max_step: float, horizontal: list[int]) -> Array:
    """The path ``(N, 3)`` that starts at ``ground[k]`` and follows ``ground (N, 3)`` forwards and backwards from
    there with horizontal steps no longer than ``max_step``: a foot that may roll but never slides fast."""
    out = ground.copy()

    def step(i: int, j: int) -> None:
        d = ground[j, horizontal] - ground[i, horizontal]
        length = float(np.linalg.norm(d))
        if length > max_step:
            d = d * (max_step / length)
        out[j, horizontal] = out[i, horizontal] + d

    for i in range(k, len(ground) - 1):  # frames of one contact phase
        step(i, i + 1)
    for i in range(k, 0, -1):
        step(i, i - 1)
    return out


def plant_feet(skeleton: Skeleton, local_rotations: ArrayLike, root_translation: ArrayLike,
               legs: Sequence[tuple[int, int, int]], down: ArrayLike, fps: float, periodic: bool = False,
               ground_velocity: ArrayLike | None = None, up_axis: int = 1, blend_frames: int = 2,
               max_speed: float = 0.4) -> Array:
    """Local rotations ``(T, J, 4)`` with each leg's ankle held in place while its foot is down.

    ``legs``: per foot the chain ``(hip, knee, ankle)`` (joint indices); ``down``: ``(T, F)`` contact per frame
    and foot; ``periodic``: the ``T`` frames are one loop (phases may wrap); ``ground_velocity (3,)`` m/s: for
    clips played in place, the ground moves at minus this under the character, so a pinned ankle follows it.
    ``max_speed`` m/s: inside a phase the ankle still follows its animated ground path (a foot rolls), but never
    faster than this (by default 0.4 m/s, below the skate threshold of :mod:`anim_core.contacts`).
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
    frames = np.arange(n)
    for f, chain in enumerate(legs):  # one solve per leg over all frames
        _, pos = skeleton.forward_kinematics(rot, root)
        ankle = pos[:, chain[2]]
        speed = np.linalg.norm(np.gradient(ankle, axis=0)[:, horizontal] * fps + g[horizontal], axis=1)
        target = ankle.copy()
        weight = np.zeros(n)
        for start, stop in contact_intervals(contact[:, f], periodic):  # one per contact phase
            inside = np.arange(start, stop)
            ground = ankle[inside % n] + g * (inside / fps)[:, None]  # the ankle on the ground
            pinned = _creep(ground, int(np.argmin(speed[inside % n])), max_speed / fps, horizontal)
            pinned = np.concatenate([np.repeat(pinned[:1], blend_frames, 0), pinned,
                                     np.repeat(pinned[-1:], blend_frames, 0)])
            span = np.arange(start - blend_frames, stop + blend_frames)
            w = np.where(span < start, _smoothstep((span - start + blend_frames + 1) / (blend_frames + 1)),
                         np.where(span >= stop, _smoothstep((stop + blend_frames - span) / (blend_frames + 1)), 1.0))
            if not periodic:
                keep = (span >= 0) & (span < n)
                span, w, pinned = span[keep], w[keep], pinned[keep]
            idx = span % n
            better = w > weight[idx]
            idx, span, w = idx[better], span[better], w[better]
            moving = pinned[better] - g * (span / fps)[:, None]  # the ground place in the clip's frame
            target[idx[:, None], horizontal] = moving[:, horizontal]
            weight[idx] = w
        active = frames[weight > 0]
        if active.size:
            rot[active] = two_bone_ik(skeleton, rot[active], root[active], chain, target[active],
                                      weight=weight[active])
    return rot
