"""Posing crowds fast: any clip as a uniform table of keys, evaluated for many characters by one compiled kernel.

The reference implementation is ``clip.sample(t, method="nlerp")`` followed by ``Skeleton.forward_kinematics``
(numpy, float64).  For a crowd, every clip (dense keyframe or hybrid) becomes a :class:`PoseTable`: keys on a
uniform time grid, sign-continuous, float32.  A keyframe clip's own keys are used as they are (the table gives
exactly the reference's nlerp); a hybrid clip is *baked* once at build time, its SQUAD or spring curve sampled
at ``rate`` keys per second, so that posing a hybrid character costs exactly what posing a keyframe character
costs: gather two keys, nlerp, forward kinematics; the memory of dense keys is the price (the benchmark's
``baked`` variant).  :func:`anim_core.runtime.pose_crowd` runs that per character and joint in the numba kernel
of :class:`anim_core.runtime.TableRuntime` (single- or multi-threaded); without numba it falls back to
:func:`pose_crowd_numpy`.  The runtime builds on this module's tables; this module imports nothing of it.
:mod:`anim_core.runtime` evaluates hybrids from their own keys instead.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from ..math.clip import PLAYBACK_MODES, KeyframeClip, playback_time
from ..math.quat import make_continuous, quat_angle
from ..math.skeleton import Skeleton

if TYPE_CHECKING:
    from ..methods.hybrid import AnimClip

Array = NDArray[np.float64]
BAKE_RATE = 30.0  # keys per second a baked hybrid table starts from (the keyframe rate), doubled as needed
# Largest angle between a joint's global rotation from a baked table and from the exact curve, at any time.  The
# spring crouch's path has corners at its keys, which a table of any rate cuts by up to a quarter of its step
# times the jump in angular velocity, so the tolerance cannot be much tighter than 0.2 degree at sane table sizes.
BAKE_TOLERANCE_DEG = 0.25
MAX_BAKE_RATE = 7680.0

try:  # the compiled kernel is optional; the numpy path is the reference and the fallback
    import numba
except ImportError:  # pragma: no cover - numba is a dependency, but keep working without it
    numba = None


@dataclass(frozen=True, eq=False)
class PoseTable:
    """A clip as keys on a uniform grid: ``rotations (K, J, 4)`` float32 (w, x, y, z), sign-continuous along K;
    ``root (K, 3)`` float32; key ``k`` at ``k * dt`` seconds, the last at the clip's ``duration``."""

    skeleton: Skeleton
    rotations: NDArray[np.float32]
    root: NDArray[np.float32]
    dt: float
    mode: str
    velocity: NDArray[np.float32]  # horizontal travel per second added in loop mode (zero for in-place clips)

    @property
    def duration(self) -> float:
        return self.dt * (self.rotations.shape[0] - 1)

    @property
    def nbytes(self) -> int:
        return int(self.rotations.nbytes + self.root.nbytes)


def uniform(times: Array) -> bool:
    """Whether key ``times (K,)`` are evenly spaced (to rounding), so that a key is found by division."""
    dt = np.diff(times)
    return bool(np.allclose(dt, dt[0], rtol=1e-9, atol=1e-12))


def table_from_keyframes(clip: KeyframeClip) -> PoseTable:
    """The keyframe clip's own keys (they must be uniformly spaced, as the clip set's are)."""
    if not uniform(clip.times):
        raise ValueError("keyframe clip keys are not uniformly spaced; resample() it first")
    dt = np.diff(clip.times)
    return _table(clip.skeleton, clip.rotations, clip.root_translation, clip.times, float(dt[0]), clip.mode,
                  clip.velocity, travels=clip.mode == "loop" and not clip.in_place, in_place=clip.in_place)


def root_offsets(root: Array, times: Array, velocity: Array, travels: bool, in_place: bool) -> tuple[Array, Array]:
    """``(K, 3)`` the root at the key ``times (K,)`` without its travel, and ``(3,)`` the travel per second a
    kernel adds back (zero unless ``travels``, a travelling loop); an in-place clip's keys lose it for good."""
    if travels or in_place:
        root = root - velocity * times[:, None]
    return root, (velocity if travels else np.zeros(3))


def keyframe_root(clip: KeyframeClip) -> tuple[Array, Array]:
    """:func:`root_offsets` of a keyframe clip's keys (the root that :meth:`KeyframeClip.sample` interpolates)."""
    return root_offsets(clip.root_translation, clip.times, clip.velocity,
                        travels=clip.mode == "loop" and not clip.in_place, in_place=clip.in_place)


