"""Keyframe clips: local joint rotations and root translation at key times, and their playback.

Every clip in ``anim_core`` (dense keyframe or hybrid) answers ``sample(t) -> Pose`` for an array of times in
seconds, so a batch of characters at different times is one call.  Playback modes map the running time onto
the clip's own time axis ``[0, duration]``:

* ``"loop"``: wraps around; the root keeps travelling (each cycle adds the clip's horizontal displacement)
  unless the clip is played ``in_place``.
* ``"pingpong"``: forward, then backward, period ``2 * duration``.
* ``"clamp"``: holds the first/last pose outside the clip.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .quat import identity, make_continuous, nlerp, quat_conj, quat_mul, slerp
from .skeleton import Skeleton

Array = NDArray[np.float64]
PlaybackMode = Literal["loop", "pingpong", "clamp"]
PLAYBACK_MODES: tuple[PlaybackMode, ...] = ("loop", "pingpong", "clamp")


class Pose(NamedTuple):
    """Local rotations ``(..., J, 4)`` (w, x, y, z) and root translation ``(..., 3)`` of a batch of poses."""

    rotations: Array
    root_translation: Array


def playback_time(t: ArrayLike, duration: float, mode: PlaybackMode) -> tuple[Array, Array]:
    """Map running times ``t (...)`` in seconds to clip times in ``[0, duration]``.

    Returns ``(clip_time, cycles)``: ``cycles`` counts completed loops (``floor(t / duration)``) for ``"loop"`` and
    is 0 otherwise; the root's travel uses it.
    """
    t = np.asarray(t, dtype=np.float64)
    if mode == "clamp":
        return np.clip(t, 0.0, duration), np.zeros_like(t)
    if mode == "loop":
        cycles = np.floor(t / duration)
        return np.clip(t - cycles * duration, 0.0, duration), cycles
    if mode == "pingpong":
        tt = np.mod(t, 2.0 * duration)
        return np.where(tt > duration, 2.0 * duration - tt, tt), np.zeros_like(t)
    raise ValueError(f"playback mode must be one of {PLAYBACK_MODES}, got {mode!r}")


def horizontal(v: ArrayLike, up_axis: int) -> Array:
    """``v (..., 3)`` with its component along the up axis set to 0."""
    out = np.array(v, dtype=np.float64)
    out[..., up_axis] = 0.0
    return out


@dataclass(frozen=True, eq=False)
class KeyframeClip:
    """Dense keyframe animation (e.g. motion capture).

    ``times``: ``(K,)`` strictly increasing key times in seconds (shifted so the first is 0); ``rotations``:
    ``(K, J, 4)`` local joint rotations; ``root_translation``: ``(K, 3)`` in skeleton units.  For ``"loop"`` the
    last key should be the pose that repeats the first one (one full cycle ends there).  ``in_place`` removes
    the root's mean horizontal velocity over the clip (a treadmill); ``up_axis`` is 1 (Y) for BVH data.
    """

    skeleton: Skeleton
    times: Array
    rotations: Array
    root_translation: Array
    mode: PlaybackMode = "loop"
    in_place: bool = False
    up_axis: int = 1
    name: str = ""
    velocity: Array = field(init=False, repr=False)

    def __post_init__(self) -> None:
        times = np.asarray(self.times, dtype=np.float64)
        rot = np.asarray(self.rotations, dtype=np.float64)
        root = np.asarray(self.root_translation, dtype=np.float64)
        k, j = times.shape[0], self.skeleton.n_joints
        if times.ndim != 1 or k < 2:
            raise ValueError(f"a keyframe clip needs at least 2 key times, got shape {times.shape}")
        if rot.shape != (k, j, 4) or root.shape != (k, 3):
            raise ValueError(f"expected rotations ({k}, {j}, 4) and root translation ({k}, 3), "
                             f"got {rot.shape} and {root.shape}")
        if not np.all(np.diff(times) > 0):
            raise ValueError("key times must be strictly increasing")
        if self.mode not in PLAYBACK_MODES:
            raise ValueError(f"playback mode must be one of {PLAYBACK_MODES}, got {self.mode!r}")
        times = times - times[0]
        # Sign-continuous keys make every interpolation between neighbours take the short way.
        rot = make_continuous(rot, axis=0)
        velocity = horizontal(root[-1] - root[0], self.up_axis) / times[-1]
        for name, value in (("times", times), ("rotations", rot), ("root_translation", root),
                            ("velocity", velocity)):
            value.flags.writeable = False
            object.__setattr__(self, name, value)

    @property
    def duration(self) -> float:
        return float(self.times[-1])

    @property
    def n_keys(self) -> int:
        return int(self.times.shape[0])

    @property
    def key_times(self) -> Array:
        """``(K,)`` times of the stored keys: a loop's last key repeats its first and is not stored."""
        return self.times[:-1] if self.mode == "loop" else self.times

    @property
    def key_rotations(self) -> Array:
        """``(K, J, 4)`` rotations of the stored keys (as :attr:`key_times`)."""
        return self.rotations[: self.key_times.size]

    def _segments(self, clip_t: Array) -> tuple[Array, Array]:
        i = np.clip(np.searchsorted(self.times, clip_t, side="right") - 1, 0, self.n_keys - 2)
        frac = (clip_t - self.times[i]) / (self.times[i + 1] - self.times[i])
        return i, frac

    def sample(self, t: ArrayLike, method: Literal["nlerp", "slerp"] = "nlerp") -> Pose:
        """Pose at running times ``t`` (seconds, any shape ``(...)``) -> rotations ``(..., J, 4)``, root ``(..., 3)``.

        ``method``: ``"nlerp"`` (what game runtimes use on dense keys) or ``"slerp"`` between the two neighbouring
        keys; root translation is interpolated linearly.
        """
        t = np.asarray(t, dtype=np.float64)
        clip_t, cycles = playback_time(t, self.duration, self.mode)
        i, frac = self._segments(clip_t)
        interp = nlerp if method == "nlerp" else slerp
        rot = interp(self.rotations[i], self.rotations[i + 1], frac[..., None])
        f = frac[..., None]
        root = self.root_translation[i] * (1.0 - f) + self.root_translation[i + 1] * f
        if self.in_place:
            root = root - self.velocity * clip_t[..., None]
        elif self.mode == "loop":
            root = root + self.velocity * (cycles * self.duration)[..., None]
        return Pose(rot, root)

    def resample(self, rate: float) -> KeyframeClip:
        """A clip with keys every ``1 / rate`` seconds (slerp between the original keys); the end key is kept."""
        if rate <= 0:
            raise ValueError(f"rate must be positive, got {rate}")
        n = int(np.floor(self.duration * rate + 1e-9))
        times = np.arange(n + 1) / rate
        if self.duration - times[-1] > 1e-9:
            times = np.append(times, self.duration)
        i, frac = self._segments(times)
        rot = slerp(self.rotations[i], self.rotations[i + 1], frac[:, None])
        root = self.root_translation[i] + (self.root_translation[i + 1] - self.root_translation[i]) * frac[:, None]
        return KeyframeClip(self.skeleton, times, rot, root, self.mode, self.in_place, self.up_axis, self.name)

    def closed_loop(self) -> KeyframeClip:
        """A copy whose last key repeats the first exactly, so the loop has no pop.

        Motion capture never returns exactly to its first pose; the mismatch ``c = last^-1 first`` of each joint is
        spread over the cycle (key at time ``t`` gets ``c^(t / duration)`` applied), as is the root's vertical
        mismatch.  The horizontal drift is the travel, which loop playback handles.
        """
        s = self.times / self.duration
        mismatch = quat_mul(quat_conj(self.rotations[-1]), self.rotations[0])  # (J, 4)
        rot = quat_mul(self.rotations, slerp(identity(mismatch.shape[:-1]), mismatch, s[:, None]))
        root = self.root_translation.copy()
        root[:, self.up_axis] += s * (root[0, self.up_axis] - root[-1, self.up_axis])
        return KeyframeClip(self.skeleton, self.times, rot, root, self.mode, self.in_place, self.up_axis, self.name)

    def key_pose(self, time: float) -> Pose:
        """The pose of the key nearest to ``time`` seconds (keys are taken from the data, not interpolated)."""
        k = int(np.argmin(np.abs(self.times - time)))
        return Pose(self.rotations[k].copy(), self.root_translation[k].copy())

    def nearest_key_time(self, time: float) -> float:
        return float(self.times[int(np.argmin(np.abs(self.times - time)))])

    def segment(self, start: float, stop: float, mode: PlaybackMode | None = None, in_place: bool | None = None,
                name: str | None = None) -> KeyframeClip:
        """The keys with ``start <= time <= stop`` (seconds) as a new clip starting at 0."""
        keep = (self.times >= start - 1e-9) & (self.times <= stop + 1e-9)
        if keep.sum() < 2:
            raise ValueError(f"segment {start}..{stop} s holds fewer than 2 keys of clip {self.name!r} "
                             f"(0..{self.duration:.3f} s)")
        return KeyframeClip(self.skeleton, self.times[keep], self.rotations[keep], self.root_translation[keep],
                            self.mode if mode is None else mode,
                            self.in_place if in_place is None else in_place, self.up_axis,
                            self.name if name is None else name)
