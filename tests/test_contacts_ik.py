"""Foot contact detection and two-bone IK on synthetic data (issue 14): planted and moving feet, reachable and
unreachable targets, a stable knee plane."""

import numpy as np
import pytest

from anim_core.math import contacts
from anim_core.math import quat as Q
from anim_core.math.skeleton import Skeleton
from anim_core.methods.footplant import plant_feet
from anim_core.methods.ik import two_bone_ik

FPS = 30.0


def foot_track(n: int, ankle_y, toe_y, x_speed) -> np.ndarray:
    """(n, 1, 2, 3): one foot (ankle, toe 0.15 m ahead), heights per frame, moving along x at x_speed m/s."""
    t = np.arange(n) / FPS
    x = np.broadcast_to(np.asarray(x_speed, dtype=float), (n,)).cumsum() / FPS if np.ndim(x_speed) else x_speed * t
    p = np.zeros((n, 1, 2, 3))
    p[:, 0, 0] = np.stack([x, np.broadcast_to(ankle_y, (n,)), np.zeros(n)], axis=1)
    p[:, 0, 1] = np.stack([x, np.broadcast_to(toe_y, (n,)), np.full(n, 0.15)], axis=1)
    return p


def test_planted_foot_is_down_and_does_not_skate():
    feet = foot_track(60, 0.08, 0.02, 0.0)
    assert contacts.foot_down(feet).all()
    assert contacts.foot_skate_ratio(feet, FPS) == 0.0
    np.testing.assert_allclose(contacts.standing_heights(feet), [[0.08, 0.02]])


def test_sliding_foot_skates_above_the_speed_threshold_only():
    assert contacts.foot_skate_ratio(foot_track(60, 0.08, 0.02, 0.6), FPS) == 1.0
    assert contacts.foot_skate_ratio(foot_track(60, 0.08, 0.02, 0.4), FPS) == 0.0


def test_a_window_in_the_air_is_judged_against_the_standing_heights_given():
    # A swing skimming 9 cm over the floor at 2 m/s: against its own frames' heights it looks planted and skates;
    # against the standing heights of the whole loop (ankle 8 cm, toe 2 cm) it is in the air (issue 39: a
    # transition window against the loop's heights, as the yardstick's frames against the whole take's).
    skim = foot_track(12, 0.17, 0.11, 2.0)
    assert contacts.foot_skate_ratio(skim, FPS) == 1.0
    assert contacts.foot_skate_ratio(skim, FPS, standing=[[0.08, 0.02]]) == 0.0
    assert contacts.foot_skate_ratio(foot_track(12, 0.08, 0.02, 2.0), FPS, standing=[[0.08, 0.02]]) == 1.0


def test_a_foot_is_down_only_when_ankle_and_toe_are_both_low():
    n = 90
    ankle = np.full(n, 0.08)
    toe = np.full(n, 0.02)
    ankle[30:60] += 0.06  # heel up: rolling over the toe, 6 cm > 5 cm
    toe[40:50] += 0.2  # toe in the air too
    feet = foot_track(n, ankle, toe, 1.0)  # fast everywhere
    down = contacts.foot_down(feet)[:, 0]
    assert not down[30:60].any() and down[:30].all() and down[60:].all()
    assert contacts.foot_skate_ratio(feet, FPS) == pytest.approx(60 / 90)


def test_slowest_joint_decides_and_ground_velocity_counts():
    feet = foot_track(40, 0.08, 0.02, 0.0)
    feet[:, 0, 0, 0] += np.arange(40) / FPS * 2.0  # the ankle moves, the toe stays: rolling, not skating
    assert contacts.foot_skate_ratio(feet, FPS) == 0.0
    treadmill = foot_track(40, 0.08, 0.02, -1.0)  # played in place: the ground runs back at 1 m/s
    assert contacts.foot_skate_ratio(treadmill, FPS, ground_velocity=[1.0, 0.0, 0.0]) == 0.0
    assert contacts.foot_skate_ratio(treadmill, FPS) == 1.0


def test_standing_height_is_a_low_percentile_so_a_raised_floor_is_found():
    rng = np.random.default_rng(3)
    ankle = 0.5 + 0.08 + 0.3 * (rng.random(100) < 0.4)  # on a 0.5 m platform, 40 % of frames lifted
    feet = foot_track(100, ankle, ankle - 0.06, 0.0)
    np.testing.assert_allclose(contacts.standing_heights(feet)[0, 0], 0.58)
    assert contacts.foot_down(feet)[:, 0].sum() == int((ankle < 0.6).sum())


