"""Posing crowds from the keys each clip stores: one compiled kernel per kind of clip, nothing resampled in time.

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
  joint, sign flips), which is exact because the mirror commutes with SQUAD.
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

LOD: ``active`` (a per-joint mask, :func:`bone_lod_mask`) holds unselected joints at the clip's first key
without sampling them (bone LOD: a far character's fingers and toes stop moving, its skeleton stays whole);
``first``/``stride`` pose only characters ``first, first + stride, ...`` and leave the others' buffers as they
were (update-rate LOD: each character re-posed every ``stride``-th frame).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..math.clip import PLAYBACK_MODES, KeyframeClip, Pose
from ..math.quat import quat_angle, quat_conj, quat_log, quat_mul, squad_eval
from ..math.skeleton import Skeleton
from ..methods.c2spline import C2Clip
from ..methods.compression import QuantizedClip
from ..methods.footlock import FootLockedClip
from ..methods.hybrid import SpringClip, SquadClip, spring
from ..methods.ik import _STRAIGHT
from ..rig.mirror import Mirror
from .crowd import CrowdBuffers, PoseTable, keyframe_root, numba, pose_crowd_numpy, table_from_keyframes, uniform

Array = NDArray[np.float64]
F32 = NDArray[np.float32]
FIT_TOLERANCE_DEG = 0.25  # largest angle between a joint's global rotation from the fitted curve and exact SQUAD
_FIT_SAMPLES = 96  # samples per segment the control points are fitted on
_FIT_ROUNDS = 30  # Lawson iterations: the weights converge towards the minimax fit
_CHECK_RATE = 240.0  # samples per second of the fit check in global rotations
_MIRROR_TOLERANCE = 1e-6  # quaternion components: the second half must be the mirrored first half to rounding
# Largest angle between a joint's global rotation from the C2 kernel (the exact curve in float32) and
# :meth:`C2Clip.sample`, measured when the runtime is built.
C2_TOLERANCE_DEG = 0.01
# The same for the foot-locked hybrid: the IK in the kernel is that of anim_core.methods.ik (float64 on the float32
# pose)
# and, with its hinge, well-conditioned at a straight knee, so what is left is its base's fit error
# (<= FIT_TOLERANCE_DEG; the spring's is float32 rounding).
FOOT_LOCK_TOLERANCE_DEG = FIT_TOLERANCE_DEG

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


def _frozen(a: ArrayLike, dtype: Any) -> NDArray[Any]:
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
        characters split across numba's worker threads; ``active``, ``first``, ``stride``: LOD (module
        docstring).  Every input is checked before the kernel touches memory (``ValueError`` otherwise).
        """
        if numba is None:  # pragma: no cover - numba is a dependency
            raise RuntimeError("the keys runtime needs numba")
        t, out, active = check_inputs(self.skeleton, t, out, active, first, stride)
        kernel = self._kernels()[1 if parallel else 0]
        kernel(*self.arrays().values(), t, *_skeleton_arrays(self.skeleton), active, first, stride, out.rotations,
               out.positions)
        return out

    def _kernels(self) -> tuple[Any, Any]:
        raise NotImplementedError


@lru_cache(maxsize=64)
def _skeleton_arrays(skeleton: Skeleton) -> tuple[NDArray[np.int64], F32]:
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
        return cls(table.skeleton, _frozen(table.rotations, np.float32), _frozen(table.root, np.float32),
                   _frozen(table.velocity, np.float32),
                   _frozen([table.dt, table.duration, PLAYBACK_MODES.index(table.mode)], np.float64),
                   _frozen(np.zeros(0), np.float64))

    @classmethod
    def from_uneven_keys(cls, clip: KeyframeClip) -> TableRuntime:
        """A keyframe clip's own keys at their own times (a ``reduced`` clip), searched per character."""
        root, velocity = keyframe_root(clip)
        return cls(clip.skeleton, _frozen(clip.rotations, np.float32), _frozen(root, np.float32),
                   _frozen(velocity, np.float32),
                   _frozen([0.0, clip.duration, PLAYBACK_MODES.index(clip.mode)], np.float64),
                   _frozen(clip.times, np.float64))

    def _kernels(self) -> tuple[Any, Any]:
        return _table_serial, _table_parallel


@dataclass(frozen=True, eq=False)
class SplineRuntime(_Runtime):
    """A SQUAD clip as normalized cubic Bezier segments in R^4.

    ``seg_times (S + 1,)`` float64: the stored segments' start times and the last one's end (for a mirrored gait
    the first half cycle only); ``controls (3 S + 1, J, 4)``: segment ``s`` has control points ``3s .. 3s + 3``,
    the keys at ``3s``; ``root_times (R + 1,)`` float64 and ``root_coef (R, 4, 3)``: the root spline of the
    whole period, cubic in seconds from the segment start, highest power first (scipy's ``CubicSpline.c``);
    ``mirror_src (J,)`` int32: each joint's partner, and ``mirror_sign (1 or J, 4)``: the sign of each
    component after mirroring (both empty without mirror); ``velocity (3,)`` travel per second in loop mode;
    ``params (3,)`` float64 = (duration s, playback mode index, half period s or 0 without mirror).
    ``fit_error_deg``: the measured largest global-rotation error against the exact curve (not runtime data).
    """

    skeleton: Skeleton
    seg_times: Array
    controls: F32
    root_times: Array
    root_coef: F32
    mirror_src: NDArray[np.int32]
    mirror_sign: F32
    velocity: F32
    params: Array
    fit_error_deg: float

    def _kernels(self) -> tuple[Any, Any]:
        return _spline_serial, _spline_parallel


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

    def _kernels(self) -> tuple[Any, Any]:
        return _spring_serial, _spring_parallel


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

    def _kernels(self) -> tuple[Any, Any]:
        return _quantized_serial, _quantized_parallel


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

    def _kernels(self) -> tuple[Any, Any]:
        return _c2_serial, _c2_parallel


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

    def _kernels(self) -> tuple[Any, Any]:
        if isinstance(self.base, SplineRuntime):
            return _spline_ik_serial, _spline_ik_parallel
        return _spring_ik_serial, _spring_ik_parallel


AnyRuntime = TableRuntime | SplineRuntime | SpringRuntime | QuantizedRuntime | C2Runtime | FootLockRuntime


# --- building (offline, once per clip) ---------------------------------------------------------------------------

