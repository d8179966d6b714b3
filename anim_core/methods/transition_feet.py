"""Feet held through a blended transition (issue 39): a composed sequence's stance feet pinned with two-bone IK.

Why: a crossfade (or an inertialization) moves each joint from the outgoing take's local rotation to the incoming
one's, so a foot's position *relative to the root* moves from the outgoing take's ``p_A(u)`` to the incoming take's
``p_B(u)``.  With the root's velocity blended as the weights are, a foot planted in both takes moves in the world at
``w'(u) (p_B(u) - p_A(u))`` (plus its takes' own slide): the weight's rate times the distance between where the two
takes have that foot.  Measured on idle -> walk -> run (a 250 ms smoothstep crossfade, each take entered in the
outgoing take's leg phase): the two takes' ankles 0.31-0.39 m apart against the hips at the switches, so the
first term reaches 1.5 / 0.25 s x 0.39 m = 2.3 m/s (the smoothstep's steepest rate) while each take's own planted
foot moves at 0.02 m/s.  No entry time or time warp of the two cycles closes that distance (a run's stride is
longer than a walk's, an idle's feet stand under the hips), so the foot is held instead.

How (:func:`lock_transition_feet`): on the composed loop (frames at ``fps``, the root with the loop's travel), the
contact phases (:func:`anim_core.math.contacts.foot_down`, standing heights of the whole loop) in which the foot
slows to ``rest_speed`` (:func:`anim_core.methods.footlock.steps`) and that overlap a transition (its switch to its
end) are held from the switch on, or from the landing if the foot lands during the transition, to one frame after
the phase (:func:`held_phases`).  The foot is on the ground with its slowest joint (heel or toe) moving at most
``max_speed`` m/s (:func:`anim_core.methods.footplant.foot_targets`): a foot down at the switch stays where the
outgoing take put it, one that lands rests at its slowest frame, eased in (smoothstep) over the swing since the
switch; after the hold its offset eases out over the swing to the foot's next step, at most ``release_s``
(:func:`eased_offsets`).  The leg is solved by the analytic two-bone IK of :mod:`anim_core.methods.ik` (knee
about its hinge, soft reach, the foot keeping its world orientation).  Every other frame, every frame before a
switch, and every joint but the legs' hip, knee and ankle keep the composed rotations bit for bit, and the root is
the blend's.  The loop is held as one period in place (the ground moving under it at the loop's mean velocity), so
a phase may run across the loop's seam.  Offline, as the transition itself is (the clip stores the result); a
runtime would run the same IK after its blend job.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..math import contacts
from ..math.clip import KeyframeClip
from ..math.skeleton import Skeleton
from .footlock import SOFT_REACH, steps
from .footplant import foot_targets, leg_hinge
from .ik import smoothstep, two_bone_ik

Array = NDArray[np.float64]


@dataclass(frozen=True)
class FeetLock:
    """What :func:`lock_transition_feet` holds: per foot the leg chain ``(hip, knee, ankle)`` and the joints that
    touch the ground (e.g. ankle and toe) as joint indices; ``release_s``: the longest a held foot's offset takes
    to ease in or out over a swing beside its hold (:func:`eased_offsets`); ``rest_speed`` m/s: a contact phase
    is held only if its foot's slowest joint gets this slow in it (a swing skimming the floor at 2-3 m/s is not a
    step; a foot landing during an inertialization's decay may not get under the 0.5 m/s skate threshold before
    the blend moves it again: 0.67 m/s at the least on a walk into a run, which 0.5 left to skate);
    ``max_speed`` m/s the fastest a held foot's slowest joint moves (under the 0.5 m/s skate threshold of
    :mod:`anim_core.math.contacts`)."""

    legs: tuple[tuple[int, int, int], ...]
    feet: tuple[tuple[int, ...], ...]
    release_s: float = 0.3
    max_speed: float = 0.4
    rest_speed: float = 1.0


def held_phases(down: ArrayLike, windows: Sequence[tuple[int, int]]) -> NDArray[np.bool_]:
    """``(T, F)``: of each contact phase of ``down (T, F)`` (one period of a loop; phases may wrap) that overlaps a
    window ``[start, stop)`` (frames, ``0 <= start < T``; ``stop`` may pass ``T``), its frames from the window's
    start on and the frame after it: what a transition moves is held, what comes before its switch is the outgoing
    take's own; the frame after, because the skate measure takes central differences (a foot let go there moves
    in the last contact frame) and a held foot lifts later than the contact band says."""
    d = np.asarray(down, dtype=bool)
    n = d.shape[0]
    out = np.zeros_like(d)
    for f in range(d.shape[1]):  # one column per foot
        for start, stop in contacts.contact_intervals(d[:, f], periodic=True):  # one per phase; stop may pass n
            for w0, w1 in windows:
                for a in (w0, w0 + n):  # a phase running across the loop's seam meets a window at 0 one loop on
                    if start < max(w1, w0 + 1) + a - w0 and stop > a:
                        out[np.arange(max(start, a), stop + 1) % n, f] = True
    return out


def _free(taken: NDArray[np.bool_], edge: int, step: int, limit: int, walls: set[int]) -> NDArray[np.intp]:
    """Frames (mod ``T``) from ``edge + step`` on in direction ``step`` while the foot is not ``taken`` (a step or a
    hold), at most ``limit``, never into a frame of ``walls`` going backwards (a switch: before it the outgoing
    take plays as it is) nor past one going forwards."""
    n = taken.size
    out: list[int] = []
    k = edge
    while len(out) < limit:
        if step < 0 and k % n in walls:
            break
        k += step
        if taken[k % n] or (step > 0 and k % n in walls):
            break
        out.append(k % n)
    return np.array(out, dtype=np.intp)


def eased_offsets(offsets: ArrayLike, held: ArrayLike, steps_down: ArrayLike, switches: Sequence[int],
                  release: int) -> Array:
    """Each foot's ankle offsets ``(T, F, 3)`` from its animated place through its holds and the swings beside
    them, from the held frames' ``offsets`` (where :func:`anim_core.methods.footplant.foot_targets` puts the ankle
    minus where the animation does, resting at each hold's slowest frame; 0 elsewhere).

    A hold that starts at a switch (``switches``: frames; the foot was down as the transition began) is held from
    there: its offsets less its first frame's (they differ by a constant wherever they rest), so the foot stays
    where the outgoing take put it and nothing before the switch changes.  A hold that starts later (the foot lands
    during the transition) rests at its slowest frame, and its first offset eases in (smoothstep) over the swing
    before it, from the switch or the foot's previous step on.  After every hold its last offset eases out over
    the swing to the foot's next step, at most ``release`` frames, so no leg is let go in a frame or two."""
    off = np.array(offsets, dtype=np.float64)
    h = np.asarray(held, dtype=bool)
    taken = h | np.asarray(steps_down, dtype=bool)
    n = h.shape[0]
    walls = {int(f) % n for f in switches}
    for f in range(h.shape[1]):  # one column per foot
        for start, stop in contacts.contact_intervals(h[:, f], periodic=True):  # one per hold
            frames = np.arange(start, stop) % n
            if start % n in walls:
                off[frames, f] -= off[start % n, f]
            else:
                before = _free(taken[:, f], int(start), -1, release, walls)
                ease = smoothstep(np.arange(len(before), 0, -1) / (len(before) + 1))
                off[before, f] = ease[:, None] * off[start % n, f]
            after = _free(taken[:, f], int(stop) - 1, 1, release, walls)
            ease = 1.0 - smoothstep(np.arange(1, len(after) + 1) / (len(after) + 1))
            off[after, f] = ease[:, None] * off[(stop - 1) % n, f]
    return off


