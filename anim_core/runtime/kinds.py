"""The runtime kinds: posing crowds from the keys each clip stores, one compiled kernel per kind of clip
(:mod:`anim_core.runtime.kernels`), nothing resampled in time.  Built offline by :mod:`anim_core.runtime.offline`,
checked by :mod:`anim_core.runtime.checks`.

Conventions: quaternions ``(w, x, y, z)`` (see :mod:`anim_core.math.quat`), times in seconds, runtime arrays float32
unless a comment says otherwise; every output is the model-space (global) rotation ``(N, J, 4)`` and position
``(N, J, 3)`` of every joint of ``N`` characters, each at its own running time ``t (N,)``.

The runtimes, built once per clip at load time (:func:`runtime_for`), evaluated per frame by :meth:`pose`:

* :class:`TableRuntime`: keys on a uniform grid, nlerp between two of them (a keyframe clip's own keys, or a
  hybrid baked by :func:`anim_core.runtime.crowd.bake`); or keys at uneven times (a ``reduced`` clip: the reduction
  keeps
  whole poses, so one binary search of the key times per character), nlerp the same way.
* :class:`QuantizedRuntime`: a ``quantized`` clip's integers (uint8 up to 8 bits, uint16 up to 16) with each
  track's ``low`` and ``step``; the kernel dequantizes the two keys it blends, normalizes each (as
  :meth:`~anim_core.methods.compression.QuantizedTracks.dequantize` does), then nlerps as the table does.
* :class:`SplineRuntime`: a SQUAD hybrid (gait, idle).  Exact SQUAD costs three slerps per joint; instead each
  segment between two keys is a cubic Bezier curve in R^4, normalized, whose two inner control points per joint
  are fitted once to the exact SQUAD curve (minimax, Lawson's iteratively reweighted least squares).  The end
  control points are the keys themselves, so the curve passes through every key.  Per joint and frame that is
  four weighted quaternions and a normalization, like nlerp's two.  The fit's error against the exact curve is
  measured when the runtime is built (``fit_error_deg``) and must stay within :data:`FIT_TOLERANCE_DEG`.
  A mirrored gait (second half cycle = the mirror image of the first, as :func:`anim_core.methods.hybrid.build_gait`
  makes it) stores the first half only; the second half is evaluated there and mirrored per joint (partner
  joint, then a fixed 4x4 orthogonal map: the mirror about the character's bind pose is a left and a right
  multiplication by unit quaternions), which is exact because such a map commutes with SQUAD and normalization.
* :class:`SpringRuntime`: the crouch.  Per character the closed-form spring gives the path parameter
  (:func:`crouch_path_parameter`), per joint an unclamped slerp between the two keys of its segment with the
  angle precomputed.
* :class:`C2Runtime`: a ``hybrid_c2`` clip's cumulative B-spline (:mod:`anim_core.methods.c2spline`) evaluated exactly
  from its control points: per character the knot span and the cubic basis, per joint the first control point
  times three exponentials of the steps between control points (their logarithms, as half angle and axis, are
  computed at load time); the root is the SQUAD clip's root spline.  Checked at load against
  :meth:`C2Clip.sample` (``error_deg`` <= :data:`C2_TOLERANCE_DEG`).
* :class:`FootLockRuntime`: a ``hybrid_ik`` clip: its hybrid's runtime (the fitted SQUAD segments or the spring)
  poses the character, then per leg the ankle target and weight are evaluated from the clip's
  cubic tracks (stored as the values and slopes at each frame: a cubic Hermite piece per frame interval is
  exactly the spline's piece) and the analytic two-bone IK of :func:`anim_core.methods.ik.two_bone_ik` (the knee's
  hinge, no pole, the soft reach, the ankle keeping its world orientation) turns hip and knee; the leg's joints
  below the hip are re-posed from the new rotations.  A leg with weight 0 is left alone.  Checked at load
  against :meth:`FootLockedClip.sample` (``error_deg`` <=
  :data:`FOOT_LOCK_TOLERANCE_DEG`).

Memory: every array a runtime holds for its clip is animation data and counts in :attr:`runtime_bytes` (the keys,
control points, angles, segment times, the few scalars as a float64 array; a quantized clip's integers and
ranges; a foot-locked clip's base runtime, legs, joint lists and tracks); the skeleton (parents, offsets) is
shared by all clips of a character and the output buffers are per character, so neither counts.

Threads: ``pose(..., parallel=True)`` splits the characters it poses into :func:`pose_threads` runs of
consecutive ones, one per thread, each running the kind's one kernel, which releases the GIL; every character is
posed by the same code either way, so the results are identical.

LOD: ``active`` (a per-joint mask, :func:`bone_lod_mask`) holds unselected joints at the clip's first key
without sampling them (bone LOD: a far character's fingers and toes stop moving, its skeleton stays whole);
``first``/``stride`` pose only characters ``first, first + stride, ...`` and leave the others' buffers as they
were (update-rate LOD: each character re-posed every ``stride``-th frame).
"""
from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, fields
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..math.clip import PLAYBACK_MODES, KeyframeClip
from ..math.skeleton import Skeleton
from ..methods.c2spline import C2Clip
from ..methods.footlock import FootLockedClip
from ..methods.hybrid import SpringClip, SquadClip
from . import kernels
from .crowd import CrowdBuffers, PoseTable, keyframe_root, numba, pose_crowd_numpy

