"""The hybrid method: spring, increments, mirroring and the gait / crouch / idle players.

Synthetic skeletons check the algebra; the real CMU clips from the data directory check that the method does
what it claims on motion capture (feet swap under mirroring, the gait loops smoothly through its keys, the
crouch overshoots and settles).
"""

import dataclasses

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from anim_core.io.bvh import clip_from_bvh, read_bvh
from anim_core.math import quat as Q
from anim_core.math.clip import KeyframeClip, Pose
from anim_core.math.skeleton import Skeleton
from anim_core.methods.hybrid import (
    THESIS_OMEGA,
    THESIS_TIME_SCALE,
    THESIS_ZETA,
    build_crouch,
    build_gait,
    build_idle,
    increment_key_times,
    spring,
    spring_settle_time,
)
from anim_core.rig.mirror import Mirror, mirror_partners
from tests.synthetic import BIPED_NAMES, BIPED_PARENTS, biped, random_rotations

CMU = "mocap/cmu/"


@pytest.fixture(scope="module")
def walk(data) -> KeyframeClip:
    return clip_from_bvh(read_bvh(data / CMU / "12_03_walk.bvh.gz"), first_frame=1, name="walk")


def joint_positions(clip_or_skeleton, pose: Pose, *names):
    skeleton = getattr(clip_or_skeleton, "skeleton", clip_or_skeleton)
    _, pos = skeleton.forward_kinematics(pose.rotations, pose.root_translation)
    return [pos[..., skeleton.index(n), :] for n in names]


def gait_keys(clip: KeyframeClip):
    """Thesis keys of one gait cycle, found from the feet: (left foot forward, left foot passing), period.

    A deliberately simple picker for the tests (the clip-set issue provides the real one).
    """
    pose = clip.sample(clip.times)
    left, right, hips = joint_positions(clip, pose, "LeftToeBase", "RightToeBase", "Hips")
    direction = hips[-1] - hips[0]
    direction[1] = 0
    direction /= np.linalg.norm(direction)
    ahead = (left - right) @ direction
    peaks = [i for i in range(1, len(ahead) - 1)
             if ahead[i] >= ahead[i - 1] and ahead[i] > ahead[i + 1] and ahead[i] > 0.7 * ahead.max()]
    first, second = peaks[0], next(p for p in peaks if p > peaks[0] + 30)
    passing = first + int(np.argmax(ahead[first:second] < 0))  # the right foot swings past the planted left
    return clip.times[first], clip.times[passing], clip.times[second] - clip.times[first], direction


# --- spring --------------------------------------------------------------------------------------------------

@pytest.mark.parametrize(("zeta", "omega"), [(THESIS_ZETA, THESIS_OMEGA), (0.2, 3.0), (0.0, 7.0), (0.95, 25.0)])
def test_spring_matches_numerical_ode_solution(zeta, omega):
    t = np.linspace(0.0, 3.0, 301)
    sol = solve_ivp(lambda _t, y: [y[1], -2 * zeta * omega * y[1] - omega**2 * y[0]], (0.0, 3.0), [1.0, 0.0],
                    t_eval=t, rtol=1e-12, atol=1e-14, method="DOP853")
    err = np.abs(spring(t, zeta, omega) - sol.y[0]).max()
    print(f"zeta={zeta} omega={omega}: max |closed form - solve_ivp| = {err:.1e}")
    assert err < 1e-6


def test_spring_with_initial_velocity_and_validation():
    t = np.linspace(0.0, 2.0, 101)
    sol = solve_ivp(lambda _t, y: [y[1], -2 * 0.5 * 4 * y[1] - 16 * y[0]], (0, 2), [0.3, -2.0], t_eval=t,
                    rtol=1e-12, atol=1e-14, method="DOP853")
    assert np.abs(spring(t, 0.5, 4.0, x0=0.3, v0=-2.0) - sol.y[0]).max() < 1e-6
    with pytest.raises(ValueError, match="underdamped"):
        spring(t, 1.0, 4.0)


def test_thesis_spring_overshoots_by_the_damping_ratio_amount_and_settles():
    t = np.linspace(0.0, 3.0, 30001)
    x = spring(THESIS_TIME_SCALE * t)
    expected_overshoot = np.exp(-np.pi * THESIS_ZETA / np.sqrt(1 - THESIS_ZETA**2))  # 4.6 %
    np.testing.assert_allclose(-x.min(), expected_overshoot, rtol=1e-6)
    settle = spring_settle_time()
    assert np.abs(x[t >= settle]).max() < 0.01


