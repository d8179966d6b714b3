"""Builders of composite animations (issue 39), registered by :mod:`anim_core.methods.conditions` with
``applies_to``: what a sequence or a layered animation hands a builder, the transition methods' parameter models
and builders, and the reference of every form (:func:`build_reference`).

* ``keyframe`` (the reference): a take's own keys; a sequence's takes switched by a cut; a layered animation's
  layers as described.
* ``cut``: a sequence's takes switched without blending (the same clip as a sequence's reference).
* ``crossfade`` (``duration_ms``, ``curve`` linear/smoothstep, ``interp`` nlerp/slerp) and ``inertialization``
  (``duration_ms``; Bollo's quintic per quaternion component): :mod:`anim_core.methods.transitions`; both hold the
  feet through the transition unless ``foot_lock = false`` (:mod:`anim_core.methods.transition_feet`).
* ``parametric`` (``weight`` 0..1, ``interp``, ``sync`` feet/phase): a blend's two takes mixed after time alignment
  (the feet's landings synced by default); its reference is the first take.
* ``override`` (``space`` local/model) and ``additive`` (``reference_pose`` first/rest/a frame, ``weight``): a
  layered animation with every layer applied in that mode, whatever mode the clip-set file gives it, so two ways
  of layering one take are conditions of one animation (``studies/layers.toml``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from ..math.clip import KeyframeClip
from ..rig.character import FEET, LEGS
from .base import Animation, Params
from .transition_feet import FeetLock, landings
from .transitions import (
    Composite,
    CompositeError,
    Entry,
    RootMotion,
    TransitionSpec,
    compose_sequence,
    cycle_from,
    entry_time,
    layered,
    parametric,
)

#: The longest transition a condition may ask for (a crossfade must also fit in the shortest segment).
MAX_TRANSITION_MS = 5000


@dataclass(frozen=True, eq=False)
class SequenceAnimation:
    """A sequence as a builder receives it: each take's :class:`Animation` with its seconds, the root-motion rule
    (None: the takes agree), the frame rate, where each take is entered (:func:`compose_sequence`'s ``entry``)."""

    name: str
    segments: tuple[tuple[Animation, float], ...]
    root_motion: RootMotion | None
    fps: int
    entry: Entry = "matched"


@dataclass(frozen=True, eq=False)
class LayeredAnimation:
    """A layered animation: the base take and its layers ``(take, joint mask (J,), mode, reference pose (J, 4) or
    None)``, all on the base's skeleton; ``rests``: each layer take's rest pose there (``(J, 4)``, what an additive
    ``"rest"`` reference means; empty: the skeleton's rest pose)."""

    name: str
    base: Animation
    layers: tuple[tuple[Animation, NDArray[np.bool_], str, NDArray[np.float64] | None], ...] = field(repr=False)
    fps: int = 30
    rests: tuple[NDArray[np.float64], ...] = field(default=(), repr=False)


@dataclass(frozen=True, eq=False)
class BlendAnimation:
    """Two looping takes that ``parametric`` mixes (a clip-set file's ``blend = ["A", "B"]``): ``a`` (weight 0,
    the reference) and ``b``, at ``fps`` frames per second."""

    name: str
    a: Animation
    b: Animation
    fps: int = 30


@dataclass(frozen=True, eq=False)
class SequenceClip(KeyframeClip):
    """A composed sequence: a looping keyframe clip with its switch times (s) and the seconds each switch takes to
    settle (:class:`~anim_core.methods.transitions.Composite`), for the transition metrics."""

    switch_times: tuple[float, ...] = ()
    settle_s: tuple[float, ...] = ()
    transition_s: float = 0.0


class CutParams(Params):
    """A cut has no parameters."""


class CrossfadeParams(Params):
    duration_ms: int = Field(ge=1, le=MAX_TRANSITION_MS, description="length of the blend, milliseconds")
    curve: Literal["linear", "smoothstep"] = Field("linear", description="weight over the blend")
    interp: Literal["nlerp", "slerp"] = Field("nlerp", description="per-joint rotation blend")
    foot_lock: bool = Field(True, description="hold the feet in contact through the blend (two-bone IK)")


class InertializationParams(Params):
    duration_ms: int = Field(ge=1, le=MAX_TRANSITION_MS, description="time for the offsets to decay, milliseconds")
    foot_lock: bool = Field(True, description="hold the feet in contact through the transition (two-bone IK)")


class OverrideParams(Params):
    space: Literal["local", "model"] = Field("local", description="local rotations, or the set's top joints kept in "
                                                                   "the layer's model space")


class AdditiveParams(Params):
    reference_pose: Literal["first", "rest"] | int = Field(
        "first", description="the pose the delta is taken against: the layer's first frame, the rest pose or a frame "
                             "number of the layer")
    weight: float = Field(1.0, ge=0.0, le=2.0, description="how much of the delta is added (1: all of it)")


class ParametricParams(Params):
    weight: float = Field(ge=0, le=1, description="share of the second take: 0 is the first, 1 the second")
    interp: Literal["nlerp", "slerp"] = Field("slerp", description="per-joint rotation blend")
    sync: Literal["feet", "phase"] = Field("feet", description="time alignment: each foot's landing together, or "
                                                               "one linear phase")


def feet_lock(skeleton: Any) -> FeetLock:
    """The character's legs and feet (:data:`anim_core.rig.character.LEGS`, ``FEET``) as joint indices."""
    return FeetLock(tuple(tuple(int(j) for j in skeleton.indices(leg)) for leg in LEGS),  # type: ignore[misc]
                    tuple(tuple(int(j) for j in skeleton.indices(foot)) for foot in FEET))


def _compose(animation: SequenceAnimation, spec: TransitionSpec, foot_lock: bool = False) -> SequenceClip:
    segments = [(a.reference, seconds) for a, seconds in animation.segments]
    lock = feet_lock(segments[0][0].skeleton) if foot_lock else None
    comp: Composite = compose_sequence(segments, animation.fps, spec, animation.root_motion, animation.name,
                                       animation.entry, lock)
    c = comp.clip
    return SequenceClip(c.skeleton, c.times, c.rotations, c.root_translation, c.mode, c.in_place, c.up_axis,
                        c.name, tuple(f / animation.fps for f in comp.switch_frames), comp.settle_s, spec.duration_s)


def build_cut(animation: SequenceAnimation, params: CutParams) -> SequenceClip:
    return _compose(animation, TransitionSpec("cut"))


def build_crossfade(animation: SequenceAnimation, params: CrossfadeParams) -> SequenceClip:
    return _compose(animation, TransitionSpec("crossfade", params.duration_ms / 1000.0, params.curve, params.interp),
                    params.foot_lock)


def build_inertialization(animation: SequenceAnimation, params: InertializationParams) -> SequenceClip:
    return _compose(animation, TransitionSpec("inertialization", params.duration_ms / 1000.0), params.foot_lock)


def build_parametric(animation: BlendAnimation, params: ParametricParams) -> KeyframeClip:
    """The two takes mixed by ``weight`` (:func:`~anim_core.methods.transitions.parametric`) after time alignment:
    the second take's cycle entered at its frame nearest the first take's first pose
    (:func:`~anim_core.methods.transitions.entry_time`: the same foot forward), then with ``sync = "feet"`` each
    foot's landing in the one synced with its landing in the other
    (:func:`~anim_core.methods.transition_feet.landings` as sync markers), with ``"phase"`` both mapped onto one
    linear phase (a weight of 0 or 1 is the take as it is either way)."""
    a, b = animation.a.reference, animation.b.reference
    b = cycle_from(b, entry_time(a.sample(np.array([0.0])), b, animation.fps))
    lock = feet_lock(a.skeleton)
    markers = None
    if params.sync == "feet":
        markers = landings(a, lock), landings(b, lock)
        if markers[0] is None or markers[1] is None:
            which = " and ".join(n for n, m in zip((animation.a.name, animation.b.name), markers, strict=True)
                                 if m is None)
            raise CompositeError(f"sync = 'feet': {which} does not land each foot once per cycle; give "
                                 "sync = 'phase'")
    return parametric(a, b, params.weight, animation.fps, params.interp, markers)


def _relayer(animation: LayeredAnimation, mode: str, reference: NDArray[np.float64] | None = None,
             space: Literal["local", "model"] = "local", weight: float = 1.0) -> KeyframeClip:
    return layered(animation.base.reference, [(a.reference, mask, mode, reference if mode == "additive" else None)
                                              for a, mask, _, _ in animation.layers],
                   animation.fps, animation.name, space, weight)


def build_override(animation: LayeredAnimation, params: OverrideParams) -> KeyframeClip:
    return _relayer(animation, "override", space=params.space)


def build_additive(animation: LayeredAnimation, params: AdditiveParams) -> KeyframeClip:
    """Every layer additive against ``params.reference_pose``: ``"first"`` (each layer's first frame), ``"rest"``
    (each layer take's rest pose, :attr:`LayeredAnimation.rests`) or a frame of each layer's clip (out of range:
    :class:`CompositeError`)."""
    ref = params.reference_pose
    if ref == "first":
        return _relayer(animation, "additive", None, weight=params.weight)
    if ref == "rest":
        rests = animation.rests or (np.asarray(animation.base.reference.skeleton.rest_rotations),) * len(
            animation.layers)
        return layered(animation.base.reference, [(a.reference, mask, "additive", rest) for (a, mask, _, _), rest
                                                  in zip(animation.layers, rests, strict=True)],
                       animation.fps, animation.name, weight=params.weight)
    clips = [a.reference for a, _, _, _ in animation.layers]
    short = min(c.rotations.shape[0] for c in clips)
    if not 0 <= ref < short:
        raise CompositeError(f"reference_pose: a frame 0..{short - 1} of every layer, got {ref}")
    return layered(animation.base.reference, [(c, mask, "additive", c.rotations[ref]) for c, (_, mask, _, _)
                                              in zip(clips, animation.layers, strict=True)],
                   animation.fps, animation.name, weight=params.weight)


def build_reference(animation: Any, params: Params) -> Any:
    """The reference of every form: a take's keys, a sequence's cut, a layered animation's layers, a blend's first
    take."""
    if isinstance(animation, SequenceAnimation):
        return build_cut(animation, CutParams())
    if isinstance(animation, LayeredAnimation):
        return layered(animation.base.reference, [(a.reference, mask, mode, ref) for a, mask, mode, ref
                                                  in animation.layers], animation.fps, animation.name)
    if isinstance(animation, BlendAnimation):
        return animation.a.reference
    return animation.reference


#: (name, parameter model, builder, forms it applies to), registered by :mod:`anim_core.methods.conditions`.
COMPOSITE_METHODS: tuple[tuple[str, type[Params], Callable[[Any, Any], Any], tuple[str, ...]], ...] = (
    ("cut", CutParams, build_cut, ("sequence",)),
    ("crossfade", CrossfadeParams, build_crossfade, ("sequence",)),
    ("inertialization", InertializationParams, build_inertialization, ("sequence",)),
    ("parametric", ParametricParams, build_parametric, ("blend",)),
    ("override", OverrideParams, build_override, ("layered",)),
    ("additive", AdditiveParams, build_additive, ("layered",)),
)
