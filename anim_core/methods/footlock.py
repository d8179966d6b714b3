"""The hybrid with locked feet: the ``hybrid_ik`` condition (thesis, future work 7.1: foot sliding).

Conventions as in :mod:`anim_core.methods.footplant` (frames at ``fps``, metres, Y up, quaternions ``(w, x, y, z)``).

Built once (:func:`lock_feet`), per foot and frame of one period:

1. *steps*: the contact phases of the *reference* (keyframe) clip (:func:`anim_core.math.contacts.foot_down`, every
   foot joint within ``clearance`` m of its standing height) in which its foot comes to rest at least once
   (slowest joint at most ``rest_speed``, default the skate threshold): a phase in which the reference's foot never
   slows is its swing passing low over the floor (a *skim*) and is not held (:func:`steps`);
2. with ``contact_source="union"`` (default) each step grows by the run of the hybrid's own contact frames that
   overlaps it (the hybrid's feet land earlier and lift later than the reference's, and those frames are where
   it skates); the hybrid's contact runs away from every step are skims and stay as animated (:func:`joined`).
   With ``"reference"`` the reference's steps alone are held (with step 7 the hybrid's swing is lifted
   out of its early and late contact frames instead: on a walk's hybrid 0, whose feet are down in 31 of 40
   frames, holding the union leaves a few frames to swing each foot a whole stride, a pop);
3. *holds*: each grown by one frame on either side, because the skate measure takes central differences, and
   gaps of at most ``2 * blend_frames`` frames filled (:func:`held_frames`);
4. :func:`anim_core.methods.footplant.foot_targets` turns the hybrid's own feet over each hold into ankle targets: the
   foot on the ground from its slowest frame on, its slowest joint moving at most ``max_speed`` (by default
   0.3 m/s: a margin under the 0.5 m/s skate threshold for what the IK cannot reach at a hold's edges);
5. *standing*: each hold is cut to the frames around its slowest one over which the leg reaches the foothold
   posed as animated: the IK turns the thigh and changes the knee's bend by at most ``max_leg_change_deg``
   (default 10 degrees, as the reference's own foot planting) (:func:`standing`).  A contact phase is a height
   band, and on a run (or a hybrid 0 skimming the floor) it also holds frames in which the foot still swings in
   or already swings out at 1-5 m/s; held there, the foot would stay at its foothold while the animated ankle is
   up to 0.7 m away, and the IK would pull the leg straight towards it (issue 35's Bandai run: bones 82 degrees
   from the reference against the plain hybrid's 25).  Those frames are swing;
6. *swings*: between two holds the ankle's offset from its animated place eases (smoothstep) from one foothold to
   the next over the whole gap (:func:`swing_offsets`), so the foot is never let go in a few frames; every
   frame's target is then brought back towards the animated ankle as far as needed to keep the thigh and the
   knee within ``max_leg_change_deg`` of the hybrid's
   (:func:`anim_core.methods.footplant.leg_limited_targets`): an offset carried from a hold into a leg that is
   nearly straight as it lifts off would otherwise straighten its knee (the walk's hybrid 0: 4 degrees against
   the hybrid's 27).  So, but for step 7, the locked legs are never more than that from the hybrid's;
7. *clearance* (``swing_clearance=True``; swing clearance as game foot IK does it): the ankle target is
   raised so that no joint of the foot is lower above the floor (its height over its standing height) than the
   reference's same joint at that frame: by the largest shortfall of the foot's joints, or 0.  The hybrid's swing
   foot passes low and fast where the reference's is up (inside the contact band at swing speed it skates, above
   all where a hold lets it go or takes it); raised, it skims only where the reference's own foot skims.  The
   lift is a continuous function of the two clips' poses, so it needs no blend of its own (eased from the holds
   over ``blend_frames``, the hybrid 0's foot still skates in the frames it lifts off and lands in); inside a
   hold it is the reference's heel or toe rising before the hybrid's (vertical only: the hold stays in place).
   Off by default: it follows the reference's pose, seam included, so a loop whose reference is not cyclic (a
   seam jump of its own, which the hybrid through its keys does not have) gets the reference's jump at its feet.

Stored: the hybrid's keys plus one ankle target ``(3,)`` and weight per leg and frame of one period, each knee's
hinge and the soft reach.  At playback (:meth:`FootLockedClip.sample`) the hybrid is evaluated, the targets and
weights are interpolated between frames by cubic splines and the analytic two-bone IK of :mod:`anim_core.methods.ik`
(hip-knee-ankle, knee kept in its animated plane and bending about its hinge, so it never flips; soft reach near
full extension, so it does not kink; foot keeping its world orientation) moves each leg; bone lengths are the
skeleton's, so they stay exact.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.interpolate import CubicSpline

from ..math.clip import KeyframeClip, PlaybackMode, Pose, playback_time
from ..math.contacts import (
    CONTACT_CLEARANCE_M,
    SKATE_SPEED_MPS,
    contact_intervals,
    foot_down,
    foot_speed,
    interval_mask,
    standing_heights,
)
from ..math.skeleton import Skeleton
from .footplant import foot_targets, leg_angles, leg_limited_targets
from .hybrid import HybridClip
from .ik import hinge_axis, smoothstep, two_bone_ik

Array = NDArray[np.float64]
ContactSource = Literal["reference", "union"]
SOFT_REACH = 0.005  # the legs' soft IK starts this fraction of their reach short of full extension
#: A hold keeps each thigh and knee bend within this many degrees of the hybrid's own leg (:func:`standing`): the
#: tolerance of the reference's foot planting (``anim_core.clips.reference.PLANT_LEG_TOLERANCE_DEG``, half the gate's
#: pose limit), for the same reason: a foot is held where the leg reaches it posed as in the motion.
HOLD_LEG_TOLERANCE_DEG = 10.0


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
    ping-pong clip's span ``0..duration``); targets are relative to the root without its travel.  ``hinges
    (F, 3)``: each knee's hinge in its local frame (:func:`anim_core.methods.ik.hinge_axis`), so a knee near straight
    never flips; ``soft``: the IK's soft reach (:func:`anim_core.methods.ik.two_bone_ik`), so a leg passing full
    extension does not kink."""

    base: HybridClip
    legs: tuple[tuple[int, int, int], ...]
    fps: float
    targets: Array
    weights: Array
    hinges: Array
    soft: float = 0.0

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

    @property
    def velocity(self) -> Array:
        """``(3,)`` the hybrid's travel per second (zero for a crouch)."""
        return np.asarray(self.base.velocity, dtype=np.float64)

    @property
    def in_place(self) -> bool:
        return bool(self.base.in_place)

    def tracks(self) -> tuple[CubicSpline, CubicSpline]:
        """The splines :meth:`sample` interpolates the targets ``(..., F, 3)`` and weights ``(..., F)`` with over
        clip time (read by :class:`anim_core.runtime.FootLockRuntime`)."""
        return self._tracks()

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
            rot = two_bone_ik(self.skeleton, rot, root, chain, target_t[..., leg, :], weight=weight_t[..., leg],
                              hinge=self.hinges[leg], soft=self.soft)
        return Pose(rot, pose.root_translation)


