"""Composite motion: sequences of animations joined by transitions, layers over a base, parametric blends.

Pure functions over pose arrays on a frame grid (local rotations ``(T, J, 4)`` (w, x, y, z), root translation
``(T, 3)``), plus :func:`compose_sequence`, which turns a sequence of clips with durations into one looping
:class:`~anim_core.math.clip.KeyframeClip`.  The formulas are in docs/methods/transitions.md.

Transitions (at a switch from the *outgoing* clip ``A`` to the *incoming* clip ``B``, ``u`` seconds after the switch;
``A`` keeps playing its own time past its segment's end, ``B`` starts at its entry time, 0 unless the sequence's
``entry`` is ``"matched"``: see :func:`compose_sequence`):

* ``cut``: ``B(u)`` from the switch on.
* ``crossfade``: ``blend(A(s_A + u), B(u), w(u))`` with ``w = clip(u / d, 0, 1)`` (``linear``) or
  ``3 s^2 - 2 s^3`` (``smoothstep``), per joint ``nlerp`` or ``slerp``; the root's *velocity* is blended and
  integrated (never its position: two takes stand at different places).
* ``inertialization``: Bollo's quintic offset decay (GDC 2018, "Inertialization: High-Performance Animation
  Transitions in Gears of War"), in the variant stated here: at the switch the offset ``x0 = A - B`` and its
  velocity ``v0 = A' - B'`` are taken per *quaternion component* (B's hemisphere) and per root component, each
  decays by the quintic ``x(u)`` with ``x(0) = x0, x'(0) = v0, x''(0) = a0 = (-8 v0 d - 20 x0) / d^2`` and
  ``x = x' = x'' = 0`` at ``u = d``; the pose is ``normalize(B(u) + x(u))``.  Bollo works along one axis of the
  rotation offset and clamps ``a0 >= 0`` and the duration when the offset overshoots; per component, without those
  clamps, the output equals ``A`` and moves with ``A``'s velocity at the switch exactly (C1), which is what is
  tested.  Not dead blending.

Layers (joint sets named once in :data:`JOINT_SETS`, each a set of subtrees, so an overridden wrist never rides on
an arm driven by the other animation unless the set says so):

* ``override``: the set's joints take the layer's local rotations, every other joint keeps the base's (bit for
  bit).  With ``space = "model"`` the set's top joints keep the layer's model-space rotation (the base's parents'
  rotation is undone), so the upper body keeps its orientation whatever the pelvis does.
* ``additive``: ``base * delta^weight`` per joint of the set with ``delta = reference^-1 layer`` taken against a
  stated reference pose (a frame of the layer, or the rest pose); a delta that is exactly the identity leaves the
  base bit-identical.

Parametric (two takes mixed by a weight after time alignment): both cycles mapped onto one phase, linearly or
piecewise between sync markers (each foot's landing: between two markers each take plays its own stretch), the
blended clip lasts ``(1 - w) T_A + w T_B``, per joint ``slerp(A(t_A(p)), B(t_B(p)), w)``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..math.clip import KeyframeClip, Pose
from ..math.quat import (
    align_hemisphere,
    identity,
    nlerp,
    quat_angle,
    quat_conj,
    quat_mul,
    quat_normalize,
    slerp,
)
from ..math.skeleton import Skeleton
from .ik import smoothstep
from .transition_feet import FeetLock, lock_transition_feet

Array = NDArray[np.float64]
Curve = Literal["linear", "smoothstep"]
Interp = Literal["nlerp", "slerp"]
Transition = Literal["cut", "crossfade", "inertialization"]
RootMotion = Literal["travel", "in_place"]

#: Joint sets of the character's (cmu_mb) skeleton: ``name -> (subtree roots, subtree roots excluded)``.
JOINT_SETS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "upper_body": (("LowerBack",), ()),
    "lower_body": (("Hips",), ("LowerBack",)),
    "arms": (("LeftShoulder", "RightShoulder"), ()),
    "left_arm": (("LeftShoulder",), ()),
    "right_arm": (("RightShoulder",), ()),
    "legs": (("LHipJoint", "RHipJoint"), ()),
    "left_leg": (("LHipJoint",), ()),
    "right_leg": (("RHipJoint",), ()),
    "head": (("Neck",), ()),
}
#: Step of the central differences that give velocities of a clip (seconds).
VELOCITY_STEP_S = 1e-3
#: Largest angle (degrees) between the transition's pose and the incoming clip's at which the pose is settled.
SETTLE_DEG = 1.0


class CompositeError(ValueError):
    """A composite cannot be built as described; the message names the field."""


def joint_mask(skeleton: Skeleton, joint_set: str | tuple[tuple[str, ...], tuple[str, ...]],
               sets: Mapping[str, tuple[tuple[str, ...], tuple[str, ...]]] = JOINT_SETS) -> NDArray[np.bool_]:
    """``(J,)`` True for every joint of ``joint_set`` (a name of ``sets`` or ``(roots, excluded roots)``): the
    subtrees under ``roots`` without those under the excluded roots.  Unknown set or joint: :class:`CompositeError`."""
    if isinstance(joint_set, str):
        if joint_set not in sets:
            raise CompositeError(f"joints: unknown joint set {joint_set!r}; known: {', '.join(sets)}")
        roots, excluded = sets[joint_set]
    else:
        roots, excluded = joint_set
    missing = [n for n in (*roots, *excluded) if n not in skeleton.names]
    if missing:
        raise CompositeError(f"joints: joint set {joint_set!r} needs joint {missing[0]!r}, which the character's "
                             f"skeleton does not have")

    def subtree(names: Sequence[str]) -> NDArray[np.bool_]:
        inside = np.zeros(skeleton.n_joints, bool)
        inside[[skeleton.index(n) for n in names]] = True
        for j in range(1, skeleton.n_joints):  # parents come first (topological order)
            inside[j] |= inside[skeleton.parents[j]]
        return inside

    return subtree(roots) & ~subtree(excluded) if excluded else subtree(roots)


# --- weights and blends -------------------------------------------------------------------------------------------

def blend_weights(u: ArrayLike, duration: float, curve: Curve = "linear") -> Array:
    """Weight of the incoming clip ``u`` seconds after the switch: ``s = clip(u / duration, 0, 1)``, linear ``s``
    or smoothstep ``3 s^2 - 2 s^3``; duration 0 is a cut (1 from the switch on)."""
    u = np.asarray(u, dtype=np.float64)
    if duration <= 0:
        return np.where(u >= 0, 1.0, 0.0)
    s = np.clip(u / duration, 0.0, 1.0)
    if curve == "linear":
        return s
    if curve == "smoothstep":
        return smoothstep(s)
    raise ValueError(f"curve must be 'linear' or 'smoothstep', got {curve!r}")


def blend_rotations(a: ArrayLike, b: ArrayLike, w: ArrayLike, interp: Interp = "nlerp") -> Array:
    """Per joint ``nlerp``/``slerp`` from ``a (..., J, 4)`` to ``b`` by ``w (...)`` (one weight per pose); exactly
    ``a`` where ``w == 0`` and ``b`` where ``w == 1``."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    w = np.asarray(w, np.float64)[..., None]
    mixed = (nlerp if interp == "nlerp" else slerp)(a, b, np.broadcast_to(w, a.shape[:-1]))
    return np.where(w[..., None] == 0, a, np.where(w[..., None] == 1, b, mixed))


