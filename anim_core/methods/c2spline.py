"""A rotation spline with continuous angular acceleration (C2) through the hybrid's keys: the ``hybrid_c2`` condition.

Conventions as in :mod:`anim_core.math.quat`: quaternions ``(..., 4)`` scalar first ``(w, x, y, z)``, times in seconds.

The curve is the *cumulative* cubic B-spline on unit quaternions of Kim, Kim and Shin (M.-J. Kim, M.-S. Kim,
S. Y. Shin, "A general construction scheme for unit quaternion curves with simple high order derivatives",
SIGGRAPH 1995, eq. 9): on the knot interval ``[k_m, k_m+1)``, with the four cubic B-spline basis functions
``N_0..N_3`` that are non-zero there (any knot vector; Cox–de Boor recursion) and their cumulative sums
``B~_j = N_j + ... + N_3``::

    q(t) = c_(m-1) exp(B~_1(t) w_m) exp(B~_2(t) w_(m+1)) exp(B~_3(t) w_(m+2)),   w_i = log(c_(i-1)^-1 c_i)

Each factor is a rotation about a fixed axis by a C2 function of time, so the curve is C2 (continuous angular
acceleration) wherever the basis is, i.e. everywhere for simple knots.  The knots are the key times and the control
points ``c_i`` are solved so that the curve *interpolates* the keys: at knot ``k_m`` only ``c_(m-1), c_m, c_(m+1)``
matter, and Newton's method (Jacobian by forward differences, per joint, step halved while the residual
grows) solves for the rotation-vector residuals at the knots; it stops below :data:`SOLVE_TOLERANCE_RAD`.

Loops (gait) use a periodic knot vector; ping-pong clips (idle) are the periodic spline through the keys followed
by the same keys backwards, which is symmetric about both turns, so the velocity is zero there and the
acceleration continuous across the reversal.  Keys, mirrored second half cycle, root spline and travel are those
of the :class:`~anim_core.methods.hybrid.SquadClip` it is built from (:func:`c2_from_squad`); only the rotation curve
differs.  The crouch's spring clip has no SQUAD spline and no C2 counterpart here.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..math.clip import PlaybackMode, Pose, playback_time
from ..math.quat import canonicalize, make_continuous, quat_conj, quat_exp, quat_log, quat_mul
from ..math.skeleton import Skeleton
from .hybrid import SquadClip

Array = NDArray[np.float64]

SOLVE_TOLERANCE_RAD = 1e-10  # largest rotation from a key to the curve at its knot when the solve stops
_MAX_ROUNDS = 200


def _basis(knots: Array, span: NDArray[np.intp], t: Array) -> Array:
    """``(..., 4)`` cubic B-spline basis values ``N_0..N_3`` at ``t (...)`` in knot interval ``span`` (The NURBS
    Book, algorithm A2.2); ``knots`` are indexed so that interval ``span`` is ``[knots[span], knots[span + 1])``."""
    n = np.zeros((*t.shape, 4))
    n[..., 0] = 1.0
    left = np.zeros((*t.shape, 4))
    right = np.zeros((*t.shape, 4))
    for j in range(1, 4):  # the degree, not the data
        left[..., j] = t - knots[span + 1 - j]
        right[..., j] = knots[span + j] - t
        saved = np.zeros(t.shape)
        for r in range(j):
            temp = n[..., r] / (right[..., r + 1] + left[..., j - r])
            n[..., r] = saved + right[..., r + 1] * temp
            saved = left[..., j - r] * temp
        n[..., j] = saved
    return n


def _step_logs(c: Array) -> Array:
    """``w_i = log(c_(i-1)^-1 c_i)`` for the cyclic control points ``c (K, ..., 4)`` with their signs as they are:
    an interpolating spline through fast keys needs control points up to three times further apart than the keys
    (a knee bending 90 degrees every key), so a step may turn by more than half a turn (up to a whole one)."""
    return quat_log(quat_mul(quat_conj(np.roll(c, 1, axis=0)), c))


@dataclass(frozen=True, eq=False)
class PeriodicC2Spline:
    """Periodic C2 quaternion curve interpolating keys ``(K, ..., 4)`` at strictly increasing ``times (K,)`` s
    with period ``period`` (``> times[-1] - times[0]``); evaluate with :meth:`__call__`."""

    times: Array
    keys: Array
    period: float
    control: Array = field(init=False, repr=False)
    _knots: Array = field(init=False, repr=False)

    def __post_init__(self) -> None:
        t = np.asarray(self.times, dtype=np.float64)
        q = make_continuous(np.asarray(self.keys, dtype=np.float64), axis=0)
        k = t.size
        if t.ndim != 1 or k < 2 or q.shape[0] != k or np.any(np.diff(t) <= 0) or not self.period > t[-1] - t[0]:
            raise ValueError(f"a periodic C2 spline needs >= 2 strictly increasing key times within one period, "
                             f"got {k} keys, times {np.round(t, 4).tolist()}, period {self.period}")
        # Knots k_m for m = -3 .. K+3, stored at index m + 3.
        m = np.arange(-3, k + 4)
        knots = t[m % k] + self.period * np.floor_divide(m, k)
        object.__setattr__(self, "times", t)
        object.__setattr__(self, "keys", q)
        object.__setattr__(self, "_knots", knots)
        # Basis values at each knot k_m (span m, N_3 = 0) weigh c_(m-1), c_m, c_(m+1).
        c = q.copy()
        object.__setattr__(self, "control", c)
        err = self._residual(c)
        for _ in range(_MAX_ROUNDS):  # Newton rounds with step halving; quadratic convergence near the solution
            if np.max(np.linalg.norm(err, axis=-1)) * 2.0 < SOLVE_TOLERANCE_RAD:
                break
            step = self._newton_step(c, err)
            for _halving in range(30):
                trial = quat_mul(c, quat_exp(step))
                trial_err = self._residual(trial)
                if np.max(np.linalg.norm(trial_err, axis=-1)) < np.max(np.linalg.norm(err, axis=-1)):
                    break
                step = 0.5 * step
            c, err = trial, trial_err
        else:
            raise ValueError("the C2 spline's control points did not converge (keys too far apart?)")
        object.__setattr__(self, "control", c)

    def _residual(self, c: Array) -> Array:
        """``(K, ..., 3)`` ``log(q(t_m)^-1 key_m)`` with control points ``c``."""
        object.__setattr__(self, "control", c)
        return quat_log(canonicalize(quat_mul(quat_conj(self._eval(self.times)), self.keys)))

    def _newton_step(self, c: Array, err: Array) -> Array:
        """``(K, ..., 3)`` corrections ``d`` (``c_i <- c_i exp(d_i)``) solving the linearized residual, per joint:
        every joint's curve is independent, so one perturbation of control point ``i`` along axis ``a`` gives that
        column of every joint's ``3K x 3K`` Jacobian (forward differences)."""
        k = self.times.size
        h = 1e-7
        cols = []
        for i in range(k):  # 3K perturbations, each evaluates all joints at once
            for a in range(3):
                d = np.zeros((*c.shape[:-1], 3))
                d[i, ..., a] = h
                cols.append((self._residual(quat_mul(c, quat_exp(d))) - err) / h)
        jac = np.stack(cols, axis=-1)  # (K, ..., 3, 3K): residual (m, axis) by perturbation (i, a)
        jac = np.moveaxis(jac, 0, -3).reshape(*c.shape[1:-1], 3 * k, 3 * k)
        rhs = np.moveaxis(err, 0, -2).reshape(*c.shape[1:-1], 3 * k, 1)
        step = -np.linalg.solve(jac, rhs)[..., 0].reshape(*c.shape[1:-1], k, 3)
        object.__setattr__(self, "control", c)
        return np.moveaxis(step, -2, 0)

    def _eval(self, t: Array) -> Array:
        k = self.times.size
        tt = self.times[0] + np.mod(np.asarray(t, dtype=np.float64) - self.times[0], self.period)
        span = np.clip(np.searchsorted(self._knots, tt, side="right") - 1, 3, k + 2)
        n = _basis(self._knots, span, tt)
        cum = np.cumsum(n[..., ::-1], axis=-1)[..., ::-1]  # B~_j = N_j + ... + N_3
        m = span - 3
        c = self.control
        w = _step_logs(c)
        extra = (1,) * (c.ndim - 2)  # the joint axes of the keys
        out = c[(m - 1) % k]
        for j in range(1, 4):
            b = cum[..., j].reshape(*tt.shape, *extra, 1)
            out = quat_mul(out, quat_exp(b * w[(m - 1 + j) % k]))
        return out

    def __call__(self, t: ArrayLike) -> Array:
        """Rotations ``(N..., ..., 4)`` at times ``t (N...)`` seconds (wrapped into the period)."""
        return self._eval(np.asarray(t, dtype=np.float64))

    @property
    def knots(self) -> Array:
        """``(K + 7,)`` the knots ``k_-3 .. k_(K+3)`` in seconds (key times continued periodically), for runtimes
        that evaluate the curve themselves (:class:`anim_core.runtime.C2Runtime`)."""
        return self._knots


