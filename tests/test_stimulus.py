"""Issue 14 on the real clip set: the two sides of a pair differ in the method only — the crouch in phase with
its keyframe clip, seamless loops and turns, reference feet as planted as their source mocap."""

import dataclasses

import numpy as np
import pytest
from scipy.signal import find_peaks

from anim_core.clips.measure import clip_warnings
from anim_core.io.bvh import read_bvh
from anim_core.math import contacts
from anim_core.math import quat as Q
from anim_core.rig.character import FEET
from server.assets import character as load_character
from server.clipset.build import load_source
from server.clipset.config import load_config

ANIMATIONS = ("walk", "run", "crouch", "idle")
CMU_METRES = 0.056444


@pytest.fixture(scope="module")
def clips(built_clip_set):
    return built_clip_set()


@pytest.fixture(scope="module")
def by_id(clips):
    return {c.id: c for c in clips}


def deep_minima(x):
    """Frames of the minima of a periodic signal that are at least a quarter of its range deep."""
    n = len(x)
    peaks, _ = find_peaks(-np.tile(x, 3), prominence=0.25 * (x.max() - x.min()))
    return sorted(int(p - n) for p in peaks if n <= p < 2 * n)


def test_crouch_is_deepest_as_often_and_when_its_keyframe_clip_is(by_id):
    keyframe = by_id["crouch-keyframe"].world_positions[:, 0, 1]
    expected = deep_minima(keyframe)
    assert len(expected) >= 1
    for inc in (0, 1, 2):
        hips = by_id[f"crouch-hybrid{inc}"].world_positions[:, 0, 1]
        found = deep_minima(hips)
        print(inc, expected, found, np.corrcoef(keyframe, hips)[0, 1])
        assert len(found) == len(expected)
        assert all(abs(a - b) <= 3 for a, b in zip(found, expected, strict=True))
        assert np.corrcoef(keyframe, hips)[0, 1] >= 0.8


def test_every_clip_has_a_seamless_wrap(clips):
    for c in clips:
        p = c.world_positions
        steps = np.linalg.norm(np.roll(p, -1, axis=0) - p, axis=-1).max(axis=1) * 1000  # mm, last = wrap
        limit = 2 * np.median(steps[:-1]) + 5
        assert steps[-1] <= limit, f"{c.id}: seam {steps[-1]:.1f} mm > {limit:.1f} mm"
        assert c.metrics["seam_jump_mm"] == pytest.approx(steps[-1])


def test_pingpong_turns_are_at_rest(clips):
    """Velocity is continuous where ping-pong reverses time only if it is zero there: no bounce."""
    h = 1e-4
    for c in clips:
        if c.playback != "pingpong":
            continue
        half = c.duration_s / 2
        t = np.array([0.0, h, half - h, half])
        _, p = c.character.skeleton.forward_kinematics(*c.clip.sample(t))
        speed = np.linalg.norm(p[[1, 2]] - p[[0, 3]], axis=-1).max(axis=-1) / h  # m/s, largest joint
        assert speed.max() < 0.05, f"{c.id}: joints leave the turn at {speed.round(3)} m/s"


def source_skate(data, animation):
    cfg = load_config().animations[animation]
    bvh = read_bvh(data / cfg.source)
    rot, root = bvh.pose_arrays()
    sk = bvh.posed_skeleton()
    first, last = cfg.frames
    step = round(1 / (30 * bvh.frame_time))  # every 4th frame of 120 fps, every frame of 30 fps
    idx = np.arange(first, last + 1, step)
    _, pos = sk.forward_kinematics(rot[idx], root[idx])
    feet = pos[:, np.array([sk.indices(f) for f in FEET])] * CMU_METRES
    return contacts.foot_skate_ratio(feet, 1 / (bvh.frame_time * step))


def test_reference_feet_skate_no_more_than_their_source(data, by_id):
    for animation in ANIMATIONS:
        c = by_id[f"{animation}-keyframe"]
        src = source_skate(data, animation)
        feet = np.array([c.character.skeleton.indices(f) for f in FEET])
        ground = c.clip.velocity if c.in_place else np.zeros(3)
        skate = contacts.foot_skate_ratio(c.world_positions[:, feet], c.fps, periodic=True, ground_velocity=ground)
        print(animation, f"source {src:.3f} character {skate:.3f}")
        assert skate <= src + 0.01
        assert c.metrics["source_foot_skate_ratio"] == pytest.approx(src, abs=0.01)