# --- increments ----------------------------------------------------------------------------------------------

def test_increments_insert_midpoints():
    np.testing.assert_allclose(increment_key_times([0.0, 1.0], 1), [0.0, 0.5, 1.0])
    np.testing.assert_allclose(increment_key_times([0.0, 1.0], 2), [0.0, 0.25, 0.5, 0.75, 1.0])
    np.testing.assert_allclose(increment_key_times([0.0, 0.2], 1, end=0.5), [0.0, 0.1, 0.2, 0.35])
    assert len(increment_key_times([0.0, 0.2], 2, end=0.5)) == 8
    with pytest.raises(ValueError, match="increasing"):
        increment_key_times([1.0, 0.0], 1)


# --- mirroring -----------------------------------------------------------------------------------------------

def test_partners_from_names():
    names = ("Hips", "LHipJoint", "LeftUpLeg", "RHipJoint", "RightUpLeg", "LowerBack", "Lthing", "hand.L",
             "hand.R", "foot_l", "foot_r")
    perm = mirror_partners(names)
    assert [names[i] for i in perm] == ["Hips", "RHipJoint", "RightUpLeg", "LHipJoint", "LeftUpLeg",
                                        "LowerBack", "Lthing", "hand.R", "hand.L", "foot_r", "foot_l"]
    with pytest.raises(ValueError, match="no partner 'RightArm'"):
        mirror_partners(("Hips", "LeftArm"))
    custom = mirror_partners(("Hips", "Port", "Starboard"), overrides={"Port": "Starboard"})
    assert custom.tolist() == [0, 2, 1]


def symmetric_rig(rng):
    """The biped with random (non-identity) rest rotations and a mirror-symmetric rest pose.

    Offsets are chosen so the world-space rest offsets of left and right joints are mirror images, as on a real
    rig whose joint frames point along its bones in any direction.
    """
    n = len(BIPED_NAMES)
    rest = Q.quat_normalize(rng.normal(size=(n, 4)))
    world_offsets = biped().offsets  # symmetric in x
    provisional = Skeleton(BIPED_NAMES, BIPED_PARENTS, world_offsets, rest)
    g_rest, _ = provisional.rest_global()
    local = world_offsets.copy()
    for j in range(1, n):
        local[j] = Q.rotate(Q.quat_conj(g_rest[BIPED_PARENTS[j]]), world_offsets[j])
    return Skeleton(BIPED_NAMES, BIPED_PARENTS, local, rest)


@pytest.mark.parametrize("rig", ["bvh", "rotated_rest"])
def test_mirror_is_an_involution(rng, rig):
    skeleton = biped() if rig == "bvh" else symmetric_rig(rng)
    mirror = Mirror(skeleton, normal=[1.0, 0.2, 0.0], offset=0.3)
    pose = Pose(random_rotations(rng, (20, skeleton.n_joints)), rng.normal(size=(20, 3)))
    twice = mirror(mirror(pose))
    assert Q.quat_angle(twice.rotations, pose.rotations).max() < 1e-12
    np.testing.assert_allclose(twice.root_translation, pose.root_translation, atol=1e-12)


@pytest.mark.parametrize("rig", ["bvh", "rotated_rest"])
def test_mirrored_pose_is_the_reflection_of_the_original(rng, rig):
    skeleton = biped() if rig == "bvh" else symmetric_rig(rng)
    mirror = Mirror(skeleton)
    pose = Pose(random_rotations(rng, (10, skeleton.n_joints)), rng.normal(size=(10, 3)))
    _, pos = skeleton.forward_kinematics(*pose)
    _, mirrored_pos = skeleton.forward_kinematics(*mirror(pose))
    expected = (pos * [-1.0, 1.0, 1.0])[:, mirror.partners]
    np.testing.assert_allclose(mirrored_pos, expected, atol=1e-12)