Array = NDArray[np.float64]
F32 = NDArray[np.float32]
AnimClip = KeyframeClip | SquadClip | SpringClip | C2Clip | FootLockedClip

# Bone LOD: joints whose names contain one of these hold their first key (level 0 evaluates every joint).
BONE_LODS: dict[int, tuple[str, ...]] = {
    0: (),
    1: ("Toe", "Finger", "Index", "Thumb"),
    2: ("Toe", "Finger", "Index", "Thumb", "Hand", "Neck1", "Shoulder"),
}


def bone_lod_mask(skeleton: Skeleton, level: int) -> NDArray[np.uint8]:
    """``(J,)`` 1 for every joint evaluated at LOD ``level`` (see :data:`BONE_LODS`), 0 for joints held still."""
    if level not in BONE_LODS:
        raise ValueError(f"bone LOD level must be one of {sorted(BONE_LODS)}, got {level!r}")
    return np.array([not any(p in name for p in BONE_LODS[level]) for name in skeleton.names], np.uint8)


def animated_joints(clip: Any, level: int = 0) -> NDArray[np.uint8]:
    """``(J,)`` 1 for every joint the crowd runtime samples when it plays ``clip`` at bone LOD ``level``, 0 for the
    joints it holds: those of ``level`` (:func:`bone_lod_mask`) and a bone-LOD clip's frozen joints
    (:class:`~anim_core.methods.lod.BoneLodClip`: their keys are the bind pose throughout, so the runtime copies
    the first key, never samples or interpolates them; forward kinematics still places them).  This is the mask
    a bone-LOD clip is played, timed and costed with (``animstudy bench``, the clip manifest's
    ``cost_ms_per_1000``)."""
    from ..methods.lod import BoneLodClip

    mask = bone_lod_mask(clip.skeleton, level)
    if isinstance(clip, BoneLodClip):
        mask = mask & (~np.asarray(clip.frozen, bool)).astype(np.uint8)
    return mask


def frozen(a: ArrayLike, dtype: Any) -> NDArray[Any]:
    out = np.ascontiguousarray(a, dtype=dtype).copy()
    out.flags.writeable = False
    return out