def lock_transition_feet(skeleton: Skeleton, local_rotations: ArrayLike, root_translation: ArrayLike,
                         windows: Sequence[tuple[int, int]], fps: float, lock: FeetLock, up_axis: int = 1) -> Array:
    """Local rotations ``(T, J, 4)`` of a composed loop with the feet held through its transitions.

    ``local_rotations (T, J, 4)``: one period; ``root_translation (T + 1, 3)``: the root at every frame and one
    loop on (its difference to frame 0 is the loop's travel); ``windows``: the frames ``[start, stop)`` of each
    transition (its switch to its end); units of the skeleton's offsets (metres)."""
    rot = np.array(local_rotations, dtype=np.float64)
    root = np.asarray(root_translation, dtype=np.float64)
    n = rot.shape[0]
    if root.shape != (n + 1, 3):
        raise ValueError(f"expected the root at {n + 1} frames (one period and the loop's end), got {root.shape}")
    velocity = (root[n] - root[0]) * fps / n
    velocity[up_axis] = 0.0
    in_place = root[:n] - velocity * (np.arange(n) / fps)[:, None]
    pos = skeleton.forward_kinematics(rot, in_place)[1]
    feet = np.array([list(f) for f in lock.feet])
    chains = [tuple(int(j) for j in c) for c in lock.legs]
    points = pos[:, feet]
    # Steps: contact phases in which the foot slows to rest_speed (a swing skimming the floor is not held).
    down = steps(contacts.foot_down(points, up_axis),
                 contacts.foot_speed(points, fps, up_axis, periodic=True, ground_velocity=velocity), periodic=True,
                 rest_speed=lock.rest_speed)
    held = held_phases(down, windows)
    if not held.any():
        return rot
    targets, _ = foot_targets(skeleton, rot, in_place, chains, held, fps, feet.tolist(), periodic=True,
                              ground_velocity=velocity, up_axis=up_axis, blend_frames=0, max_speed=lock.max_speed,
                              rest_speed=np.inf)
    ankles = pos[:, [c[2] for c in chains]]
    offsets = eased_offsets(np.where(held[..., None], targets - ankles, 0.0), held, down,
                            [int(w0) % n for w0, _ in windows], max(1, round(lock.release_s * fps)))
    weights = np.any(offsets != 0.0, axis=-1).astype(np.float64)
    soft = SOFT_REACH * min(float(np.linalg.norm(skeleton.offsets[m]) + np.linalg.norm(skeleton.offsets[e]))
                            for _, m, e in chains)
    for leg, chain in enumerate(chains):  # one solve per leg over the frames it moves
        active = np.flatnonzero(weights[:, leg] > 0)
        if active.size:
            rot[active] = two_bone_ik(skeleton, rot[active], in_place[active], chain,
                                      ankles[active, leg] + offsets[active, leg], weight=weights[active, leg],
                                      hinge=leg_hinge(skeleton, local_rotations, in_place, chain), soft=soft)
    return rot


