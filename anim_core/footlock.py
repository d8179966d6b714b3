"""The hybrid with locked feet: the ``hybrid_ik`` condition (thesis, future work 7.1: foot sliding).

Conventions as in :mod:`anim_core.footplant` (frames at ``fps``, metres, Y up, quaternions ``(w, x, y, z)``).

Built once (:func:`lock_feet`): the contacts are detected on the *reference* (keyframe) clip with
:func:`anim_core.contacts.foot_down` (every foot joint within ``clearance`` m of its standing height) — by default
joined with the frames where the hybrid's own feet are down, see ``contact_source`` — and
:func:`anim_core.footplant.foot_targets` turns the hybrid's own feet over those phases into ankle targets: the foot
held on the ground from its slowest frame on (its slowest joint moves at most ``max_speed``), blended in and out
over ``blend_frames`` frames (smoothstep weights, so no pop at a contact boundary).  Stored: the hybrid's keys plus
one ankle target ``(3,)`` and weight per leg and frame of one period.  At playback (:meth:`FootLockedClip.sample`)
the hybrid is evaluated, the targets and weights are interpolated between frames by cubic splines and the analytic
two-bone IK of :mod:`anim_core.ik` (hip-knee-ankle, knee kept in its animated plane, foot keeping its world
orientation) moves each leg; bone lengths are the skeleton's, so they stay exact.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.interpolate import CubicSpline

from .clip import KeyframeClip, PlaybackMode, Pose, playback_time
from .contacts import CONTACT_CLEARANCE_M, foot_down
from .footplant import foot_targets
from .hybrid import HybridClip
from .ik import two_bone_ik
from .skeleton import Skeleton

Array = NDArray[np.float64]
ContactSource = Literal["reference", "union"]


def _travel(clip: HybridClip, t: Array) -> Array:
    """``(..., 3)`` the root's travel that :meth:`sample` adds at running times ``t`` (0 for in-place and ping-pong)."""
    velocity = np.asarray(getattr(clip, "velocity", np.zeros(3)), dtype=np.float64)
    if clip.mode != "loop" or getattr(clip, "in_place", True):
        return np.zeros((*t.shape, 3))
    clip_t, cycles = playback_time(t, clip.duration, clip.mode)
    return velocity * (clip_t + cycles * clip.duration)[..., None]


@dataclass(frozen=True, eq=False)
class FootLockedClip:
    """``base`` (a hybrid clip) with the legs ``legs`` ((hip, knee, ankle) per foot) solved each frame towards
    ``targets (T, F, 3)`` with ``weights (T, F)``, one period of ``T`` frames at ``fps`` (a loop's frames wrap, a
    ping-pong clip's span ``0..duration``); targets are relative to the root without its travel."""

    base: HybridClip
    legs: tuple[tuple[int, int, int], ...]
    fps: float
    targets: Array
    weights: Array

    @property
    def skeleton(self) -> Skeleton:
        return self.base.skeleton

    @property
    def mode(self) -> PlaybackMode:
        return self.base.mode

    @property
    def duration(self) -> float:
        return self.base.duration

    @property
    def name(self) -> str:
        return self.base.name

    @property
    def key_times(self) -> Array:
        return np.asarray(self.base.key_times)

    @property
    def key_rotations(self) -> Array:
        return np.asarray(self.base.key_rotations)

    def _tracks(self) -> tuple[CubicSpline, CubicSpline]:
        """Cubic splines through the targets and weights over clip time (periodic for a loop), so the IK adds no
        kink between frames; built on first use."""
        cached = self.__dict__.get("_splines")
        if cached is None:
            n = self.weights.shape[0]
            if self.mode == "loop":
                times = np.arange(n + 1) / self.fps
                cached = (CubicSpline(times, np.concatenate([self.targets, self.targets[:1]]), bc_type="periodic"),
                          CubicSpline(times, np.concatenate([self.weights, self.weights[:1]]), bc_type="periodic"))
            else:
                times = np.arange(n) / self.fps
                cached = (CubicSpline(times, self.targets, bc_type="clamped"),
                          CubicSpline(times, self.weights, bc_type="clamped"))
            object.__setattr__(self, "_splines", cached)
        return cached

    def sample(self, t: ArrayLike) -> Pose:
        """Poses at running times ``t (...)`` s: the hybrid's, with both legs solved by two-bone IK towards the
        targets and weights interpolated by cubic splines (C2) between frames."""
        t = np.asarray(t, dtype=np.float64)
        pose = self.base.sample(t)
        clip_t, _ = playback_time(t, self.duration, self.mode)
        targets, weights = self._tracks()
        target_t, weight_t = targets(clip_t), weights(clip_t)
        root = pose.root_translation - _travel(self.base, t)
        rot = pose.rotations
        for leg, chain in enumerate(self.legs):  # two legs
            rot = two_bone_ik(self.skeleton, rot, root, chain, target_t[..., leg, :], weight=weight_t[..., leg])
        return Pose(rot, pose.root_translation)


