"""The hybrid method: a few keys taken from motion capture, the rest procedural.

* **Gait** (walk, run): keys from the left half of one gait cycle are mirrored into the right half and played
  as a cyclic SQUAD spline (2 keys -> a 4-key cycle at increment 0).
* **Crouch**: stand -> crouch keys driven by an underdamped spring through an *unclamped* slerp, so the pose
  overshoots the crouch key; played ping-pong.  Timed by the mocap (:func:`build_crouch`), the ping-pong turns at
  the spring's first overshoot peak, where the source is deepest.
* **Idle**: sway keys on a SQUAD spline, played ping-pong.
* **Other** (any motion): keys picked by :mod:`anim_core.methods.keypick` on a SQUAD spline, no mirroring, played loop
  or
  ping-pong as configured (:func:`build_other`).
* **Increments** add keys from the mocap midway between existing ones: gait 4 -> 8 -> 16, crouch/idle 2 -> 3 -> 5.

Everything that depends only on the keys (SQUAD control points, root splines, mirror set-up) is computed when
a clip is built; ``sample`` only evaluates.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.interpolate import CubicSpline
from scipy.optimize import brentq

from ..math.clip import KeyframeClip, PlaybackMode, Pose, horizontal, playback_time
from ..math.quat import (
    make_continuous,
    quat_conj,
    quat_from_axis_angle,
    quat_mul,
    rotate,
    slerp_unclamped,
    squad_eval,
    squad_tangents,
)
from ..math.skeleton import Skeleton
from ..rig.mirror import Mirror

Array = NDArray[np.float64]

THESIS_ZETA = 0.7
THESIS_OMEGA = 10.0
THESIS_TIME_SCALE = 0.7


def spring(t: ArrayLike, zeta: float = THESIS_ZETA, omega: float = THESIS_OMEGA, x0: float = 1.0,
           v0: float = 0.0) -> Array:
    """Closed-form underdamped spring ``x'' + 2 zeta omega x' + omega^2 x = 0``, ``x(0) = x0``, ``x'(0) = v0``.

    ``x(t) = exp(-omega zeta t) (x0 cos(alpha t) + (v0 + omega zeta x0) / alpha sin(alpha t))``,
    ``alpha = omega sqrt(1 - zeta^2)``; ``t`` in seconds, ``omega`` in rad/s, ``0 <= zeta < 1``.  Exact at any time,
    so unlike a per-frame integrator it does not depend on the frame rate.
    """
    if not 0.0 <= zeta < 1.0 or omega <= 0:
        raise ValueError(f"an underdamped spring needs 0 <= zeta < 1 and omega > 0, got {zeta}, {omega}")
    t = np.asarray(t, dtype=np.float64)
    alpha = omega * np.sqrt(1.0 - zeta * zeta)
    return np.exp(-omega * zeta * t) * (x0 * np.cos(alpha * t) + (v0 + omega * zeta * x0) / alpha * np.sin(alpha * t))


def spring_settle_time(zeta: float = THESIS_ZETA, omega: float = THESIS_OMEGA,
                       time_scale: float = THESIS_TIME_SCALE, tolerance: float = 0.001) -> float:
    """Seconds after which the spring's envelope ``exp(-zeta omega s t)`` is below ``tolerance``."""
    return float(np.log(1.0 / tolerance) / (zeta * omega * time_scale))


def increment_key_times(times: Sequence[float], increment: int, end: float | None = None) -> Array:
    """Key times after ``increment`` rounds of inserting a key midway between neighbouring keys.

    With ``end`` (the end of a gait half-cycle, where the mirrored first key follows) the interval from the
    last key to ``end`` is split too; ``end`` itself is not a key.  2 keys give 3 and 5 keys without ``end``,
    4 and 8 with it.
    """
    if increment < 0:
        raise ValueError(f"increment must be >= 0, got {increment}")
    t = np.asarray(times, dtype=np.float64)
    if t.ndim != 1 or t.size < 2 or np.any(np.diff(t) <= 0):
        raise ValueError(f"need at least 2 strictly increasing key times, got {list(times)}")
    for _ in range(increment):
        bounds = t if end is None else np.append(t, end)
        mids = 0.5 * (bounds[:-1] + bounds[1:])
        t = np.sort(np.concatenate([t, mids]))
    return t


