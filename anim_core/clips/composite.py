"""Building a composite animation's clips (issue 39): a sequence of takes or a base take with layers, one clip per
condition that applies to it (the reference first), sampled, placed on the floor and measured like a take's
clips, plus the transition metrics of a sequence (docs/methods/transitions.md):

* ``transition_foot_skate_ratio`` and ``transition_foot_slide_mm``: the feet over the transition window of every
  switch (from :data:`WINDOW_BEFORE_S` before it to the transition's end plus :data:`WINDOW_AFTER_S`), in world
  space, a foot down against the whole loop's standing heights, the worst switch; ``source_foot_skate_ratio`` is
  the worst of the takes' own over their whole spans, and ``source_window_foot_skate_ratio`` the like-for-like
  yardstick: per switch, the worst window of the same length
  in either of its two takes' own frames (a take's skate is uneven over its cycle: a window's worst is higher
  than its whole), the worst switch;
* ``switch_velocity_jump_rad_s`` / ``switch_accel_jump_rad_s2``: the largest jump of any joint's angular velocity
  (frame-to-frame rotation ``2 log(q_(f+1) q_f^-1) fps``) and of its angular acceleration from one frame to the next
  within those windows;
* ``settle_s``: the longest time after a switch until every joint's global rotation stays within
  :data:`anim_core.methods.transitions.SETTLE_DEG` of the incoming take's.

The composite plays on the skeleton (and character) of its first take (a sequence) or its base; every other take
is re-expressed on it first (:func:`rebound`: each take is bound on its own, and a take's rotations played on
another's skeleton put its feet up to 0.3 m elsewhere).  Foot metrics of
a composite are taken in world space on the non-periodic frames (its speed changes, so no single ground velocity
describes it).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter1d

from ..math import contacts
from ..math.clip import KeyframeClip, Pose
from ..math.quat import canonicalize, quat_conj, quat_log, quat_mul
from ..methods.base import Animation
from ..methods.composite_builders import BlendAnimation, LayeredAnimation, SequenceAnimation, SequenceClip
from ..methods.conditions import Condition
from ..methods.transitions import CompositeError, joint_mask
from ..rig.character import UP, RetargetedCharacter, rebind
from . import fidelity, metrics
from .build import place_on_floor
from .entry import ConfigError, Source
from .measure import clip_feet, measure
from .record import BuiltClip
from .reference import reference_animation, source_skate, source_skating_frames, worst_window

Array = NDArray[np.float64]
WINDOW_BEFORE_S = 0.25
WINDOW_AFTER_S = 0.25
MIN_WINDOW_S = 0.25
#: Seconds (Gaussian sigma) over which a sequence's forward velocity is smoothed into the floor's travel.
FLOOR_SMOOTHING_S = 0.3


@dataclass(frozen=True)
class LayerSpec:
    """One layer of a layered composite: the take, its joint set, ``override`` or ``additive``, and for additive the
    reference pose: ``"first"`` (the layer's first frame), ``"rest"`` (the skeleton's rest pose) or a frame number
    of the layer's clip."""

    animation: str
    joints: str
    mode: str
    reference_pose: str | int = "first"


@dataclass(frozen=True)
class CompositeSpec:
    """A composite of a clip-set file: ``segments`` ``((take, seconds), ...)``, ``root_motion`` and ``entry`` for a
    sequence, ``base`` and ``layers`` for a layered animation, the two takes of a ``blend``."""

    name: str
    form: str  # "sequence" | "layered" | "blend"
    segments: tuple[tuple[str, float], ...] = ()
    root_motion: str | None = None
    base: str | None = None
    layers: tuple[LayerSpec, ...] = ()
    entry: str = "matched"
    blend: tuple[str, ...] = ()

    @property
    def takes(self) -> tuple[str, ...]:
        names = [n for n, _ in self.segments] + ([self.base] if self.base else []) + list(self.blend)
        names += [la.animation for la in self.layers]
        return tuple(dict.fromkeys(names))


def _angular_jumps(local: Array, fps: int, frames: Array) -> tuple[float, float]:
    """Largest jump of angular velocity (rad/s) and of angular acceleration (rad/s^2) of any joint between
    consecutive frames among ``frames`` (indices into the periodic sequence ``local (T, J, 4)``)."""
    t = local.shape[0]
    step = canonicalize(quat_mul(np.roll(local, -1, axis=0), quat_conj(local)))
    omega = 2.0 * quat_log(step) * fps  # (T, J, 3): frame f to f + 1
    d_omega = np.linalg.norm(omega - np.roll(omega, 1, axis=0), axis=-1)  # jump into frame f
    alpha = (omega - np.roll(omega, 1, axis=0)) * fps
    d_alpha = np.linalg.norm(alpha - np.roll(alpha, 1, axis=0), axis=-1)
    f = np.asarray(frames) % t
    return float(d_omega[f].max()), float(d_alpha[f].max())