def quintic_offset(x0: ArrayLike, v0: ArrayLike, u: ArrayLike, duration: float) -> Array:
    """Bollo's quintic decay of offsets ``x0 (..., C)`` with velocity ``v0`` at times ``u (T,)`` after the switch
    -> ``(T, ..., C)``: ``x(0) = x0, x'(0) = v0, x''(0) = a0 = (-8 v0 d - 20 x0) / d^2``, zero value, velocity and
    acceleration at ``d``; 0 after ``d``."""
    x0, v0 = np.asarray(x0, np.float64), np.asarray(v0, np.float64)
    t1 = float(duration)
    u = np.asarray(u, np.float64).reshape((-1,) + (1,) * x0.ndim)
    a0 = (-8.0 * v0 * t1 - 20.0 * x0) / t1**2
    a = -(a0 * t1**2 + 6.0 * v0 * t1 + 12.0 * x0) / (2.0 * t1**5)
    b = (3.0 * a0 * t1**2 + 16.0 * v0 * t1 + 30.0 * x0) / (2.0 * t1**4)
    c = -(3.0 * a0 * t1**2 + 12.0 * v0 * t1 + 20.0 * x0) / (2.0 * t1**3)
    t = np.clip(u, 0.0, t1)
    x = ((((a * t + b) * t + c) * t + 0.5 * a0) * t + v0) * t + x0
    return np.where(u < t1, x, 0.0)


