"""Objective motion-quality metrics of an animation clip.

Units: positions in metres with Y up and the floor at ``y = 0``, time in seconds, angles in radians.  Results are
reported in the units a reader compares at a glance: millimetres for small distances, m/s³ for jerk, rad/s for
angular-velocity jumps.

Periodic sequences (``periodic=True``) hold exactly one period of ``T`` frames *without* a repeated end frame:
frame ``T`` is frame ``0`` again.  For a loop clip whose last key repeats the first, drop that last frame; for a
ping-pong clip pass the whole forward-and-back period.  A repeated end frame would add a zero step at the seam.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..math.quat import canonicalize, quat_conj, quat_log, quat_mul

Array = NDArray[np.float64]

CONTACT_CLEARANCE_M = 0.05  # a foot joint closer than this to its flat-standing height is planted
SKATE_SPEED_MPS = 0.5  # a planted foot joint moving faster than this horizontally is skating


def _horizontal_speed(positions: Array, fps: float, periodic: bool, ground_velocity: Array) -> Array:
    """Horizontal (x, z) speed in m/s of ``positions (T, ..., 3)`` by central differences along axis 0, plus the
    ground velocity ``(3,)``."""
    xz = positions[..., [0, 2]]
    if periodic:
        # Frame T follows frame T-1, so the seam is measured like any other frame.
        vel = (np.roll(xz, -1, axis=0) - np.roll(xz, 1, axis=0)) * (0.5 * fps)
    else:
        # Central differences inside, one-sided first differences at both ends.
        vel = np.gradient(xz, 1.0 / fps, axis=0, edge_order=1)
    return np.linalg.norm(vel + ground_velocity[[0, 2]], axis=-1)


def foot_metrics(feet: ArrayLike, contact_heights: ArrayLike, fps: float, periodic: bool = True,
                 ground_velocity: ArrayLike | None = None) -> dict[str, float]:
    """Foot skating, sliding, floor penetration and floating over a clip.

    ``feet``: ``(T, F, K, 3)`` world positions in metres of ``F`` feet, each tracked by ``K`` joints (e.g. ankle and
    toe), over ``T`` frames at ``fps`` frames per second.  ``contact_heights``: ``(F, K)`` height in metres of each
    joint above the floor when its foot stands flat (an ankle ~0.07, a toe ~0.02); a joint's *clearance* is
    ``y - contact_height``.  ``ground_velocity``: ``(3,)`` m/s added to every joint's velocity, for clips played in
    place (their root's removed travel), so speeds are measured against the ground.

    A foot is *in contact* in a frame when all its joints are within :data:`CONTACT_CLEARANCE_M` of their flat
    height (the whole foot is down; a foot swinging just above the floor lifts its heel or toe), and it *skates*
    when even its slowest joint moves horizontally faster than :data:`SKATE_SPEED_MPS` (a foot rolling over its
    heel or toe keeps that point still; a sliding foot moves everywhere).

    Returns a dict of floats:

    * ``foot_skate_ratio``: share of frames (0..1) in which at least one foot in contact skates.
    * ``foot_slide_mm``: mean horizontal displacement per frame in mm of the slowest joint of feet in contact
      (0 if no foot is ever in contact).
    * ``penetration_mm``: mean over frames of how far the lowest joint (smallest clearance) is below the floor.
    * ``floating_mm``: mean over frames of how far the lowest joint is above the floor.  Flight phases of a run
      count as floating too; compare clips of the same motion.
    """
    p = np.asarray(feet, dtype=np.float64)
    h = np.asarray(contact_heights, dtype=np.float64)
    if p.ndim != 4 or p.shape[-1] != 3 or p.shape[0] < 2:
        raise ValueError(f"expected foot positions of shape (T >= 2, F, K, 3), got {p.shape}")
    if h.shape != p.shape[1:3]:
        raise ValueError(f"expected contact heights of shape {p.shape[1:3]}, got {h.shape}")
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    g = np.zeros(3) if ground_velocity is None else np.asarray(ground_velocity, dtype=np.float64)

    clearance = p[..., 1] - h  # (T, F, K)
    contact = np.all(clearance < CONTACT_CLEARANCE_M, axis=2)  # (T, F)
    speed = _horizontal_speed(p, fps, periodic, g).min(axis=2)  # (T, F): the foot's slowest joint
    skating = np.any(contact & (speed > SKATE_SPEED_MPS), axis=1)
    # Displacement per frame is speed / fps; mean over in-contact samples only.
    slide_mm = float(np.mean(speed[contact]) / fps * 1000.0) if np.any(contact) else 0.0
    lowest = np.min(clearance, axis=(1, 2))  # (T,)
    return {
        "foot_skate_ratio": float(np.mean(skating)),
        "foot_slide_mm": slide_mm,
        "penetration_mm": float(np.mean(np.maximum(0.0, -lowest)) * 1000.0),
        "floating_mm": float(np.mean(np.maximum(0.0, lowest)) * 1000.0),
    }


def mpjpe_mm(a: ArrayLike, b: ArrayLike, root: int = 0) -> float:
    """Root-relative mean per-joint position error in mm between pose sequences ``a`` and ``b``, ``(T, J, 3)`` m.

    Each sequence's ``root`` joint position is subtracted per frame first, so global translation is ignored.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 3 or a.shape[-1] != 3:
        raise ValueError(f"expected two pose sequences of the same shape (T, J, 3), got {a.shape} and {b.shape}")
    rel_a = a - a[:, root : root + 1]
    rel_b = b - b[:, root : root + 1]
    return float(np.mean(np.linalg.norm(rel_a - rel_b, axis=-1)) * 1000.0)


def jerk_mean(positions: ArrayLike, fps: float, periodic: bool = True) -> float:
    """Mean magnitude in m/s³ of the third time derivative of joint positions ``(T, J, 3)`` sampled at ``fps``.

    Forward third differences times ``fps**3``: ``T - 3`` of them, or ``T`` with ``periodic=True``, where the
    differences wrap around the loop seam so that a popping loop shows up.
    """
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 3 or p.shape[-1] != 3 or p.shape[0] < 4:
        raise ValueError(f"expected joint positions of shape (T >= 4, J, 3), got {p.shape}")
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    if periodic:
        # d[i] = p[i+3] - 3 p[i+2] + 3 p[i+1] - p[i] with indices mod T.
        d3 = np.roll(p, -3, axis=0) - 3.0 * np.roll(p, -2, axis=0) + 3.0 * np.roll(p, -1, axis=0) - p
    else:
        d3 = np.diff(p, n=3, axis=0)
    return float(np.mean(np.linalg.norm(d3, axis=-1)) * fps**3)


def angular_velocity_jumps(
    sample_rotations: Callable[[Array], ArrayLike], key_times: ArrayLike, delta: float = 1e-4
) -> float:
    """Mean jump in rad/s of each joint's angular velocity across the key times (a C1 check of the interpolant).

    ``sample_rotations`` maps times ``(N,)`` in seconds to local joint rotations ``(N, J, 4)``; it is called once,
    with the ``3K`` times ``t - delta``, ``t``, ``t + delta`` of the ``K`` key times ``key_times (K,)``.  The angular
    velocity of a step ``q_a -> q_b`` over ``delta`` seconds is ``2 log(r) / delta`` with ``r = q_b conj(q_a)``
    (``w >= 0``, the short way round); the jump at a key is the norm of (after - before).  Mean over keys and joints.
    """
    t = np.asarray(key_times, dtype=np.float64)
    if t.ndim != 1 or t.shape[0] < 1:
        raise ValueError(f"expected key times of shape (K >= 1,), got {t.shape}")
    if delta <= 0:
        raise ValueError(f"delta must be positive, got {delta}")
    k = t.shape[0]
    q = np.asarray(sample_rotations(np.concatenate([t - delta, t, t + delta])), dtype=np.float64)
    if q.ndim != 3 or q.shape[0] != 3 * k or q.shape[-1] != 4:
        raise ValueError(f"sample_rotations must return ({3 * k}, J, 4) for {3 * k} times, got {q.shape}")
    before, at, after = q[:k], q[k : 2 * k], q[2 * k :]
    w_before = 2.0 * quat_log(canonicalize(quat_mul(at, quat_conj(before)))) / delta
    w_after = 2.0 * quat_log(canonicalize(quat_mul(after, quat_conj(at)))) / delta
    return float(np.mean(np.linalg.norm(w_after - w_before, axis=-1)))


def angular_acceleration_jumps(
    sample_rotations: Callable[[Array], ArrayLike], key_times: ArrayLike, delta: float = 1e-3
) -> float:
    """Mean jump in rad/s² of each joint's angular acceleration across the key times (a C2 check).

    Like :func:`angular_velocity_jumps`, with the five times ``t - 2 delta .. t + 2 delta`` per key (one call of
    ``sample_rotations`` with ``5K`` times): the acceleration before the key is the difference of the angular
    velocities over ``[t - 2 delta, t - delta]`` and ``[t - delta, t]`` divided by ``delta``, after it likewise on
    the other side; the jump is the norm of (after - before).  For a C2 curve it tends to 0 with ``delta`` (as
    ``delta`` times the jerk), for a C1 curve to the true jump.
    """
    t = np.asarray(key_times, dtype=np.float64)
    if t.ndim != 1 or t.shape[0] < 1:
        raise ValueError(f"expected key times of shape (K >= 1,), got {t.shape}")
    if delta <= 0:
        raise ValueError(f"delta must be positive, got {delta}")
    k = t.shape[0]
    q = np.asarray(sample_rotations(np.concatenate([t + i * delta for i in (-2, -1, 0, 1, 2)])), dtype=np.float64)
    if q.ndim != 3 or q.shape[0] != 5 * k or q.shape[-1] != 4:
        raise ValueError(f"sample_rotations must return ({5 * k}, J, 4) for {5 * k} times, got {q.shape}")
    q = q.reshape(5, k, *q.shape[1:])
    w = 2.0 * quat_log(canonicalize(quat_mul(q[1:], quat_conj(q[:-1])))) / delta  # (4, K, J, 3)
    before = (w[1] - w[0]) / delta
    after = (w[3] - w[2]) / delta
    return float(np.mean(np.linalg.norm(after - before, axis=-1)))


def storage_bytes(n_keys: int, n_joints: int) -> int:
    """Bytes to store ``n_keys`` keys as float32: ``n_joints`` quaternions, a root translation and the key time."""
    return int(n_keys) * (int(n_joints) * 4 + 3 + 1) * 4


def frame_steps_mm(positions: ArrayLike) -> Array:
    """``(T,)`` largest joint displacement in mm from each frame to the next of one period ``(T, J, 3)`` m; the
    last entry is the step across the wrap (frame ``T - 1`` to frame 0)."""
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 3 or p.shape[-1] != 3 or p.shape[0] < 2:
        raise ValueError(f"expected joint positions of shape (T >= 2, J, 3), got {p.shape}")
    return np.linalg.norm(np.roll(p, -1, axis=0) - p, axis=-1).max(axis=1) * 1000.0


def seam_jump_mm(positions: ArrayLike) -> float:
    """Largest joint displacement in mm across the wrap of one period ``(T, J, 3)`` m (see :func:`frame_steps_mm`)."""
    return float(frame_steps_mm(positions)[-1])


def seam_limit_mm(positions: ArrayLike) -> float:
    """The largest seam jump that is no pop: twice the median per-frame step (wrap excluded) plus 5 mm."""
    return float(2.0 * np.median(frame_steps_mm(positions)[:-1]) + 5.0)


def phase_alignment(reference: ArrayLike, other: ArrayLike, max_lag: int | None = None) -> tuple[float, int]:
    """How well two periodic signals over one period, ``(T,)`` or ``(T, C)`` channels, move in step.

    Returns ``(r0, lag)``: the Pearson correlation at lag 0 (channels z-scored and pooled), and the circular
    lag in frames, in ``[-T/2, T/2)``, at which ``other`` correlates best with ``reference``: positive when
    ``other`` runs late (``other[t + lag]`` matches ``reference[t]``).  A constant channel counts as uncorrelated.
    ``max_lag``: search only lags with ``|lag| <= max_lag`` (a gait's hips bob twice per cycle: a quarter cycle).
    """
    a = np.asarray(reference, dtype=np.float64)
    b = np.asarray(other, dtype=np.float64)
    if a.shape != b.shape or a.ndim not in (1, 2) or a.shape[0] < 3:
        raise ValueError(f"expected two signals of the same shape (T >= 3,) or (T, C), got {a.shape}, {b.shape}")
    a = a.reshape(a.shape[0], -1)
    b = b.reshape(b.shape[0], -1)

    def z(x: Array) -> Array:
        sd = x.std(axis=0)
        return np.where(sd > 1e-12, (x - x.mean(axis=0)) / np.maximum(sd, 1e-300), 0.0)

    za, zb = z(a), z(b)
    n = a.shape[0]
    # Circular cross-correlation of every lag at once: corr[L] = mean_t za[t] zb[t + L].
    corr = np.real(np.fft.ifft(np.conj(np.fft.fft(za, axis=0)) * np.fft.fft(zb, axis=0), axis=0)).mean(axis=1) / n
    lags = (np.arange(n) + n // 2) % n - n // 2
    allowed = np.abs(lags) <= (n if max_lag is None else max_lag)
    best = int(lags[allowed][int(np.argmax(corr[allowed]))])
    return float(corr[0]), best