def transition_metrics(c: BuiltClip, source_skate: float,
                       skating: Sequence[NDArray[np.bool_]] = ()) -> dict[str, float | None]:
    """The transition metrics of a sequence's clip (module docstring); empty for any other clip.  ``skating``:
    per segment of the sequence, its take's frames where a foot skates (:func:`source_skating_frames`)."""
    clip = c.clip
    if not isinstance(clip, SequenceClip):
        return {}
    yardstick = []
    feet, contact = clip_feet(c)
    window = max(clip.transition_s, MIN_WINDOW_S)
    skate, slide, v_jump, a_jump = [], [], [], []
    # Down is judged against the whole loop's standing heights, as the yardstick judges a take's frames against the
    # whole take's (a window's own lowest frames need not be standing ones: a window mostly in the air).
    standing = contacts.standing_heights(c.world_positions[:, feet], UP)
    for s in clip.switch_times:
        frames = np.arange(round((s - WINDOW_BEFORE_S) * c.fps), round((s + window + WINDOW_AFTER_S) * c.fps))
        # World positions over the window, unwrapped across the loop's seam by the loop's travel.
        travel = np.floor(frames / c.n_frames)[:, None, None] * (clip.velocity * clip.duration)
        pos = c.world_positions[frames % c.n_frames] + travel
        skate.append(contacts.foot_skate_ratio(pos[:, feet], c.fps, UP, periodic=False, standing=standing))
        if skating:  # switch k enters segment k from segment k - 1 (the first from the last: the loop's)
            k = clip.switch_times.index(s)
            yardstick.append(max(worst_window(skating[i], len(frames)) for i in (k - 1, k)))
        slide.append(metrics.foot_metrics(pos[:, feet], contact, c.fps, periodic=False)["foot_slide_mm"])
        jv, ja = _angular_jumps(c.local_rotations, c.fps, frames)
        v_jump.append(jv)
        a_jump.append(ja)
    return {"transition_foot_skate_ratio": max(skate), "transition_foot_slide_mm": max(slide),
            "source_foot_skate_ratio": source_skate,
            "source_window_foot_skate_ratio": max(yardstick) if yardstick else None,
            "switch_velocity_jump_rad_s": max(v_jump),
            "switch_accel_jump_rad_s2": max(a_jump), "settle_s": max(clip.settle_s)}


def format_transitions(clips: Sequence[BuiltClip]) -> str:
    """The transition metrics of the clips that have them, as a table (empty without a sequence)."""
    rows = [c for c in clips if "switch_velocity_jump_rad_s" in c.metrics]
    if not rows:
        return ""
    width = max(16, *(len(c.id) for c in rows))
    lines = [f"\n{'transition':{width}} {'skate':>6} {'source':>6} {'src win':>7} {'slide mm':>8} {'dw rad/s':>9} "
             f"{'da rad/s2':>10} {'settle s':>8}"]
    for c in rows:
        m = c.metrics
        window = m.get("source_window_foot_skate_ratio")
        lines.append(f"{c.id:{width}} {m['transition_foot_skate_ratio']:6.3f} {m['source_foot_skate_ratio']:6.3f} "
                     f"{'-' if window is None else format(window, '7.3f'):>7} "
                     f"{m['transition_foot_slide_mm']:8.1f} {m['switch_velocity_jump_rad_s']:9.1f} "
                     f"{m['switch_accel_jump_rad_s2']:10.0f} {m['settle_s']:8.2f}")
    return "\n".join(lines) + "\n"


def _reference_pose(spec: LayerSpec, animation: Any, rest: Array, where: str) -> Array | None:
    if spec.mode != "additive" or spec.reference_pose == "first":
        return None
    if spec.reference_pose == "rest":
        return rest
    frames = animation.reference.rotations
    if not isinstance(spec.reference_pose, int) or not 0 <= spec.reference_pose < frames.shape[0]:
        raise ConfigError(f"{where} reference_pose: 'first', 'rest' or a frame 0..{frames.shape[0] - 1} of "
                          f"{spec.animation!r}, got {spec.reference_pose!r}")
    return frames[spec.reference_pose]


def rest_pose(source: RetargetedCharacter, target: RetargetedCharacter) -> Array:
    """``(J, 4)``: the rest pose of a take bound by ``source`` (identity rotations) on ``target``'s skeleton, the
    reference an additive layer's ``"rest"`` means."""
    return rebind(Pose(np.asarray(source.skeleton.rest_rotations), np.zeros(3)), source, target).rotations


