"""Accuracy checks of the runtimes: the exact curve of a clip, a runtime's pose under a LOD, the angle between
them (the benchmark's and the offline fits' measure).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..math.clip import KeyframeClip
from ..math.quat import quat_angle
from .kinds import AnimClip, AnyRuntime, bone_lod_mask

Array = NDArray[np.float64]
F32 = NDArray[np.float32]


def period(clip: AnimClip) -> float:
    """Seconds after which the clip's playback repeats (a ping-pong clip's forward and back)."""
    return float(clip.duration) * (2.0 if clip.mode == "pingpong" else 1.0)


def sample_times(clip: AnimClip, rate: float) -> Array:
    """One period at ``rate`` samples per second, offset off any grid so no sample sits on a table key."""
    n = max(8, int(np.ceil(period(clip) * rate)))
    return (np.arange(n) + 0.3711) * (period(clip) / n)


def exact_global(clip: AnimClip, t: Array) -> tuple[Array, Array]:
    """The reference curve's global rotations and positions (numpy, float64; nlerp for keyframe clips)."""
    pose = clip.sample(t, method="nlerp") if isinstance(clip, KeyframeClip) else clip.sample(t)
    return clip.skeleton.forward_kinematics(pose.rotations, pose.root_translation)


def lod_pose(runtime: AnyRuntime, t: Array, bone_lod: int = 0, update_every: int = 1,
             frame_s: float = 1.0 / 60.0) -> F32:
    """Global rotations ``(N, J, 4)`` shown at times ``t`` under a LOD: bone LOD ``bone_lod``, and with
    ``update_every = k`` the worst case of the update-rate LOD, a pose ``k - 1`` frames of ``frame_s`` old."""
    active = bone_lod_mask(runtime.skeleton, bone_lod)
    return runtime.pose(np.asarray(t, np.float64) - (update_every - 1) * frame_s, active=active).rotations


def angle_error_deg(a: ArrayLike, b: ArrayLike) -> tuple[float, float]:
    """Largest and mean angle in degrees between corresponding rotations ``(..., 4)``."""
    angle = np.degrees(quat_angle(np.asarray(a, np.float64), np.asarray(b, np.float64)))
    return float(angle.max()), float(angle.mean())


def max_error_deg(runtime: AnyRuntime, clip: AnimClip, rate: float, **lod: Any) -> float:
    """Largest angle (degrees) between a joint's global rotation from ``runtime`` and from the exact curve over
    one period at ``rate`` samples per second (``lod``: see :func:`lod_pose`)."""
    t = sample_times(clip, rate)
    exact, _ = exact_global(clip, t)
    return angle_error_deg(lod_pose(runtime, t, **lod), exact)[0]