# --- layers -------------------------------------------------------------------------------------------------------

def override(base: ArrayLike, layer: ArrayLike, mask: NDArray[np.bool_], skeleton: Skeleton | None = None,
             space: Literal["local", "model"] = "local") -> Array:
    """The joints of ``mask`` from ``layer``'s local rotations ``(..., J, 4)``, the others ``base``'s bit for bit.
    ``space = "model"``: the set's top joints (parent outside the set) keep the layer's model-space rotation:
    ``local = G_base(parent)^-1 G_layer(parent) layer_local`` (``skeleton`` needed)."""
    base, layer = np.asarray(base, np.float64), np.asarray(layer, np.float64)
    out = np.where(mask[:, None], layer, base)
    if space == "model":
        if skeleton is None:
            raise ValueError("override in model space needs the skeleton")
        tops = [j for j in np.flatnonzero(mask) if skeleton.parents[j] >= 0 and not mask[skeleton.parents[j]]]
        if tops:
            parents = skeleton.parents[tops]
            g_base, _ = skeleton.forward_kinematics(base)
            g_layer, _ = skeleton.forward_kinematics(layer)
            out[..., tops, :] = quat_mul(quat_mul(quat_conj(g_base[..., parents, :]), g_layer[..., parents, :]),
                                         layer[..., tops, :])
    return out


def additive_delta(layer: ArrayLike, reference: ArrayLike) -> Array:
    """``reference^-1 layer`` per joint (``(..., J, 4)``; ``reference (J, 4)`` broadcast): exactly the identity
    where the two are equal."""
    layer, reference = np.asarray(layer, np.float64), np.asarray(reference, np.float64)
    delta = quat_mul(quat_conj(reference), layer)
    same = np.all(layer == reference, axis=-1, keepdims=True)
    return np.where(same, identity(delta.shape[:-1]), delta)


def additive(base: ArrayLike, delta: ArrayLike, mask: NDArray[np.bool_], weight: float = 1.0) -> Array:
    """``base * delta^weight`` on the joints of ``mask`` (``delta^w = slerp(1, delta, w)``), ``base`` elsewhere;
    where the delta is exactly the identity the base is kept bit for bit."""
    base, delta = np.asarray(base, np.float64), np.asarray(delta, np.float64)
    if weight != 1.0:
        delta = slerp(identity(delta.shape[:-1]), delta, np.full(delta.shape[:-1], weight))
    is_identity = np.all(delta == identity(()), axis=-1, keepdims=True)
    moved = quat_mul(base, delta)
    return np.where(mask[:, None] & ~is_identity, moved, base)


# --- parametric ---------------------------------------------------------------------------------------------------

