"""The level-of-detail methods of issue 38 on small synthetic skeletons: update_rate holds the reference's poses
exactly and changes them only at the update frames (worked out by hand below), its crowd path poses a character
only when its pose changes; bone_lod leaves every other joint bit-identical; skin_influences keeps the strongest
weights and changes the skin only where weights were dropped."""

import numpy as np
import pytest

from anim_core.math import quat as Q
from anim_core.math.clip import KeyframeClip
from anim_core.math.skeleton import Skeleton
from anim_core.math.skinning import SkinnedMesh, invert_transforms, transforms
from anim_core.methods.builders import UpdateRateParams, update_rate_refused
from anim_core.methods.conditions import Condition, ConditionError
from anim_core.methods.lod import HeldClip, bone_lod, frozen_joints, max_influences, strongest_influences
from anim_core.runtime import HeldCrowd, runtime_for
from tests.synthetic import biped, random_rotations

FPS = 30


def grid_clip(rng, n_keys, mode="loop", in_place=False):
    sk = biped()
    rot = random_rotations(rng, (n_keys, sk.n_joints))
    root = np.cumsum(rng.normal(scale=0.05, size=(n_keys, 3)), axis=0)
    if mode == "loop":
        rot[-1], root[-1] = rot[0], root[0] + [0.3, 0.0, 0.0]
    return KeyframeClip(sk, np.arange(n_keys) / FPS, rot, root, mode, in_place)


def changes(clip, n_frames):
    """Frames at which the pose differs in any bit from the frame before (frame 0 counts)."""
    pose = clip.sample(np.arange(n_frames) / FPS)
    differ = np.any(pose.rotations[1:] != pose.rotations[:-1], axis=(1, 2))
    return [0, *(np.flatnonzero(differ) + 1).tolist()]


# Update frames on the 30 fps grid, by hand: rate 6 every 5 frames; rate 4 at k * 7.5 frames rounded up; rate 16
# at k * 1.875 frames rounded up.
@pytest.mark.parametrize("rate, expected", [
    (6, [0, 5, 10, 15, 20, 25, 30, 35]),
    (4, [0, 8, 15, 23, 30, 38]),
    (16, [0, 2, 4, 6, 8, 10, 12, 14, 15, 17, 19, 21, 23, 25, 27, 29, 30, 32, 34, 36, 38]),
])
def test_update_rate_holds_reference_poses_exactly_and_changes_only_at_update_frames(rng, rate, expected):
    ref = grid_clip(rng, 41)  # a loop of 40 frames
    held = HeldClip(ref, rate, FPS)
    assert changes(held, 40) == expected
    pose = held.sample(np.arange(40) / FPS)
    shown = np.repeat(expected, np.diff([*expected, 40]))  # the last update frame at or before each frame
    np.testing.assert_array_equal(pose.rotations, ref.rotations[shown])
    np.testing.assert_array_equal(held.key_times, np.array(expected) / FPS)
    # A loop restarts at its seam and travels on: the second cycle is the first moved by one stride.
    again = held.sample(np.arange(40, 80) / FPS)
    np.testing.assert_array_equal(again.rotations, pose.rotations)
    np.testing.assert_allclose(again.root_translation - pose.root_translation, [[0.3, 0.0, 0.0]] * 40, atol=1e-12)


def test_update_rate_ping_pong_holds_on_running_time(rng):
    ref = grid_clip(rng, 11, mode="pingpong")  # 10 frames forward, 10 back
    held = HeldClip(ref, 6, FPS)
    # Running frames 0-4 show key 0, 5-9 key 5, 10-14 key 10 (the turn), 15-19 key 5 again on the way back.
    np.testing.assert_array_equal(held.shown, [0] * 5 + [5] * 5 + [10] * 5 + [5] * 5)
    pose = held.sample(np.arange(20) / FPS)
    np.testing.assert_array_equal(pose.rotations[15], ref.rotations[5])


def test_update_rate_at_or_above_the_clip_rate_is_refused(rng):
    ref = grid_clip(rng, 11)
    for rate in (30, 45):
        with pytest.raises(ValueError, match="below the clip's own rate of 30"):
            HeldClip(ref, rate, FPS)
        assert "at or above the clips' own rate of 30" in update_rate_refused(UpdateRateParams(rate=rate), FPS)
    assert update_rate_refused(UpdateRateParams(rate=24), FPS) is None
    with pytest.raises(ConditionError, match="rate: Input should be greater than 0"):
        Condition.parse("x", "update_rate", {"rate": 0})


def test_held_crowd_poses_only_characters_whose_pose_changed(rng):
    ref = grid_clip(rng, 41)
    held = HeldClip(ref, 6, FPS)
    runtime = runtime_for(ref)
    n = 50
    crowd = HeldCrowd(held, runtime, n)
    phases = rng.uniform(0.0, 3.0, n)
    posed = []
    for frame in range(61):  # one second of a 60 Hz clock after the first frame
        t = phases + frame / 60.0
        out = crowd.pose(t)
        posed.append(crowd.posed)
        full = runtime.pose(held.held_time(t))  # every character posed at its held time
        np.testing.assert_array_equal(out.rotations, full.rotations)
        np.testing.assert_array_equal(out.positions, full.positions)
    assert posed[0] == n
    # At 6 updates a second each character is re-posed 6 times in a second (5 or 7 at the ends of the window).
    assert 5 * n <= sum(posed[1:]) <= 7 * n