def test_crouch_hybrids_pass_through_their_keys(by_id):
    keyframe = by_id["crouch-keyframe"]
    for inc in (0, 1, 2):
        c = by_id[f"crouch-hybrid{inc}"]
        sampled = c.clip.sample(c.key_times).rotations
        assert Q.quat_angle(sampled, c.key_rotations).max() < 1e-6
        # ... which are the keyframe clip's poses at the times the hybrid passes them (but the last: the spring
        # passes the deepest key before it is deepest at the turn).
        mocap = keyframe.clip.sample(c.key_times[:-1]).rotations
        assert Q.quat_angle(sampled[:-1], mocap).max() < 1e-6
        assert Q.quat_angle(c.key_rotations[-1], keyframe.clip.sample(np.array([c.duration_s / 2])).rotations[0]
                            ).max() < 1e-9


def test_build_warns_about_pairs_out_of_phase_and_seams_that_jump(clips):
    assert clip_warnings(clips) == []
    c = clips[1]
    late = dataclasses.replace(c, metrics={**c.metrics, "phase_knee_lag": 3, "seam_jump_mm": 99.0,
                                           "median_step_mm": 10.0})
    warnings = clip_warnings([late])
    assert len(warnings) == 2
    assert "out of phase" in warnings[1] and "+3 frames" in warnings[1] and c.id in warnings[1]
    assert "seam jumps 99.0 mm" in warnings[0]


def bone_angles_deg(skeleton, a, b):
    """(T, J-1) angle between the bones of two pose batches (local rotations, root)."""
    _, p = skeleton.forward_kinematics(*a)
    _, q = skeleton.forward_kinematics(*b)
    j = np.arange(1, skeleton.n_joints)
    u = p[:, j] - p[:, skeleton.parents[j]]
    v = q[:, j] - q[:, skeleton.parents[j]]
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(u, v), axis=-1), np.sum(u * v, axis=-1)))


@pytest.mark.parametrize("animation", ANIMATIONS)
def test_planting_turns_only_the_legs_and_them_a_little(data, animation):
    """Bone directions stay the mocap's except where IK pins a foot; there the largest deviation is printed."""
    from anim_core.clips import reference as cs

    config = load_config()
    cfg = config.animations[animation]
    source = load_source(data, load_character(data), cfg, config.relocate)
    t = source.time_of
    if cfg.kind == "gait":
        first, _, last = cs.pick_gait(source)
        clip, src_t = cs._grid_clip(source, t(first), t(last), 30, True, "loop")
        clip = cs._crossfaded_loop(source, clip, src_t, cs.LOOP_BLEND_S)
    else:
        first, last = cs.pick_crouch(source) if cfg.kind == "crouch" else cs.pick_idle(source)
        clip, src_t = cs._grid_clip(source, t(first), t(last), 30, False, "pingpong", cs.TURN_EASE_S)
    planted = cs._planted(source, clip, src_t)
    sk = clip.skeleton
    angle = bone_angles_deg(sk, (clip.rotations, clip.root_translation),
                            (planted.rotations, planted.root_translation))
    legs = [k for k, name in enumerate(sk.names[1:]) if name in {"LeftLeg", "LeftFoot", "RightLeg", "RightFoot"}]
    others = [k for k in range(sk.n_joints - 1) if k not in legs]
    assert angle[:, others].max() < 1e-6
    print(animation, f"largest leg-bone deviation where IK pins a foot: {angle[:, legs].max():.2f} deg")
    assert angle[:, legs].max() < 10.0
    # The unplanted keys are the mocap's own rotations: on the mocap's skeleton the bones point the same way.
    middle = len(clip.times) // 2  # outside any fade
    mocap = source.clip.sample(src_t[middle:middle + 1], method="slerp")
    assert Q.quat_angle(clip.rotations[middle], mocap.rotations[0]).max() < 1e-9


def test_gait_loops_are_c1_at_the_seam(by_id):
    """The keyframe loop's velocity jumps no more across the wrap than across any other key (dense keys are
    piecewise linear, so each key has some jump); the hybrid loops are cyclic SQUAD (C1 everywhere)."""
    for animation in ("walk", "run"):
        c = by_id[f"{animation}-keyframe"]
        p = c.world_positions  # one period, in place
        v = np.roll(p, -1, axis=0) - p  # velocity after each frame (per frame)
        jump = np.linalg.norm(v - np.roll(v, 1, axis=0), axis=-1).max(axis=1)  # at each frame
        print(animation, f"seam {jump[0] * 1000:.1f} mm/frame, median {np.median(jump) * 1000:.1f}, "
                         f"max elsewhere {jump[1:].max() * 1000:.1f}")
        assert jump[0] <= jump[1:].max()