def _snap(source: KeyframeClip, times: Array) -> Array:
    snapped = np.array([source.nearest_key_time(t) for t in times])
    if np.any(np.diff(snapped) <= 0):
        raise ValueError(f"keys {np.round(times, 4).tolist()} s fall on the same source frames; "
                         "the source has too few frames for this increment")
    return snapped


def _keys(source: KeyframeClip, times: Array) -> Pose:
    idx = [int(np.argmin(np.abs(source.times - t))) for t in times]
    return Pose(source.rotations[idx].copy(), source.root_translation[idx].copy())


@dataclass(frozen=True, eq=False)
class SquadClip:
    """Keys on a SQUAD spline: cyclic for ``mode="loop"`` (gait), reflecting ends for ``"pingpong"`` (idle).

    ``key_times``: ``(K,)`` seconds from 0, ``key_rotations``: ``(K, J, 4)``, ``key_root``: ``(K, 3)``.  For a loop
    the clip returns to key 0 at ``duration`` (``> key_times[-1]``); for ping-pong ``duration == key_times[-1]``.
    The root follows a cubic spline through the key root positions (periodic, or with zero end slopes), plus the
    travel ``velocity * t`` in loop mode unless ``in_place``.  ``mirror``: for a gait whose second half's keys are
    the mirror images of its first half's (:func:`build_gait`), the :class:`~anim_core.rig.mirror.Mirror` that made
    them (a runtime stores the first half only and mirrors it); None otherwise.
    """

    skeleton: Skeleton
    key_times: Array
    key_rotations: Array
    key_root: Array
    duration: float
    mode: PlaybackMode = "loop"
    velocity: Array = field(default_factory=lambda: np.zeros(3))
    in_place: bool = False
    name: str = ""
    mirror: Mirror | None = field(default=None, repr=False)
    _seg_times: Array = field(init=False, repr=False)
    _q: Array = field(init=False, repr=False)
    _a: Array = field(init=False, repr=False)
    _b: Array = field(init=False, repr=False)
    _root: Any = field(init=False, repr=False)

    def __post_init__(self) -> None:
        t = np.asarray(self.key_times, dtype=np.float64)
        rot = np.asarray(self.key_rotations, dtype=np.float64)
        root = np.asarray(self.key_root, dtype=np.float64)
        if rot.shape != (t.size, self.skeleton.n_joints, 4) or root.shape != (t.size, 3):
            raise ValueError(f"key arrays do not match {t.size} key times and {self.skeleton.n_joints} joints")
        if t[0] != 0.0:
            raise ValueError("key times must start at 0")
        if self.mode == "loop":
            if not self.duration > t[-1]:
                raise ValueError("a looping clip's duration must exceed its last key time")
            seg_times = np.append(t, self.duration)
            q, a, b = squad_tangents(rot, seg_times, ends="cyclic")
            root_spline = CubicSpline(seg_times, np.vstack([root, root[:1]]), bc_type="periodic")
        elif self.mode == "pingpong":
            if not np.isclose(self.duration, t[-1]):
                raise ValueError("a ping-pong clip's duration must equal its last key time")
            seg_times = t
            q, a, b = squad_tangents(rot, seg_times, ends="reflect")
            root_spline = CubicSpline(seg_times, root, bc_type="clamped")
        else:
            raise ValueError(f"SquadClip plays 'loop' or 'pingpong', got {self.mode!r}")
        for name, value in (("_seg_times", seg_times), ("_q", q), ("_a", a), ("_b", b), ("_root", root_spline),
                            ("velocity", np.asarray(self.velocity, dtype=np.float64))):
            object.__setattr__(self, name, value)

    @property
    def n_keys(self) -> int:
        return int(np.asarray(self.key_times).size)

    def precomputed(self) -> tuple[Array, Array, Array, Array, CubicSpline]:
        """What the clip computed from its keys when it was built, for runtimes that evaluate it elsewhere:
        segment times ``(S + 1,)`` s, SQUAD keys ``q (S + 1, J, 4)`` (sign-continuous) and control points
        ``a, b (S, J, 4)`` (see :func:`~anim_core.math.quat.squad_tangents`), and the root spline (before travel)."""
        return self._seg_times, self._q, self._a, self._b, self._root

    def tangents(self) -> tuple[Array, Array, Array]:
        """The SQUAD control points from the keys (computed once at build time; see :meth:`sample`)."""
        return squad_tangents(self.key_rotations, self._seg_times, ends="cyclic" if self.mode == "loop" else "reflect")

    def sample(self, t: ArrayLike, controls: tuple[Array, Array, Array] | None = None) -> Pose:
        """Poses at running times ``t (...)`` seconds -> rotations ``(..., J, 4)``, root ``(..., 3)``.

        ``controls``: SQUAD control points to use instead of the precomputed ones (the benchmark's naive variant
        passes freshly computed :meth:`tangents`).
        """
        t = np.asarray(t, dtype=np.float64)
        q, a, b = controls if controls is not None else (self._q, self._a, self._b)
        clip_t, cycles = playback_time(t, self.duration, self.mode)
        seg = np.clip(np.searchsorted(self._seg_times, clip_t, side="right") - 1, 0, len(self._seg_times) - 2)
        h = (clip_t - self._seg_times[seg]) / (self._seg_times[seg + 1] - self._seg_times[seg])
        rot = squad_eval(q[seg], q[seg + 1], a[seg], b[seg], h[..., None])
        root = self._root(clip_t)
        if self.mode == "loop" and not self.in_place:
            root = root + self.velocity * (clip_t + cycles * self.duration)[..., None]
        return Pose(rot, root)