def runtime_for(clip: AnimClip) -> AnyRuntime:
    """The keys runtime of a clip, from what it stores: a keyframe clip's keys (on a grid, or at a reduced clip's
    own times), a quantized clip's integers, SQUAD keys as fitted segments, spring keys, a C2 spline's control
    points, or a foot-locked hybrid's base runtime plus its tracks."""
    if isinstance(clip, QuantizedClip):
        return quantized_runtime(clip)
    if isinstance(clip, KeyframeClip):
        if uniform(clip.times):
            return TableRuntime.from_table(table_from_keyframes(clip))
        return TableRuntime.from_uneven_keys(clip)
    if isinstance(clip, SquadClip):
        return spline_runtime(clip)
    if isinstance(clip, SpringClip):
        return spring_runtime(clip)
    if isinstance(clip, C2Clip):
        return c2_runtime(clip)
    if isinstance(clip, FootLockedClip):
        return foot_lock_runtime(clip)
    raise ValueError(f"no runtime for clips of type {type(clip).__name__}")


def quantized_runtime(clip: QuantizedClip) -> QuantizedRuntime:
    """The integers of a quantized clip as its smallest unsigned type, its tracks' ranges, its root and times."""
    tracks = clip.tracks
    if tracks.bits > 16:
        raise ValueError(f"clip {clip.name!r}: the quantized runtime takes up to 16 bits, got {tracks.bits}")
    codes = tracks.codes.astype(np.uint8 if tracks.bits <= 8 else np.uint16)
    on_grid = uniform(clip.times)
    root, velocity = keyframe_root(clip)
    dt = float(clip.times[1] - clip.times[0]) if on_grid else 0.0
    return QuantizedRuntime(clip.skeleton, _frozen(codes, codes.dtype), _frozen(tracks.low, np.float32),
                            _frozen(tracks.step, np.float32), _frozen(root, np.float32),
                            _frozen(velocity, np.float32),
                            _frozen([dt, clip.duration, PLAYBACK_MODES.index(clip.mode)], np.float64),
                            _frozen(np.zeros(0) if on_grid else clip.times, np.float64))


def _root_arrays(clip: SquadClip) -> tuple[Array, F32, F32]:
    """The SQUAD clip's root spline (breakpoints, coefficients) and travel per second, as the kernels take them."""
    spline = clip.precomputed()[4]
    return (_frozen(spline.x, np.float64), _frozen(np.moveaxis(spline.c, 0, 1), np.float32),
            _frozen(clip.velocity if clip.mode == "loop" and not clip.in_place else np.zeros(3), np.float32))


def c2_runtime(clip: C2Clip, tolerance_deg: float = C2_TOLERANCE_DEG) -> C2Runtime:
    """The C2 clip's control points with the logarithms of their steps, its knots and the SQUAD root."""
    spline = clip.spline
    c = spline.control
    w = quat_log(quat_mul(quat_conj(np.roll(c, 1, axis=0)), c))  # w_i = log(c_(i-1)^-1 c_i), as the spline has it
    theta = np.linalg.norm(w, axis=-1)
    axis = np.where(theta[..., None] > 0, w / np.where(theta > 0, theta, 1.0)[..., None], 0.0)
    steps = np.concatenate([theta[..., None], axis], axis=-1)
    runtime = C2Runtime(clip.skeleton, _frozen(spline.knots, np.float64), _frozen(c, np.float32),
                        _frozen(steps, np.float32), *_root_arrays(clip.squad),
                        _frozen([clip.duration, PLAYBACK_MODES.index(clip.mode), spline.period,
                                 spline.times[0]], np.float64), 0.0)
    error = max_error_deg(runtime, clip, _CHECK_RATE)
    if error > tolerance_deg:
        raise ValueError(f"clip {clip.name!r}: the C2 kernel is {error:.4f} degrees from the clip's curve, more "
                         f"than {tolerance_deg} degrees")
    object.__setattr__(runtime, "error_deg", error)
    return runtime


def foot_lock_runtime(clip: FootLockedClip, tolerance_deg: float = FOOT_LOCK_TOLERANCE_DEG) -> FootLockRuntime:
    """The hybrid's runtime plus the legs, the joints they move and the targets' and weights' tracks."""
    base = spline_runtime(clip.base) if isinstance(clip.base, SquadClip) else spring_runtime(clip.base)
    sk = clip.skeleton
    targets, weights = clip.tracks()
    knots = np.asarray(targets.x, np.float64)
    if not (np.array_equal(knots, weights.x) and np.allclose(knots, np.arange(knots.size) / clip.fps, atol=1e-9)):
        raise ValueError(f"clip {clip.name!r}: the foot-lock tracks are not on the clip's frame grid")
    values = np.concatenate([targets(knots), weights(knots)[..., None]], axis=-1)
    slopes = np.concatenate([targets(knots, 1), weights(knots, 1)[..., None]], axis=-1)
    chains = np.array(clip.legs, np.int32)
    under = [_below(sk, chain) for chain in clip.legs]
    width = max(len(u) for u in under)
    below = np.full((len(under), width), -1, np.int32)
    turns = np.full((len(under), width), 2, np.int32)
    for leg, joints in enumerate(under):
        below[leg, :len(joints)] = [j for j, _ in joints]
        turns[leg, :len(joints)] = [k for _, k in joints]
    loop = clip.mode == "loop"
    travel = clip.velocity if loop and not clip.in_place else np.zeros(3)
    runtime = FootLockRuntime(sk, base, _frozen(chains, np.int32), _frozen(clip.hinges, np.float32),
                              _frozen(below, np.int32),
                              _frozen(turns, np.int32), _frozen(values, np.float32), _frozen(slopes, np.float32),
                              _frozen([clip.fps, 1.0 if loop else 0.0, clip.duration,
                                       PLAYBACK_MODES.index(clip.mode), *travel, clip.soft, _STRAIGHT],
                                      np.float64), 0.0)
    error = max_error_deg(runtime, clip, _CHECK_RATE)
    if error > tolerance_deg:
        raise ValueError(f"clip {clip.name!r}: the foot-lock kernel is {error:.4f} degrees from the clip's pose, "
                         f"more than {tolerance_deg} degrees")
    object.__setattr__(runtime, "error_deg", error)
    return runtime


def _below(skeleton: Skeleton, chain: tuple[int, int, int]) -> list[tuple[int, int]]:
    """Joints under a leg's hip in topological order, each with what turns it: 0 the hip's rotation, 1 the
    knee's, 2 nothing (the ankle keeps its world orientation, so do the joints under it)."""
    s, m, e = chain
    out = []
    for j in range(s + 1, skeleton.n_joints):  # parents come before their children
        line = [j]
        while line[-1] > s:
            line.append(int(skeleton.parents[line[-1]]))
        if line[-1] == s:
            out.append((j, 2 if e in line else 1 if m in line else 0))
    return out


def _bernstein(h: Array) -> Array:
    g = 1.0 - h
    return np.stack([g**3, 3.0 * g * g * h, 3.0 * g * h * h, h**3], axis=-1)