def parametric(a: KeyframeClip, b: KeyframeClip, weight: float, fps: int, interp: Interp = "slerp",
               markers: tuple[ArrayLike, ArrayLike] | None = None) -> KeyframeClip:
    """Two cycles (loops) mixed by ``weight`` (0: ``a``, 1: ``b``) after time alignment: both played over a
    normalized phase, the result lasting ``(1 - w) T_a + w T_b`` on the ``fps`` grid, rotations blended per joint,
    the root's position blended (the travel per cycle with it); played in place if ``a`` is.  Where each cycle
    starts is the caller's (:func:`cycle_from` aligns ``b``'s start with ``a``'s).

    ``markers``: sync markers, ``K`` times (s) in ``a``'s cycle and the ``K`` corresponding times in ``b``'s (e.g.
    each foot's landing, :func:`anim_core.methods.transition_feet.landings`), in the same cyclic order: between two
    markers both takes play their own stretch, the blend's stretch lasting ``(1 - w)`` of ``a``'s plus ``w`` of
    ``b``'s, so the markers coincide (the feet land together); None: one linear phase.  Output time 0 is ``a``'s
    time 0 in either case."""
    if not 0.0 <= weight <= 1.0:
        raise CompositeError(f"weight: between 0 and 1, got {weight!r}")
    if a.mode != "loop" or b.mode != "loop":
        raise CompositeError(f"blend: both takes loop (their cycles are mapped onto one phase), got {a.mode!r} "
                             f"and {b.mode!r}")
    duration = (1.0 - weight) * a.duration + weight * b.duration
    n = max(2, round(duration * fps))
    phase = np.arange(n + 1) / n
    if markers is None or weight in (0.0, 1.0):
        ta, tb = phase * a.duration, phase * b.duration
    else:
        ta, tb = _synced_times(np.asarray(markers[0], np.float64), np.asarray(markers[1], np.float64),
                               a.duration, b.duration, weight, phase)
    # Sampled with their travel (a clip played in place keeps its keys' root and takes its speed from them).
    pa = _travelling(a, "travel").sample(ta)
    pb = _travelling(b, "travel").sample(tb)
    if a is b or weight == 0.0:
        rot, root = pa.rotations, pa.root_translation
    else:
        rot = blend_rotations(pa.rotations, pb.rotations, np.full(n + 1, weight), interp)
        root = (1.0 - weight) * pa.root_translation + weight * pb.root_translation
    return KeyframeClip(a.skeleton, phase * duration, rot, root, a.mode, a.in_place, a.up_axis, a.name)


def _synced_times(ma: Array, mb: Array, duration_a: float, duration_b: float, weight: float,
                  phase: Array) -> tuple[Array, Array]:
    """``a``'s and ``b``'s times ``(n,)`` at the blend's ``phase`` ``(n,)`` (0..1 over one cycle, 0 at ``a``'s time
    0) with sync markers ``ma``/``mb`` ``(K,)`` (:func:`parametric`); both increase over exactly one cycle."""
    if ma.shape != mb.shape or ma.ndim != 1 or ma.size == 0:
        raise CompositeError(f"blend: as many sync markers in each take, got {ma.shape} and {mb.shape}")
    order = np.argsort(np.mod(ma, duration_a))
    ma, mb = np.mod(ma, duration_a)[order], mb[order]
    mb = mb[0] + np.mod(mb - mb[0], duration_b)  # b's markers from its first, within one cycle
    if np.any(np.diff(ma) <= 0) or np.any(np.diff(mb) <= 0):
        raise CompositeError("blend: the takes' sync markers (their feet's landings) come in different orders")
    xa, xb = np.append(ma, ma[0] + duration_a), np.append(mb, mb[0] + duration_b)
    xo = np.concatenate([[0.0], np.cumsum((1.0 - weight) * np.diff(xa) + weight * np.diff(xb))])
    period = xo[-1]
    # Two periods of knots, so that a cycle starting anywhere in the first is covered.
    xo2, xa2, xb2 = (np.concatenate([x, x[1:] + span]) for x, span in ((xo, period), (xa, duration_a),
                                                                         (xb, duration_b)))
    u = np.interp(duration_a, xa, xo) + phase * period  # a's time 0 (= its duration) on the blend's knots
    ta = np.interp(u, xo2, xa2) - duration_a
    tb = np.interp(u, xo2, xb2)
    return ta, tb - duration_b * np.floor(tb[0] / duration_b)