@dataclass(frozen=True, eq=False)
class SpringClip:
    """Crouch: an underdamped spring drives an unclamped slerp along the keys, played ping-pong.

    ``key_params``: ``(K,)`` positions of the keys on the path, 0 for the first (standing) and 1 for the last
    (crouched) key.  At clip time ``t`` the path parameter is ``u = 1 - spring(time_scale * t)``; it passes 1 and
    overshoots, so the last segment is extrapolated (the pose goes beyond the crouch key and settles back).

    With ``land_on_last_key`` (default) ``u`` is divided by its value at ``duration``, so the ping-pong turns
    exactly on the crouch key instead of wherever the spring has got to (with the thesis constants and a 1.3 s
    half the factor is 1.002; the overshoot is unchanged).  In full, with ``c`` the clip time of
    :func:`~anim_core.math.clip.playback_time`::

        u(t) = (1 - spring(time_scale * c)) / (1 - spring(time_scale * duration) if land_on_last_key else 1)

    and the pose is the unclamped slerp (and linear root) between keys ``k`` and ``k + 1`` at
    ``(u - key_params[k]) / (key_params[k + 1] - key_params[k])``, ``k`` the last key with ``key_params[k] <= u``
    (at most ``K - 2``).  The crouch timed by the mocap (:func:`build_crouch` with ``time_scale=None``) has
    ``land_on_last_key=False``, a fitted ``time_scale`` and ``key_params`` that are not evenly spaced.
    """

    skeleton: Skeleton
    key_params: Array
    key_rotations: Array
    key_root: Array
    duration: float
    zeta: float = THESIS_ZETA
    omega: float = THESIS_OMEGA
    time_scale: float = THESIS_TIME_SCALE
    mode: PlaybackMode = "pingpong"
    land_on_last_key: bool = True
    name: str = ""

    def __post_init__(self) -> None:
        p = np.asarray(self.key_params, dtype=np.float64)
        if p.ndim != 1 or p.size < 2 or p[0] != 0.0 or p[-1] != 1.0 or np.any(np.diff(p) <= 0):
            raise ValueError("key parameters must increase strictly from 0 to 1")
        rot = make_continuous(np.asarray(self.key_rotations, dtype=np.float64), axis=0)
        if rot.shape != (p.size, self.skeleton.n_joints, 4) or np.shape(self.key_root) != (p.size, 3):
            raise ValueError(f"key arrays do not match {p.size} keys and {self.skeleton.n_joints} joints")
        spring(0.0, self.zeta, self.omega)  # validates the parameters once, at build time
        object.__setattr__(self, "key_params", p)
        object.__setattr__(self, "key_rotations", rot)
        object.__setattr__(self, "key_root", np.asarray(self.key_root, dtype=np.float64))

    @property
    def n_keys(self) -> int:
        return int(self.key_params.size)

    @property
    def in_place(self) -> bool:
        """A crouch never travels (it plays ping-pong on the spot)."""
        return False

    @property
    def velocity(self) -> Array:
        """``(3,)`` horizontal travel per second: none."""
        return np.zeros(3)

    def path_parameter(self, t: ArrayLike) -> Array:
        """``u (...)`` along the key path at running times ``t (...)`` seconds."""
        clip_t, _ = playback_time(t, self.duration, self.mode)
        u = 1.0 - spring(self.time_scale * clip_t, self.zeta, self.omega)
        if self.land_on_last_key:
            u = u / (1.0 - spring(self.time_scale * self.duration, self.zeta, self.omega))
        return u

    @property
    def key_times(self) -> Array:
        """``(K,)`` seconds at which the path first reaches each key (0 for the first)."""
        t = np.linspace(0.0, self.duration, 4097)
        u = self.path_parameter(t)
        times = [0.0]
        for p in self.key_params[1:]:
            k = int(np.argmax(u >= p - 1e-12))  # u rises monotonically until it first reaches 1
            if k == 0:
                raise ValueError("the spring never reaches the key within the clip's duration")
            times.append(float(brentq(lambda x, p=p: self.path_parameter(x) - p, t[k - 1], t[k])))
        return np.array(times)

    def sample(self, t: ArrayLike) -> Pose:
        u = self.path_parameter(t)
        p = self.key_params
        seg = np.clip(np.searchsorted(p, u, side="right") - 1, 0, p.size - 2)
        local = (u - p[seg]) / (p[seg + 1] - p[seg])  # not clamped: > 1 past the last key
        rot = slerp_unclamped(self.key_rotations[seg], self.key_rotations[seg + 1], local[..., None],
                              shortest=False)
        f = local[..., None]
        root = self.key_root[seg] + (self.key_root[seg + 1] - self.key_root[seg]) * f
        return Pose(rot, root)