def test_mirroring_without_removing_the_rest_pose_would_be_wrong(rng):
    """The same mirror applied to raw local rotations of a rotated-rest rig does not reflect the body."""
    skeleton = symmetric_rig(rng)
    pose = Pose(random_rotations(rng, (10, skeleton.n_joints)), rng.normal(size=(10, 3)))
    mirror = Mirror(skeleton)
    naive = Pose(mirror.reflect_rotations(pose.rotations)[:, mirror.partners], pose.root_translation * [-1, 1, 1])
    _, pos = skeleton.forward_kinematics(*pose)
    _, naive_pos = skeleton.forward_kinematics(*naive)
    assert np.abs(naive_pos - (pos * [-1.0, 1.0, 1.0])[:, mirror.partners]).max() > 0.1


def test_mirroring_a_real_walk_key_swaps_the_feet(walk):
    t_forward, _, _, direction = gait_keys(walk)
    key = walk.key_pose(t_forward)
    mirrored = Mirror(walk.skeleton)(key)
    left, right = joint_positions(walk, key, "LeftFoot", "RightFoot")
    m_left, m_right = joint_positions(walk, mirrored, "LeftFoot", "RightFoot")
    ahead, m_ahead = (left - right) @ direction, (m_left - m_right) @ direction
    print(f"left foot ahead of right: {ahead:.2f} units in the key, {m_ahead:.2f} mirrored")
    assert ahead > 3.0  # CMU units (x 0.056 m): the left foot leads by more than 17 cm ...
    assert m_ahead < -3.0  # ... and after mirroring the right foot leads
    assert abs(ahead + m_ahead) < 0.1 * ahead  # by about as much (CMU skeletons are nearly symmetric)


# --- players on real data ------------------------------------------------------------------------------------

@pytest.mark.parametrize("increment", [0, 1, 2])
def test_hybrid_gait_on_real_walk(walk, increment):
    t_forward, t_passing, period, _ = gait_keys(walk)
    gait = build_gait(walk, [t_forward, t_passing], period, increment=increment, name="walk")
    assert gait.n_keys == 4 * 2**increment
    # Passes through the mocap keys (first half) and through their mirror images (second half).
    half = gait.n_keys // 2
    source_times = gait.key_times[:half] + t_forward
    source = walk.sample(source_times)
    sampled = gait.sample(gait.key_times)
    assert Q.quat_angle(sampled.rotations[:half], source.rotations).max() < 1e-12
    mirrored = Mirror(walk.skeleton)(Pose(source.rotations, source.root_translation))
    assert Q.quat_angle(sampled.rotations[half:], mirrored.rotations).max() < 1e-12
    # Loops seamlessly: one period later the rotations repeat and the root has moved one stride on.
    t = np.linspace(0.0, period, 50)
    a, b = gait.sample(t), gait.sample(t + period)
    assert Q.quat_angle(a.rotations, b.rotations).max() < 1e-12
    stride = gait.velocity * period
    np.testing.assert_allclose(b.root_translation - a.root_translation, np.broadcast_to(stride, (50, 3)), atol=1e-9)
    # C1 everywhere including the keys and the wrap: angular velocity has no jumps.
    delta = 1e-6
    tk = gait.key_times
    q = [gait.sample(tk + d).rotations for d in (-delta, 0.0, delta)]
    w_before = 2 * Q.quat_log(Q.align_hemisphere(Q.quat_mul(q[1], Q.quat_conj(q[0])), Q.identity())) / delta
    w_after = 2 * Q.quat_log(Q.align_hemisphere(Q.quat_mul(q[2], Q.quat_conj(q[1])), Q.identity())) / delta
    jump = np.linalg.norm(w_after - w_before, axis=-1).max()
    print(f"increment {increment}: {gait.n_keys} keys, max angular-velocity jump at keys {jump:.1e} rad/s")
    assert jump < 1e-3


def test_hybrid_gait_rejects_keys_outside_a_half_cycle(walk):
    t_forward, _, period, _ = gait_keys(walk)
    with pytest.raises(ValueError, match="half cycle"):
        build_gait(walk, [t_forward, t_forward + 0.6 * period], period)
    with pytest.raises(ValueError, match="whole cycle"):
        build_gait(walk, [walk.duration - 0.2, walk.duration - 0.1], period)


@pytest.fixture(scope="module")
def crouch(data) -> KeyframeClip:
    return clip_from_bvh(read_bvh(data / CMU / "115_06_crouch_first164.bvh.gz"), first_frame=1, mode="clamp")


