"""Building the runtimes (offline, once per clip at load time): :func:`runtime_for` picks the kind of runtime
(:mod:`anim_core.runtime.kinds`) from what the clip stores and fits or packs its arrays: SQUAD segments fitted as
cubic Bezier curves (minimax, Lawson's iteratively reweighted least squares), the spring's parameters, a C2
spline's steps, a foot-locked hybrid's tracks, a quantized clip's integers.  Every fit is measured against the exact
curve (:mod:`anim_core.runtime.checks`) and refused beyond its tolerance.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from ..math.clip import PLAYBACK_MODES, KeyframeClip, Pose
from ..math.quat import quat_angle, quat_conj, quat_log, quat_mul, squad_eval
from ..math.skeleton import Skeleton
from ..methods.c2spline import C2Clip
from ..methods.compression import QuantizedClip
from ..methods.footlock import FootLockedClip
from ..methods.hybrid import SpringClip, SquadClip, spring
from ..methods.ik import STRAIGHT
from ..methods.lod import HeldClip
from .checks import max_error_deg
from .crowd import keyframe_root, table_from_keyframes, uniform
from .held import HeldRuntime
from .kinds import (
    AnimClip,
    AnyRuntime,
    C2Runtime,
    FootLockRuntime,
    QuantizedRuntime,
    SplineRuntime,
    SpringRuntime,
    TableRuntime,
    frozen,
)

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


def runtime_for(clip: AnimClip | HeldClip) -> AnyRuntime | HeldRuntime:
    """The keys runtime of a clip, from what it stores: a keyframe clip's keys (on a grid, or at a reduced clip's
    own times), a quantized clip's integers, SQUAD keys as fitted segments, spring keys, a C2 spline's control
    points, or a foot-locked hybrid's base runtime plus its tracks; a held clip's (``update_rate``) is its base's
    runtime evaluated at held times (:class:`anim_core.runtime.held.HeldRuntime`)."""
    if isinstance(clip, HeldClip):
        return HeldRuntime(clip, runtime_for(clip.base))  # type: ignore[arg-type]
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
    return QuantizedRuntime(clip.skeleton, frozen(codes, codes.dtype), frozen(tracks.low, np.float32),
                            frozen(tracks.step, np.float32), frozen(root, np.float32),
                            frozen(velocity, np.float32),
                            frozen([dt, clip.duration, PLAYBACK_MODES.index(clip.mode)], np.float64),
                            frozen(np.zeros(0) if on_grid else clip.times, np.float64))


def _root_arrays(clip: SquadClip) -> tuple[Array, F32, F32]:
    """The SQUAD clip's root spline (breakpoints, coefficients) and travel per second, as the kernels take them."""
    spline = clip.precomputed()[4]
    return (frozen(spline.x, np.float64), frozen(np.moveaxis(spline.c, 0, 1), np.float32),
            frozen(clip.velocity if clip.mode == "loop" and not clip.in_place else np.zeros(3), np.float32))