HybridClip = SquadClip | SpringClip


def build_gait(source: KeyframeClip, key_times: Sequence[float], period: float, increment: int = 0,
               mirror: Mirror | None = None, in_place: bool = False, name: str = "") -> SquadClip:
    """Hybrid walk/run from keys of the left half of one gait cycle of ``source``.

    ``key_times``: source times (s) of the base keys (thesis: left foot forward at full extension, then the left
    foot passing), all within ``[key_times[0], key_times[0] + period / 2)``; ``period``: gait cycle length (s).
    The keys (``2 * 2**increment`` of them) and their mirror images half a cycle later form the cyclic spline.
    The root moves with the cycle's mean horizontal velocity plus a periodic spline of the keys' offsets from
    that line; the mirror plane passes through the mean of the cycle.  A cycle that walks off the (vertical) mirror
    plane by more than a fifth of its speed is mirrored in its own heading frame: turned about the vertical until
    it walks in the plane, mirrored, and turned back (the hybrid walks the cycle's mean direction).  A turning
    take is straightened before (:func:`anim_core.clips.build.straighten_heading`): one loop has one heading.
    """
    t0 = float(key_times[0])
    if not (t0 <= key_times[-1] < t0 + period / 2):
        raise ValueError(f"gait keys {list(key_times)} s must lie within one half cycle "
                         f"[{t0:.3f}, {t0 + period / 2:.3f}) s")
    if t0 < 0 or t0 + period > source.duration + 1e-9:
        raise ValueError(f"source clip {source.name!r} ({source.duration:.3f} s) does not hold a whole cycle "
                         f"of {period:.3f} s from {t0:.3f} s")
    mirror = mirror or Mirror(source.skeleton)
    times = _snap(source, increment_key_times(key_times, increment, end=t0 + period / 2))
    keys = _keys(source, times)

    cycle_t = np.linspace(t0, t0 + period, 64)
    cycle_root = source.sample(cycle_t).root_translation
    velocity = horizontal(cycle_root[-1] - cycle_root[0], source.up_axis) / period
    speed = np.linalg.norm(velocity)
    # Mirrored in the walk's own heading frame: a cycle walking off the mirror plane is turned into it about the
    # vertical, mirrored there and turned back (a walk mirrored across a plane it crosses would walk off sideways).
    # Within the old tolerance (a fifth of the speed across the plane) nothing is turned, so those builds are as
    # they were.
    yaw = None
    if speed > 1e-9 and abs(velocity @ mirror.normal) > 0.2 * speed:
        up = np.zeros(3)
        up[source.up_axis] = 1.0
        if abs(mirror.normal @ up) > 1e-9:
            raise ValueError(f"the walking direction {np.round(velocity / speed, 3).tolist()} is not in the mirror "
                             f"plane (normal {mirror.normal.tolist()}), and the plane is not vertical: a gait is "
                             f"mirrored about a vertical plane")
        along_plane = np.cross(mirror.normal, up)
        along_plane *= np.sign(along_plane @ velocity) or 1.0
        yaw = quat_from_axis_angle(up, np.arctan2(np.cross(velocity, along_plane) @ up, velocity @ along_plane))
        keys, cycle_root, velocity = (_yawed(source.skeleton, keys, yaw), _yawed_root(source.skeleton, cycle_root, yaw),
                                      rotate(yaw, velocity))
    # Offsets from the straight travel line; mirrored through the cycle's mean lateral position.
    offsets = keys.root_translation - velocity * (times - t0)[:, None]
    along = (cycle_root - velocity * (cycle_t - t0)[:, None] + source.skeleton.offsets[0]) @ mirror.normal
    mirrored = mirror.with_offset(float(np.mean(along)))(Pose(keys.rotations, offsets))
    both = Pose(np.concatenate([keys.rotations, mirrored.rotations]),
                np.concatenate([offsets, mirrored.root_translation]))
    if yaw is not None:  # back to the heading the cycle walks in
        both, velocity = _yawed(source.skeleton, both, quat_conj(yaw)), rotate(quat_conj(yaw), velocity)
    return SquadClip(
        source.skeleton,
        key_times=np.concatenate([times - t0, times - t0 + period / 2]),
        key_rotations=both.rotations, key_root=both.root_translation,
        # turned into the plane and back, the second half is no longer the mirror map of the first alone
        duration=period, mode="loop", velocity=velocity, in_place=in_place, name=name,
        mirror=mirror if yaw is None else None,
    )


