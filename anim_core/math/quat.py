"""Quaternion math over arrays.

Conventions used everywhere in ``anim_core``:

* A quaternion is the last axis of an array, shape ``(..., 4)``, in **scalar-first order ``(w, x, y, z)``**
  (the order of ``numpy-quaternion``; note that ``scipy.spatial.transform`` uses ``(x, y, z, w)``).
* Rotations are active and act on column vectors: ``rotate(q, v)`` equals ``matrix_from_quat(q) @ v``, and
  ``quat_mul(a, b)`` is the rotation "first ``b``, then ``a``".
* Angles are in radians.  ``quat_log`` returns the rotation vector divided by two (``half angle * axis``), the
  Lie-algebra element whose ``quat_exp`` is the quaternion, as in Shoemake's SQUAD formulas.
* Every function broadcasts over leading axes; none loops in Python over elements.

Edge cases are handled explicitly: the angle between two quaternions is computed with ``atan2`` (accurate for
tiny and for large angles, unlike ``arccos`` of a dot product near 1), the ``sin(x)/x`` factors use
``numpy.sinc`` (exact at 0), and the shortest-path variants flip the sign of the second quaternion where the
4-D dot product is negative (``q`` and ``-q`` are the same rotation).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

_AXIS_INDEX = {"x": 0, "y": 1, "z": 2}


def _f(a: ArrayLike) -> Array:
    return np.asarray(a, dtype=np.float64)


def identity(shape: tuple[int, ...] = ()) -> Array:
    """Identity quaternions of shape ``shape + (4,)``."""
    q = np.zeros((*shape, 4))
    q[..., 0] = 1.0
    return q


def quat_mul(a: ArrayLike, b: ArrayLike) -> Array:
    """Hamilton product ``a * b`` of quaternions ``(..., 4)`` (broadcasting)."""
    a, b = _f(a), _f(b)
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_conj(q: ArrayLike) -> Array:
    """Conjugate ``(w, -x, -y, -z)``; the inverse of a unit quaternion."""
    q = _f(q)
    return np.concatenate([q[..., :1], -q[..., 1:]], axis=-1)


def quat_inv(q: ArrayLike) -> Array:
    """Inverse of any non-zero quaternion (conjugate divided by the squared norm)."""
    q = _f(q)
    return quat_conj(q) / np.sum(q * q, axis=-1, keepdims=True)


def quat_normalize(q: ArrayLike) -> Array:
    """Scale quaternions to unit norm.  A zero quaternion raises ``ValueError`` (it is no rotation)."""
    q = _f(q)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n == 0.0):
        raise ValueError("cannot normalize a zero quaternion")
    return q / n


def quat_dot(a: ArrayLike, b: ArrayLike) -> Array:
    """4-D dot product, shape ``(...)``."""
    return np.sum(_f(a) * _f(b), axis=-1)


def canonicalize(q: ArrayLike) -> Array:
    """Return the representative of each rotation with ``w >= 0`` (ties broken by the first non-zero part)."""
    q = _f(q)
    # The lexicographic sign rule makes the result unique even for w == 0.
    first = np.where(q[..., 0] != 0, q[..., 0], np.where(q[..., 1] != 0, q[..., 1],
                                                         np.where(q[..., 2] != 0, q[..., 2], q[..., 3])))
    return np.where((first < 0)[..., None], -q, q)


def align_hemisphere(q: ArrayLike, reference: ArrayLike) -> Array:
    """Flip the sign of ``q`` where it lies in the hemisphere opposite ``reference`` (dot < 0)."""
    q = _f(q)
    return np.where((quat_dot(q, reference) < 0)[..., None], -q, q)


def make_continuous(q: ArrayLike, axis: int = 0) -> Array:
    """Flip signs along ``axis`` so that consecutive quaternions have a non-negative dot product.

    Needed before any spline through a sequence of keys: ``q`` and ``-q`` are the same rotation, but an
    interpolant between them takes the long way round.
    """
    q = np.moveaxis(_f(q), axis, 0)
    if q.shape[0] < 2:
        return np.moveaxis(q.copy(), 0, axis)
    flips = np.sum(q[1:] * q[:-1], axis=-1) < 0
    # Each flip changes the sign of all later elements relative to the first one.
    sign = np.where(np.cumsum(flips, axis=0) % 2 == 1, -1.0, 1.0)
    out = q.copy()
    out[1:] *= sign[..., None]
    return np.moveaxis(out, 0, axis)


def rotate(q: ArrayLike, v: ArrayLike) -> Array:
    """Rotate vectors ``v (..., 3)`` by unit quaternions ``q (..., 4)`` (broadcasting)."""
    q, v = _f(q), _f(v)
    w = q[..., :1]
    u = q[..., 1:]
    # v' = v + 2w (u x v) + 2 u x (u x v): two cross products, no matrix.
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def quat_between(a: ArrayLike, b: ArrayLike) -> Array:
    """The smallest rotation turning directions ``a (..., 3)`` into ``b (..., 3)`` (any lengths > 0).

    ``q = normalize(|a||b| + a.b, a x b)``; for opposite directions (no unique smallest rotation) a half turn
    about an axis perpendicular to ``a``.
    """
    a, b = _f(a), _f(b)
    a, b = np.broadcast_arrays(a, b)
    w = np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1) + np.sum(a * b, axis=-1)
    q = np.concatenate([w[..., None], np.cross(a, b)], axis=-1)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    opposite = n[..., 0] <= 1e-12 * np.maximum(np.sum(a * a, axis=-1), 1e-300)
    if np.any(opposite):
        helper = np.where(np.abs(a[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
        perp = np.cross(a, helper)
        half_turn = np.concatenate([np.zeros((*a.shape[:-1], 1)), perp], axis=-1)
        q = np.where(opposite[..., None], half_turn, q)
        n = np.linalg.norm(q, axis=-1, keepdims=True)
    return q / n


def quat_angle(a: ArrayLike, b: ArrayLike | None = None) -> Array:
    """Rotation angle in radians (0..pi) of ``a``, or of the rotation taking ``b`` to ``a`` when given."""
    a = _f(a)
    r = a if b is None else quat_mul(a, quat_conj(b))
    return 2.0 * np.arctan2(np.linalg.norm(r[..., 1:], axis=-1), np.abs(r[..., 0]))


def quat_log(q: ArrayLike) -> Array:
    """Logarithm of unit quaternions: ``(..., 4) -> (..., 3)``, the vector ``half_angle * axis``.

    The result is the principal value for ``q`` as given (no sign flip), so ``quat_exp(quat_log(q)) == q``;
    for ``w < 0`` its norm lies in ``(pi/2, pi]``.
    """
    q = _f(q)
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1)
    theta = np.arctan2(s, q[..., 0])
    # theta / s is finite and accurate for tiny s (atan2(s, w) ~ s / w); exactly zero s needs the limit 1/w.
    safe_s = np.where(s > 0, s, 1.0)
    k = np.where(s > 0, theta / safe_s, 1.0 / np.where(q[..., 0] != 0, q[..., 0], 1.0))
    return v * k[..., None]


def quat_exp(v: ArrayLike) -> Array:
    """Exponential of pure quaternions ``(..., 3) -> (..., 4)``: rotation by ``2 |v|`` about ``v / |v|``."""
    v = _f(v)
    theta = np.linalg.norm(v, axis=-1)
    k = np.sinc(theta / np.pi)  # sin(theta) / theta, exact at 0
    return np.concatenate([np.cos(theta)[..., None], v * k[..., None]], axis=-1)


def quat_from_axis_angle(axis: ArrayLike, angle: ArrayLike) -> Array:
    """Quaternions for rotations by ``angle`` (radians, ``(...)``) about ``axis`` (``(..., 3)``, normalized here)."""
    axis = _f(axis)
    axis = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    half = 0.5 * _f(angle)[..., None]
    v = np.sin(half) * axis
    w = np.broadcast_to(np.cos(half), (*v.shape[:-1], 1))
    return np.concatenate([w, v], axis=-1)


def quat_from_rotvec(rv: ArrayLike) -> Array:
    """Quaternions from rotation vectors (angle * axis, radians) ``(..., 3)``."""
    return quat_exp(0.5 * _f(rv))


def rotvec_from_quat(q: ArrayLike) -> Array:
    """Rotation vectors (angle * axis, radians, angle in [0, pi]) of quaternions ``(..., 4)``."""
    return 2.0 * quat_log(canonicalize(q))


def _interp_weights(a: Array, b: Array, t: Array) -> tuple[Array, Array]:
    # Angle between the 4-D unit vectors via atan2: accurate near 0 and near pi.
    omega = 2.0 * np.arctan2(np.linalg.norm(a - b, axis=-1), np.linalg.norm(a + b, axis=-1))
    sinc_omega = np.sinc(omega / np.pi)
    # sin(k w)/sin(w) = k * sinc(k w)/sinc(w): finite and exact as w -> 0 (weights tend to 1-t, t).
    wa = (1.0 - t) * np.sinc((1.0 - t) * omega / np.pi) / sinc_omega
    wb = t * np.sinc(t * omega / np.pi) / sinc_omega
    return wa, wb


def slerp_unclamped(a: ArrayLike, b: ArrayLike, t: ArrayLike, *, shortest: bool = True) -> Array:
    """Spherical linear interpolation that also **extrapolates** for ``t`` outside ``[0, 1]``.

    ``a``, ``b``: unit quaternions ``(..., 4)``; ``t``: parameter ``(...)``, all broadcast together.
    With ``shortest=True`` the sign of ``b`` is flipped where ``dot(a, b) < 0`` so the path is the shorter arc
    (at most pi radians of rotation); with ``shortest=False`` the quaternions are used exactly as given, which
    SQUAD needs (its inner curves must follow the signs chosen for the keys).  Two exactly antipodal
    quaternions with ``shortest=False`` have no unique great circle and raise ``ValueError``.
    """
    a, b, t = _f(a), _f(b), _f(t)
    if shortest:
        b = align_hemisphere(b, a)
    elif np.any(np.linalg.norm(a + b, axis=-1) == 0):
        raise ValueError("slerp between exactly antipodal quaternions is undefined with shortest=False")
    wa, wb = _interp_weights(a, b, t)
    return wa[..., None] * a + wb[..., None] * b


def slerp(a: ArrayLike, b: ArrayLike, t: ArrayLike, *, shortest: bool = True) -> Array:
    """Spherical linear interpolation with ``t`` clamped to ``[0, 1]``; see :func:`slerp_unclamped`."""
    return slerp_unclamped(a, b, np.clip(_f(t), 0.0, 1.0), shortest=shortest)


def nlerp(a: ArrayLike, b: ArrayLike, t: ArrayLike, *, shortest: bool = True) -> Array:
    """Normalized linear interpolation (what game runtimes use for dense keys); ``t`` is not clamped."""
    a, b, t = _f(a), _f(b), _f(t)
    if shortest:
        b = align_hemisphere(b, a)
    q = a + (b - a) * t[..., None]
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


SquadEnds = Literal["open", "cyclic", "reflect"]


def squad_tangents(
    keys: ArrayLike, times: ArrayLike | None = None, ends: SquadEnds = "open"
) -> tuple[Array, Array, Array]:
    """Precompute Shoemake's SQUAD control quaternions for a key sequence.

    ``keys``: unit quaternions ``(K, ..., 4)`` along axis 0 (K >= 2); ``times``: ``(K,)`` strictly increasing key
    times (default ``0..K-1``).  For ``ends="cyclic"`` the curve returns from the last key to the first one, and
    ``times`` must then have ``K + 1`` entries (the last one is the period end, where key 0 repeats).

    Returns ``(q, a, b)`` with shape ``(S, ..., 4)`` for the ``S`` segments (``K - 1``, or ``K`` when cyclic):
    segment ``i`` runs from ``q[i]`` to ``q[i + 1]`` (``q`` has ``S + 1`` entries, sign-continuous) with inner
    control points ``a[i]`` (at its start) and ``b[i]`` (at its end).  Evaluate with :func:`squad_eval`.

    The tangent at key ``i`` is ``q_i exp(-(log(q_i^-1 q_i+1) + log(q_i^-1 q_i-1)) / 4)`` for evenly spaced keys;
    for uneven spacing the neighbouring logarithm is scaled by the ratio of the key intervals exactly as
    ``numpy-quaternion``'s ``squad`` does, so the curve stays C1 in time.  End conditions:

    * ``"open"``: as ``numpy-quaternion``: the control point at each end equals the end key.
    * ``"cyclic"``: the neighbours of the first and last key wrap around (a seamless loop).
    * ``"reflect"``: the missing neighbour is the mirror image of the existing one (``q_-1 = q_1``), which gives
      zero angular velocity at both ends: the right choice for ping-pong playback, where time reverses there.
    """
    q = _f(keys)
    k = q.shape[0]
    if k < 2:
        raise ValueError(f"SQUAD needs at least 2 keys, got {k}")
    n_seg = k if ends == "cyclic" else k - 1
    if times is None:
        t = np.arange(n_seg + 1, dtype=np.float64)
    else:
        t = _f(times)
        if t.shape != (n_seg + 1,):
            raise ValueError(f"expected {n_seg + 1} key times for {k} keys with ends={ends!r}, got {t.shape}")
    dt = np.diff(t)
    if np.any(dt <= 0):
        raise ValueError("key times must be strictly increasing")

    # Extended, sign-continuous sequence e[0..S+2] = (q_-1, q_0, ..., q_S, q_S+1) and interval lengths.
    if ends == "cyclic":
        idx = np.arange(-1, n_seg + 2) % k
        ext = make_continuous(q[idx], axis=0)
        h = np.concatenate([dt[-1:], dt, dt[:1]])
    elif ends == "reflect":
        idx = np.concatenate([[1], np.arange(k), [k - 2]])
        ext = make_continuous(q[idx], axis=0)
        h = np.concatenate([dt[:1], dt, dt[-1:]])
    elif ends == "open":
        ext = make_continuous(q, axis=0)
        ext = np.concatenate([ext[:1], ext, ext[-1:]])  # placeholders; end control points are set below
        h = np.concatenate([dt[:1], dt, dt[-1:]])
    else:
        raise ValueError(f"ends must be 'open', 'cyclic' or 'reflect', got {ends!r}")

    inv = quat_conj(ext)
    # fwd[j] = log(e_j^-1 e_j+1): the step leaving e_j, for j = 0..S+1.
    fwd = quat_log(quat_mul(inv[:-1], ext[1:]))
    seg = np.arange(n_seg)
    shape = (-1,) + (1,) * (q.ndim - 1)
    # Control point after key i (segment i starts at e[i+1]): backward step scaled by h_i / h_{i-1}.
    ratio_a = (h[seg + 1] / h[seg]).reshape(shape)
    a = quat_mul(ext[seg + 1], quat_exp((-fwd[seg + 1] + fwd[seg] * ratio_a) * 0.25))
    # Control point before key i+1 (segment i ends at e[i+2]): forward step scaled by h_i / h_{i+1}.
    ratio_b = (h[seg + 1] / h[seg + 2]).reshape(shape)
    b = quat_mul(ext[seg + 2], quat_exp((fwd[seg + 2] * ratio_b - fwd[seg + 1]) * -0.25))
    if ends == "open":
        a[0] = ext[1]
        b[-1] = ext[-2]
    return ext[1 : n_seg + 2], a, b


def squad_eval(q0: ArrayLike, q1: ArrayLike, a: ArrayLike, b: ArrayLike, h: ArrayLike) -> Array:
    """``Squad(q0, q1, a, b, h) = Slerp(Slerp(q0, q1, h), Slerp(a, b, h), 2h(1-h))`` for ``h (...)`` in [0, 1].

    No shortest-path flips: the signs fixed by :func:`squad_tangents` are what keeps the curve C1.
    """
    h = _f(h)
    return slerp_unclamped(
        slerp_unclamped(q0, q1, h, shortest=False),
        slerp_unclamped(a, b, h, shortest=False),
        2.0 * h * (1.0 - h),
        shortest=False,
    )


def matrix_from_quat(q: ArrayLike) -> Array:
    """Rotation matrices ``(..., 3, 3)`` from unit quaternions ``(..., 4)``."""
    q = _f(q)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    m = np.stack(
        [
            1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
            2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
            2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy),
        ],
        axis=-1,
    )
    return m.reshape(*q.shape[:-1], 3, 3)


def quat_from_matrix(m: ArrayLike) -> Array:
    """Unit quaternions (``w >= 0``) from rotation matrices ``(..., 3, 3)``.

    Uses the numerically stable branch for each matrix (largest of ``w, x, y, z``), so it is exact to rounding
    for 180-degree rotations too.
    """
    m = _f(m)
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    tr = m00 + m11 + m22
    cand = np.stack(
        [
            np.stack([1 + tr, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0],
                      m[..., 1, 0] - m[..., 0, 1]], -1),
            np.stack([m[..., 2, 1] - m[..., 1, 2], 1 + m00 - m11 - m22, m[..., 0, 1] + m[..., 1, 0],
                      m[..., 0, 2] + m[..., 2, 0]], -1),
            np.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0], 1 - m00 + m11 - m22,
                      m[..., 1, 2] + m[..., 2, 1]], -1),
            np.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1],
                      1 - m00 - m11 + m22], -1),
        ],
        axis=-2,
    )  # (..., 4 branches, 4): each row is 4 * q_k * q for branch k
    diag = np.stack([1 + tr, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    best = np.argmax(diag, axis=-1)
    q = np.take_along_axis(cand, best[..., None, None], axis=-2)[..., 0, :]
    return canonicalize(q / np.linalg.norm(q, axis=-1, keepdims=True))


def _parse_order(order: str) -> tuple[list[int], bool]:
    if len(order) != 3 or not (order.isupper() or order.islower()) or set(order.lower()) != {"x", "y", "z"}:
        raise ValueError(
            f"Euler order must be a permutation of 'XYZ' (intrinsic, upper case) or 'xyz' (extrinsic, lower "
            f"case), got {order!r}"
        )
    return [_AXIS_INDEX[c] for c in order.lower()], order.isupper()


def quat_from_euler(angles: ArrayLike, order: str) -> Array:
    """Quaternions from Euler angles ``(..., 3)`` in radians, in the axis order ``order``.

    Upper case (``"ZYX"``) means intrinsic rotations about the moving axes, so ``"ZYX"`` is
    ``R = Rz(a0) @ Ry(a1) @ Rx(a2)`` — the BVH convention for ``CHANNELS ... Zrotation Yrotation Xrotation``.
    Lower case (``"xyz"``) means extrinsic rotations about fixed axes, ``R = Rz(a2) @ Ry(a1) @ Rx(a0)``
    (scipy's convention for both cases).
    """
    axes, intrinsic = _parse_order(order)
    angles = _f(angles)
    if angles.shape[-1] != 3:
        raise ValueError(f"expected Euler angles of shape (..., 3), got {angles.shape}")
    q = identity(angles.shape[:-1])
    for i, axis in enumerate(axes):
        e = np.zeros((*angles.shape[:-1], 4))
        e[..., 0] = np.cos(0.5 * angles[..., i])
        e[..., 1 + axis] = np.sin(0.5 * angles[..., i])
        q = quat_mul(q, e) if intrinsic else quat_mul(e, q)
    return q


def euler_from_quat(q: ArrayLike, order: str) -> Array:
    """Euler angles ``(..., 3)`` in radians from quaternions, inverse of :func:`quat_from_euler`.

    The middle angle lies in ``[-pi/2, pi/2]``, the others in ``(-pi, pi]``.  Works on the quaternion directly
    (Bernardes & Viollet 2022, the method scipy uses), which stays accurate near gimbal lock: there only the sum
    or difference of the outer angles is defined, and when the middle angle is within 1e-9 rad of +-pi/2 the
    last angle (in ``order``) is set to 0.
    """
    axes, intrinsic = _parse_order(order)
    q = _f(q)
    # Solve the extrinsic problem; intrinsic "ABC" is extrinsic "cba" with the angles reversed.
    i, j, k = axes[::-1] if intrinsic else axes
    sign = (i - j) * (j - k) * (k - i) // 2  # +1 for cyclic axis orders, -1 otherwise
    w, qi, qj, qk = q[..., 0], q[..., 1 + i], q[..., 1 + j], q[..., 1 + k] * sign
    a, b, c, d = w - qj, qi + qk, qj + w, qk - qi
    middle = 2.0 * np.arctan2(np.hypot(c, d), np.hypot(a, b))
    half_sum = np.arctan2(b, a)
    half_diff = np.arctan2(d, c)
    first = half_sum - half_diff
    last = half_sum + half_diff
    # Gimbal lock: middle (before the -pi/2 shift) at 0 or pi, where only first + last (or first - last) is
    # defined; put the whole outer rotation on the angle that comes first in the caller's order.
    lock0 = np.abs(middle) <= 1e-9
    lock_pi = np.abs(middle - np.pi) <= 1e-9
    locked = lock0 | lock_pi
    if intrinsic:
        last = np.where(lock0, 2.0 * half_sum, np.where(lock_pi, 2.0 * half_diff, last))
        first = np.where(locked, 0.0, first)
    else:
        first = np.where(lock0, 2.0 * half_sum, np.where(lock_pi, -2.0 * half_diff, first))
        last = np.where(locked, 0.0, last)
    last = last * sign
    middle = middle - np.pi / 2
    angles = np.stack([first, middle, last], axis=-1)
    angles = (angles + np.pi) % (2 * np.pi) - np.pi
    angles = np.where(angles <= -np.pi, angles + 2 * np.pi, angles)
    return angles[..., ::-1] if intrinsic else angles