def rebound(animation: Animation, source: RetargetedCharacter, target: RetargetedCharacter) -> Animation:
    """``animation`` (a take's reference on ``source``'s skeleton) re-expressed on ``target``'s skeleton
    (:func:`anim_core.rig.character.rebind`): the same mesh motion, so that takes bound on their own can be mixed."""
    if source is target:
        return animation
    ref = animation.reference
    pose = rebind(Pose(ref.rotations, ref.root_translation), source, target)
    clip = KeyframeClip(target.skeleton, ref.times, pose.rotations, pose.root_translation, ref.mode, ref.in_place,
                        ref.up_axis, ref.name)
    return replace(animation, reference=clip, bind_rotations=target.mirror_bind(pose.rotations))


def build_composite(spec: CompositeSpec, sources: Mapping[str, Source], fps: int, conditions: Sequence[Condition],
                    progress: Callable[[str], None] = lambda _msg: None) -> list[BuiltClip]:
    """One clip per condition that applies to the composite's form (the reference first), measured."""
    where = f"[animations.{spec.name}]"
    first = spec.takes[0]
    source = sources[first]
    own = {name: reference_animation(sources[name], fps)[0] for name in spec.takes}
    refs = {name: rebound(own[name], sources[name].character, source.character) for name in spec.takes}
    skeleton = refs[first].reference.skeleton
    if spec.form == "blend":
        animation: Any = BlendAnimation(spec.name, refs[spec.blend[0]], refs[spec.blend[1]], fps)
    elif spec.form == "sequence":
        animation = SequenceAnimation(spec.name, tuple((refs[n], s) for n, s in spec.segments),
                                           spec.root_motion, fps, spec.entry)  # type: ignore[arg-type]
    else:
        layers, rests = [], []
        for k, layer in enumerate(spec.layers):
            try:
                mask = joint_mask(skeleton, layer.joints)
            except CompositeError as exc:
                raise ConfigError(f"{where} layers #{k + 1} {exc}") from None
            take = refs[layer.animation]
            rests.append(rest_pose(sources[layer.animation].character, source.character))
            layers.append((take, mask, layer.mode, _reference_pose(layer, take, rests[-1], f"{where} layers #{k + 1}")))
        animation = LayeredAnimation(spec.name, refs[first], tuple(layers), fps, tuple(rests))
    applying = [c for c in conditions if c.applies(spec.form)]
    ordered = [*(c for c in applying if c.is_reference), *(c for c in applying if not c.is_reference)]
    skate = max(source_skate(sources[n], sources[n].time_of(sources[n].config.frames[0]),
                             sources[n].time_of(sources[n].config.frames[1]), fps) for n in spec.takes)
    skating = [source_skating_frames(sources[n], sources[n].time_of(sources[n].config.frames[0]),
                                     sources[n].time_of(sources[n].config.frames[1]), fps)
               for n, _ in spec.segments] if spec.form == "sequence" else []
    built: list[BuiltClip] = []
    for condition in ordered:
        clip_id = f"{spec.name}-{condition.id}"
        try:
            clip = condition.build(animation)
        except (CompositeError, ValueError) as exc:
            raise ConfigError(f"[[conditions]] {condition.id!r} on animation {spec.name!r}: {exc}") from None
        n_frames = clip.n_keys - 1 if clip.mode == "loop" else 2 * (clip.n_keys - 1)
        progress(f"  {clip_id}: {n_frames} frames")
        pose = clip.sample(np.arange(n_frames) / fps)
        built.append(BuiltClip(clip_id, spec.name, "other", condition.id, condition.method, condition.params_dict(),
                               clip, np.asarray(clip.key_times), np.asarray(clip.key_rotations), fps, n_frames,
                               clip.mode, clip.in_place,
                               float(np.linalg.norm(clip.velocity)) if clip.in_place else 0.0,
                               {"composite": spec.form, "takes": list(spec.takes),
                                **({"sequence": [[n, s] for n, s in spec.segments]} if spec.segments else {})},
                               source.character, pose.rotations, pose.root_translation,
                               *source.character.skeleton.forward_kinematics(*pose)))
    if spec.form == "blend":  # each its own motion (at weight 1 the second take), speed and length: placed on the
        # floor by its own feet and measured on its own (no frame-by-frame reference)
        return _gated(spec, [measure(place_on_floor([c]), np.asarray(c.clip.velocity) if c.in_place else np.zeros(3),
                                     "other", skate)[0] for c in built], own, sources)
    placed = place_on_floor(built)
    if spec.form == "layered":  # plays as its base does (in place: a treadmill at the base's speed)
        base = placed[0].clip
        ground = np.asarray(base.velocity) if base.in_place else np.zeros(3)
        return _gated(spec, measure(placed, ground, "other", skate), own, sources)
    # A composite's speed changes along it: measured on its frames as they are, against a still ground.
    # The periodic metrics (seam, jerk, phase) on one period with the loop's travel spread over it, as a take's
    # travelling loop is measured; the feet then in world space on the frames as they are.
    views = []
    for c in placed:
        shift = np.asarray(c.clip.velocity) * (np.arange(c.n_frames) / fps)[:, None]
        views.append(replace(c, root_positions=c.root_positions - shift,
                             world_positions=c.world_positions - shift[:, None]))
    measured = [replace(c, metrics=v.metrics) for c, v in
                zip(placed, measure(views, np.zeros(3), "other", skate), strict=True)]
    out = []
    for c in measured:
        m = dict(c.metrics)
        feet, contact = clip_feet(c)
        m.update(metrics.foot_metrics(c.world_positions[:, feet], contact, fps, periodic=False))
        m["foot_skate_ratio"] = contacts.foot_skate_ratio(c.world_positions[:, feet], fps, UP, periodic=False)
        m.update(transition_metrics(c, skate, skating))
        out.append(_shown_in_place(replace(c, metrics=m)))
    return _gated(spec, out, own, sources)