def landings(clip: KeyframeClip, lock: FeetLock, up_axis: int = 1) -> Array | None:
    """``(F,)`` the time (s, in ``[0, duration)``) at which each foot of a looping clip (its last key repeating the
    first) lands: within its one step per cycle (a contact phase in which the foot slows to ``lock.rest_speed``,
    :func:`anim_core.methods.footlock.steps`; one period in place, the ground moving under it at the loop's mean
    velocity), the first frame at which its slowest joint is under the skate threshold
    (:data:`anim_core.math.contacts.SKATE_SPEED_MPS`), or its slowest frame.  Not the phase's first frame: a
    run's foot enters the contact height band still swinging at up to 5 m/s (Bandai's run: 4 frames early, its two
    landings 0.23 and 0.50 s apart instead of half its 0.73 s cycle each).  None if a foot does not step exactly
    once (an idle, a shuffle)."""
    fps = (clip.rotations.shape[0] - 1) / clip.duration
    velocity = np.array(clip.velocity, dtype=np.float64)
    root = clip.root_translation[:-1] - velocity * clip.times[:-1, None]
    points = clip.skeleton.forward_kinematics(clip.rotations[:-1], root)[1][:, np.array([list(f) for f in lock.feet])]
    speed = contacts.foot_speed(points, fps, up_axis, periodic=True, ground_velocity=velocity)
    down = steps(contacts.foot_down(points, up_axis), speed, periodic=True, rest_speed=lock.rest_speed)
    n = down.shape[0]
    out = []
    for f in range(down.shape[1]):
        phases = contacts.contact_intervals(down[:, f], periodic=True)
        if len(phases) != 1 or phases[0, 1] - phases[0, 0] >= n:
            return None
        frames = np.arange(phases[0, 0], phases[0, 1]) % n
        slow = np.flatnonzero(speed[frames, f] <= contacts.SKATE_SPEED_MPS)
        out.append(frames[slow[0] if slow.size else int(np.argmin(speed[frames, f]))] / fps)
    return np.array(out)
