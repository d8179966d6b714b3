"""Generic hybrid keys for an animation of kind ``other``: the fewest keys, spread by an error criterion.

Conventions: a source is a :class:`~anim_core.math.clip.KeyframeClip` (one key per mocap frame); its hybrid is SQUAD
through the picked keys, no mirroring (:func:`~anim_core.methods.hybrid.build_other`), played ping-pong (default) or
as a
loop (``mode="loop"``: the source's last key repeats its first).  The error of a set of keys is the largest
distance, over all source frames and joints, between the joint positions of the hybrid and of the source (forward
kinematics, metres = source units x ``metres_per_unit``).

:func:`pick_keys` is greedy (Douglas-Peucker-like refinement): it starts from the first and last frames (a loop:
the first and the middle one) and adds, one at a time, the frame where the error is largest, until the error is
within ``tolerance`` metres.  The result is small but not proven minimal.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..math.clip import KeyframeClip, PlaybackMode
from .hybrid import build_other

Array = NDArray[np.float64]


@dataclass(frozen=True)
class PickedKeys:
    """``frames``: source frame indices of the keys (increasing); ``times``: their times (s); ``error``: the largest
    joint position error (m) of the hybrid through them; ``tolerance``: what was asked."""

    frames: tuple[int, ...]
    times: tuple[float, ...]
    error: float
    tolerance: float


def hybrid_error(source: KeyframeClip, frames: NDArray[np.intp], metres_per_unit: float = 1.0,
                 mode: PlaybackMode = "pingpong") -> Array:
    """``(F,)`` largest joint position error (m) per source frame of the SQUAD hybrid through ``frames`` played
    ``mode`` (the source's keys as they are, travel included)."""
    times = source.times[frames]
    clip = build_other(source.segment(0.0, source.duration, mode, in_place=False), times.tolist())
    pose = clip.sample(source.times - times[0])
    target = source.skeleton.forward_kinematics(source.rotations, source.root_translation)[1]
    got = source.skeleton.forward_kinematics(pose.rotations, pose.root_translation)[1]
    return np.linalg.norm(got - target, axis=-1).max(axis=-1) * metres_per_unit


def pick_keys(source: KeyframeClip, tolerance: float = 0.02, metres_per_unit: float = 1.0,
              max_keys: int = 64, mode: PlaybackMode = "pingpong") -> PickedKeys:
    """Keys whose SQUAD hybrid played ``mode`` reproduces ``source`` within ``tolerance`` metres at every frame
    (see module).

    Raises ``ValueError`` if ``max_keys`` keys do not reach the tolerance (the error reached is in the message); a
    clip-set entry sets ``max_keys`` (default :data:`anim_core.clips.entry.DEFAULT_MAX_KEYS`, 64).
    """
    if not tolerance > 0:
        raise ValueError(f"tolerance must be positive, got {tolerance}")
    n = len(source.times)
    if mode == "loop" and n < 3:
        raise ValueError(f"a loop of {n} frames has no keys to pick")
    frames = np.array([0, (n - 1) // 2 if mode == "loop" else n - 1], dtype=np.intp)
    while True:
        err = hybrid_error(source, frames, metres_per_unit, mode)
        if mode == "loop":
            err = err[:-1]  # the last frame is where the loop starts again: key 0, not a key of its own
        worst = int(np.argmax(err))
        if err[worst] <= tolerance:
            break
        if len(frames) >= max_keys or worst in frames:
            raise ValueError(f"{len(frames)} keys reproduce the motion within {err[worst] * 1000:.1f} mm only, not "
                             f"{tolerance * 1000:.1f} mm; allow more keys (max_keys, now {max_keys}) or a larger "
                             f"tolerance")
        frames = np.sort(np.append(frames, worst))
    return PickedKeys(tuple(int(f) for f in frames), tuple(float(t) for t in source.times[frames]),
                      float(err.max()), tolerance)
