"""The conditions of issue 16 built beside an animation's keyframe and hybrid clips, sampled and measured like them.

Condition ids (clip id ``<animation>-<condition>``):

* ``hybrid_ik<i>``: hybrid increment ``i`` with locked feet (:mod:`anim_core.footlock`); every animation.
* ``hybrid_c2_<i>``: hybrid increment ``i`` on the C2 spline (:mod:`anim_core.c2spline`); gait and idle.  The
  crouch has no SQUAD spline: its ``hybrid_c2_0`` is the spring hybrid 0 itself (one geodesic driven by the
  closed-form spring, C2 already); it has no ``hybrid_c2_1``, ``hybrid_c2_2``.
* ``reduced<eps>``: the keyframe clip reduced to within ``eps`` degrees (:func:`anim_core.compression.reduce_keys`),
  ``.`` written ``_`` (``reduced0_5``).
* ``quantized<b>``: the keyframe clip at ``b`` bits per component; ``quantized<b>_reduced<eps>`` both.

This module sits outside the clip-set builder until the condition registry exists; :func:`build_extra` takes the
:class:`~anim_core.clipset.BuiltClip` s of one animation (keyframe first) and returns the new ones, measured by the
clip set's own metric code against the same keyframe clip, plus ``key_accel_jump_rad_s2`` and ``stored_bytes``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from . import clipset, metrics
from .c2spline import c2_from_squad
from .clipset import FEET, LEGS, UP, BuiltClip
from .compression import keyframe_bytes, quantized_clip, reduce_keys
from .footlock import lock_feet
from .hybrid import SquadClip
from .quat import quat_angle


@dataclass(frozen=True)
class ExtraConfig:
    """Parameters of the conditions (defaults: those of the example studies)."""

    increments: tuple[int, ...] = (0, 1, 2)
    blend_frames: int = 3
    clearance_m: float = 0.05
    epsilons_deg: tuple[float, ...] = (0.5, 2.0, 5.0)
    bits: tuple[int, ...] = (8, 12)
    reduced_quantized: tuple[tuple[int, float], ...] = ((12, 2.0),)


def _built(template: BuiltClip, clip_id: str, method: str, inc: int | None, clip: Any, key_times: np.ndarray,
           key_rotations: np.ndarray, shift: np.ndarray) -> BuiltClip:
    pose = clip.sample(template.times)
    g_rot, g_pos = template.character.skeleton.forward_kinematics(*pose)
    return replace(template, id=f"{template.animation}-{clip_id}", condition_id=clip_id, method=method,
                   increment=inc, clip=clip,
                   key_times=np.asarray(key_times, np.float64), key_rotations=np.asarray(key_rotations),
                   local_rotations=pose.rotations, root_positions=pose.root_translation + shift,
                   world_rotations=g_rot, world_positions=g_pos + shift, metrics={})


def build_extra(clips: Sequence[BuiltClip], kind: clipset.Kind, config: ExtraConfig = ExtraConfig()
                ) -> list[BuiltClip]:
    """The new conditions of one animation from its built clips (keyframe first, then ``hybrid`` increments)."""
    keyframe = clips[0]
    if keyframe.method != "keyframe":
        raise ValueError("the first clip of an animation must be its keyframe clip")
    sk = keyframe.character.skeleton
    ref = keyframe.clip
    shift = keyframe.root_positions[0] - ref.sample(np.zeros(1)).root_translation[0]
    hybrids = {c.increment: c for c in clips if c.method == "hybrid"}
    legs = [tuple(int(j) for j in sk.indices(leg)) for leg in LEGS]
    feet = [[int(j) for j in sk.indices(foot)] for foot in FEET]
    out: list[BuiltClip] = []
    for i in config.increments:
        h = hybrids[i].clip
        locked = lock_feet(h, ref, legs, feet, keyframe.fps, config.blend_frames, config.clearance_m, up_axis=UP)
        out.append(_built(keyframe, f"hybrid_ik{i}", "hybrid_ik", i, locked, hybrids[i].key_times,
                          hybrids[i].key_rotations, shift))
        if isinstance(h, SquadClip) or i == 0:
            # The crouch's spring clip at increment 0 is one geodesic driven by the closed-form spring, turning
            # where its velocity is 0: already C2, so it is its own hybrid_c2_0 (no C2 crouch with more keys).
            c2 = c2_from_squad(h) if isinstance(h, SquadClip) else h
            out.append(_built(keyframe, f"hybrid_c2_{i}", "hybrid_c2", i, c2, hybrids[i].key_times,
                              hybrids[i].key_rotations, shift))
    loop = ref.mode == "loop"
    for eps in config.epsilons_deg:
        r = reduce_keys(ref, eps)
        out.append(_built(keyframe, f"reduced{eps:g}".replace(".", "_"), "reduced", None, r,
                          r.times[:-1] if loop else r.times, r.rotations, shift))
    variants = [(b, None) for b in config.bits] + [(b, e) for b, e in config.reduced_quantized]
    for bits, eps in variants:
        src = ref if eps is None else reduce_keys(ref, eps)
        q, _tracks = quantized_clip(src, bits)
        suffix = "" if eps is None else f"_reduced{eps:g}".replace(".", "_")
        out.append(_built(keyframe, f"quantized{bits}{suffix}", "quantized", None, q,
                          q.times[:-1] if loop else q.times, q.rotations, shift))
    ground = ref.velocity if keyframe.in_place else np.zeros(3)
    measured = clipset._measure([keyframe, *out], ground, kind, keyframe.metrics["source_foot_skate_ratio"])[1:]
    for c in measured:
        c.metrics["key_accel_jump_rad_s2"] = _accel_jump(c)
        c.metrics["stored_bytes"] = c.metrics["bytes"] = stored_bytes(c)
        c.metrics["max_global_error_deg"] = float(np.degrees(
            np.max(quat_angle(c.world_rotations, keyframe.world_rotations)))) if c.method in ("reduced", "quantized") \
            else None
    return measured


def _accel_jump(c: BuiltClip) -> float:
    return metrics.angular_acceleration_jumps(lambda t: c.clip.sample(t).rotations, c.key_times)


def stored_bytes(c: BuiltClip) -> int:
    """Bytes a condition stores: keys as float32 (quantized: packed codes + per-track range); ``hybrid_ik`` adds
    an ankle target (3 float32) and a weight per leg and frame."""
    j = c.character.skeleton.n_joints
    n_keys = int(c.key_times.size)  # a loop's repeated end key is not stored
    if c.method == "quantized":
        bits = int(c.condition.removeprefix("quantized").split("_")[0])
        return keyframe_bytes(n_keys, j, bits)
    base = keyframe_bytes(n_keys, j)
    if c.method == "hybrid_ik":
        base += int(c.clip.weights.size * 4 * 4)
    return base
