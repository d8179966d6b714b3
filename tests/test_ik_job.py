"""The run-time two-bone IK job (issue 39, held feet through a transition) against the offline
:func:`anim_core.methods.ik.two_bone_ik` and against geometry: the legs' rotations as the offline solve gives them
within a stated tolerance, a reachable ankle target met to 1e-6 m with the bones' lengths kept, weight 0 and every
joint off the legs untouched; bad buffers refused before the kernel.  The bench's held-feet crossfade row exists.
Seeded."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from anim_core.bench.blend import CASES, _steps, blend_stage, format_blend
from anim_core.bench.suite import interleaved_ms
from anim_core.math import quat as Q
from anim_core.math.clip import KeyframeClip
from anim_core.methods.ik import two_bone_ik
from anim_core.runtime.blending import LocalPose, local_to_model
from anim_core.runtime.ik import TwoBoneIKJob
from tests.synthetic import biped

N = 400
LEGS = ((3, 4, 5), (6, 7, 8))  # the biped's hip, knee, ankle
HINGE = np.array([1.0, 0.0, 0.0])  # the biped's knees (shin straight down, Z forward) bend about +X
A = B = 0.45  # the biped's thigh and shin
# The job runs the offline solve's steps in float64 on a float32 pose (its FK and its outputs are float32, 1e-7
# relative); the offline solve runs on the same rotations in float64.  A leg's rotations agree to this many degrees
# (seen: 1.7e-4 on seed 1, at most 1.03e-3 over 29 seeds, on a nearly straight knee whose animated plane comes from
# the cross product of two nearly parallel float32 bones; with the bone lengths in float32, as the kernel had them,
# 0.0064 at full reach, where the bend goes as sqrt(L - d) and float32 rounding of a * a + b * b exceeds the solve's
# 1e-9 margin).
TOL_DEG = 0.003
TOL_M = 1e-6  # a reachable target is met, and bones keep their lengths, to float32 rounding of metre positions


def _crowd(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Local rotations ``(N, J, 4)`` (float32 values) and roots ``(N, 3)``: every joint turned at random by up to
    ~35 degrees, each knee bent about its hinge by 5..120 degrees (a few straight, one hyper-extended)."""
    rng = np.random.default_rng(seed)
    j = biped().n_joints
    axes = rng.normal(size=(N, j, 3))
    rot = Q.quat_from_axis_angle(axes / np.linalg.norm(axes, axis=-1, keepdims=True), rng.uniform(0, 0.6, (N, j)))
    for _, knee, _ in LEGS:
        bend = rng.uniform(np.radians(5), np.radians(120), N)
        bend[:4] = [0.0, 0.0, -0.05, 1e-4]
        rot[:, knee] = Q.quat_from_axis_angle(HINGE, bend)
    root = rng.uniform(-1.0, 1.0, (N, 3))
    return rot.astype(np.float32), root.astype(np.float32)