def test_contact_intervals_and_wrapping():
    down = np.array([1, 1, 0, 0, 1, 1, 1, 0, 1], dtype=bool)
    np.testing.assert_array_equal(contacts.contact_intervals(down), [[0, 2], [4, 7], [8, 9]])
    np.testing.assert_array_equal(contacts.contact_intervals(down, periodic=True), [[4, 7], [8, 11]])
    np.testing.assert_array_equal(contacts.contact_intervals(np.ones(5, bool), periodic=True), [[0, 5]])
    assert contacts.contact_intervals(np.zeros(5, bool)).shape == (0, 2)
    mask = contacts.interval_mask([[4, 7], [8, 11]], 9)
    np.testing.assert_array_equal(mask, down)


def test_contacts_reject_bad_shapes():
    with pytest.raises(ValueError, match=r"\(T >= 2, F, K, 3\)"):
        contacts.foot_down(np.zeros((10, 2, 3)))
    with pytest.raises(ValueError, match="fps"):
        contacts.foot_speed(np.zeros((10, 1, 2, 3)), 0.0)


# --- IK -----------------------------------------------------------------------------------------------------

def leg() -> Skeleton:
    """root -> hip -> knee -> ankle -> toe, thigh 0.45 m and shin 0.42 m pointing down, toe forward (+z)."""
    return Skeleton(("root", "hip", "knee", "ankle", "toe"), [-1, 0, 1, 2, 3],
                    [[0, 1.0, 0], [0.1, -0.05, 0], [0, -0.45, 0], [0, -0.42, 0], [0, -0.05, 0.14]])


def random_bent_poses(rng, n):
    rot = Q.quat_from_rotvec(rng.normal(0, 0.3, (n, 5, 3)))
    rot[:, 2] = Q.quat_from_axis_angle([1.0, 0, 0], rng.uniform(0.2, 1.5, n))  # knee bends about x
    return rot, rng.normal(0, 0.2, (n, 3))


def bone_lengths(sk, rot, root):
    _, p = sk.forward_kinematics(rot, root)
    return np.linalg.norm(p[:, 1:] - p[:, sk.parents[1:]], axis=-1)