def _alone(spec: CompositeSpec, c: BuiltClip) -> list[tuple[str, NDArray[np.intp]]]:
    """The frames of a sequence's clip that show one take alone, per segment: from its switch (once the switch has
    settled, :attr:`SequenceClip.settle_s`) to the next switch; none for a layered or blended clip."""
    clip = c.clip
    if not isinstance(clip, SequenceClip):
        return []
    starts = [*clip.switch_times, clip.duration]  # segment k starts at switch k (the first: the loop's own)
    return [(name, np.arange(round((starts[k] + clip.settle_s[k]) * c.fps), round(starts[k + 1] * c.fps)))
            for k, (name, _) in enumerate(spec.segments)]


def _gated(spec: CompositeSpec, clips: list[BuiltClip], own: Mapping[str, Animation],
           sources: Mapping[str, Source]) -> list[BuiltClip]:
    """The fidelity gate on a composite's clips (:func:`anim_core.clips.fidelity.check_composite`): held against
    its takes as each plays on its own skeleton.  A failure raises :class:`ConfigError` naming the composite, the
    condition and the frame, unless a take accepts being unfaithful (then the clips are marked)."""
    poses = {n: a.reference.skeleton.forward_kinematics(a.reference.rotations, a.reference.root_translation)[1]
             for n, a in own.items()}
    accept = any(sources[n].config.accept_unfaithful for n in spec.takes)
    out = []
    for c in clips:
        check = fidelity.check_composite(c.world_positions, c.character.contact_heights, poses[spec.takes[0]],
                                         [(n, frames, poses[n]) for n, frames in _alone(spec, c)])
        if check.problems and not accept:
            raise ConfigError(f"[animations.{spec.name}] condition {c.condition!r} fails the fidelity gate: "
                              f"{'; '.join(check.problems)}")
        out.append(replace(c, metrics={**c.metrics, **check.as_metrics(), "unfaithful": float(not check.ok)},
                           fidelity=check))
    return out


def _shown_in_place(c: BuiltClip) -> BuiltClip:
    """A travelling sequence's frames as the renderer shows them: its travel along +Z (the takes' heading) taken off
    the stored positions and kept as ``floor_travel``, which the renderer moves the ground by; the metrics were
    measured on the travelling frames before.  The travel is the root's forward velocity smoothed over
    :data:`FLOOR_SMOOTHING_S` (periodic) and integrated, so a walk's surge within its cycle and an idle's sway stay
    on the body, as on a take's treadmill (its mean speed)."""
    clip = c.clip
    step = np.diff(np.append(c.root_positions[:, 2], c.root_positions[0, 2] + clip.velocity[2] * clip.duration))
    if not np.any(step):
        return c
    smooth = gaussian_filter1d(step, FLOOR_SMOOTHING_S * c.fps, mode="wrap")
    travel = np.concatenate([[0.0], np.cumsum(smooth)[:-1]])
    shift = np.zeros_like(c.root_positions)
    shift[:, 2] = travel
    return replace(c, root_positions=c.root_positions - shift, world_positions=c.world_positions - shift[:, None],
                   floor_travel=travel)