def c2_runtime(clip: C2Clip, tolerance_deg: float = C2_TOLERANCE_DEG) -> C2Runtime:
    """The C2 clip's control points with the logarithms of their steps, its knots and the SQUAD root."""
    spline = clip.spline
    c = spline.control
    w = quat_log(quat_mul(quat_conj(np.roll(c, 1, axis=0)), c))  # w_i = log(c_(i-1)^-1 c_i), as the spline has it
    theta = np.linalg.norm(w, axis=-1)
    axis = np.where(theta[..., None] > 0, w / np.where(theta > 0, theta, 1.0)[..., None], 0.0)
    steps = np.concatenate([theta[..., None], axis], axis=-1)
    runtime = C2Runtime(clip.skeleton, frozen(spline.knots, np.float64), frozen(c, np.float32),
                        frozen(steps, np.float32), *_root_arrays(clip.squad),
                        frozen([clip.duration, PLAYBACK_MODES.index(clip.mode), spline.period,
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
    chains, below, turns = leg_arrays(sk, clip.legs)
    loop = clip.mode == "loop"
    travel = clip.velocity if loop and not clip.in_place else np.zeros(3)
    runtime = FootLockRuntime(sk, base, frozen(chains, np.int32), frozen(clip.hinges, np.float32),
                              frozen(below, np.int32),
                              frozen(turns, np.int32), frozen(values, np.float32), frozen(slopes, np.float32),
                              frozen([clip.fps, 1.0 if loop else 0.0, clip.duration,
                                       PLAYBACK_MODES.index(clip.mode), *travel, clip.soft, STRAIGHT],
                                      np.float64), 0.0)
    error = max_error_deg(runtime, clip, _CHECK_RATE)
    if error > tolerance_deg:
        raise ValueError(f"clip {clip.name!r}: the foot-lock kernel is {error:.4f} degrees from the clip's pose, "
                         f"more than {tolerance_deg} degrees")
    object.__setattr__(runtime, "error_deg", error)
    return runtime


def leg_arrays(skeleton: Skeleton, legs: Sequence[tuple[int, int, int]]
               ) -> tuple[NDArray[np.int32], NDArray[np.int32], NDArray[np.int32]]:
    """What the legs' IK kernel (:func:`anim_core.runtime.kernels.solve_leg`) takes of the legs: ``chains (F, 3)``
    (hip, knee, ankle), ``below (F, L)`` the joints under each hip in topological order (-1 padded) and
    ``turns (F, L)`` what turns each (:func:`_below`), int32."""
    chains = np.array(legs, np.int32).reshape(-1, 3)
    under = [_below(skeleton, (int(s), int(m), int(e))) for s, m, e in chains]
    width = max([1, *(len(u) for u in under)])
    below = np.full((len(under), width), -1, np.int32)
    turns = np.full((len(under), width), 2, np.int32)
    for leg, joints in enumerate(under):
        below[leg, :len(joints)] = [j for j, _ in joints]
        turns[leg, :len(joints)] = [k for _, k in joints]
    return chains, below, turns


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
    """Partner ``(J,)`` and per-joint linear map ``(J, 4, 4)`` if the clip's second half cycle is its mirrored first
    half (:attr:`SquadClip.mirror`), else None."""
    k = clip.n_keys
    mirror = clip.mirror
    if mirror is None or clip.mode != "loop" or k % 2 or not np.allclose(
            clip.key_times[k // 2:], clip.key_times[:k // 2] + clip.duration / 2, atol=1e-12):
        return None
    j = clip.skeleton.n_joints
    # The mirror is linear in each quaternion: column c of joint j's map is the image of basis vector e_c.
    basis = np.zeros((4, j, 4))
    basis[np.arange(4), :, np.arange(4)] = 1.0
    cols = mirror(Pose(basis, np.zeros((4, 3)))).rotations  # (4 = c, J, 4); joint j holds its partner's image
    src = mirror.partners.astype(np.int32)
    maps = np.moveaxis(cols, 0, -1)  # (J, 4 out, 4 in): applied to the partner's quaternion
    half = clip.key_rotations[k // 2:]
    image = np.einsum("joi,kji->kjo", maps, clip.key_rotations[:k // 2][:, src])
    if not np.all(np.abs(np.abs(np.sum(half * image, axis=-1)) - 1.0) < _MIRROR_TOLERANCE):
        return None
    return src, maps


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
    src, maps = mirrored if mirrored is not None else (np.zeros(0, np.int32), np.zeros((0, 4, 4)))
    if maps.size and np.allclose(maps, maps[:1], atol=1e-12):
        maps = maps[:1]  # the same map for every joint: one
    root_times, root_coef, velocity = _root_arrays(clip)
    runtime = SplineRuntime(
        clip.skeleton, frozen(seg_times[: stored + 1], np.float64), frozen(controls, np.float32),
        root_times, root_coef, frozen(src, np.int32), frozen(maps, np.float32), velocity,
        frozen([clip.duration, PLAYBACK_MODES.index(clip.mode),
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
    return SpringRuntime(clip.skeleton, frozen(clip.key_params, np.float64), frozen(keys, np.float32),
                         frozen(angles, np.float32), frozen(inv_sin, np.float32),
                         frozen(clip.key_root, np.float32), frozen(params, np.float64))


def _crouch_u_numpy(ct: Array, params: Array) -> Array:
    zeta, omega, ts, norm = params[:4]
    x = ts * ct
    alpha = omega * np.sqrt(1.0 - zeta * zeta)
    spring = np.exp(-omega * zeta * x) * (np.cos(alpha * x) + omega * zeta / alpha * np.sin(alpha * x))
    return (1.0 - spring) * norm