@dataclass(frozen=True, eq=False)
class C2Clip:
    """The rotation curve of a :class:`~anim_core.methods.hybrid.SquadClip` (its keys, root, travel and playback) as the
    C2 spline of this module; build with :func:`c2_from_squad`."""

    skeleton: Skeleton
    squad: SquadClip
    mode: PlaybackMode = field(init=False)
    name: str = field(init=False)
    spline: PeriodicC2Spline = field(init=False, repr=False)

    def __post_init__(self) -> None:
        s = self.squad
        t = np.asarray(s.key_times, dtype=np.float64)
        rot = np.asarray(s.key_rotations, dtype=np.float64)
        if s.mode == "loop":
            spline = PeriodicC2Spline(t, rot, s.duration)
        else:  # ping-pong: forward keys, then the inner keys backwards, period twice the span
            back = slice(-2, 0, -1)
            spline = PeriodicC2Spline(np.concatenate([t, 2.0 * s.duration - t[back]]),
                                      np.concatenate([rot, rot[back]]), 2.0 * s.duration)
        object.__setattr__(self, "mode", s.mode)
        object.__setattr__(self, "name", s.name)
        object.__setattr__(self, "spline", spline)

    @property
    def duration(self) -> float:
        return self.squad.duration

    @property
    def key_times(self) -> Array:
        return np.asarray(self.squad.key_times)

    @property
    def key_rotations(self) -> Array:
        return np.asarray(self.squad.key_rotations)

    @property
    def n_keys(self) -> int:
        return self.squad.n_keys

    @property
    def velocity(self) -> Array:
        """``(3,)`` the SQUAD clip's travel per second (loop mode, unless in place)."""
        return self.squad.velocity

    @property
    def in_place(self) -> bool:
        return self.squad.in_place

    def sample(self, t: ArrayLike) -> Pose:
        """Poses at running times ``t (...)`` s: rotations ``(..., J, 4)`` from the C2 spline, root as the SQUAD
        clip's."""
        t = np.asarray(t, dtype=np.float64)
        clip_t, _ = playback_time(t, self.duration, self.mode)
        return Pose(self.spline(clip_t), self.squad.sample(t).root_translation)


def c2_from_squad(clip: SquadClip) -> C2Clip:
    """The ``hybrid_c2`` clip: same keys (mirrored gait, increments), root and playback as ``clip``, C2 rotations."""
    return C2Clip(clip.skeleton, clip)