def _model(rot: np.ndarray, root: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    sk = biped()
    g_rot, g_pos = np.empty((N, sk.n_joints, 4), np.float32), np.empty((N, sk.n_joints, 3), np.float32)
    local_to_model(sk, LocalPose(rot.copy(), root.copy()), g_rot, g_pos)
    return g_rot, g_pos


def _to_local(g_rot: np.ndarray) -> np.ndarray:
    parents = biped().parents
    g = g_rot.astype(np.float64)
    local = g.copy()
    local[:, 1:] = Q.quat_mul(Q.quat_conj(g[:, parents[1:]]), g[:, 1:])
    return local


def _targets(seed: int, g_pos: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Per character and leg a target at a random direction from the hip, at a distance drawn in ``lo..hi``."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(N, 2, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    hips = g_pos[:, [s for s, _, _ in LEGS]].astype(np.float64)
    return (hips + d * rng.uniform(lo, hi, (N, 2, 1))).astype(np.float32)


def test_job_gives_the_offline_solves_leg_rotations() -> None:
    sk = biped()
    rot, root = _crowd(1)
    g_rot, g_pos = _model(rot, root)
    soft = 0.005 * (A + B)
    targets = _targets(2, g_pos, 0.02, 1.2 * (A + B))  # from folded to out of reach
    weights = np.random.default_rng(3).uniform(0, 1, (N, 2)).astype(np.float32)
    weights[:20] = 1.0
    job = TwoBoneIKJob.for_legs(sk, LEGS, [HINGE, HINGE], soft)
    job.run(g_rot, g_pos, targets, weights)

    expected = rot.astype(np.float64)
    for leg, chain in enumerate(LEGS):
        expected = two_bone_ik(sk, expected, root.astype(np.float64), chain, targets[:, leg].astype(np.float64),
                               weight=weights[:, leg].astype(np.float64), hinge=HINGE, soft=soft)
    got = _to_local(g_rot)
    for chain in LEGS:
        angle = np.degrees(Q.quat_angle(got[:, list(chain)], expected[:, list(chain)]))
        assert angle.max() < TOL_DEG, (chain, angle.max())
    e_rot, e_pos = sk.forward_kinematics(expected, root.astype(np.float64))
    assert np.abs(g_pos - e_pos).max() < 5e-6  # metres (seen: 1.3e-6)
    assert np.degrees(Q.quat_angle(g_rot, e_rot)).max() < TOL_DEG


def test_reachable_targets_are_met_with_the_bones_kept() -> None:
    sk = biped()
    rot, root = _crowd(4)
    g_rot, g_pos = _model(rot, root)
    before_rot, before_pos = g_rot.copy(), g_pos.copy()
    targets = _targets(5, g_pos, 0.05, 0.85)  # inside [|a - b|, a + b] = [0, 0.9] by 5 cm
    weights = np.ones((N, 2), np.float32)
    weights[-50:, 1] = 0.0  # the right leg of the last 50 characters is let alone
    TwoBoneIKJob.for_legs(sk, LEGS, [HINGE, HINGE]).run(g_rot, g_pos, targets, weights)

    solved = weights > 0
    for leg, (s, m, e) in enumerate(LEGS):
        on = solved[:, leg]
        assert np.linalg.norm(g_pos[on, e] - targets[on, leg], axis=-1).max() < TOL_M
        assert np.abs(np.linalg.norm(g_pos[:, m] - g_pos[:, s], axis=-1) - A).max() < TOL_M
        assert np.abs(np.linalg.norm(g_pos[:, e] - g_pos[:, m], axis=-1) - B).max() < TOL_M
        assert np.array_equal(g_pos[:, s], before_pos[:, s])  # the hip stays where it is
        # the foot keeps its world orientation (float32 rounding of a re-written quaternion at most)
        assert np.degrees(Q.quat_angle(g_rot[:, e], before_rot[:, e])).max() < 1e-3
        # the knee bends about its hinge, never backwards: (thigh x shin) along the hinge in world space
        normal = np.cross(g_pos[on, m] - g_pos[on, s], g_pos[on, e] - g_pos[on, m])
        hinge = Q.rotate(g_rot[on, m].astype(np.float64), HINGE)
        assert np.all(np.sum(normal * hinge, axis=-1) > 0.0)
    let_alone = ~solved[:, 1]
    assert np.array_equal(g_rot[let_alone][:, 6:9], before_rot[let_alone][:, 6:9])
    assert np.array_equal(g_pos[let_alone][:, 6:9], before_pos[let_alone][:, 6:9])
    assert np.array_equal(g_rot[:, :3], before_rot[:, :3]) and np.array_equal(g_pos[:, :3], before_pos[:, :3])
    assert not np.array_equal(g_rot[:, 3:5], before_rot[:, 3:5])  # the job did something


def test_bad_buffers_are_refused_before_the_kernel() -> None:
    sk = biped()
    rot, root = _crowd(6)
    g_rot, g_pos = _model(rot, root)
    job = TwoBoneIKJob.for_legs(sk, LEGS, [HINGE, HINGE])
    targets, weights = _targets(7, g_pos, 0.1, 0.8), np.ones((N, 2), np.float32)
    bad_target = targets.copy()
    bad_target[7, 1, 2] = np.nan
    frozen = g_pos.copy()
    frozen.flags.writeable = False
    cases = [
        ((g_rot, g_pos, bad_target, weights), "targets must be finite"),
        ((g_rot, g_pos, targets.astype(np.float64), weights), "targets must be a float32 array"),
        ((g_rot, g_pos, targets[:, :1], weights), r"targets must have shape \(400, 2, 3\)"),
        ((g_rot, g_pos, targets, np.full((N, 2), 1.5, np.float32)), "weights must be finite weights in"),
        ((g_rot, g_pos, targets, weights[:-1]), "weights must have shape"),
        ((g_rot, g_pos[:, :-1], targets, weights), "model positions must have shape"),
        ((g_rot[..., :3], g_pos, targets, weights), "model rotations must have shape"),
        ((g_rot.astype(np.float64), g_pos, targets, weights), "model rotations must be a float32 array"),
        ((g_rot, np.asfortranarray(g_pos), targets, weights), "model positions must be C-contiguous"),
        ((g_rot, frozen, targets, weights), "model positions must be writeable"),
        ((g_rot[0], g_pos, targets, weights), r"model rotations must be an \(N, J, 4\) array"),
    ]
    before_rot, before_pos = g_rot.copy(), g_pos.copy()
    for args, message in cases:
        with pytest.raises(ValueError, match=message):
            job.run(*args)
    assert np.array_equal(g_rot, before_rot) and np.array_equal(g_pos, before_pos)  # nothing written
    with pytest.raises(ValueError, match="is not hip -> knee -> ankle"):
        TwoBoneIKJob.for_legs(sk, ((3, 5, 4),), [HINGE])
    with pytest.raises(ValueError, match="hinges must be 2 finite non-zero"):
        TwoBoneIKJob.for_legs(sk, LEGS, [HINGE, [0.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="soft must be in"):
        TwoBoneIKJob.for_legs(sk, LEGS, [HINGE, HINGE], soft=0.9)


def _walk(sk, seed: int, speed: float) -> KeyframeClip:
    rng = np.random.default_rng(seed)
    times = np.arange(31) / 30
    rot = Q.quat_normalize(Q.identity((31, sk.n_joints)) + 0.1 * rng.normal(size=(31, sk.n_joints, 4)))
    for _, knee, _ in LEGS:
        rot[:, knee] = Q.quat_from_axis_angle(HINGE, 0.6 + 0.4 * np.sin(2 * np.pi * times))
    root = np.stack([np.zeros(31), np.full(31, 0.9), times * speed], axis=-1)
    return KeyframeClip(sk, times, Q.make_continuous(rot), root, "loop", False, 1, f"walk{seed}")


def test_the_blend_stage_has_a_held_feet_crossfade_row() -> None:
    sk = biped()
    clips = [SimpleNamespace(method="keyframe", animation=name, clip=_walk(sk, k, 1.0 + k))
             for k, name in enumerate(("walk", "run"))]

    def timer(cases, phases, frames, warmup):
        return dict(enumerate(interleaved_ms([c.step for c in cases], phases, frames, warmup)))

    rows, memory = blend_stage(clips, [7], 2, 1, np.random.default_rng(0), timer)
    assert "crossfade_feet" in CASES
    for animation in ("walk", "run"):
        by_case = {r["method"]: r for r in rows if r["animation"] == animation and r["characters"] == 7}
        assert set(by_case) == set(CASES)
        feet = by_case["crossfade_feet"]
        assert feet["ms_per_1000"] > 0 and feet["stage"] == "blend" and feet["frames"] == 2
        # the takes' keys and the legs' job (chains, hinges, joints under the hips, two parameters)
        assert feet["runtime_bytes"] > by_case["crossfade"]["runtime_bytes"]
    assert {m["method"] for m in memory} == set(CASES)
    assert "crossfade_feet" in format_blend(rows)


def test_the_held_feet_step_moves_the_ankles_and_only_the_legs() -> None:
    sk = biped()
    a, b = _walk(sk, 0, 1.0), _walk(sk, 1, 2.0)
    steps, _ = _steps(a, b, 50, 9)
    t = np.random.default_rng(10).uniform(0, 2, 50)
    free_rot, free_pos = (x.copy() for x in steps["crossfade"](t, 0))
    held_rot, held_pos = steps["crossfade_feet"](t, 0)
    moved = np.linalg.norm(held_pos[:, [5, 8]] - free_pos[:, [5, 8]], axis=-1)
    assert np.all(moved > 1e-4) and moved.max() < 0.1 * np.sqrt(3) + 1e-6  # the held offsets: up to 10 cm a side
    assert np.array_equal(held_pos[:, :3], free_pos[:, :3]) and np.array_equal(held_rot[:, :3], free_rot[:, :3])