def steps(down: ArrayLike, speed: ArrayLike, periodic: bool, rest_speed: float = SKATE_SPEED_MPS) -> NDArray[np.bool_]:
    """``(T, F)`` the contact frames ``down (T, F)`` that belong to a step: a contact phase in which the foot's
    slowest joint gets down to ``rest_speed`` m/s (``speed (T, F)``, :func:`anim_core.math.contacts.foot_speed`) at
    least once.  A phase in which the foot never slows so far is a swing passing low over the floor (a skim),
    and holding it would drag the swinging foot back."""
    d = np.asarray(down, dtype=bool)
    v = np.asarray(speed, dtype=np.float64)
    out = np.zeros_like(d)
    n = d.shape[0]
    for f in range(d.shape[1]):  # one column per foot
        for start, stop in contact_intervals(d[:, f], periodic):  # one per contact phase
            frames = np.arange(start, stop) % n
            if v[frames, f].min() <= rest_speed:
                out[frames, f] = True
    return out


def joined(seeds: ArrayLike, down: ArrayLike, periodic: bool) -> NDArray[np.bool_]:
    """``(T, F)`` ``seeds`` (the steps) grown by every run of ``down`` that overlaps one: frames where the foot is
    down next to a step are part of it, runs of ``down`` away from every step are not."""
    s = np.asarray(seeds, dtype=bool)
    both = s | np.asarray(down, dtype=bool)
    out = np.zeros_like(s)
    n = s.shape[0]
    for f in range(s.shape[1]):  # one column per foot
        for start, stop in contact_intervals(both[:, f], periodic):  # one per run
            frames = np.arange(start, stop) % n
            if s[frames, f].any():
                out[frames, f] = True
    return out


