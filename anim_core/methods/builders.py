"""The built-in methods: each one's parameter model and builder (registered, in one list, by
:mod:`anim_core.methods.conditions`), usable in any clip-set file as ``[[conditions]] id/method/params``.

* ``keyframe`` (:class:`KeyframeParams`): the reference itself.
* ``hybrid`` (:class:`HybridParams`): the thesis method, :func:`build_hybrid`.

* ``hybrid_ik`` (:class:`HybridIkParams`): the hybrid of ``increment`` with locked feet
  (:mod:`anim_core.methods.footlock`):
  the steps detected on the reference (``contact_source = "reference"``), or each also grown by the hybrid's own
  contact frames next to it (``"union"``, default), below ``clearance_m``; held by two-bone leg IK only where
  the leg reaches the foothold within 10 degrees of the hybrid's thigh and knee, each swing making up the
  difference between two holds over at least ``2 * blend_frames + 1`` frames within the same 10 degrees; with
  ``swing_clearance`` each foot raised to at least the reference's foot height (off by default: it copies a
  reference's own seam jump into a loop whose hybrid has none).  ``conditions16.toml`` holds ``"reference"`` with
  the clearance, which meets every gait goal of issue 16.
* ``hybrid_c2`` (:class:`HybridC2Params`): the hybrid of ``increment`` on the C2 spline
  (:mod:`anim_core.methods.c2spline`)
  through the same keys.  A crouch follows its keys with the spring, not SQUAD: at increment 0 that is one geodesic
  driven by the closed-form spring, C2 already, so its ``hybrid_c2`` is the spring hybrid itself; a crouch has no C2
  clip with more keys (an error naming the condition).
* ``reduced`` (:class:`ReducedParams`): the reference with the fewest keys keeping every joint's global rotation
  within ``epsilon_deg`` (:func:`anim_core.methods.compression.reduce_keys`, greedy).
* ``quantized`` (:class:`QuantizedParams`): the reference (or, with ``reduced_epsilon_deg``, its reduction) stored at
  ``bits`` bits per quaternion component (:func:`anim_core.methods.compression.quantized_clip`), dequantized at
  playback.

* ``update_rate`` (:class:`UpdateRateParams`): the reference's pose updated ``rate`` times a second and held in
  between, on its own frame grid (:class:`anim_core.methods.lod.HeldClip`); a rate at or above the clip set's
  ``fps`` would be the reference and is refused.
* ``bone_lod`` (:class:`BoneLodParams`): the joints of a named set (``joints``: fingers, toes, neck) or deeper than
  ``depth`` held at their bind pose, the others the reference's keys (:func:`anim_core.methods.lod.bone_lod`).
* ``skin_influences`` (:class:`SkinInfluencesParams`): the reference's motion rendered with the ``influences``
  strongest skin weights per vertex (a render-time condition: :func:`skin_influences_render`).

Stored bytes (the ``bytes`` metric) of ``hybrid_ik``, ``quantized`` and ``bone_lod`` (its held joints store one
pose) differ from a clip of float32 keys; their ``stored_bytes`` functions are registered with them.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from ..math.clip import KeyframeClip
from ..rig.character import FEET, LEGS
from ..rig.mirror import Mirror
from .base import Animation, Params
from .c2spline import C2Clip, c2_from_squad
from .compression import QuantizedClip, keyframe_bytes, quantized_clip, reduce_keys
from .footlock import FootLockedClip, lock_feet
from .hybrid import SpringClip, SquadClip, build_crouch, build_gait, build_idle, build_other
from .lod import BoneLodClip, HeldClip, JointSet, bone_lod, frozen_joints


class KeyframeParams(Params):
    """The reference has no parameters."""


class HybridParams(Params):
    increment: int = Field(ge=0, le=4, description="extra keys per interval between the base keys (thesis: 0..2)")


def build_keyframe(animation: Animation, params: KeyframeParams) -> KeyframeClip:
    """The reference itself: the dense keys on the grid."""
    return animation.reference


def build_hybrid(animation: Animation, params: HybridParams) -> SquadClip | SpringClip:
    """The thesis's hybrid: a gait mirrors half a cycle of keys onto the other half (SQUAD), a crouch follows its
    keys with the spring, an idle sways on SQUAD between its two extremes, any other motion goes through its picked
    keys on SQUAD, loop or ping-pong as its reference plays (:mod:`anim_core.methods.hybrid`)."""
    ref, keys = animation.reference, list(animation.key_times)
    if animation.kind == "gait":
        # build_gait measures the travel from its source, so it gets the reference travelling.
        travelling = KeyframeClip(ref.skeleton, ref.times, ref.rotations, ref.root_translation, ref.mode,
                                  False, ref.up_axis, ref.name)
        mirror = Mirror(ref.skeleton, bind=animation.bind_rotations)
        return build_gait(travelling, keys, animation.period, increment=params.increment, mirror=mirror,
                          in_place=animation.in_place, name=animation.name)
    if animation.kind == "crouch":
        return build_crouch(ref, keys, increment=params.increment, duration=animation.period, time_scale=None,
                            name=animation.name)
    if animation.kind == "idle":
        return build_idle(ref, keys, increment=params.increment, name=animation.name)
    return build_other(ref, keys, increment=params.increment, in_place=animation.in_place, name=animation.name)


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


def hybrid_ik_bytes(clip: FootLockedClip, params: HybridIkParams) -> int:
    # The hybrid's keys plus an ankle target (3 float32) and a weight (1 float32) per leg and frame, and each
    # knee's hinge (3 float32) and the soft reach (1 float32).
    return (keyframe_bytes(clip.key_times.size, clip.skeleton.n_joints) + int(clip.weights.size * 4 * 4)
            + int(clip.hinges.size * 4) + 4)


def quantized_bytes(clip: KeyframeClip, params: QuantizedParams) -> int:
    return keyframe_bytes(clip.key_times.size, clip.skeleton.n_joints, params.bits)


def build_hybrid_ik(animation: Animation, params: HybridIkParams) -> FootLockedClip:
    base = build_hybrid(animation, HybridParams(increment=params.increment))
    sk = animation.reference.skeleton
    legs = [tuple(int(j) for j in sk.indices(leg)) for leg in LEGS]
    feet = [[int(j) for j in sk.indices(foot)] for foot in FEET]
    return lock_feet(base, animation.reference, legs, feet, animation.fps, params.blend_frames, params.clearance_m,
                     up_axis=animation.reference.up_axis, contact_source=params.contact_source,
                     swing_clearance=params.swing_clearance)


def build_hybrid_c2(animation: Animation, params: HybridC2Params) -> C2Clip | SpringClip:
    base = build_hybrid(animation, HybridParams(increment=params.increment))
    if isinstance(base, SquadClip):
        return c2_from_squad(base)
    if params.increment == 0:
        return base  # one geodesic driven by the closed-form spring: C2 already
    raise ValueError(f"a {animation.kind} follows its keys with the spring: hybrid_c2 exists for it at increment 0 "
                     f"only (the spring hybrid 0, C2 already), got increment {params.increment}")


def build_reduced(animation: Animation, params: ReducedParams) -> KeyframeClip:
    return reduce_keys(animation.reference, params.epsilon_deg)


def build_quantized(animation: Animation, params: QuantizedParams) -> QuantizedClip:
    ref = animation.reference
    src = ref if params.reduced_epsilon_deg is None else reduce_keys(ref, params.reduced_epsilon_deg)
    return quantized_clip(src, params.bits)[0]


class UpdateRateParams(Params):
    rate: float = Field(gt=0, le=240, description="pose updates per second (each pose held 1/rate s)")


class BoneLodParams(Params):
    joints: JointSet | None = Field(None, description="the named set of joints held at their bind pose")
    depth: int | None = Field(None, ge=0, le=64, description="joints deeper than this (the root is 0) are held at "
                              "their bind pose")

    @model_validator(mode="after")
    def _one(self) -> BoneLodParams:
        if (self.joints is None) == (self.depth is None):
            raise ValueError("give exactly one of joints (a named set: fingers, toes, neck) and depth")
        return self


class SkinInfluencesParams(Params):
    influences: int = Field(ge=1, le=4, description="skin weights kept per vertex, the strongest, renormalised")


def update_rate_refused(params: UpdateRateParams, fps: int) -> str | None:
    if params.rate >= fps:
        return (f"rate {params.rate:g} poses/s is at or above the clips' own rate of {fps} keys/s: every frame "
                f"would be updated, the clip would be the reference")
    return None


def bone_lod_bytes(clip: BoneLodClip, params: BoneLodParams) -> int:
    # The moving joints' keys (float32, with the root and time per key) and one float32 pose of the held joints.
    held = int(clip.frozen.sum())
    return keyframe_bytes(clip.key_times.size, clip.skeleton.n_joints - held) + held * 4 * 4


def build_update_rate(animation: Animation, params: UpdateRateParams) -> HeldClip:
    reason = update_rate_refused(params, animation.fps)
    if reason is not None:
        raise ValueError(reason)
    return HeldClip(animation.reference, params.rate, animation.fps)


def build_bone_lod(animation: Animation, params: BoneLodParams) -> BoneLodClip:
    ref = animation.reference
    return bone_lod(ref, frozen_joints(ref.skeleton, params.joints, params.depth), animation.bind_rotations)


def build_skin_influences(animation: Animation, params: SkinInfluencesParams) -> KeyframeClip:
    """The reference's motion: the condition is how it is skinned (:func:`skin_influences_render`)."""
    return animation.reference


def skin_influences_render(params: SkinInfluencesParams) -> dict[str, int]:
    return {"skin_influences": params.influences}
