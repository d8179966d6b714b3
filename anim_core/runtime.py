"""Posing crowds from the keys each clip stores: one compiled kernel per kind of clip, nothing resampled in time.

Conventions: quaternions ``(w, x, y, z)`` (see :mod:`anim_core.quat`), times in seconds, runtime arrays float32
unless a comment says otherwise; every output is the model-space (global) rotation ``(N, J, 4)`` and position
``(N, J, 3)`` of every joint of ``N`` characters, each at its own running time ``t (N,)``.

Three runtimes, built once per clip at load time (:func:`runtime_for`), evaluated per frame by :meth:`pose`:

* :class:`TableRuntime`: keys on a uniform grid, nlerp between two of them (a keyframe clip's own keys, or a
  hybrid baked by :func:`anim_core.crowd.bake`).
* :class:`SplineRuntime`: a SQUAD hybrid (gait, idle).  Exact SQUAD costs three slerps per joint; instead each
  segment between two keys is a cubic Bezier curve in R^4, normalized, whose two inner control points per joint
  are fitted once to the exact SQUAD curve (minimax, Lawson's iteratively reweighted least squares).  The end
  control points are the keys themselves, so the curve passes through every key.  Per joint and frame that is
  four weighted quaternions and a normalization, like nlerp's two.  The fit's error against the exact curve is
  measured when the runtime is built (``fit_error_deg``) and must stay within :data:`FIT_TOLERANCE_DEG`.
  A mirrored gait (second half cycle = the mirror image of the first, as :func:`anim_core.hybrid.build_gait`
  makes it) stores the first half only; the second half is evaluated there and mirrored per joint (partner
  joint, sign flips), which is exact because the mirror commutes with SQUAD.
* :class:`SpringRuntime`: the crouch.  Per character the closed-form spring gives the path parameter
  (:func:`crouch_path_parameter`), per joint an unclamped slerp between the two keys of its segment with the
  angle precomputed.

Memory: every array a runtime holds for its clip is animation data and counts in :attr:`runtime_bytes` (the keys,
control points, angles, segment times, the few scalars as a float64 array); the skeleton (parents, offsets) is
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

from .clip import PLAYBACK_MODES, KeyframeClip, Pose
from .crowd import CrowdBuffers, PoseTable, numba, table_from_keyframes
from .hybrid import AnimClip, SpringClip, SquadClip, spring
from .mirror import Mirror
from .quat import quat_angle, squad_eval
from .skeleton import Skeleton

Array = NDArray[np.float64]
F32 = NDArray[np.float32]
FIT_TOLERANCE_DEG = 0.25  # largest angle between a joint's global rotation from the fitted curve and exact SQUAD
_FIT_SAMPLES = 96  # samples per segment the control points are fitted on
_FIT_ROUNDS = 30  # Lawson iterations: the weights converge towards the minimax fit
_CHECK_RATE = 240.0  # samples per second of the fit check in global rotations
_MIRROR_TOLERANCE = 1e-6  # quaternion components: the second half must be the mirrored first half to rounding

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
    """Keys on a uniform grid (:class:`anim_core.crowd.PoseTable`): ``rotations (K, J, 4)``, ``root (K, 3)``,
    ``velocity (3,)``, ``params (3,)`` float64 = (key step s, duration s, playback mode index)."""

    skeleton: Skeleton
    rotations: F32
    root: F32
    velocity: F32
    params: Array

    @classmethod
    def from_table(cls, table: PoseTable) -> TableRuntime:
        return cls(table.skeleton, _frozen(table.rotations, np.float32), _frozen(table.root, np.float32),
                   _frozen(table.velocity, np.float32),
                   _frozen([table.dt, table.duration, PLAYBACK_MODES.index(table.mode)], np.float64))

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
    playback mode index), read off the :class:`~anim_core.hybrid.SpringClip`'s fields."""

    skeleton: Skeleton
    key_params: Array
    keys: F32
    angles: F32
    inv_sin: F32
    key_root: F32
    params: Array

    def _kernels(self) -> tuple[Any, Any]:
        return _spring_serial, _spring_parallel


AnyRuntime = TableRuntime | SplineRuntime | SpringRuntime


# --- building (offline, once per clip) ---------------------------------------------------------------------------

def runtime_for(clip: AnimClip) -> AnyRuntime:
    """The keys runtime of a clip: its dense keys, its SQUAD keys as fitted segments, or its spring keys."""
    if isinstance(clip, KeyframeClip):
        return TableRuntime.from_table(table_from_keyframes(clip))
    if isinstance(clip, SquadClip):
        return spline_runtime(clip)
    if isinstance(clip, SpringClip):
        return spring_runtime(clip)
    raise ValueError(f"no runtime for clips of type {type(clip).__name__}")


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
    seg_times, q, a, b, spline = clip.precomputed()
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
    runtime = SplineRuntime(
        clip.skeleton, _frozen(seg_times[: stored + 1], np.float64), _frozen(controls, np.float32),
        _frozen(spline.x, np.float64), _frozen(np.moveaxis(spline.c, 0, 1), np.float32),
        _frozen(src, np.int32), _frozen(sign, np.float32),
        _frozen(clip.velocity if clip.mode == "loop" and not clip.in_place else np.zeros(3), np.float32),
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
        """(clip time, completed loops) as :func:`anim_core.clip.playback_time`."""
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
    def _table_one(c, keys, roots, velocity, params, times, parents, offsets, active, out_rot, out_pos):
        dt, duration, mode = params[0], params[1], int(params[2])
        ct, cycles = _clip_time(times[c], duration, mode)
        f = ct / dt
        i = min(max(int(np.floor(f)), 0), keys.shape[0] - 2)
        a = np.float32(f - i)
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
    def _spline_one(c, seg_times, ctrl, root_times, root_coef, src, sign, velocity, params, times, parents,
                    offsets, active, out_rot, out_pos):
        duration, mode, half = params[0], int(params[1]), params[2]
        ct, cycles = _clip_time(times[c], duration, mode)
        # Root: the spline of the whole period, Horner in seconds from its segment's start.
        r = 0
        while r < root_times.shape[0] - 2 and ct >= root_times[r + 1]:
            r += 1
        dx = np.float32(ct - root_times[r])
        travel = ct + cycles * duration
        rx = ((root_coef[r, 0, 0] * dx + root_coef[r, 1, 0]) * dx + root_coef[r, 2, 0]) * dx + root_coef[r, 3, 0]
        ry = ((root_coef[r, 0, 1] * dx + root_coef[r, 1, 1]) * dx + root_coef[r, 2, 1]) * dx + root_coef[r, 3, 1]
        rz = ((root_coef[r, 0, 2] * dx + root_coef[r, 1, 2]) * dx + root_coef[r, 2, 2]) * dx + root_coef[r, 3, 2]
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
        form of :func:`anim_core.hybrid.spring` from rest at 1 (the one place the crouch's timing lives)."""
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

    @numba.njit(cache=True)
    def _table_serial(keys, roots, velocity, params, times, parents, offsets, active, first, stride,
                      out_rot, out_pos):
        for c in range(first, times.shape[0], stride):
            _table_one(c, keys, roots, velocity, params, times, parents, offsets, active, out_rot, out_pos)

    @numba.njit(cache=True, parallel=True)
    def _table_parallel(keys, roots, velocity, params, times, parents, offsets, active, first, stride,
                        out_rot, out_pos):
        for k in numba.prange((times.shape[0] - first + stride - 1) // stride):
            _table_one(first + k * stride, keys, roots, velocity, params, times, parents, offsets, active,
                       out_rot, out_pos)

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