def held_frames(down: ArrayLike, periodic: bool, blend_frames: int) -> NDArray[np.bool_]:
    """``(T, F)`` the frames a foot is held in, from its contact frames ``down (T, F)``: each contact phase grown
    by one frame on either side, then gaps of at most ``2 * blend_frames`` frames between two phases filled.

    Why: the skate measure (:func:`anim_core.math.contacts.foot_speed`) takes central differences, so a contact frame
    whose neighbour is a blend frame (the foot moving as animated) gets half the animated speed however well the
    contact frame itself is held; and two phases closer than their blends would overlap, the target switching
    from one phase's hold to the other's in mid-blend (a pop)."""
    d = np.array(down, dtype=bool)
    if periodic:
        d = d | np.roll(d, 1, axis=0) | np.roll(d, -1, axis=0)
    else:
        d[1:] |= np.asarray(down, dtype=bool)[:-1]
        d[:-1] |= np.asarray(down, dtype=bool)[1:]
    n = d.shape[0]
    for f in range(d.shape[1]):  # one column per foot
        if not d[:, f].any():
            continue
        gaps = contact_intervals(~d[:, f], periodic)
        if not periodic:  # a gap at either end lies beside one phase only
            gaps = gaps[(gaps[:, 0] > 0) & (gaps[:, 1] < n)]
        d[:, f] |= interval_mask(gaps[gaps[:, 1] - gaps[:, 0] <= 2 * blend_frames], n)
    return d


def swing_offsets(offsets: ArrayLike, held: ArrayLike, periodic: bool, blend_frames: int) -> tuple[Array, Array]:
    """Each foot's ankle offsets ``(T, F, 3)`` from its animated place, and IK weights ``(T, F)``, between its holds:
    ``offsets`` are given in the held frames ``held (T, F)`` (where the hold puts the ankle, minus where the
    animation does).  In a gap between two holds (a swing) the offset eases (smoothstep) from the first hold's
    last offset to the next hold's first over the whole gap, at weight 1: the swing makes up the difference
    between the two footholds, so a foot held far from its animated place is not let go in a few frames (a pop).
    Before the first and after the last hold of a non-periodic clip, the weight eases out over ``blend_frames``."""
    off = np.array(offsets, dtype=np.float64)
    h = np.asarray(held, dtype=bool)
    n = h.shape[0]
    weights = h.astype(np.float64)
    for f in range(h.shape[1]):  # one column per foot
        if not h[:, f].any():
            continue
        for start, stop in contact_intervals(~h[:, f], periodic):  # one per gap between holds
            frames = np.arange(start, stop) % n
            g = stop - start
            if periodic or (start > 0 and stop < n):
                ease = smoothstep(np.arange(1, g + 1) / (g + 1))[:, None]
                first, last = off[(start - 1) % n, f], off[stop % n, f]
                off[frames, f] = first + ease * (last - first)
                weights[frames, f] = 1.0
            else:  # before the first hold or after the last: fade out from the hold beside it
                edge = stop % n if start == 0 else start - 1
                distance = np.abs(frames - edge)
                weights[frames, f] = smoothstep(1.0 - distance / (blend_frames + 1))
                off[frames, f] = off[edge, f]
    return off, weights