def _fit_segment(q0: Array, q1: Array, a: Array, b: Array) -> tuple[Array, Array]:
    """Inner control points ``(J, 4)`` x 2 of one segment: minimax fit of the normalized Bezier to exact SQUAD."""
    h = (np.arange(_FIT_SAMPLES) + 0.5) / _FIT_SAMPLES
    basis = _bernstein(h)  # (H, 4)
    exact = squad_eval(q0, q1, a, b, h[:, None])  # (H, J, 4)
    rest = exact - basis[:, :1, None] * q0 - basis[:, 3:, None] * q1
    inner = basis[:, 1:3]  # (H, 2)
    w = np.ones(exact.shape[:2])
    for _ in range(_FIT_ROUNDS):  # Lawson: weighted least squares, weights multiplied by the error each round
        normal = np.einsum("hj,hk,hl->jkl", w, inner, inner)
        rhs = np.einsum("hj,hk,hjc->jkc", w, inner, rest)
        x = np.linalg.solve(normal, rhs)  # (J, 2, 4)
        p = basis[:, :1, None] * q0 + basis[:, 3:, None] * q1 + np.einsum("hk,jkc->hjc", inner, x)
        err = quat_angle(p / np.linalg.norm(p, axis=-1, keepdims=True), exact) + 1e-15
        w = w * err
        w /= w.sum(axis=0, keepdims=True)
    return x[:, 0], x[:, 1]