def _yawed_root(skeleton: Skeleton, root_translation: Array, q: Array) -> Array:
    """Root translations ``(..., 3)`` of poses turned by ``q`` about the vertical through the world origin."""
    return rotate(q, root_translation + skeleton.offsets[0]) - skeleton.offsets[0]


def _yawed(skeleton: Skeleton, pose: Pose, q: Array) -> Pose:
    """Poses ``(..., J, 4)``, ``(..., 3)`` turned by ``q`` about the vertical through the world origin."""
    rot = np.array(pose.rotations)
    rot[..., 0, :] = quat_mul(q, rot[..., 0, :])
    return Pose(rot, _yawed_root(skeleton, np.asarray(pose.root_translation, dtype=np.float64), q))


def build_idle(source: KeyframeClip, key_times: Sequence[float], increment: int = 0, name: str = "") -> SquadClip:
    """Hybrid idle: SQUAD through the sway keys (thesis: its two extremes), played ping-pong over their span."""
    times = _snap(source, increment_key_times(key_times, increment))
    keys = _keys(source, times)
    return SquadClip(source.skeleton, times - times[0], keys.rotations, keys.root_translation,
                     duration=float(times[-1] - times[0]), mode="pingpong", name=name)


def build_other(source: KeyframeClip, key_times: Sequence[float], increment: int = 0, in_place: bool = False,
                name: str = "") -> SquadClip:
    """Hybrid of any motion (kind ``other``): SQUAD through keys taken from ``source``, no mirroring, played as the
    source plays.

    Ping-pong: :func:`build_idle` (the clip spans the first to the last key).  Loop: a cyclic spline over the
    source's whole ``duration`` (its last key repeats the first, as a looping :class:`KeyframeClip`'s does); the key
    times (s) lie in ``[0, duration)`` and start at 0, increments split the interval to ``duration`` too; the root
    moves with the source's mean horizontal velocity plus a periodic spline of the keys' offsets from that line
    (none of it with ``in_place``).  Picked keys may be neighbouring frames: an increment adds a key only where
    the source has a frame between two keys (one that snaps onto a loop's end is key 0 and left out).
    """
    loop = source.mode == "loop"
    times = np.unique([source.nearest_key_time(t) for t in
                       increment_key_times(key_times, increment, end=source.duration if loop else None)])
    if not loop:
        return build_idle(source, times, 0, name)
    # A key inserted between the last key and the loop's end may snap onto the end: that frame is key 0 again.
    times = times[times < source.duration - 1e-9] if times[0] == 0.0 else times
    if times[0] != 0.0 or times[-1] >= source.duration:
        raise ValueError(f"the keys of a loop lie in [0, {source.duration:.3f}) s and start at 0, got "
                         f"{np.round(times, 4).tolist()} s")
    keys = _keys(source, times)
    offsets = keys.root_translation - source.velocity * times[:, None]
    return SquadClip(source.skeleton, times, keys.rotations, offsets, duration=source.duration, mode="loop",
                     velocity=source.velocity, in_place=in_place, name=name)