def lock_feet(base: HybridClip, reference: KeyframeClip, legs: Sequence[tuple[int, int, int]],
              feet: Sequence[Sequence[int]], fps: float, blend_frames: int = 3,
              clearance: float = CONTACT_CLEARANCE_M, max_speed: float = 0.4, rest_speed: float = np.inf,
              up_axis: int = 1, contact_source: ContactSource = "union") -> FootLockedClip:
    """The ``hybrid_ik`` clip of ``base`` with contacts detected on ``reference`` (same duration and playback).

    ``legs``: (hip, knee, ankle) joint indices per foot; ``feet``: per foot the joints that touch the ground (ankle,
    toe); ``fps``: frames per second of the period the targets are computed on; ``blend_frames``: frames of the
    blend in and out at each contact boundary; ``clearance`` m: the contact threshold of
    :func:`anim_core.contacts.foot_down`; ``max_speed``, ``rest_speed`` m/s as in
    :func:`anim_core.footplant.plant_feet` (by default every contact phase is held: a hybrid's foot that slides
    through a whole phase is exactly what the condition corrects); ``contact_source``: ``"reference"`` holds the
    feet where the reference's are down, ``"union"`` also where the hybrid's own feet are down (the hybrid's
    feet stay low for longer than the reference's, and those frames are where it skates).
    """
    if not np.isclose(base.duration, reference.duration) or base.mode != reference.mode:
        raise ValueError(f"the hybrid ({base.duration:.4f} s, {base.mode}) and its reference "
                         f"({reference.duration:.4f} s, {reference.mode}) differ in duration or playback")
    if blend_frames < 0 or clearance <= 0:
        raise ValueError(f"blend_frames must be >= 0 and clearance > 0, got {blend_frames}, {clearance}")
    loop = base.mode == "loop"
    n = round(base.duration * fps) + (0 if loop else 1)
    times = np.arange(n) / fps
    sk = base.skeleton
    feet_idx = np.array([[int(j) for j in foot] for foot in feet])
    ref = reference.sample(times)
    down = foot_down(sk.forward_kinematics(ref.rotations, ref.root_translation)[1][:, feet_idx], up_axis,
                     clearance)
    pose = base.sample(times)
    if contact_source == "union":
        down = down | foot_down(sk.forward_kinematics(*pose)[1][:, feet_idx], up_axis, clearance)
    elif contact_source != "reference":
        raise ValueError(f"contact_source must be 'reference' or 'union', got {contact_source!r}")
    velocity = np.asarray(getattr(base, "velocity", np.zeros(3)), dtype=np.float64) if loop else np.zeros(3)
    root = pose.root_translation - _travel(base, times)
    targets, weights = foot_targets(sk, pose.rotations, root, [tuple(c) for c in legs], down, fps,
                                    feet_idx.tolist(), periodic=loop, ground_velocity=velocity, up_axis=up_axis,
                                    blend_frames=blend_frames, max_speed=max_speed, rest_speed=rest_speed)
    return FootLockedClip(base, tuple(tuple(int(j) for j in c) for c in legs), float(fps), targets, weights)