def cycle_from(clip: KeyframeClip, start: float) -> KeyframeClip:
    """The loop ``clip`` with its cycle starting ``start`` seconds in (its keys' times, the poses ``start`` later,
    the travel carried across the wrap): the same motion, entered elsewhere."""
    if clip.mode != "loop":
        raise CompositeError(f"blend: a take that loops, got {clip.mode!r}")
    pose = _travelling(clip, "travel").sample(clip.times + start)
    return KeyframeClip(clip.skeleton, clip.times, pose.rotations, pose.root_translation, clip.mode, clip.in_place,
                        clip.up_axis, clip.name)


# --- sequences ----------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class TransitionSpec:
    """How a sequence switches: ``method``, ``duration_s`` (crossfade, inertialization), weight ``curve`` and
    rotation ``interp`` (crossfade)."""

    method: Transition = "cut"
    duration_s: float = 0.0
    curve: Curve = "linear"
    interp: Interp = "nlerp"


@dataclass(frozen=True, eq=False)
class Composite:
    """A composed sequence: ``clip`` (a loop on the frame grid, its last key the first again), the frame of each
    switch (``switch_frames``, the loop's back to the start at frame 0 included), the incoming clip's weight at
    every frame (``weights``; 1 for a cut, the crossfade's ``w``, for inertialization 1 - the remaining offset
    share), and per switch the seconds until the pose stays within :data:`SETTLE_DEG` of the incoming clip's
    (``settle_s``).  ``rotations (T, J, 4)``: the frames as composed (the clip's keys are the same up to
    sign: a keyframe clip makes its keys sign-continuous)."""

    clip: KeyframeClip
    rotations: Array
    switch_frames: tuple[int, ...]
    weights: Array
    settle_s: tuple[float, ...]


def _travelling(clip: KeyframeClip, root_motion: RootMotion) -> KeyframeClip:
    in_place = root_motion == "in_place"
    if clip.in_place == in_place:
        return clip
    return KeyframeClip(clip.skeleton, clip.times, clip.rotations, clip.root_translation, clip.mode, in_place,
                        clip.up_axis, clip.name)


def _velocity(clip: KeyframeClip, t: Array, forward: bool = False) -> tuple[Array, Array]:
    """Local-rotation component velocities ``(T, J, 4)`` and root velocity ``(T, 3)`` by central differences, or
    forward ones (``forward``: an incoming clip starts at its time 0, nothing before it counts)."""
    h = VELOCITY_STEP_S
    mid, after = clip.sample(t), clip.sample(t + h)
    before = mid if forward else clip.sample(t - h)
    # A loop's keys may change sign across its wrap: both sides in the hemisphere of the pose at t.
    q0, q1 = align_hemisphere(before.rotations, mid.rotations), align_hemisphere(after.rotations, mid.rotations)
    span = h if forward else 2 * h
    return (q1 - q0) / span, (after.root_translation - before.root_translation) / span


Entry = Literal["start", "matched"]
ENTRIES: tuple[str, ...] = ("start", "matched")


def _pose_cost(candidates: Array, outgoing: Pose) -> Array:
    """Per candidate pose ``(N, J, 4)``: the sum over the non-root joints of the angle to ``outgoing``'s rotations."""
    return quat_angle(candidates[:, 1:], np.asarray(outgoing.rotations)[:, 1:]).sum(axis=1)


def entry_time(outgoing: Pose, clip: KeyframeClip, fps: int) -> float:
    """The time of ``clip`` (a loop) whose pose is nearest ``outgoing`` (one pose, ``(1, J, 4)`` local rotations):
    the frame of its cycle (on the ``fps`` grid) with the least sum over the non-root joints of the angle between
    the local rotations.  A walk entered there is in the outgoing take's leg phase (the same foot forward, the
    stance leg the same), so that a blend does not cross two strides (issue 39: walk into run from their time 0
    skated more than the sources)."""
    n = max(1, round(clip.duration * fps))
    t = np.arange(n) / fps
    return float(t[int(np.argmin(_pose_cost(clip.sample(t).rotations, outgoing)))])