def standing(skeleton: Skeleton, local_rotations: ArrayLike, root_translation: ArrayLike,
             legs: Sequence[tuple[int, int, int]], held: ArrayLike, targets: ArrayLike, periodic: bool,
             hinges: ArrayLike, soft: float = 0.0, max_leg_change_deg: float = HOLD_LEG_TOLERANCE_DEG
             ) -> NDArray[np.bool_]:
    """``(T, F)`` the frames of ``held (T, F)`` in which each foot stands on its foothold: of each run of held
    frames, the frames around its *resting frame* (the one whose target ``targets (T, F, 3)`` is nearest the
    animated ankle: where the foot comes to rest, the hold leaves it as animated) over which the leg of poses
    ``local_rotations (T, J, 4)`` / ``root_translation (T, 3)``, solved onto the target as
    :meth:`FootLockedClip.sample` solves it (``hinges (F, 3)``, ``soft``), keeps its thigh within
    ``max_leg_change_deg`` of the animated thigh's direction and its knee within that of the animated bend.

    Why: a contact phase is a foot within the clearance of its standing height, and that band also holds frames
    in which the foot still swings in or already swings out (a run's landing foot at 2-5 m/s, 4 frames of the
    Bandai run's one-cycle take; the walk's hybrid 0 lifting its foot at 1-2 m/s over the 6 frames the union
    grows a step by).  Held there, the foot stays where it comes to rest, so its target trails the animated ankle
    by the rest of the swing (0.35 m on that walk, 0.72 m on that run): out of the leg's reach, the IK pulls the
    knee straight (0 degrees against the reference's 75) and swings the thigh by 50.  Those frames belong to the
    swing, over which :func:`swing_offsets` eases the foot from one foothold to the next."""
    rot = np.asarray(local_rotations, dtype=np.float64)
    root = np.asarray(root_translation, dtype=np.float64)
    h = np.asarray(held, dtype=bool)
    goal = np.asarray(targets, dtype=np.float64)
    tolerance = np.radians(max_leg_change_deg)
    n = h.shape[0]
    ankles = skeleton.forward_kinematics(rot, root)[1][:, [int(c[2]) for c in legs]]
    out = np.zeros_like(h)
    for f, chain in enumerate(legs):  # one solve per leg over all frames
        thigh0, bend0 = leg_angles(skeleton, rot, root, chain)
        solved = two_bone_ik(skeleton, rot, root, chain, goal[:, f], hinge=hinges[f], soft=soft)
        thigh, bend = leg_angles(skeleton, solved, root, chain)
        turn = np.arccos(np.clip(np.sum(thigh * thigh0, axis=-1), -1.0, 1.0))
        fits = (turn <= tolerance) & (np.abs(bend - bend0) <= tolerance)
        off = np.linalg.norm(goal[:, f] - ankles[:, f], axis=-1)
        for start, stop in contact_intervals(h[:, f], periodic):  # one per hold
            frames = np.arange(start, stop) % n
            rest = int(np.argmin(off[frames]))
            misses = np.flatnonzero(~fits[frames])
            first = misses[misses < rest].max(initial=-1) + 1
            last = misses[misses > rest].min(initial=len(frames)) - 1
            out[frames[first:last + 1], f] = True  # the resting frame is kept whatever its fit
    return out