def spring_peak_time(zeta: float = THESIS_ZETA, omega: float = THESIS_OMEGA,
                     time_scale: float = THESIS_TIME_SCALE) -> float:
    """Seconds to the spring's first overshoot peak, ``pi / (alpha s)`` with ``alpha = omega sqrt(1 - zeta^2)``
    and time scale ``s``: there ``x' = 0`` (for ``v0 = 0``), so a ping-pong turn there has no bounce."""
    spring(0.0, zeta, omega)
    return float(np.pi / (omega * np.sqrt(1.0 - zeta * zeta) * time_scale))


def build_crouch(source: KeyframeClip, key_times: Sequence[float], increment: int = 0,
                 duration: float | None = None, zeta: float = THESIS_ZETA, omega: float = THESIS_OMEGA,
                 time_scale: float | None = THESIS_TIME_SCALE, name: str = "") -> SpringClip:
    """Hybrid crouch from a standing and a crouched key (plus keys between per increment).

    ``duration``: seconds of the downward half of the ping-pong.  Two timings:

    * ``time_scale`` given (the thesis's 0.7): the keys are spaced on the path by their source times, the
      half lasts by default until the spring has settled within 0.1 % (1.41 s with the thesis constants) and
      the path is scaled to land exactly on the crouch key there;
    * ``time_scale=None`` (*timed by the mocap*): ``key_times`` are the source's standing and deepest times and
      ``duration`` their distance.  The time scale is fitted so that the spring's first overshoot peak falls on
      ``duration`` — the turn, where the source is deepest — so both are deepest at the same moment and the turn
      has zero velocity; the path is not rescaled, so the pose overshoots the crouch key by the spring's own
      amount there.  The spring passes the crouch key earlier (at 0.75 of the half, the spring's first zero);
      keys added by increments are source poses at times midway between the keys' *passing* times, and each sits
      at the path parameter the spring has at that time, so the hybrid passes it exactly when the source does.
    """
    if time_scale is None:
        if duration is None:
            raise ValueError("a crouch timed by the mocap needs the duration of its downward half")
        t0, t1 = float(key_times[0]), float(key_times[-1])
        if not np.isclose(t1 - t0, duration):
            raise ValueError(f"the crouch keys {list(key_times)} s must span the half's {duration} s")
        time_scale = spring_peak_time(zeta, omega, 1.0) / duration
        alpha = omega * np.sqrt(1.0 - zeta * zeta)
        reach = float((np.pi - np.arctan2(alpha, zeta * omega)) / (alpha * time_scale))  # first u = 1 (x = 0)
        between = increment_key_times([0.0, reach], increment)[1:-1]
        times = np.concatenate([[t0], _snap(source, t0 + between), [t1]]) if between.size else np.array([t0, t1])
        if np.any(np.diff(times) <= 0) or (between.size and times[-2] - t0 >= reach):
            raise ValueError("the crouch's keys fall on the same source frames; the source has too few frames")
        keys = _keys(source, times)
        params = np.concatenate([[0.0], 1.0 - spring(time_scale * (times[1:-1] - t0), zeta, omega), [1.0]])
        return SpringClip(source.skeleton, params, keys.rotations, keys.root_translation, float(duration),
                          zeta, omega, time_scale, land_on_last_key=False, name=name)
    times = _snap(source, increment_key_times(key_times, increment))
    keys = _keys(source, times)
    params = (times - times[0]) / (times[-1] - times[0])
    if duration is None:
        duration = spring_settle_time(zeta, omega, time_scale)
    return SpringClip(source.skeleton, params, keys.rotations, keys.root_translation, float(duration),
                      zeta, omega, time_scale, name=name)


#: Every clip type: each has ``skeleton``, ``mode``, ``duration``, ``sample(t)``, ``key_times``, ``key_rotations``,
#: ``velocity`` and ``in_place``.
AnimClip = KeyframeClip | SquadClip | SpringClip