def _checked_sequence(segments: Sequence[tuple[KeyframeClip, float]], fps: int, transition: TransitionSpec,
                      root_motion: RootMotion | None, entry: Entry) -> tuple[list[KeyframeClip], Array, RootMotion]:
    """The clips (with the root-motion rule applied), their seconds and the rule, or CompositeError naming the
    field (:func:`compose_sequence`)."""
    if len(segments) < 2:
        raise CompositeError("sequence: at least 2 animations")
    clips = [c for c, _ in segments]
    seconds = np.array([s for _, s in segments], np.float64)
    if not np.all(np.isfinite(seconds)) or np.any(seconds <= 0):
        raise CompositeError(f"sequence seconds: every duration is positive, got {seconds.tolist()}")
    if np.any(np.abs(seconds * fps - np.round(seconds * fps)) > 1e-6):
        raise CompositeError(f"sequence seconds: every duration is a whole number of frames at {fps} fps")
    if transition.method != "cut" and not 0 < transition.duration_s <= seconds.min():
        raise CompositeError(f"duration: a {transition.method} of {transition.duration_s} s needs 0 < duration <= "
                             f"the shortest segment ({seconds.min()} s)")
    travelling = {not c.in_place and c.mode == "loop" for c in clips}
    if root_motion is None:
        if len(travelling) > 1:
            raise CompositeError("root_motion: the sequence mixes clips played in place with travelling ones; "
                                 "say root_motion = \"travel\" or \"in_place\"")
        root_motion = "travel" if travelling.pop() else "in_place"
    clips = [_travelling(c, root_motion) for c in clips]
    if entry not in ENTRIES:
        raise CompositeError(f"entry: one of {', '.join(map(repr, ENTRIES))}, got {entry!r}")
    return clips, seconds, root_motion


def _chained_entries(clips: Sequence[KeyframeClip], seconds: Array, first: float, fps: int) -> Array:
    """Entry times when the first clip starts at ``first`` and every looping clip after it is entered matched."""
    begin = np.zeros(len(clips))
    begin[0] = first
    for s in range(1, len(clips)):
        if clips[s].mode == "loop":
            begin[s] = entry_time(clips[s - 1].sample(np.array([begin[s - 1] + seconds[s - 1]])), clips[s], fps)
    return begin


def _entry_times(clips: Sequence[KeyframeClip], seconds: Array, entry: Entry, fps: int) -> Array:
    """Where each clip starts playing, s of its own time (:func:`compose_sequence`'s ``entry``).  ``"matched"``
    also matches the loop's own switch, from the last clip back into the first: a looping first clip starts at the
    frame of its cycle (the chain after it following) whose pose is nearest the pose the last clip ends on (issue
    39: started at 0, the run's swing foot came down into the walk's toe-off, 0.304 of the window skating)."""
    if entry != "matched":
        return np.zeros(len(clips))
    if clips[0].mode != "loop":
        return _chained_entries(clips, seconds, 0.0, fps)
    starts = np.arange(max(1, round(clips[0].duration * fps))) / fps
    chains = [_chained_entries(clips, seconds, t, fps) for t in starts]
    ends = [clips[-1].sample(np.array([b[-1] + seconds[-1]])) for b in chains]
    heads = clips[0].sample(starts).rotations
    cost = [float(_pose_cost(heads[i:i + 1], end)[0]) for i, end in enumerate(ends)]
    return chains[int(np.argmin(cost))]