def lock_feet(base: HybridClip, reference: KeyframeClip, legs: Sequence[tuple[int, int, int]],
              feet: Sequence[Sequence[int]], fps: float, blend_frames: int = 3,
              clearance: float = CONTACT_CLEARANCE_M, max_speed: float = 0.3, rest_speed: float = SKATE_SPEED_MPS,
              up_axis: int = 1, contact_source: ContactSource = "union", swing_clearance: bool = False,
              max_leg_change_deg: float = HOLD_LEG_TOLERANCE_DEG) -> FootLockedClip:
    """The ``hybrid_ik`` clip of ``base`` with contacts detected on ``reference`` (same duration and playback).

    ``legs``: (hip, knee, ankle) joint indices per foot; ``feet``: per foot the joints that touch the ground (ankle,
    toe); ``fps``: frames per second of the period the targets are computed on; ``blend_frames``: holds closer
    than ``2 * blend_frames`` frames are joined, and a non-periodic clip's first and last holds fade in and out
    over that many frames; ``clearance`` m: the contact threshold of :func:`anim_core.math.contacts.foot_down`;
    ``max_speed`` m/s: the held foot's slowest joint moves at most this fast (it may roll, not slide);
    ``rest_speed`` m/s: a reference contact phase whose foot never gets this slow is a skim, not a step;
    ``contact_source``: ``"reference"`` holds the reference's steps, ``"union"`` grows each by the hybrid's own
    contact frames next to it; ``swing_clearance``: each foot raised to at least the reference's foot height;
    ``max_leg_change_deg``: a hold ends where holding the foot would turn the thigh or change the knee's bend by
    more than this (:func:`standing`), and no swing target asks more of the leg (steps 1-7 of the module
    docstring).
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
    if contact_source not in ("reference", "union"):
        raise ValueError(f"contact_source must be 'reference' or 'union', got {contact_source!r}")
    velocity = np.asarray(getattr(base, "velocity", np.zeros(3)), dtype=np.float64) if loop else np.zeros(3)
    ref = reference.sample(times)
    ref_root = ref.root_translation - (0.0 if reference.in_place or not loop else velocity * times[:, None])
    ref_feet = sk.forward_kinematics(ref.rotations, ref_root)[1][:, feet_idx]
    down = steps(foot_down(ref_feet, up_axis, clearance),
                 foot_speed(ref_feet, fps, up_axis, periodic=loop, ground_velocity=velocity), loop, rest_speed)
    pose = base.sample(times)
    root = pose.root_translation - _travel(base, times)
    positions = sk.forward_kinematics(pose.rotations, root)[1]
    if contact_source == "union":
        down = joined(down, foot_down(positions[:, feet_idx], up_axis, clearance), loop)
    # Every step is held, however fast the hybrid's foot slides through it (rest_speed=inf): that sliding is
    # exactly what the condition corrects.
    held = held_frames(down, loop, blend_frames)
    chains = [tuple(int(j) for j in c) for c in legs]
    targets, _ = foot_targets(sk, pose.rotations, root, chains, held, fps, feet_idx.tolist(), periodic=loop,
                              ground_velocity=velocity, up_axis=up_axis, blend_frames=0, max_speed=max_speed,
                              rest_speed=np.inf)
    # The knees' hinges from the reference: mocap, whose knees bend well in every cycle.
    hinges = np.array([hinge_axis(sk, ref.rotations, ref.root_translation, c) for c in chains])
    soft = SOFT_REACH * min(float(np.linalg.norm(sk.offsets[m]) + np.linalg.norm(sk.offsets[e])) for _, m, e in chains)
    # Step 5: a hold's offsets are measured from its resting frame, which the trim keeps, so they stand as they are.
    held = standing(sk, pose.rotations, root, chains, held, targets, loop, hinges, soft, max_leg_change_deg)
    ankles = positions[:, [c[2] for c in chains]]
    offsets, weights = swing_offsets(targets - ankles, held, loop, blend_frames)
    for leg, chain in enumerate(chains):  # step 6, one leg at a time
        limited = leg_limited_targets(sk, pose.rotations, root, chain, ankles[:, leg] + offsets[:, leg],
                                      weights[:, leg], np.radians(max_leg_change_deg), None, hinges[leg], soft,
                                      smooth_frames=blend_frames, periodic=loop)
        offsets[:, leg] = limited - ankles[:, leg]
    if swing_clearance:
        # Step 7: each foot's joints' heights above their standing heights, the hybrid's where the offsets put them
        # (the foot keeps its world orientation, so an offset moves all of its joints alike).
        hyb_feet = positions[:, feet_idx]
        hyb_heights = hyb_feet[..., up_axis] + offsets[:, :, None, up_axis] - standing_heights(hyb_feet, up_axis)
        ref_heights = ref_feet[..., up_axis] - standing_heights(ref_feet, up_axis)
        offsets[..., up_axis] += np.maximum(np.max(ref_heights - hyb_heights, axis=2), 0.0)
    return FootLockedClip(base, tuple(chains), float(fps), ankles + offsets, weights, hinges, soft)