def _gait_mirror(clip: SquadClip) -> tuple[NDArray[np.int32], Array] | None:
    """Partner and per-component signs if the clip's second half cycle is its mirrored first half, else None."""
    k = clip.n_keys
    if clip.mode != "loop" or k % 2 or not np.allclose(clip.key_times[k // 2:], clip.key_times[:k // 2]
                                                       + clip.duration / 2, atol=1e-12):
        return None
    mirror = Mirror(clip.skeleton)
    j = clip.skeleton.n_joints
    # The mirror is linear in each quaternion: column c of joint j's map is the image of basis vector e_c.
    basis = np.zeros((4, j, 4))
    basis[np.arange(4), :, np.arange(4)] = 1.0
    cols = mirror(Pose(basis, np.zeros((4, 3)))).rotations  # (4 = c, J, 4)
    maps = np.moveaxis(cols, 0, -1)  # (J, 4 out, 4 in)
    if not np.allclose(np.abs(maps), np.eye(4), atol=1e-12):
        return None  # not a signed identity (a rig with rest rotations): store every segment
    sign = np.diagonal(maps, axis1=1, axis2=2)
    src = mirror.partners.astype(np.int32)
    half = clip.key_rotations[k // 2:]
    image = sign * clip.key_rotations[:k // 2][:, src]
    if not np.all(np.abs(np.abs(np.sum(half * image, axis=-1)) - 1.0) < _MIRROR_TOLERANCE):
        return None
    return src, sign


def spline_runtime(clip: SquadClip, tolerance_deg: float = FIT_TOLERANCE_DEG) -> SplineRuntime:
    """Fit the runtime of a SQUAD clip (its SQUAD control points are precomputed on the clip)."""
    seg_times, q, a, b, _root = clip.precomputed()
    n_seg = seg_times.size - 1
    mirrored = _gait_mirror(clip)
    stored = n_seg // 2 if mirrored is not None else n_seg
    controls = np.empty((3 * stored + 1, clip.skeleton.n_joints, 4))
    controls[0::3] = q[: stored + 1]
    for s in range(stored):
        controls[3 * s + 1], controls[3 * s + 2] = _fit_segment(q[s], q[s + 1], a[s], b[s])
    src, sign = mirrored if mirrored is not None else (np.zeros(0, np.int32), np.zeros((0, 4)))
    if sign.size and np.all(sign == sign[:1]):
        sign = sign[:1]  # the same flips for every joint: one row
    root_times, root_coef, velocity = _root_arrays(clip)
    runtime = SplineRuntime(
        clip.skeleton, _frozen(seg_times[: stored + 1], np.float64), _frozen(controls, np.float32),
        root_times, root_coef, _frozen(src, np.int32), _frozen(sign, np.float32), velocity,
        _frozen([clip.duration, PLAYBACK_MODES.index(clip.mode),
                 clip.duration / 2 if mirrored is not None else 0.0], np.float64), 0.0)
    error = max_error_deg(runtime, clip, _CHECK_RATE)
    if error > tolerance_deg:
        raise ValueError(f"clip {clip.name!r}: the fitted curve is {error:.3f} degrees from exact SQUAD, more than "
                         f"{tolerance_deg} degrees")
    object.__setattr__(runtime, "fit_error_deg", error)
    return runtime


def crouch_params(clip: SpringClip) -> Array:
    """``(zeta, omega, time_scale, normalization, duration, mode)`` of a spring clip, from its fields.

    The normalization is ``1 / (1 - spring(time_scale duration))`` with ``land_on_last_key`` (so ``u`` is 1 at the
    turn, as :meth:`SpringClip.path_parameter` has it), 1 otherwise; :func:`crouch_path_parameter` uses them.
    """
    norm = 1.0
    if clip.land_on_last_key:
        norm = 1.0 / (1.0 - float(spring(clip.time_scale * clip.duration, clip.zeta, clip.omega)))
    return np.array([clip.zeta, clip.omega, clip.time_scale, norm, clip.duration, PLAYBACK_MODES.index(clip.mode)])


def spring_runtime(clip: SpringClip) -> SpringRuntime:
    """Keys, per-segment angles and the spring's constants of a crouch clip."""
    keys = np.asarray(clip.key_rotations, np.float64)
    a, b = keys[:-1], keys[1:]
    angles = 2.0 * np.arctan2(np.linalg.norm(a - b, axis=-1), np.linalg.norm(a + b, axis=-1))
    small = angles < 1e-3  # sin(x) ~ x: linear weights are exact to float32 there
    inv_sin = np.where(small, 0.0, 1.0 / np.where(small, 1.0, np.sin(angles)))
    params = crouch_params(clip)
    # The kernel evaluates the documented formula from the clip's fields; if the clip's own path parameter ever
    # follows another formula, refuse to build rather than pose something else.
    t = np.linspace(0.0, clip.duration, 257)
    ours = _crouch_u_numpy(t, params)
    if not np.allclose(ours, clip.path_parameter(t), atol=1e-9):
        raise ValueError(f"clip {clip.name!r}: its path parameter does not follow the documented spring formula")
    return SpringRuntime(clip.skeleton, _frozen(clip.key_params, np.float64), _frozen(keys, np.float32),
                         _frozen(angles, np.float32), _frozen(inv_sin, np.float32),
                         _frozen(clip.key_root, np.float32), _frozen(params, np.float64))


def _crouch_u_numpy(ct: Array, params: Array) -> Array:
    zeta, omega, ts, norm = params[:4]
    x = ts * ct
    alpha = omega * np.sqrt(1.0 - zeta * zeta)
    spring = np.exp(-omega * zeta * x) * (np.cos(alpha * x) + omega * zeta / alpha * np.sin(alpha * x))
    return (1.0 - spring) * norm


# --- accuracy ----------------------------------------------------------------------------------------------------

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


# --- kernels -----------------------------------------------------------------------------------------------------

if numba is not None:
    _njit = numba.njit(cache=True, fastmath=False, inline="always")

    @_njit
    def _clip_time(t, duration, mode):
        """(clip time, completed loops) as :func:`anim_core.math.clip.playback_time`."""
        if mode == 0:
            cycles = np.floor(t / duration)
            ct = min(max(t - cycles * duration, 0.0), duration)
            return ct, cycles
        if mode == 1:
            ct = t % (2.0 * duration)
            if ct > duration:
                ct = 2.0 * duration - ct
            return ct, 0.0
        return min(max(t, 0.0), duration), 0.0

    @_njit
    def _fk(c, j, w, x, y, z, rx, ry, rz, parents, offsets, out_rot, out_pos):
        """Write joint ``j`` of character ``c`` from its local rotation (and, for the root, its translation)."""
        p = parents[j]
        ox, oy, oz = offsets[j, 0], offsets[j, 1], offsets[j, 2]
        if p < 0:
            out_rot[c, j, 0], out_rot[c, j, 1], out_rot[c, j, 2], out_rot[c, j, 3] = w, x, y, z
            out_pos[c, j, 0], out_pos[c, j, 1], out_pos[c, j, 2] = ox + rx, oy + ry, oz + rz
            return
        pw, px, py, pz = out_rot[c, p, 0], out_rot[c, p, 1], out_rot[c, p, 2], out_rot[c, p, 3]
        out_rot[c, j, 0] = pw * w - px * x - py * y - pz * z
        out_rot[c, j, 1] = pw * x + px * w + py * z - pz * y
        out_rot[c, j, 2] = pw * y - px * z + py * w + pz * x
        out_rot[c, j, 3] = pw * z + px * y - py * x + pz * w
        # offset rotated by the parent: v + 2w (u x v) + 2 u x (u x v)
        tx = np.float32(2.0) * (py * oz - pz * oy)
        ty = np.float32(2.0) * (pz * ox - px * oz)
        tz = np.float32(2.0) * (px * oy - py * ox)
        out_pos[c, j, 0] = out_pos[c, p, 0] + ox + pw * tx + (py * tz - pz * ty)
        out_pos[c, j, 1] = out_pos[c, p, 1] + oy + pw * ty + (pz * tx - px * tz)
        out_pos[c, j, 2] = out_pos[c, p, 2] + oz + pw * tz + (px * ty - py * tx)

    @_njit
    def _last_at_or_below(values, x, lo, hi):
        """The largest ``i`` in ``lo..hi`` with ``values[i] <= x`` (``lo`` if none): binary search, as
        ``searchsorted(values, x, "right") - 1`` clipped to ``lo..hi``."""
        while lo < hi:
            mid = (lo + hi + 1) // 2
            if values[mid] <= x:
                lo = mid
            else:
                hi = mid - 1
        return lo

    @_njit
    def _key_segment(ct, dt, key_times, n):
        """Key ``i`` before clip time ``ct`` and the fraction towards key ``i + 1``: on a grid of step ``dt``, or
        (``dt == 0``) searched in ``key_times``, as :meth:`KeyframeClip.sample` finds it."""
        if dt > 0.0:
            f = ct / dt
            i = min(max(int(np.floor(f)), 0), n - 2)
            return i, f - i
        i = _last_at_or_below(key_times, ct, 0, n - 2)
        return i, (ct - key_times[i]) / (key_times[i + 1] - key_times[i])

    @_njit
    def _table_one(c, keys, roots, velocity, params, key_times, times, parents, offsets, active, out_rot,
                   out_pos):
        dt, duration, mode = params[0], params[1], int(params[2])
        ct, cycles = _clip_time(times[c], duration, mode)
        i, f = _key_segment(ct, dt, key_times, keys.shape[0])
        a = np.float32(f)
        b = np.float32(1.0) - a
        travel = ct + cycles * duration
        rx = b * roots[i, 0] + a * roots[i + 1, 0] + velocity[0] * travel
        ry = b * roots[i, 1] + a * roots[i + 1, 1] + velocity[1] * travel
        rz = b * roots[i, 2] + a * roots[i + 1, 2] + velocity[2] * travel
        for j in range(keys.shape[1]):
            if active[j]:
                w = b * keys[i, j, 0] + a * keys[i + 1, j, 0]
                x = b * keys[i, j, 1] + a * keys[i + 1, j, 1]
                y = b * keys[i, j, 2] + a * keys[i + 1, j, 2]
                z = b * keys[i, j, 3] + a * keys[i + 1, j, 3]
                inv = np.float32(1.0) / np.sqrt(w * w + x * x + y * y + z * z)
                w, x, y, z = w * inv, x * inv, y * inv, z * inv
            else:
                w, x, y, z = keys[0, j, 0], keys[0, j, 1], keys[0, j, 2], keys[0, j, 3]
            _fk(c, j, w, x, y, z, rx, ry, rz, parents, offsets, out_rot, out_pos)

    @_njit
    def _root_spline(ct, root_times, root_coef):
        """The root spline of the whole period at clip time ``ct``, Horner in seconds from its segment's start."""
        r = 0
        while r < root_times.shape[0] - 2 and ct >= root_times[r + 1]:
            r += 1
        dx = np.float32(ct - root_times[r])
        rx = ((root_coef[r, 0, 0] * dx + root_coef[r, 1, 0]) * dx + root_coef[r, 2, 0]) * dx + root_coef[r, 3, 0]
        ry = ((root_coef[r, 0, 1] * dx + root_coef[r, 1, 1]) * dx + root_coef[r, 2, 1]) * dx + root_coef[r, 3, 1]
        rz = ((root_coef[r, 0, 2] * dx + root_coef[r, 1, 2]) * dx + root_coef[r, 2, 2]) * dx + root_coef[r, 3, 2]
        return rx, ry, rz

    @_njit
    def _spline_one(c, seg_times, ctrl, root_times, root_coef, src, sign, velocity, params, times, parents,
                    offsets, active, out_rot, out_pos):
        duration, mode, half = params[0], int(params[1]), params[2]
        ct, cycles = _clip_time(times[c], duration, mode)
        rx, ry, rz = _root_spline(ct, root_times, root_coef)
        travel = ct + cycles * duration
        rx += velocity[0] * travel
        ry += velocity[1] * travel
        rz += velocity[2] * travel
        mirrored = half > 0.0 and ct >= half
        if mirrored:
            ct -= half
        s = 0
        while s < seg_times.shape[0] - 2 and ct >= seg_times[s + 1]:
            s += 1
        h = (ct - seg_times[s]) / (seg_times[s + 1] - seg_times[s])
        h = min(max(h, 0.0), 1.0)
        g = 1.0 - h
        b0, b1 = np.float32(g * g * g), np.float32(3.0 * g * g * h)
        b2, b3 = np.float32(3.0 * g * h * h), np.float32(h * h * h)
        k = 3 * s
        rows = sign.shape[0]
        for j in range(ctrl.shape[1]):
            if active[j]:
                m = src[j] if mirrored else j
                w = b0 * ctrl[k, m, 0] + b1 * ctrl[k + 1, m, 0] + b2 * ctrl[k + 2, m, 0] + b3 * ctrl[k + 3, m, 0]
                x = b0 * ctrl[k, m, 1] + b1 * ctrl[k + 1, m, 1] + b2 * ctrl[k + 2, m, 1] + b3 * ctrl[k + 3, m, 1]
                y = b0 * ctrl[k, m, 2] + b1 * ctrl[k + 1, m, 2] + b2 * ctrl[k + 2, m, 2] + b3 * ctrl[k + 3, m, 2]
                z = b0 * ctrl[k, m, 3] + b1 * ctrl[k + 1, m, 3] + b2 * ctrl[k + 2, m, 3] + b3 * ctrl[k + 3, m, 3]
                inv = np.float32(1.0) / np.sqrt(w * w + x * x + y * y + z * z)
                w, x, y, z = w * inv, x * inv, y * inv, z * inv
                if mirrored:
                    row = j if rows > 1 else 0
                    w, x, y, z = w * sign[row, 0], x * sign[row, 1], y * sign[row, 2], z * sign[row, 3]
            else:
                w, x, y, z = ctrl[0, j, 0], ctrl[0, j, 1], ctrl[0, j, 2], ctrl[0, j, 3]
            _fk(c, j, w, x, y, z, rx, ry, rz, parents, offsets, out_rot, out_pos)

    @_njit
    def crouch_path_parameter(ct, params):
        """Path parameter ``u`` at clip time ``ct``: ``(1 - spring(time_scale ct)) * normalization``, the closed
        form of :func:`anim_core.methods.hybrid.spring` from rest at 1 (the one place the crouch's timing lives)."""
        zeta, omega, ts, norm = params[0], params[1], params[2], params[3]
        x = ts * ct
        alpha = omega * np.sqrt(1.0 - zeta * zeta)
        spring = np.exp(-omega * zeta * x) * (np.cos(alpha * x) + omega * zeta / alpha * np.sin(alpha * x))
        return (1.0 - spring) * norm

    @_njit
    def _spring_one(c, key_params, keys, angles, inv_sin, key_root, params, times, parents, offsets,
                    active, out_rot, out_pos):
        ct, _ = _clip_time(times[c], params[4], int(params[5]))
        u = crouch_path_parameter(ct, params)
        s = 0
        while s < key_params.shape[0] - 2 and u >= key_params[s + 1]:
            s += 1
        local = (u - key_params[s]) / (key_params[s + 1] - key_params[s])  # not clamped: > 1 past the last key
        rx = key_root[s, 0] + (key_root[s + 1, 0] - key_root[s, 0]) * local
        ry = key_root[s, 1] + (key_root[s + 1, 1] - key_root[s, 1]) * local
        rz = key_root[s, 2] + (key_root[s + 1, 2] - key_root[s, 2]) * local
        lf = np.float32(local)
        for j in range(keys.shape[1]):
            if active[j]:
                om = angles[s, j]
                if inv_sin[s, j] != 0.0:
                    wa = np.sin((np.float32(1.0) - lf) * om) * inv_sin[s, j]
                    wb = np.sin(lf * om) * inv_sin[s, j]
                else:
                    wa, wb = np.float32(1.0) - lf, lf
                w = wa * keys[s, j, 0] + wb * keys[s + 1, j, 0]
                x = wa * keys[s, j, 1] + wb * keys[s + 1, j, 1]
                y = wa * keys[s, j, 2] + wb * keys[s + 1, j, 2]
                z = wa * keys[s, j, 3] + wb * keys[s + 1, j, 3]
            else:
                w, x, y, z = keys[0, j, 0], keys[0, j, 1], keys[0, j, 2], keys[0, j, 3]
            _fk(c, j, w, x, y, z, rx, ry, rz, parents, offsets, out_rot, out_pos)

    @_njit
    def _dequantize(codes, low, step, k, j):
        """Key ``k`` of joint ``j`` dequantized and normalized (float32)."""
        w = low[j, 0] + np.float32(codes[k, j, 0]) * step[j, 0]
        x = low[j, 1] + np.float32(codes[k, j, 1]) * step[j, 1]
        y = low[j, 2] + np.float32(codes[k, j, 2]) * step[j, 2]
        z = low[j, 3] + np.float32(codes[k, j, 3]) * step[j, 3]
        inv = np.float32(1.0) / np.sqrt(w * w + x * x + y * y + z * z)
        return w * inv, x * inv, y * inv, z * inv

    @_njit
    def _quantized_one(c, codes, low, step, roots, velocity, params, key_times, times, parents, offsets, active,
                       out_rot, out_pos):
        dt, duration, mode = params[0], params[1], int(params[2])
        ct, cycles = _clip_time(times[c], duration, mode)
        i, f = _key_segment(ct, dt, key_times, codes.shape[0])
        a = np.float32(f)
        b = np.float32(1.0) - a
        travel = ct + cycles * duration
        rx = b * roots[i, 0] + a * roots[i + 1, 0] + velocity[0] * travel
        ry = b * roots[i, 1] + a * roots[i + 1, 1] + velocity[1] * travel
        rz = b * roots[i, 2] + a * roots[i + 1, 2] + velocity[2] * travel
        for j in range(codes.shape[1]):
            if active[j]:
                w0, x0, y0, z0 = _dequantize(codes, low, step, i, j)
                w1, x1, y1, z1 = _dequantize(codes, low, step, i + 1, j)
                w, x, y, z = b * w0 + a * w1, b * x0 + a * x1, b * y0 + a * y1, b * z0 + a * z1
                inv = np.float32(1.0) / np.sqrt(w * w + x * x + y * y + z * z)
                w, x, y, z = w * inv, x * inv, y * inv, z * inv
            else:
                w, x, y, z = _dequantize(codes, low, step, 0, j)
            _fk(c, j, w, x, y, z, rx, ry, rz, parents, offsets, out_rot, out_pos)

    @_njit
    def _c2_one(c, knots, control, steps, root_times, root_coef, velocity, params, times, parents, offsets,
                active, out_rot, out_pos):
        duration, mode, period, t0 = params[0], int(params[1]), params[2], params[3]
        ct, cycles = _clip_time(times[c], duration, mode)
        rx, ry, rz = _root_spline(ct, root_times, root_coef)
        travel = ct + cycles * duration
        rx += velocity[0] * travel
        ry += velocity[1] * travel
        rz += velocity[2] * travel
        k = control.shape[0]
        tt = t0 + (ct - t0) - np.floor((ct - t0) / period) * period
        span = _last_at_or_below(knots, tt, 3, k + 2)
        # The four cubic B-spline basis functions on this span (The NURBS Book A2.2, unrolled for degree 3).
        l1, l2, l3 = tt - knots[span], tt - knots[span - 1], tt - knots[span - 2]
        r1, r2, r3 = knots[span + 1] - tt, knots[span + 2] - tt, knots[span + 3] - tt
        n0 = 1.0
        tmp = n0 / (r1 + l1)
        n0, n1 = r1 * tmp, l1 * tmp
        tmp0 = n0 / (r1 + l2)
        tmp1 = n1 / (r2 + l1)
        n0, n1, n2 = r1 * tmp0, l2 * tmp0 + r2 * tmp1, l1 * tmp1
        tmp0 = n0 / (r1 + l3)
        tmp1 = n1 / (r2 + l2)
        tmp2 = n2 / (r3 + l1)
        n1, n2, n3 = l3 * tmp0 + r2 * tmp1, l2 * tmp1 + r3 * tmp2, l1 * tmp2
        b1, b2, b3 = np.float32(n1 + n2 + n3), np.float32(n2 + n3), np.float32(n3)  # cumulative basis
        m = span - 3
        i0, i1, i2, i3 = (m - 1 + k) % k, m, (m + 1) % k, (m + 2) % k
        for j in range(control.shape[1]):
            if active[j]:
                w, x, y, z = control[i0, j, 0], control[i0, j, 1], control[i0, j, 2], control[i0, j, 3]
                w, x, y, z = _times_exp(w, x, y, z, b1, steps, i1, j)
                w, x, y, z = _times_exp(w, x, y, z, b2, steps, i2, j)
                w, x, y, z = _times_exp(w, x, y, z, b3, steps, i3, j)
            else:
                w, x, y, z = control[0, j, 0], control[0, j, 1], control[0, j, 2], control[0, j, 3]
            _fk(c, j, w, x, y, z, rx, ry, rz, parents, offsets, out_rot, out_pos)

    @_njit
    def _times_exp(w, x, y, z, weight, steps, i, j):
        """``(w, x, y, z) exp(weight w_i)`` for joint ``j``, ``w_i`` stored as half angle and unit axis."""
        angle = weight * steps[i, j, 0]
        cs, sn = np.cos(angle), np.sin(angle)
        return _qmul(w, x, y, z, cs, sn * steps[i, j, 1], sn * steps[i, j, 2], sn * steps[i, j, 3])

    @_njit
    def _qmul(aw, ax, ay, az, bw, bx, by, bz):
        return (aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw)

    @_njit
    def _qrot(w, x, y, z, vx, vy, vz):
        """``v`` rotated by the unit quaternion ``(w, x, y, z)``: v + 2w (u x v) + 2 u x (u x v)."""
        tx, ty, tz = 2.0 * (y * vz - z * vy), 2.0 * (z * vx - x * vz), 2.0 * (x * vy - y * vx)
        return vx + w * tx + (y * tz - z * ty), vy + w * ty + (z * tx - x * tz), vz + w * tz + (x * ty - y * tx)

    @_njit
    def _perpendicular(vx, vy, vz):
        """A unit vector perpendicular to ``v`` (as :func:`anim_core.methods.ik._perpendicular`)."""
        hx, hy = (1.0, 0.0) if abs(vx) < 0.9 else (0.0, 1.0)
        cx, cy, cz = -vz * hy, vz * hx, vx * hy - vy * hx
        n = np.sqrt(cx * cx + cy * cy + cz * cz)
        return cx / n, cy / n, cz / n

    @_njit
    def _axis_angle(ax, ay, az, angle):
        s = np.sin(0.5 * angle) / np.sqrt(ax * ax + ay * ay + az * az)
        return np.cos(0.5 * angle), ax * s, ay * s, az * s

    @_njit
    def _between(ax, ay, az, bx, by, bz):
        """The smallest rotation turning ``a`` into ``b`` (as :func:`anim_core.math.quat.quat_between`)."""
        aa = ax * ax + ay * ay + az * az
        w = np.sqrt(aa) * np.sqrt(bx * bx + by * by + bz * bz) + ax * bx + ay * by + az * bz
        x, y, z = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
        n = np.sqrt(w * w + x * x + y * y + z * z)
        if n <= 1e-12 * max(aa, 1e-300):  # opposite: a half turn about an axis perpendicular to a
            hx, hy = (1.0, 0.0) if abs(ax) < 0.9 else (0.0, 1.0)
            w, x, y, z = 0.0, -az * hy, az * hx, ax * hy - ay * hx
            n = np.sqrt(x * x + y * y + z * z)
        return w / n, x / n, y / n, z / n

    @_njit
    def _hermite(values, slopes, i, leg, q, h00, h10, h01, h11):
        """Component ``q`` of leg ``leg``'s track on the piece from point ``i`` (basis weights given)."""
        return (h00 * values[i, leg, q] + h10 * slopes[i, leg, q] + h01 * values[i + 1, leg, q]
                + h11 * slopes[i + 1, leg, q])

    @_njit
    def _foot_lock(c, chains, hinges, below, turns, values, slopes, ik, times, parents, offsets, out_rot, out_pos):
        """Both legs of character ``c`` (posed by the base kernel) solved towards their tracks' targets: the
        steps of :func:`anim_core.methods.ik.two_bone_ik` with the knee's hinge, no pole, the soft reach and the ankle's
        world orientation kept,
        in float64; the hip's and knee's global rotations turn, every joint under the hip is re-placed."""
        fps, loop, duration, mode, soft, straight = ik[0], ik[1], ik[2], int(ik[3]), ik[7], ik[8]
        ct, cycles = _clip_time(times[c], duration, mode)
        travel = ct + cycles * duration
        n = values.shape[0]
        f = ct * fps
        if loop > 0.0:  # periodic tracks: the last point is the first one again
            f -= np.floor(f / (n - 1)) * (n - 1)
        i = min(max(int(np.floor(f)), 0), n - 2)
        u = f - i  # past 1 at a ping-pong clip's end: the last piece extrapolated, as the spline does
        h = 1.0 / fps
        h00, h10 = (2.0 * u - 3.0) * u * u + 1.0, ((u - 2.0) * u + 1.0) * u * h
        h01, h11 = (3.0 - 2.0 * u) * u * u, (u - 1.0) * u * u * h
        for leg in range(chains.shape[0]):
            weight = min(max(_hermite(values, slopes, i, leg, 3, h00, h10, h01, h11), 0.0), 1.0)
            if weight <= 0.0:
                continue
            s, m, e = chains[leg, 0], chains[leg, 1], chains[leg, 2]
            sx, sy, sz = np.float64(out_pos[c, s, 0]), np.float64(out_pos[c, s, 1]), np.float64(out_pos[c, s, 2])
            mx, my, mz = np.float64(out_pos[c, m, 0]), np.float64(out_pos[c, m, 1]), np.float64(out_pos[c, m, 2])
            ex, ey, ez = np.float64(out_pos[c, e, 0]), np.float64(out_pos[c, e, 1]), np.float64(out_pos[c, e, 2])
            tx = ex + weight * (_hermite(values, slopes, i, leg, 0, h00, h10, h01, h11) + ik[4] * travel - ex)
            ty = ey + weight * (_hermite(values, slopes, i, leg, 1, h00, h10, h01, h11) + ik[5] * travel - ey)
            tz = ez + weight * (_hermite(values, slopes, i, leg, 2, h00, h10, h01, h11) + ik[6] * travel - ez)
            a = np.sqrt(offsets[m, 0] ** 2 + offsets[m, 1] ** 2 + offsets[m, 2] ** 2)
            b = np.sqrt(offsets[e, 0] ** 2 + offsets[e, 1] ** 2 + offsets[e, 2] ** 2)
            # 1. clamped (and softened) distance and direction to the target
            dx, dy, dz = tx - sx, ty - sy, tz - sz
            dist = np.sqrt(dx * dx + dy * dy + dz * dz)
            if dist > 1e-12:
                dx, dy, dz = dx / dist, dy / dist, dz / dist
            else:
                fx, fy, fz = ex - sx, ey - sy, ez - sz
                fn = np.sqrt(fx * fx + fy * fy + fz * fz)
                if fn > 1e-12:
                    dx, dy, dz = fx / fn, fy / fn, fz / fn
                else:
                    dx, dy, dz = _perpendicular(mx - sx, my - sy, mz - sz)
            if soft > 0.0 and dist > a + b - soft:
                dist = a + b - soft - soft * np.expm1(-(dist - (a + b - soft)) / soft)
            dist = min(max(dist, abs(a - b) + 1e-9 * (a + b)), (a + b) * (1.0 - 1e-9))
            # 2. the knee's plane (normal ``side``): the animated one turned to the hinge's side, easing into the
            #    hinge's own as the animated leg straightens; the shin put at the solved angle in it
            thx, thy, thz = mx - sx, my - sy, mz - sz
            shx, shy, shz = ex - mx, ey - my, ez - mz
            ux, uy, uz = thx / a, thy / a, thz / a
            cx, cy, cz = thy * shz - thz * shy, thz * shx - thx * shz, thx * shy - thy * shx
            cn = np.sqrt(cx * cx + cy * cy + cz * cz)
            hx, hy, hz = _qrot(np.float64(out_rot[c, m, 0]), np.float64(out_rot[c, m, 1]),
                               np.float64(out_rot[c, m, 2]), np.float64(out_rot[c, m, 3]),
                               np.float64(hinges[leg, 0]), np.float64(hinges[leg, 1]), np.float64(hinges[leg, 2]))
            hu = hx * ux + hy * uy + hz * uz
            qx, qy, qz = hx - hu * ux, hy - hu * uy, hz - hu * uz
            qn = np.sqrt(qx * qx + qy * qy + qz * qz)
            if qn > 1e-12:
                qx, qy, qz = qx / qn, qy / qn, qz / qn
            else:
                qx, qy, qz = _perpendicular(thx, thy, thz)
            flip = -1.0 if cx * hx + cy * hy + cz * hz < 0.0 else 1.0
            ease = min(max(cn / (straight * a * b), 0.0), 1.0)
            ease = ease * ease * (3.0 - 2.0 * ease)
            nx, ny, nz = (cx / cn, cy / cn, cz / cn) if cn > 1e-12 else (qx, qy, qz)
            vx = ease * flip * nx + (1.0 - ease) * qx
            vy = ease * flip * ny + (1.0 - ease) * qy
            vz = ease * flip * nz + (1.0 - ease) * qz
            vn = np.sqrt(vx * vx + vy * vy + vz * vz)
            if vn > 1e-12:
                vx, vy, vz = vx / vn, vy / vn, vz / vn
            else:
                vx, vy, vz = qx, qy, qz
            cos_inner = min(max((a * a + b * b - dist * dist) / (2.0 * a * b), -1.0), 1.0)
            bend = np.pi - np.arccos(cos_inner)  # 0 = straight
            cb, sb = b * np.cos(bend), b * np.sin(bend)
            wx, wy, wz = vy * uz - vz * uy, vz * ux - vx * uz, vx * uy - vy * ux  # side x thigh direction
            nsx, nsy, nsz = cb * ux + sb * wx, cb * uy + sb * wy, cb * uz + sb * wz  # the new shin
            mw, mqx, mqy, mqz = _between(shx, shy, shz, nsx, nsy, nsz)
            # 3. swing the ankle onto the target, then twist about hip -> target so the plane (``side``, carried
            #    by the swing) is as close as it gets to the animated one
            sw, swx, swy, swz = _between(mx + nsx - sx, my + nsy - sy, mz + nsz - sz, dx, dy, dz)
            px, py, pz = _qrot(sw, swx, swy, swz, vx, vy, vz)
            vd = vx * dx + vy * dy + vz * dz
            kx, ky, kz = vx - vd * dx, vy - vd * dy, vz - vd * dz  # wanted
            angle = 0.0
            if np.sqrt(kx * kx + ky * ky + kz * kz) > 1e-9 * a:
                angle = np.arctan2(dx * (py * kz - pz * ky) + dy * (pz * kx - px * kz) + dz * (px * ky - py * kx),
                                   px * kx + py * ky + pz * kz)
            tw, twx, twy, twz = _axis_angle(dx, dy, dz, angle)
            hip = _qmul(tw, twx, twy, twz, sw, swx, swy, swz)
            knee = _qmul(hip[0], hip[1], hip[2], hip[3], mw, mqx, mqy, mqz)
            g = _qmul(hip[0], hip[1], hip[2], hip[3], out_rot[c, s, 0], out_rot[c, s, 1], out_rot[c, s, 2],
                      out_rot[c, s, 3])
            out_rot[c, s, 0], out_rot[c, s, 1], out_rot[c, s, 2], out_rot[c, s, 3] = g
            for k in range(below.shape[1]):
                j = below[leg, k]
                if j < 0:
                    break
                turn = turns[leg, k]
                if turn < 2:
                    r = hip if turn == 0 else knee
                    g = _qmul(r[0], r[1], r[2], r[3], out_rot[c, j, 0], out_rot[c, j, 1], out_rot[c, j, 2],
                              out_rot[c, j, 3])
                    out_rot[c, j, 0], out_rot[c, j, 1], out_rot[c, j, 2], out_rot[c, j, 3] = g
                p = parents[j]
                ox, oy, oz = _qrot(np.float64(out_rot[c, p, 0]), np.float64(out_rot[c, p, 1]),
                                   np.float64(out_rot[c, p, 2]), np.float64(out_rot[c, p, 3]),
                                   np.float64(offsets[j, 0]), np.float64(offsets[j, 1]), np.float64(offsets[j, 2]))
                out_pos[c, j, 0] = out_pos[c, p, 0] + ox
                out_pos[c, j, 1] = out_pos[c, p, 1] + oy
                out_pos[c, j, 2] = out_pos[c, p, 2] + oz

    @numba.njit(cache=True)
    def _table_serial(keys, roots, velocity, params, key_times, times, parents, offsets, active, first, stride,
                      out_rot, out_pos):
        for c in range(first, times.shape[0], stride):
            _table_one(c, keys, roots, velocity, params, key_times, times, parents, offsets, active, out_rot,
                       out_pos)

    @numba.njit(cache=True, parallel=True)
    def _table_parallel(keys, roots, velocity, params, key_times, times, parents, offsets, active, first, stride,
                        out_rot, out_pos):
        for k in numba.prange((times.shape[0] - first + stride - 1) // stride):
            _table_one(first + k * stride, keys, roots, velocity, params, key_times, times, parents, offsets,
                       active, out_rot, out_pos)

    @numba.njit(cache=True)
    def _quantized_serial(codes, low, step, roots, velocity, params, key_times, times, parents, offsets, active,
                          first, stride, out_rot, out_pos):
        for c in range(first, times.shape[0], stride):
            _quantized_one(c, codes, low, step, roots, velocity, params, key_times, times, parents, offsets, active,
                           out_rot, out_pos)

    @numba.njit(cache=True, parallel=True)
    def _quantized_parallel(codes, low, step, roots, velocity, params, key_times, times, parents, offsets, active,
                            first, stride, out_rot, out_pos):
        for k in numba.prange((times.shape[0] - first + stride - 1) // stride):
            _quantized_one(first + k * stride, codes, low, step, roots, velocity, params, key_times, times,
                           parents, offsets, active, out_rot, out_pos)

    @numba.njit(cache=True)
    def _c2_serial(knots, control, steps, root_times, root_coef, velocity, params, times, parents, offsets, active,
                   first, stride, out_rot, out_pos):
        for c in range(first, times.shape[0], stride):
            _c2_one(c, knots, control, steps, root_times, root_coef, velocity, params, times, parents, offsets,
                    active, out_rot, out_pos)

    @numba.njit(cache=True, parallel=True)
    def _c2_parallel(knots, control, steps, root_times, root_coef, velocity, params, times, parents, offsets,
                     active, first, stride, out_rot, out_pos):
        for k in numba.prange((times.shape[0] - first + stride - 1) // stride):
            _c2_one(first + k * stride, knots, control, steps, root_times, root_coef, velocity, params, times,
                    parents, offsets, active, out_rot, out_pos)

    @numba.njit(cache=True)
    def _spline_ik_serial(seg_times, ctrl, root_times, root_coef, src, sign, velocity, params, chains, hinges, below,
                         turns, values, slopes, ik, times, parents, offsets, active, first, stride, out_rot, out_pos):
        for c in range(first, times.shape[0], stride):
            _spline_one(c, seg_times, ctrl, root_times, root_coef, src, sign, velocity, params, times, parents,
                       offsets, active, out_rot, out_pos)
            _foot_lock(c, chains, hinges, below, turns, values, slopes, ik, times, parents, offsets, out_rot, out_pos)

    @numba.njit(cache=True, parallel=True)
    def _spline_ik_parallel(seg_times, ctrl, root_times, root_coef, src, sign, velocity, params, chains, hinges, below,
                           turns, values, slopes, ik, times, parents, offsets, active, first, stride, out_rot,
                           out_pos):
        for k in numba.prange((times.shape[0] - first + stride - 1) // stride):
            c = first + k * stride
            _spline_one(c, seg_times, ctrl, root_times, root_coef, src, sign, velocity, params, times, parents,
                       offsets, active, out_rot, out_pos)
            _foot_lock(c, chains, hinges, below, turns, values, slopes, ik, times, parents, offsets, out_rot, out_pos)

    @numba.njit(cache=True)
    def _spring_ik_serial(key_params, keys, angles, inv_sin, key_root, params, chains, hinges, below, turns, values,
                          slopes, ik, times, parents, offsets, active, first, stride, out_rot, out_pos):
        for c in range(first, times.shape[0], stride):
            _spring_one(c, key_params, keys, angles, inv_sin, key_root, params, times, parents, offsets,
                        active, out_rot, out_pos)
            _foot_lock(c, chains, hinges, below, turns, values, slopes, ik, times, parents, offsets, out_rot, out_pos)

    @numba.njit(cache=True, parallel=True)
    def _spring_ik_parallel(key_params, keys, angles, inv_sin, key_root, params, chains, hinges, below, turns, values,
                            slopes, ik, times, parents, offsets, active, first, stride, out_rot, out_pos):
        for k in numba.prange((times.shape[0] - first + stride - 1) // stride):
            c = first + k * stride
            _spring_one(c, key_params, keys, angles, inv_sin, key_root, params, times, parents, offsets,
                        active, out_rot, out_pos)
            _foot_lock(c, chains, hinges, below, turns, values, slopes, ik, times, parents, offsets, out_rot, out_pos)

    @numba.njit(cache=True)
    def _spline_serial(seg_times, ctrl, root_times, root_coef, src, sign, velocity, params, times, parents,
                       offsets, active, first, stride, out_rot, out_pos):
        for c in range(first, times.shape[0], stride):
            _spline_one(c, seg_times, ctrl, root_times, root_coef, src, sign, velocity, params, times, parents,
                        offsets, active, out_rot, out_pos)

    @numba.njit(cache=True, parallel=True)
    def _spline_parallel(seg_times, ctrl, root_times, root_coef, src, sign, velocity, params, times, parents,
                         offsets, active, first, stride, out_rot, out_pos):
        for k in numba.prange((times.shape[0] - first + stride - 1) // stride):
            _spline_one(first + k * stride, seg_times, ctrl, root_times, root_coef, src, sign, velocity, params,
                        times, parents, offsets, active, out_rot, out_pos)

    @numba.njit(cache=True)
    def _spring_serial(key_params, keys, angles, inv_sin, key_root, params, times, parents, offsets, active,
                       first, stride, out_rot, out_pos):
        for c in range(first, times.shape[0], stride):
            _spring_one(c, key_params, keys, angles, inv_sin, key_root, params, times, parents, offsets,
                        active, out_rot, out_pos)

    @numba.njit(cache=True, parallel=True)
    def _spring_parallel(key_params, keys, angles, inv_sin, key_root, params, times, parents, offsets,
                         active, first, stride, out_rot, out_pos):
        for k in numba.prange((times.shape[0] - first + stride - 1) // stride):
            _spring_one(first + k * stride, key_params, keys, angles, inv_sin, key_root, params, times, parents,
                        offsets, active, out_rot, out_pos)


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