def _inertialized(out: KeyframeClip, s_out: float, clip: KeyframeClip, begin: float, cur: Pose, v_cur: Array,
                  uu: Array, d: float, up: int) -> tuple[Array, Array, Array, Array]:
    """Rotations, root velocities, heights and incoming weights over one segment's frames ``uu`` (s since its
    switch) for an inertialization of ``d`` s from ``out`` (at its own time ``s_out``) into ``clip`` (entered at
    ``begin``; its pose ``cur`` and velocity ``v_cur`` there): the offset at the switch decays by a quintic."""
    a0 = out.sample(np.array([s_out]))
    qa_dot, va = _velocity(out, np.array([s_out]))
    b0 = clip.sample(np.array([begin]))
    qb_dot, vb = _velocity(clip, np.array([begin]), forward=True)
    qa = align_hemisphere(a0.rotations[0], b0.rotations[0])
    sign = np.where(np.sum(a0.rotations[0] * b0.rotations[0], axis=-1) < 0, -1.0, 1.0)[:, None]
    x_rot = quintic_offset(qa - b0.rotations[0], sign * qa_dot[0] - qb_dot[0], uu, d)
    rotations = quat_normalize(cur.rotations + x_rot)
    x_v = quintic_offset(va[0] - vb[0], np.zeros(3), uu, d)
    velocity = v_cur + x_v
    dy = a0.root_translation[0, up] - b0.root_translation[0, up]
    x_y = quintic_offset(np.array([dy]), np.array([va[0, up] - vb[0, up]]), uu, d)[:, 0]
    heights = cur.root_translation[:, up] + x_y
    scale = np.abs(qa - b0.rotations[0]).max()
    weights = 1.0 - (np.abs(x_rot).max(axis=(1, 2)) / scale if scale > 0 else 0.0)
    return rotations, velocity, heights, weights


def _integrated_root(vel: Array, height: Array, fps: int, up: int) -> Array:
    """The root ``(n + 1, 3)``: horizontal velocity integrated (trapezoid), height as blended; key n repeats frame 0
    one loop on."""
    v_h = vel.copy()
    v_h[:, up] = 0.0
    steps = 0.5 * (v_h + np.roll(v_h, -1, axis=0)) / fps
    root = np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)])
    root[:, up] = np.append(height, height[0])
    return root


def _settle_times(skeleton: Skeleton, rot: Array, rot_in: Array, starts: Array, fps: int) -> list[float]:
    """Per switch, the first time after it from which every joint stays within :data:`SETTLE_DEG` of the incoming
    clip's (``rot_in``)."""
    g_out, _ = skeleton.forward_kinematics(rot)
    g_in, _ = skeleton.forward_kinematics(rot_in)
    off = np.degrees(quat_angle(g_out, g_in).max(axis=1)) > SETTLE_DEG
    settle = []
    for s in range(len(starts) - 1):
        window = off[starts[s]:starts[s + 1]]
        late = np.flatnonzero(window)
        settle.append(float((late[-1] + 1) / fps) if late.size else 0.0)
    return settle


