"""Motion metrics of a built clip set (:mod:`anim_core.clips.build`): per clip, every other condition against its
animation's reference on the same frame grid, and the warnings ``animstudy clips build`` prints.

Metrics and units are listed in docs/methods/metrics.md.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from ..math import contacts
from ..math.quat import quat_angle
from ..methods.composite_builders import SequenceClip
from ..methods.conditions import REFERENCE, Kind
from ..rig.character import FEET, LEGS, UP
from . import metrics

if TYPE_CHECKING:
    from .record import BuiltClip

Array = NDArray[np.float64]

#: A clip further out of phase with its reference than this: a warning.
MAX_LAG_FRAMES = {"gait": 2, "crouch": 1, "idle": 1, "other": 1}
#: A joint turning more than this (degrees) from one frame to the next flips: a warning (the thesis clips' largest
#: step is 25 degrees).
MAX_FRAME_TURN_DEG = 90.0
#: Kind ``other``: a hybrid condition holding at least this share of its reference's keys is nearly the reference
#: (its keys were picked within ``tolerance_mm`` of it), not a cheap condition; the build says so.
NEAR_REFERENCE_KEY_RATIO = 0.5


def clip_feet(clip: BuiltClip) -> tuple[NDArray[np.intp], Array]:
    """Foot joint indices ``(2, 2)`` and their flat-standing heights above the soles."""
    idx = np.array([clip.character.skeleton.indices(foot) for foot in FEET])
    return idx, clip.character.contact_heights[idx]


def _knee_flexion(clip: BuiltClip) -> Array:
    """``(T, 2)`` bend of each knee in radians (0 = straight leg), from the joint positions."""
    legs = np.array([clip.character.skeleton.indices(leg) for leg in LEGS])
    p = clip.world_positions
    thigh = p[:, legs[:, 1]] - p[:, legs[:, 0]]
    shin = p[:, legs[:, 2]] - p[:, legs[:, 1]]
    return np.arctan2(np.linalg.norm(np.cross(thigh, shin), axis=-1), np.sum(thigh * shin, axis=-1))


def measure(clips: list[BuiltClip], ground_velocity: Array, kind: Kind, source_skate: float) -> list[BuiltClip]:
    """Fill in each clip's metrics; hybrids are compared with the keyframe clip (the first) frame by frame."""
    keyframe = clips[0]
    feet, contact = clip_feet(keyframe)
    for c in clips:
        m: dict[str, float | None] = {**metrics.foot_metrics(c.world_positions[:, feet], contact, c.fps,
                                                             periodic=True, ground_velocity=ground_velocity)}
        # The skate of issue 14: standing heights from the clip itself, as for the source on its own skeleton.
        m["foot_skate_ratio"] = contacts.foot_skate_ratio(c.world_positions[:, feet], c.fps, UP, periodic=True,
                                                          ground_velocity=ground_velocity)
        m["source_foot_skate_ratio"] = source_skate
        m["mpjpe_mm"] = (None if c is keyframe
                         else metrics.mpjpe_mm(c.world_positions, keyframe.world_positions))
        m["key_velocity_jump_rad_s"] = metrics.angular_velocity_jumps(lambda t, c=c: c.clip.sample(t).rotations,
                                                                      c.key_times)
        m["key_accel_jump_rad_s2"] = metrics.angular_acceleration_jumps(
            lambda t, c=c: c.clip.sample(t).rotations, c.key_times)
        m["max_global_error_deg"] = (None if c is keyframe else float(np.degrees(
            np.max(quat_angle(c.world_rotations, keyframe.world_rotations)))))
        m["jerk_mean"] = metrics.jerk_mean(c.world_positions, c.fps, periodic=True)
        m["bytes"] = metrics.storage_bytes(c.key_times.size, c.character.skeleton.n_joints)
        steps = metrics.frame_steps_mm(c.world_positions)
        m["seam_jump_mm"] = float(steps[-1])
        m["median_step_mm"] = float(np.median(steps[:-1]))
        for name in ("phase_hips_r", "phase_hips_lag", "phase_knee_r", "phase_knee_lag"):
            m[name] = None
        if c is not keyframe:
            # A gait's hips bob twice per cycle: a lag of half a cycle would look in phase.
            m["phase_hips_r"], m["phase_hips_lag"] = metrics.phase_alignment(
                keyframe.world_positions[:, 0, UP], c.world_positions[:, 0, UP],
                max_lag=c.n_frames // 4 if kind == "gait" else None)
            m["phase_knee_r"], m["phase_knee_lag"] = metrics.phase_alignment(_knee_flexion(keyframe),
                                                                             _knee_flexion(c))
        c.metrics.update(m)
    return clips


def clip_warnings(clips: list[BuiltClip]) -> list[str]:
    """What makes a side-by-side comparison show more than the method: a clip out of phase with its animation's
    reference (best lag beyond :data:`MAX_LAG_FRAMES`), a seam that jumps (beyond
    :func:`~anim_core.clips.metrics.seam_limit_from_median`), a joint that flips (turns more than
    :data:`MAX_FRAME_TURN_DEG` between two frames, the wrap included), or a hybrid of kind ``other`` with at least
    :data:`NEAR_REFERENCE_KEY_RATIO` of its reference's keys (nearly the reference).  A sequence's seam is its loop's
    own switch, which its transition metrics measure (:mod:`anim_core.clips.composite`), so it gets no seam warning,
    and a sequence switched without blending (its cut) turns its joints at each switch by design: those frames get no
    flip warning."""
    reference = {c.animation: c.id for c in clips if c.method == REFERENCE}
    reference_keys = {c.animation: c.key_times.size for c in clips if c.method == REFERENCE}
    out = []
    for c in clips:
        turn = np.degrees(quat_angle(np.roll(c.local_rotations, -1, axis=0), c.local_rotations))  # (T, J)
        sequence = isinstance(c.clip, SequenceClip)
        if sequence and not c.clip.transition_s:  # into each switch's frame
            turn[[(round(s * c.fps) - 1) % c.n_frames for s in c.clip.switch_times]] = 0.0
        frame, joint = np.unravel_index(int(np.argmax(turn)), turn.shape)
        if turn[frame, joint] > MAX_FRAME_TURN_DEG:
            out.append(f"{c.id}: joint {c.character.skeleton.names[joint]} turns {turn[frame, joint]:.0f} degrees "
                       f"from frame {frame} to {(frame + 1) % c.n_frames} (more than {MAX_FRAME_TURN_DEG:.0f}: a "
                       f"flip)")
        m = c.metrics
        limit = metrics.seam_limit_from_median(m["median_step_mm"])
        if m["seam_jump_mm"] > limit and not sequence:
            out.append(f"{c.id}: the seam jumps {m['seam_jump_mm']:.1f} mm (limit {limit:.1f} mm: twice the "
                       f"median step {m['median_step_mm']:.1f} mm + 5 mm)")
        n_ref = reference_keys.get(c.animation)
        if c.kind == "other" and c.method.startswith("hybrid") and n_ref:
            ratio = c.key_times.size / n_ref
            if ratio >= NEAR_REFERENCE_KEY_RATIO:
                out.append(f"{c.id}: nearly its reference, not a cheap condition: {c.key_times.size} of the "
                           f"reference's {n_ref} keys (key ratio {ratio:.2f}, at least {NEAR_REFERENCE_KEY_RATIO}); "
                           f"a larger tolerance_mm or fewer keys make it a hybrid")
        if c.method != REFERENCE:
            allowed = MAX_LAG_FRAMES[c.kind]
            for part in ("hips", "knee"):
                lag = m[f"phase_{part}_lag"]
                if lag is not None and abs(lag) > allowed:  # None: no frame-by-frame reference (a blend)
                    ref = reference.get(c.animation, "its reference")
                    out.append(f"{c.id}: out of phase with {ref}: {part} best lag {lag:+d} "
                               f"frames (allowed ±{allowed}), r = {m[f'phase_{part}_r']:.2f} at lag 0")
    return out