@pytest.mark.parametrize("increment", [0, 1, 2])
def test_hybrid_crouch_overshoots_the_key_and_settles(crouch, increment):
    pose = crouch.sample(crouch.times)
    (hips,) = joint_positions(crouch, pose, "Hips")
    t_stand, t_low = crouch.times[0], crouch.times[int(np.argmin(hips[:, 1]))]
    hybrid = build_crouch(crouch, [t_stand, t_low], increment=increment)
    assert hybrid.n_keys == [2, 3, 5][increment]
    t = np.linspace(0.0, hybrid.duration, 2001)
    u = hybrid.path_parameter(t)
    assert u.max() > 1.04  # the thesis spring overshoots by 4.6 %
    (h_hips,) = joint_positions(hybrid, hybrid.sample(t), "Hips")
    key_low = hips[:, 1].min()
    print(f"increment {increment}: lowest hips {h_hips[:, 1].min():.3f} vs crouch key {key_low:.3f}")
    assert h_hips[:, 1].min() < key_low - 0.05  # goes below the crouch key ...
    low_key = crouch.key_pose(t_low)
    # ... and turns exactly on it (the spring output is scaled to reach 1 at the end of the forward half).
    end = hybrid.sample(np.array([hybrid.duration]))
    assert Q.quat_angle(end.rotations[0], low_key.rotations).max() < 1e-12
    # The pure thesis formula turns wherever the spring has got to: off the key by the residual |x| (< 1 %)
    # along the constant-speed last slerp segment.
    pure = dataclasses.replace(hybrid, land_on_last_key=False)
    residual = abs(float(spring(THESIS_TIME_SCALE * hybrid.duration)))
    assert residual < 0.01
    last = Q.quat_angle(hybrid.key_rotations[-1], hybrid.key_rotations[-2])
    dp = hybrid.key_params[-1] - hybrid.key_params[-2]
    np.testing.assert_allclose(Q.quat_angle(pure.sample(np.array([hybrid.duration])).rotations[0],
                                            low_key.rotations), residual * last / dp, rtol=1e-6, atol=1e-12)
    # Key times: when the path first reaches each key; the pose there is the key.
    key_times = hybrid.key_times
    np.testing.assert_allclose(hybrid.path_parameter(key_times), hybrid.key_params, atol=1e-9)
    assert np.all(np.diff(key_times) > 0) and key_times[-1] < hybrid.duration
    assert Q.quat_angle(hybrid.sample(key_times).rotations, hybrid.key_rotations).max() < 1e-6
    start = hybrid.sample(np.array([0.0, 2 * hybrid.duration]))
    assert Q.quat_angle(start.rotations, crouch.key_pose(t_stand).rotations).max() < 1e-12  # ping-pong home


def test_hybrid_idle_is_smooth_pingpong_through_its_keys(data):
    idle = clip_from_bvh(read_bvh(data / CMU / "113_21_idle_30fps.bvh.gz"), mode="pingpong")
    pose = idle.sample(idle.times)
    (hips,) = joint_positions(idle, pose, "Hips")
    sway = hips[:, 0]
    keys = sorted([idle.times[int(np.argmin(sway))], idle.times[int(np.argmax(sway))]])
    for increment, n in ((0, 2), (1, 3), (2, 5)):
        hybrid = build_idle(idle, keys, increment=increment)
        assert hybrid.n_keys == n
        at_keys = hybrid.sample(hybrid.key_times)
        source = idle.sample(hybrid.key_times + keys[0])
        assert Q.quat_angle(at_keys.rotations, source.rotations).max() < 1e-12
        np.testing.assert_allclose(at_keys.root_translation, source.root_translation, atol=1e-9)
        x = np.linspace(0, hybrid.duration, 20)
        fwd, back = hybrid.sample(x), hybrid.sample(2 * hybrid.duration - x)
        assert Q.quat_angle(fwd.rotations, back.rotations).max() < 1e-12
        # Turning points are at rest: velocity there is ~0 (reflecting SQUAD ends).
        d = 1e-5
        ends = hybrid.sample(np.array([hybrid.duration - d, hybrid.duration]))
        assert Q.quat_angle(ends.rotations[0], ends.rotations[1]).max() / d < 1e-3