def compose_sequence(segments: Sequence[tuple[KeyframeClip, float]], fps: int, transition: TransitionSpec,
                     root_motion: RootMotion | None = None, name: str = "", entry: Entry = "start",
                     lock: FeetLock | None = None) -> Composite:
    """One loop from ``segments`` ``[(clip, seconds), ...]`` (each clip played for its seconds), switching by
    ``transition`` from each to the next and from the last back to the first.

    ``entry``: where each clip starts playing: ``"start"``, at its time 0; ``"matched"``, every looping clip after
    the first at the frame of its cycle nearest the pose the previous clip has at the switch (:func:`entry_time`),
    and a looping first clip where the loop's own switch from the last clip matches best (:func:`_entry_times`;
    any other first clip at 0).  The entry times depend on the takes only, never on the transition,
    so a sequence's conditions differ by how they switch alone.

    Root: the horizontal root velocity (blended as the rotations are) is integrated from frame to frame, so no
    switch moves the character; the height is blended.  ``lock``: the feet in contact during a blended transition
    are held there (:mod:`anim_core.methods.transition_feet`; a cut is left as it is), before the settling is
    measured.  Clips that travel and clips played in place mix only with
    a ``root_motion`` rule (``"travel"``: every clip with its travel, ``"in_place"``: every clip on the spot).
    """
    clips, seconds, root_motion = _checked_sequence(segments, fps, transition, root_motion, entry)
    up = clips[0].up_axis
    begin = _entry_times(clips, seconds, entry, fps)
    frames = np.round(seconds * fps).astype(int)
    starts = np.concatenate([[0], np.cumsum(frames)])
    n = int(starts[-1])
    k = np.searchsorted(starts, np.arange(n), side="right") - 1  # segment of each frame
    u = (np.arange(n) - starts[k]) / fps  # seconds since the switch into it
    prev = (k - 1) % len(clips)
    j = clips[0].skeleton.n_joints
    rot, rot_in = np.empty((n, j, 4)), np.empty((n, j, 4))
    vel, height = np.empty((n, 3)), np.empty(n)
    weights = np.ones(n)
    d = transition.duration_s
    for s, clip in enumerate(clips):
        here = k == s
        uu = u[here]
        cur = clip.sample(begin[s] + uu)
        out = clips[prev[here][0]]
        s_out = begin[prev[here][0]] + seconds[prev[here][0]]  # the outgoing clip's own time at the switch
        _, v_cur = _velocity(clip, begin[s] + uu, forward=True)
        rot_in[here] = cur.rotations
        if transition.method == "cut":
            rot[here], vel[here], height[here] = cur.rotations, v_cur, cur.root_translation[:, up]
            continue
        old = out.sample(s_out + uu)
        _, v_old = _velocity(out, s_out + uu)
        if transition.method == "crossfade":
            w = blend_weights(uu, d, transition.curve)
            weights[here] = w
            rot[here] = blend_rotations(old.rotations, cur.rotations, w, transition.interp)
            vel[here] = (1 - w)[:, None] * v_old + w[:, None] * v_cur
            height[here] = (1 - w) * old.root_translation[:, up] + w * cur.root_translation[:, up]
        elif transition.method == "inertialization":
            rot[here], vel[here], height[here], weights[here] = _inertialized(out, s_out, clip, begin[s], cur, v_cur,
                                                                              uu, d, up)
        else:
            raise CompositeError(f"method: unknown transition {transition.method!r}")
    root = _integrated_root(vel, height, fps, up)
    if lock is not None and transition.method != "cut":
        span = max(1, round(d * fps))
        rot = lock_transition_feet(clips[0].skeleton, rot, root, [(int(f), int(f) + span) for f in starts[:-1]],
                                   fps, lock, up)
    rotations = np.concatenate([rot, rot[:1]])
    clip = KeyframeClip(clips[0].skeleton, np.arange(n + 1) / fps, rotations, root, "loop",
                        root_motion == "in_place", up, name)
    settle = _settle_times(clips[0].skeleton, rot, rot_in, starts, fps)
    return Composite(clip, rot, tuple(int(x) for x in starts[:-1]), weights, tuple(settle))


def layered(base: KeyframeClip, layers: Sequence[tuple[KeyframeClip, NDArray[np.bool_], str, Array | None]],
            fps: int, name: str = "", space: Literal["local", "model"] = "local", weight: float = 1.0
            ) -> KeyframeClip:
    """``base`` with ``layers`` ``[(clip, joint mask, mode, reference pose (J, 4) or None), ...]`` applied in
    order at the base's own keys (the layer sampled there by its own playback; a loop's last key takes the layer
    at time 0, so the loop stays closed): ``override`` (in ``space``, :func:`override`) or ``additive`` (delta
    against the reference pose, None: the layer's first frame, taken to ``weight``).  Joints outside every layer
    keep the base's keys bit for bit."""
    times = base.times
    layer_times = times.copy()
    if base.mode == "loop":
        layer_times[-1] = 0.0
    rot = base.rotations.copy()
    for clip, mask, mode, reference in layers:
        layer = clip.sample(layer_times).rotations
        if mode == "override":
            rot = override(rot, layer, mask, base.skeleton, space)
        elif mode == "additive":
            ref = clip.sample(np.array([0.0])).rotations[0] if reference is None else reference
            rot = additive(rot, additive_delta(layer, ref), mask, weight)
        else:
            raise CompositeError(f"mode: 'override' or 'additive', got {mode!r}")
    return KeyframeClip(base.skeleton, times, rot, base.root_translation, base.mode, base.in_place, base.up_axis,
                        name)