class _Runtime:
    """Shared by the runtimes: memory accounting, buffer validation, the call into the compiled kernel."""

    skeleton: Skeleton

    def arrays(self) -> dict[str, NDArray[Any]]:
        """Every array the runtime holds for its clip, in the order the kernel takes them."""
        return {f.name: getattr(self, f.name) for f in fields(self)  # type: ignore[arg-type]
                if isinstance(getattr(self, f.name), np.ndarray)}

    @property
    def runtime_bytes(self) -> int:
        return int(sum(a.nbytes for a in self.arrays().values()))

    def pose(self, t: ArrayLike, out: CrowdBuffers | None = None, parallel: bool = False,
             active: NDArray[np.uint8] | None = None, first: int = 0, stride: int = 1) -> CrowdBuffers:
        """Global rotations and positions of ``N`` characters at running times ``t (N,)`` seconds.

        ``out``: buffers ``(N, J, 4)`` / ``(N, J, 3)`` float32 to write (allocated when ``None``); ``parallel``:
        characters split across :func:`pose_threads` threads (module docstring); ``active``, ``first``,
        ``stride``: LOD (module docstring).  Every input is checked before the kernel touches memory
        (``ValueError`` otherwise).
        """
        if numba is None:  # pragma: no cover - numba is a dependency
            raise RuntimeError("the keys runtime needs numba")
        t, out, active = check_inputs(self.skeleton, t, out, active, first, stride)
        kernel, arrays = self._kernel(), (*self.arrays().values(), t, *skeleton_arrays(self.skeleton), active)
        threads = min(pose_threads(), len(t)) if parallel else 1
        if threads <= 1:
            kernel(*arrays, first, stride, len(t), out.rotations, out.positions)
            return out
        # The characters first, first + stride, ... in `threads` runs of consecutive ones, one per thread.
        count = -(-(len(t) - first) // stride)
        starts = [first + (count * i // threads) * stride for i in range(threads + 1)]
        pool = _thread_pool(threads - 1)
        shares = [pool.submit(kernel, *arrays, starts[i], stride, starts[i + 1], out.rotations, out.positions)
                  for i in range(1, threads)]
        kernel(*arrays, starts[0], stride, starts[1], out.rotations, out.positions)
        for share in shares:
            share.result()
        return out

    def _kernel(self) -> Any:
        raise NotImplementedError


def pose_threads() -> int:
    """How many threads ``pose(..., parallel=True)`` uses: one per core this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


_pools: dict[tuple[int, int], ThreadPoolExecutor] = {}
_pools_lock = threading.Lock()


def _thread_pool(workers: int) -> ThreadPoolExecutor:
    """The process's pool of ``workers`` threads (per process id: a forked child does not inherit threads)."""
    key = (os.getpid(), workers)
    with _pools_lock:
        if key not in _pools:
            _pools[key] = ThreadPoolExecutor(workers, thread_name_prefix="anim-pose")
        return _pools[key]


@lru_cache(maxsize=64)
def skeleton_arrays(skeleton: Skeleton) -> tuple[NDArray[np.int64], F32]:
    """Parents and offsets as the kernels take them (per skeleton, shared by all its clips)."""
    return skeleton.parents.astype(np.int64), skeleton.offsets.astype(np.float32)


def check_inputs(skeleton: Skeleton, t: ArrayLike, out: CrowdBuffers | None, active: NDArray[np.uint8] | None,
                 first: int, stride: int) -> tuple[Array, CrowdBuffers, NDArray[np.uint8]]:
    """Validated kernel inputs: times ``(N,)`` float64, output buffers, joint mask ``(J,)`` uint8."""
    times = np.asarray(t)
    if times.ndim != 1:
        raise ValueError(f"times must be a 1-D array (one per character), got shape {times.shape}")
    if not np.issubdtype(times.dtype, np.number) or np.issubdtype(times.dtype, np.complexfloating):
        raise ValueError(f"times must be real numbers, got dtype {times.dtype}")
    times = np.ascontiguousarray(times, dtype=np.float64)
    if not np.all(np.isfinite(times)):
        raise ValueError("times must be finite")
    n, j = times.shape[0], skeleton.n_joints
    if out is None:
        out = CrowdBuffers.for_crowd(n, j)
    for name, buf, width in (("rotations", out.rotations, 4), ("positions", out.positions, 3)):
        if not isinstance(buf, np.ndarray) or buf.dtype != np.float32:
            raise ValueError(f"output {name} must be a float32 array, got {getattr(buf, 'dtype', type(buf))}")
        if buf.shape != (n, j, width):
            raise ValueError(f"output {name} must have shape ({n}, {j}, {width}) for {n} characters, "
                             f"got {buf.shape}")
        if not buf.flags.c_contiguous or not buf.flags.writeable:
            raise ValueError(f"output {name} must be C-contiguous and writeable")
    if active is None:
        active = np.ones(j, np.uint8)
    active = np.asarray(active)
    if active.shape != (j,) or active.dtype not in (np.uint8, np.bool_):
        raise ValueError(f"active must be a (J,) = ({j},) uint8 or bool mask, got {active.shape} {active.dtype}")
    if isinstance(stride, bool) or not isinstance(stride, int | np.integer) or stride < 1:
        raise ValueError(f"stride must be a whole number >= 1, got {stride!r}")
    if isinstance(first, bool) or not isinstance(first, int | np.integer) or not 0 <= first < stride:
        raise ValueError(f"first must be a whole number in [0, stride), got {first!r}")
    return times, out, np.ascontiguousarray(active, np.uint8)


# --- the runtimes ------------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class TableRuntime(_Runtime):
    """Keys on a uniform grid (:class:`anim_core.runtime.crowd.PoseTable`) or at uneven times: ``rotations (K, J, 4)``,
    ``root (K, 3)`` (without travel), ``velocity (3,)``, ``params (3,)`` float64 = (key step s, or 0 for uneven
    keys; duration s; playback mode index), ``key_times (K,)`` float64 s for uneven keys (empty on a grid)."""

    skeleton: Skeleton
    rotations: F32
    root: F32
    velocity: F32
    params: Array
    key_times: Array

    @classmethod
    def from_table(cls, table: PoseTable) -> TableRuntime:
        return cls(table.skeleton, frozen(table.rotations, np.float32), frozen(table.root, np.float32),
                   frozen(table.velocity, np.float32),
                   frozen([table.dt, table.duration, PLAYBACK_MODES.index(table.mode)], np.float64),
                   frozen(np.zeros(0), np.float64))

    @classmethod
    def from_uneven_keys(cls, clip: KeyframeClip) -> TableRuntime:
        """A keyframe clip's own keys at their own times (a ``reduced`` clip), searched per character."""
        root, velocity = keyframe_root(clip)
        return cls(clip.skeleton, frozen(clip.rotations, np.float32), frozen(root, np.float32),
                   frozen(velocity, np.float32),
                   frozen([0.0, clip.duration, PLAYBACK_MODES.index(clip.mode)], np.float64),
                   frozen(clip.times, np.float64))

    def _kernel(self) -> Any:
        return kernels.TABLE


@dataclass(frozen=True, eq=False)
class SplineRuntime(_Runtime):
    """A SQUAD clip as normalized cubic Bezier segments in R^4.

    ``seg_times (S + 1,)`` float64: the stored segments' start times and the last one's end (for a mirrored gait
    the first half cycle only); ``controls (3 S + 1, J, 4)``: segment ``s`` has control points ``3s .. 3s + 3``,
    the keys at ``3s``; ``root_times (R + 1,)`` float64 and ``root_coef (R, 4, 3)``: the root spline of the
    whole period, cubic in seconds from the segment start, highest power first (scipy's ``CubicSpline.c``);
    ``mirror_src (J,)`` int32: each joint's partner, and ``mirror_map (1 or J, 4, 4)``: the linear map of each
    joint's quaternion (w, x, y, z) after the partner's is taken (both empty without
    mirror); ``velocity (3,)`` travel per second in loop mode;
    ``params (3,)`` float64 = (duration s, playback mode index, half period s or 0 without mirror).
    ``fit_error_deg``: the measured largest global-rotation error against the exact curve (not runtime data).
    """

    skeleton: Skeleton
    seg_times: Array
    controls: F32
    root_times: Array
    root_coef: F32
    mirror_src: NDArray[np.int32]
    mirror_map: F32
    velocity: F32
    params: Array
    fit_error_deg: float

    def _kernel(self) -> Any:
        return kernels.SPLINE


@dataclass(frozen=True, eq=False)
class SpringRuntime(_Runtime):
    """The spring crouch: ``key_params (K,)`` float64 (key positions on the path, 0 .. 1), ``keys (K, J, 4)``
    (sign-continuous), ``angles (K - 1, J)`` the 4-D angle between the two keys of each segment and
    ``inv_sin (K - 1, J)`` its reciprocal sine (0 where the angle is too small: linear weights there),
    ``key_root (K, 3)``; ``params (6,)`` float64 = (zeta, omega rad/s, time scale, normalization, duration s,
    playback mode index), read off the :class:`~anim_core.methods.hybrid.SpringClip`'s fields."""

    skeleton: Skeleton
    key_params: Array
    keys: F32
    angles: F32
    inv_sin: F32
    key_root: F32
    params: Array

    def _kernel(self) -> Any:
        return kernels.SPRING


@dataclass(frozen=True, eq=False)
class QuantizedRuntime(_Runtime):
    """A quantized keyframe clip: ``codes (K, J, 4)`` uint8 or uint16, component ``c`` of joint ``j`` at key ``k``
    is ``low[j, c] + codes[k, j, c] * step[j, c]`` (``low``, ``step (J, 4)`` float32); ``root (K, 3)``,
    ``velocity (3,)``, ``params (3,)`` and ``key_times`` as :class:`TableRuntime`'s."""

    skeleton: Skeleton
    codes: NDArray[np.unsignedinteger]
    low: F32
    step: F32
    root: F32
    velocity: F32
    params: Array
    key_times: Array

    def _kernel(self) -> Any:
        return kernels.QUANTIZED


@dataclass(frozen=True, eq=False)
class C2Runtime(_Runtime):
    """A ``hybrid_c2`` clip: ``knots (K + 7,)`` float64 s (:attr:`PeriodicC2Spline.knots`), ``control (K, J, 4)``
    the control points, ``steps (K, J, 4)`` = (half angle rad, unit axis) of ``w_i = log(c_(i-1)^-1 c_i)``;
    ``root_times``, ``root_coef``, ``velocity`` as :class:`SplineRuntime`'s; ``params (4,)`` float64 = (duration
    s, playback mode index, spline period s, first key time s).  ``error_deg``: the measured largest
    global-rotation error against :meth:`C2Clip.sample` (not runtime data).  A joint held by bone LOD holds its
    first control point."""

    skeleton: Skeleton
    knots: Array
    control: F32
    steps: F32
    root_times: Array
    root_coef: F32
    velocity: F32
    params: Array
    error_deg: float

    def _kernel(self) -> Any:
        return kernels.C2


@dataclass(frozen=True, eq=False)
class FootLockRuntime(_Runtime):
    """A ``hybrid_ik`` clip: ``base``, its hybrid's runtime (fitted SQUAD or spring), and per leg ``F``:
    ``chains (F, 3)`` int32 (hip, knee, ankle), ``hinges (F, 3)`` each knee's hinge in its local frame,
    ``below (F, L)`` int32 the joints under the hip in topological
    order (-1 padded) with ``turns (F, L)`` int32 what turns each (0: the hip's rotation, 1: the knee's, 2:
    nothing, under the ankle);
    ``track_values``/``track_slopes (P, F, 4)`` float32 the ankle target (x, y, z, relative to the root without
    travel) and weight at the ``P`` frames of the clip's tracks and their slopes per second; ``ik_params (9,)``
    float64 = (frames per second, 1 for a loop's periodic tracks else 0, duration s, playback mode index, travel
    per second x, y, z, the soft reach, the IK's straight-knee threshold).  ``error_deg``: measured against
    :meth:`FootLockedClip.sample` (not runtime data)."""

    skeleton: Skeleton
    base: SplineRuntime | SpringRuntime
    chains: NDArray[np.int32]
    hinges: F32
    below: NDArray[np.int32]
    turns: NDArray[np.int32]
    track_values: F32
    track_slopes: F32
    ik_params: Array
    error_deg: float

    def arrays(self) -> dict[str, NDArray[Any]]:
        """The base runtime's arrays, then the foot locking's: the order the kernel takes them."""
        return {**{f"base.{k}": v for k, v in self.base.arrays().items()}, **super().arrays()}


    def _kernel(self) -> Any:
        if isinstance(self.base, SplineRuntime):
            return kernels.SPLINE_IK
        return kernels.SPRING_IK


AnyRuntime = TableRuntime | SplineRuntime | SpringRuntime | QuantizedRuntime | C2Runtime | FootLockRuntime


def pose_crowd(table: PoseTable, t: NDArray[np.floating], out: CrowdBuffers | None = None,
               parallel: bool = False) -> CrowdBuffers:
    """Global joint rotations and positions of ``N`` characters at their own times ``t (N,)`` seconds (float32).

    The table's compiled kernel (:class:`anim_core.runtime.TableRuntime`; ``parallel``: one thread per core) when
    numba is present, numpy otherwise.
    """
    t = np.ascontiguousarray(t, dtype=np.float64)
    sk = table.skeleton
    if numba is None:
        out = out or CrowdBuffers.for_crowd(t.shape[0], sk.n_joints)
        rot, pos = pose_crowd_numpy(table, t)
        out.rotations[:], out.positions[:] = rot, pos
        return out
    return TableRuntime.from_table(table).pose(t, out, parallel=parallel)