def test_reachable_targets_are_reached_exactly_with_bone_lengths_kept(rng):
    sk = leg()
    rot, root = random_bent_poses(rng, 500)
    _, p = sk.forward_kinematics(rot, root)
    direction = rng.normal(size=(500, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    target = p[:, 1] + direction * rng.uniform(0.05, 0.86, (500, 1))  # |a - b| = 0.03 < d < a + b = 0.87
    out = two_bone_ik(sk, rot, root, (1, 2, 3), target)
    _, q = sk.forward_kinematics(out, root)
    assert np.abs(q[:, 3] - target).max() < 1e-8
    np.testing.assert_allclose(bone_lengths(sk, out, root), bone_lengths(sk, rot, root), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(out, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_array_equal(out[:, [0, 4]], rot[:, [0, 4]])  # only the chain's rotations change


def test_knee_stays_in_the_plane_of_hip_target_and_animated_knee(rng):
    sk = leg()
    rot, root = random_bent_poses(rng, 300)
    _, p = sk.forward_kinematics(rot, root)
    target = p[:, 3] + rng.normal(0, 0.05, (300, 3))
    out = two_bone_ik(sk, rot, root, (1, 2, 3), target)
    _, q = sk.forward_kinematics(out, root)
    normal = np.cross(target - p[:, 1], p[:, 2] - p[:, 1])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    assert np.abs(np.sum((q[:, 2] - p[:, 1]) * normal, axis=1)).max() < 1e-9
    # ... on the same side as the animated knee (no flip), and small target moves give small knee moves.
    side = np.sum((q[:, 2] - p[:, 1]) * (p[:, 2] - p[:, 1]), axis=1)
    assert (side > 0).all()
    assert np.linalg.norm(q[:, 2] - p[:, 2], axis=1).max() < 0.5


def test_end_keeps_its_world_orientation_and_can_aim_its_child(rng):
    sk = leg()
    rot, root = random_bent_poses(rng, 50)
    g, p = sk.forward_kinematics(rot, root)
    target = p[:, 3] + [0.05, 0.02, -0.03]
    g2, _ = sk.forward_kinematics(two_bone_ik(sk, rot, root, (1, 2, 3), target), root)
    assert Q.quat_angle(g2[:, 3], g[:, 3]).max() < 1e-9
    aim = target + np.array([0.0, -0.05, 0.14])  # the toe straight ahead of the new ankle, as at rest
    _, q = sk.forward_kinematics(two_bone_ik(sk, rot, root, (1, 2, 3), target, aim=(4, aim)), root)
    toe = (q[:, 4] - q[:, 3]) / np.linalg.norm(q[:, 4] - q[:, 3], axis=1, keepdims=True)
    wanted = (aim - q[:, 3]) / np.linalg.norm(aim - q[:, 3], axis=1, keepdims=True)
    assert np.abs(toe - wanted).max() < 1e-9


@pytest.mark.parametrize("distance", [0.0, 0.01, 0.87, 2.0, 100.0])
def test_unreachable_targets_are_clamped_without_nan(rng, distance):
    sk = leg()
    rot, root = random_bent_poses(rng, 40)
    _, p = sk.forward_kinematics(rot, root)
    direction = rng.normal(size=(40, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    target = p[:, 1] + direction * distance
    out = two_bone_ik(sk, rot, root, (1, 2, 3), target)
    assert np.isfinite(out).all()
    _, q = sk.forward_kinematics(out, root)
    reach = np.linalg.norm(q[:, 3] - q[:, 1], axis=1)
    nearest = np.clip(distance, 0.03, 0.87)
    np.testing.assert_allclose(reach, nearest, atol=1e-6)
    if distance > 0:  # pointing at the target
        d = (q[:, 3] - q[:, 1]) / reach[:, None]
        assert np.abs(d - direction).max() < 1e-6
    np.testing.assert_allclose(bone_lengths(sk, out, root), bone_lengths(sk, rot, root), atol=1e-12)


def test_straight_leg_and_weights(rng):
    sk = leg()
    rot = Q.identity((3, 5))  # a straight leg: no plane to keep, any bend direction is fine but finite
    root = np.zeros((3, 3))
    _, p = sk.forward_kinematics(rot, root)
    target = p[:, 3] + [0.0, 0.1, 0.05]
    out = two_bone_ik(sk, rot, root, (1, 2, 3), target, weight=[0.0, 0.5, 1.0])
    _, q = sk.forward_kinematics(out, root)
    assert np.isfinite(out).all()
    # weight 0: unchanged, but for the 1e-9 margin inside full extension (the knee moves ~3e-5 m).
    np.testing.assert_allclose(q[0], p[0], atol=1e-4)
    np.testing.assert_allclose(q[1, 3], p[1, 3] + [0.0, 0.05, 0.025], atol=1e-9)
    np.testing.assert_allclose(q[2, 3], target[2], atol=1e-9)


def test_ik_rejects_chains_that_are_not_linked():
    with pytest.raises(ValueError, match="not start -> mid -> end"):
        two_bone_ik(leg(), Q.identity((1, 5)), None, (1, 3, 4), np.zeros((1, 3)))


def test_plant_feet_holds_a_sliding_foot_while_it_is_down():
    sk = leg()
    n = 60
    root = np.zeros((n, 3))
    root[:, 2] = np.arange(n) / FPS * 0.4  # the whole leg slides forward at 0.4 m/s
    rot = Q.identity((n, 5))
    rot[:, 2] = Q.quat_from_axis_angle([1.0, 0, 0], 0.6)
    down = np.zeros((n, 1), bool)
    down[10:22] = True
    out = plant_feet(sk, rot, root, [(1, 2, 3)], down, FPS, blend_frames=2, max_speed=0.1)
    _, p = sk.forward_kinematics(out, root)
    speed = np.linalg.norm(np.diff(p[:, 3, [0, 2]], axis=0), axis=1) * FPS
    assert speed[10:21].max() <= 0.1 + 1e-6  # held (creeping at most 0.1 m/s) while down
    np.testing.assert_allclose(out[:7], rot[:7])  # untouched well before the phase
    np.testing.assert_allclose(p[:, 3, 1], sk.forward_kinematics(rot, root)[1][:, 3, 1], atol=0.02)


def test_plant_feet_keeps_a_straight_knee_on_its_hinge():
    """A leg that straightens (knee bend 34 -> 0 degrees, then +-0.23 degrees of noise about straight) while its foot
    is held and the hips slide sideways: the knee's direction is noise there, so the solve keeps the hinge seen
    while it was bent. (Without it the hip twisted by 180 degrees from one frame to the next and the knee bent
    backwards.)"""
    sk = leg()
    n = 40
    frames = np.arange(n)
    bend = np.where(frames < 12, 0.6 * (1 - frames / 12), 0.004 * np.sin(frames * 1.3))
    rot = Q.identity((n, 5))
    rot[:, 2] = Q.quat_from_axis_angle([1.0, 0, 0], bend)
    root = np.stack([frames / FPS * 0.2, -0.002 * frames, np.zeros(n)], axis=1)
    down = (frames >= 14)[:, None]
    out = plant_feet(sk, rot, root, [(1, 2, 3)], down, FPS, blend_frames=2, max_speed=0.05)
    step = np.degrees(Q.quat_angle(out[1:], out[:-1]))  # (n - 1, 5) per frame and joint
    assert step.max() < 5.0, step.max(axis=0)  # the animation's own steps are 2.9 degrees at most
    g, p = sk.forward_kinematics(out, root)
    hinge = Q.rotate(g[:, 2], [1.0, 0.0, 0.0])  # the knee bends about its local x
    assert (np.sum(np.cross(p[:, 2] - p[:, 1], p[:, 3] - p[:, 2]) * hinge, axis=1) > 0).all()  # never backwards
    # The foot is held (creeping at max_speed, a little more where the leg is at full reach), the hips slide 0.2 m/s.
    assert np.linalg.norm(np.diff(p[16:, 3, [0, 2]], axis=0), axis=1).max() * FPS < 0.06
    # A leg straight in every pose has no hinge to keep: it is solved without one, not refused.
    straight = plant_feet(sk, Q.identity((n, 5)), root, [(1, 2, 3)], down, FPS, blend_frames=2, max_speed=0.05)
    assert np.isfinite(straight).all() and not np.allclose(straight, Q.identity((n, 5)))


def test_quat_between_turns_one_direction_into_the_other(rng):
    a = rng.normal(size=(200, 3))
    b = rng.normal(size=(200, 3)) * rng.uniform(0.1, 5, (200, 1))
    q = Q.quat_between(a, b)
    turned = Q.rotate(q, a)
    np.testing.assert_allclose(turned / np.linalg.norm(turned, axis=1, keepdims=True),
                               b / np.linalg.norm(b, axis=1, keepdims=True), atol=1e-12)
    # The smallest rotation: its angle is the angle between the directions.
    between = np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1))
    np.testing.assert_allclose(Q.quat_angle(q), between, atol=1e-12)
    opposite = Q.quat_between([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]], [[0.0, -2.0, 0.0], [-1.0, 0.0, 0.0]])
    np.testing.assert_allclose(Q.rotate(opposite, [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]),
                               [[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0]], atol=1e-12)


def _leg_angles(sk, rot, root):
    """Per frame: the thigh's direction (unit) and the knee's bend (degrees) of the leg (1, 2, 3)."""
    _, p = sk.forward_kinematics(rot, root)
    thigh, shin = p[:, 2] - p[:, 1], p[:, 3] - p[:, 2]
    thigh /= np.linalg.norm(thigh, axis=1, keepdims=True)
    shin /= np.linalg.norm(shin, axis=1, keepdims=True)
    return thigh, np.degrees(np.arccos(np.clip(np.sum(thigh * shin, axis=1), -1, 1)))


def test_plant_feet_holds_a_landing_foot_only_as_far_as_the_leg_keeps_its_pose():
    """A bent leg (knee 34 degrees) whose foot slides on at 2 m/s while it is down, as a 30 fps run's feet do as they
    land: held in place, the leg is pulled straight (the Bandai Namco run: knee 0 against the source's 48
    degrees).  With max_leg_change_deg the hold gives way: no thigh turns and no knee bend changes by more than
    that, and the foot is still held as far as the leg allows (it travels less than animated)."""
    sk = leg()
    n = 40
    root = np.zeros((n, 3))
    root[:, 2] = np.arange(n) / FPS * 2.0
    rot = Q.identity((n, 5))
    rot[:, 2] = Q.quat_from_axis_angle([1.0, 0, 0], 0.6)
    down = np.zeros((n, 1), bool)
    down[12:30] = True
    thigh0, bend0 = _leg_angles(sk, rot, root)
    free = plant_feet(sk, rot, root, [(1, 2, 3)], down, FPS, blend_frames=3, rest_speed=np.inf)
    assert np.abs(_leg_angles(sk, free, root)[1] - bend0).max() > 25.0  # unlimited: the knee is pulled straight
    out = plant_feet(sk, rot, root, [(1, 2, 3)], down, FPS, blend_frames=3, rest_speed=np.inf, max_leg_change_deg=10.0)
    thigh, bend = _leg_angles(sk, out, root)
    assert np.abs(bend - bend0).max() <= 10.0 + 1e-3
    assert np.degrees(np.arccos(np.clip(np.sum(thigh * thigh0, axis=1), -1, 1))).max() <= 10.0 + 1e-3
    ankle = sk.forward_kinematics(out, root)[1][:, 3, [0, 2]]
    assert np.linalg.norm(ankle[29] - ankle[12]) < 17 * 2.0 / FPS - 0.1  # animated: 1.13 m; held back by 0.1 m+
    # Where the held foot is within reach of the animated pose's tolerance the limit changes nothing.
    slow = root / 20.0  # 0.1 m/s: the hold moves the ankle by under 2 cm
    np.testing.assert_array_equal(
        plant_feet(sk, rot, slow, [(1, 2, 3)], down, FPS, blend_frames=3, max_leg_change_deg=10.0),
        plant_feet(sk, rot, slow, [(1, 2, 3)], down, FPS, blend_frames=3))