def test_bone_lod_holds_its_joints_at_bind_and_leaves_the_others_bit_identical(rng):
    ref = grid_clip(rng, 21)
    sk = ref.skeleton
    bind_local = random_rotations(rng, (sk.n_joints,))
    bind_global, _ = sk.forward_kinematics(bind_local[None], np.zeros((1, 3)))
    frozen = frozen_joints(sk, None, 1)
    # Depth 1 keeps the hips, the spine and the thighs; everything deeper is held.
    assert [n for n, f in zip(sk.names, frozen, strict=True) if f] == [
        "Head", "LeftLeg", "LeftFoot", "RightLeg", "RightFoot"]
    clip = bone_lod(ref, frozen, bind_global[0])
    assert np.array_equal(clip.rotations[:, ~frozen], ref.rotations[:, ~frozen])
    q = Q.quat_normalize(np.broadcast_to(bind_local[frozen], clip.rotations[:, frozen].shape))
    np.testing.assert_allclose(np.abs(np.sum(clip.rotations[:, frozen] * q, axis=-1)), 1.0, atol=1e-12)
    t = np.arange(40) / FPS
    a, b = clip.sample(t), ref.sample(t)
    assert np.array_equal(a.rotations[:, ~frozen], b.rotations[:, ~frozen])
    ga, _ = sk.forward_kinematics(*a)
    gb, _ = sk.forward_kinematics(*b)
    untouched = np.array([n in ("Hips", "Spine", "LeftUpLeg", "RightUpLeg") for n in sk.names])
    assert np.array_equal(ga[:, untouched], gb[:, untouched])


def test_bone_lod_named_sets_must_exist_on_the_character():
    sk = biped()
    with pytest.raises(ValueError, match="joints = 'fingers': the character has no joint of that set"):
        frozen_joints(sk, "fingers", None)
    with pytest.raises(ValueError, match="depth = 3: the character has no joint deeper than 3"):
        frozen_joints(sk, None, 3)
    neck = Skeleton(("Hips", "Neck", "Neck1", "Head"), (-1, 0, 1, 2), np.ones((4, 3)))
    assert frozen_joints(neck, "neck", None).tolist() == [False, True, True, False]
    with pytest.raises(ConditionError, match="give exactly one of joints"):
        Condition.parse("x", "bone_lod", {"joints": "toes", "depth": 2})
    with pytest.raises(ConditionError, match="joints: Input should be 'fingers', 'toes' or 'neck'"):
        Condition.parse("x", "bone_lod", {"joints": "ears"})


def test_strongest_influences_by_hand():
    joints = np.array([[1, 2, 3, 0], [4, 0, 0, 0], [5, 6, 7, 0]])
    weights = np.array([[0.5, 0.3, 0.2, 0.0], [1.0, 0.0, 0.0, 0.0], [0.1, 0.6, 0.3, 0.0]])
    j, w = strongest_influences(joints, weights, 2)
    np.testing.assert_array_equal(j, [[1, 2], [4, 0], [6, 7]])
    np.testing.assert_allclose(w, [[0.625, 0.375], [1.0, 0.0], [2 / 3, 1 / 3]], atol=1e-15)
    assert w[1, 0] == 1.0  # a vertex that loses nothing keeps its weights bit for bit
    assert max_influences(weights) == 3


def test_fewer_influences_change_the_skin_only_where_weights_were_dropped(rng):
    sk = biped()
    v = rng.normal(size=(300, 3))
    count = rng.integers(1, 5, 300)  # 1..4 influences per vertex
    joints = np.stack([rng.permutation(sk.n_joints)[:4] for _ in range(300)])
    weights = rng.uniform(0.1, 1.0, (300, 4)) * (np.arange(4) < count[:, None])
    weights /= weights.sum(axis=1, keepdims=True)
    rest_g, rest_p = sk.forward_kinematics(np.tile([1.0, 0.0, 0.0, 0.0], (1, sk.n_joints, 1)), np.zeros((1, 3)))
    inverse_bind = invert_transforms(transforms(rest_g[0], rest_p[0]))
    full = SkinnedMesh(v, v / np.linalg.norm(v, axis=1, keepdims=True), joints, weights, inverse_bind)
    g, p = sk.forward_kinematics(random_rotations(rng, (1, sk.n_joints)), np.zeros((1, 3)))
    pos_full, _ = full.skin(full.skinning_matrices(g, p))
    for k in (1, 2, 3):
        cut = SkinnedMesh(full.vertices, full.normals, *strongest_influences(joints, weights, k), inverse_bind)
        pos_cut, _ = cut.skin(cut.skinning_matrices(g, p))
        dropped = count > k
        assert np.array_equal(pos_cut[0, ~dropped], pos_full[0, ~dropped])
        moved = np.linalg.norm(pos_cut[0] - pos_full[0], axis=-1)
        assert np.all(moved[dropped] > 1e-9)


def test_the_benchmark_times_a_held_clip_by_its_held_path(rng):
    from anim_core.bench.suite import _accuracy, _runtime_step
    from anim_core.runtime import HeldRuntime

    ref = grid_clip(rng, 41)
    held = HeldClip(ref, 6, FPS)
    runtime = runtime_for(held)
    assert isinstance(runtime, HeldRuntime)
    t = rng.uniform(0.0, 3.0, 20)
    np.testing.assert_array_equal(runtime.pose(t).rotations, runtime_for(ref).pose(held.held_time(t)).rotations)
    step = _runtime_step(runtime, 20)
    np.testing.assert_array_equal(step(t, 0).rotations, runtime.pose(t).rotations)

    class Clip:  # what _accuracy reads of a built clip
        clip, fps = held, FPS

    # The held runtime shows the held clip's poses: within float32 of the exact curve.
    assert _accuracy(Clip, "keys", runtime, 8 * FPS, {})["max_error_deg"] < 0.01
