"""The methods of issue 16, registered in the condition registry (:mod:`anim_core.conditions`) like ``keyframe``
and ``hybrid``: usable in any clip-set file as ``[[conditions]] id/method/params``.

* ``hybrid_ik`` (:class:`HybridIkParams`): the hybrid of ``increment`` with locked feet (:mod:`anim_core.footlock`):
  the steps detected on the reference (``contact_source = "reference"``), or each also grown by the hybrid's own
  contact frames next to it (``"union"``, default), below ``clearance_m``; held by two-bone leg IK, each swing
  making up the difference between two holds over at least ``2 * blend_frames + 1`` frames; with
  ``swing_clearance`` each foot raised to at least the reference's foot height (off by default: it copies a
  reference's own seam jump into a loop whose hybrid has none).  ``conditions16.toml`` holds ``"reference"`` with
  the clearance, which meets every gait goal of issue 16.
* ``hybrid_c2`` (:class:`HybridC2Params`): the hybrid of ``increment`` on the C2 spline (:mod:`anim_core.c2spline`)
  through the same keys.  A crouch follows its keys with the spring, not SQUAD: at increment 0 that is one geodesic
  driven by the closed-form spring, C2 already, so its ``hybrid_c2`` is the spring hybrid itself; a crouch has no C2
  clip with more keys (an error naming the condition).
* ``reduced`` (:class:`ReducedParams`): the reference with the fewest keys keeping every joint's global rotation
  within ``epsilon_deg`` (:func:`anim_core.compression.reduce_keys`, greedy).
* ``quantized`` (:class:`QuantizedParams`): the reference (or, with ``reduced_epsilon_deg``, its reduction) stored at
  ``bits`` bits per quaternion component (:func:`anim_core.compression.quantized_clip`), dequantized at playback.

Stored bytes (the ``bytes`` metric) of ``hybrid_ik`` and ``quantized`` differ from a clip of float32 keys; their
``stored_bytes`` functions are registered with them.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from .c2spline import C2Clip, c2_from_squad
from .clip import KeyframeClip
from .compression import QuantizedClip, keyframe_bytes, quantized_clip, reduce_keys
from .conditions import Animation, HybridParams, Params, build_hybrid, register
from .footlock import FootLockedClip, lock_feet
from .hybrid import SpringClip, SquadClip

EPSILON = Field(gt=0, le=45, description="largest global-rotation error of any joint at any frame, degrees")


class HybridIkParams(Params):
    increment: int = Field(ge=0, le=4, description="extra keys per interval, as for the hybrid")
    blend_frames: int = Field(3, ge=0, le=30, description="frames of the blend in and out at contact boundaries: "
                              "holds closer than twice this are joined")
    clearance_m: float = Field(0.05, gt=0, le=0.5, description="a foot is down below this height above the floor")
    contact_source: Literal["union", "reference"] = Field(
        "union", description="steps of the reference alone, or each grown by the hybrid's contact frames beside it")
    swing_clearance: bool = Field(False, description="raise each foot to at least the reference's foot height "
                                  "above the floor")


class HybridC2Params(Params):
    increment: int = Field(ge=0, le=4, description="extra keys per interval, as for the hybrid")


class ReducedParams(Params):
    epsilon_deg: float = EPSILON


class QuantizedParams(Params):
    bits: int = Field(ge=2, le=16, description="bits per quaternion component")
    reduced_epsilon_deg: float | None = Field(None, gt=0, le=45,
                                              description="reduce the keys first to within this many degrees")


def _hybrid_ik_bytes(clip: FootLockedClip, params: HybridIkParams) -> int:
    # The hybrid's keys plus an ankle target (3 float32) and a weight (1 float32) per leg and frame, and each
    # knee's hinge (3 float32) and the soft reach (1 float32).
    return (keyframe_bytes(clip.key_times.size, clip.skeleton.n_joints) + int(clip.weights.size * 4 * 4)
            + int(clip.hinges.size * 4) + 4)


def _quantized_bytes(clip: KeyframeClip, params: QuantizedParams) -> int:
    return keyframe_bytes(clip.key_times.size, clip.skeleton.n_joints, params.bits)


@register("hybrid_ik", HybridIkParams, stored_bytes=_hybrid_ik_bytes)
def build_hybrid_ik(animation: Animation, params: HybridIkParams) -> FootLockedClip:
    from .clipset import FEET, LEGS  # the character's joint names; clipset imports this registry

    base = build_hybrid(animation, HybridParams(increment=params.increment))
    sk = animation.reference.skeleton
    legs = [tuple(int(j) for j in sk.indices(leg)) for leg in LEGS]
    feet = [[int(j) for j in sk.indices(foot)] for foot in FEET]
    return lock_feet(base, animation.reference, legs, feet, animation.fps, params.blend_frames, params.clearance_m,
                     up_axis=animation.reference.up_axis, contact_source=params.contact_source,
                     swing_clearance=params.swing_clearance)


@register("hybrid_c2", HybridC2Params)
def build_hybrid_c2(animation: Animation, params: HybridC2Params) -> C2Clip | SpringClip:
    base = build_hybrid(animation, HybridParams(increment=params.increment))
    if isinstance(base, SquadClip):
        return c2_from_squad(base)
    if params.increment == 0:
        return base  # one geodesic driven by the closed-form spring: C2 already
    raise ValueError(f"a {animation.kind} follows its keys with the spring: hybrid_c2 exists for it at increment 0 "
                     f"only (the spring hybrid 0, C2 already), got increment {params.increment}")


@register("reduced", ReducedParams)
def build_reduced(animation: Animation, params: ReducedParams) -> KeyframeClip:
    return reduce_keys(animation.reference, params.epsilon_deg)


@register("quantized", QuantizedParams, stored_bytes=_quantized_bytes)
def build_quantized(animation: Animation, params: QuantizedParams) -> QuantizedClip:
    ref = animation.reference
    src = ref if params.reduced_epsilon_deg is None else reduce_keys(ref, params.reduced_epsilon_deg)
    return quantized_clip(src, params.bits)[0]