def _table(skeleton: Skeleton, rotations: Array, root: Array, times: Array, dt: float, mode: str,
           velocity: Array, travels: bool, in_place: bool) -> PoseTable:
    # The table holds the root's offsets from its travel; the kernel adds the travel back for a travelling loop.
    root, velocity = root_offsets(root, times, velocity, travels, in_place)
    return PoseTable(skeleton, np.asarray(rotations, np.float32), np.asarray(root, np.float32), dt, mode,
                     np.asarray(velocity, np.float32))


def bake(clip: AnimClip, rate: float = BAKE_RATE, tolerance_deg: float = BAKE_TOLERANCE_DEG) -> PoseTable:
    """Sample any clip (hybrid or keyframe) over one period into a table.

    Starts at ``rate`` keys per second and doubles it until every joint's global rotation between two table keys
    is within ``tolerance_deg`` of the exact curve (checked halfway between all keys, where the error peaks).
    """
    mode = clip.mode
    if mode not in PLAYBACK_MODES:
        raise ValueError(f"cannot bake playback mode {mode!r}")
    while True:
        table = _bake_at(clip, rate, mode)
        # Compare what a viewer sees, the global (model-space) rotations, where errors add up along each chain.
        mid = (np.arange(table.rotations.shape[0] - 1) + 0.5) * table.dt
        exact, _ = clip.skeleton.forward_kinematics(clip.sample(mid).rotations)
        approx = table.rotations[:-1].astype(np.float64) + table.rotations[1:]
        approx, _ = clip.skeleton.forward_kinematics(approx / np.linalg.norm(approx, axis=-1, keepdims=True))
        error = np.degrees(quat_angle(approx, exact).max())
        if error <= tolerance_deg or rate >= MAX_BAKE_RATE:
            return table
        rate *= 2


def _bake_at(clip: AnimClip, rate: float, mode: str) -> PoseTable:
    duration = float(clip.duration)
    n = max(2, int(np.ceil(duration * rate)))
    times = np.linspace(0.0, duration, n + 1)
    # Inside one period: a loop's end is its start again, which sample() would map to the next cycle's time 0.
    pose = clip.sample(np.minimum(times, np.nextafter(duration, 0.0)) if mode == "loop" else times)
    velocity = np.asarray(clip.velocity, np.float64)
    # The samples are already in place when the clip is; a travelling loop's travel comes off the table.
    table = _table(clip.skeleton, make_continuous(pose.rotations, axis=0), pose.root_translation, times,
                   duration / n, mode, velocity, travels=mode == "loop" and not clip.in_place,
                   in_place=False)
    if mode == "loop":  # close exactly: the last key is the first one, on the side that keeps the keys continuous
        sign = np.where(np.sum(table.rotations[-2] * table.rotations[0], axis=-1, keepdims=True) < 0, -1, 1)
        table.rotations[-1] = table.rotations[0] * sign
        table.root[-1] = table.root[0]
    return table


def pose_crowd_numpy(table: PoseTable, t: NDArray[np.floating]) -> tuple[Array, Array]:
    """Reference-style evaluation of a table: nlerp between its keys, then forward kinematics (float64)."""
    t = np.asarray(t, dtype=np.float64)
    clip_t, cycles = playback_time(t, table.duration, table.mode)  # type: ignore[arg-type]
    f = clip_t / table.dt
    i = np.clip(np.floor(f).astype(np.intp), 0, table.rotations.shape[0] - 2)
    frac = (f - i)[:, None, None]
    keys = table.rotations.astype(np.float64)
    q = keys[i] * (1.0 - frac) + keys[i + 1] * frac
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    root = table.root[i] * (1.0 - frac[:, 0]) + table.root[i + 1] * frac[:, 0]
    root = root + table.velocity * (clip_t + cycles * table.duration)[:, None]
    return table.skeleton.forward_kinematics(q, root)


@dataclass
class CrowdBuffers:
    """Output arrays reused from frame to frame: global rotations ``(N, J, 4)`` and positions ``(N, J, 3)``."""

    rotations: NDArray[np.float32]
    positions: NDArray[np.float32]

    @classmethod
    def for_crowd(cls, n: int, joints: int) -> CrowdBuffers:
        return cls(np.empty((n, joints, 4), np.float32), np.empty((n, joints, 3), np.float32))
