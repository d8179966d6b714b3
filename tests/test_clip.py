"""Keyframe clips: sampling, playback modes, resampling."""

import numpy as np
import pytest

from anim_core.math import quat as Q
from anim_core.math.clip import KeyframeClip, playback_time
from tests.synthetic import biped, random_rotations


def make_clip(rng, mode="loop", in_place=False, n_keys=11, rate=30.0):
    skeleton = biped()
    times = np.arange(n_keys) / rate
    rot = random_rotations(rng, (n_keys, skeleton.n_joints))
    root = np.cumsum(rng.normal(scale=0.05, size=(n_keys, 3)), axis=0)
    root[:, 2] += np.linspace(0.0, 1.0, n_keys)  # walks forward 1 unit per cycle
    return KeyframeClip(skeleton, times, rot, root, mode=mode, in_place=in_place)


@pytest.mark.parametrize("method", ["nlerp", "slerp"])
def test_sampling_at_key_times_returns_the_keys(rng, method):
    clip = make_clip(rng)
    pose = clip.sample(clip.times[:-1], method=method)
    assert Q.quat_angle(pose.rotations, clip.rotations[:-1]).max() < 1e-14
    np.testing.assert_allclose(pose.root_translation, clip.root_translation[:-1], atol=1e-15)


def test_slerp_sampling_moves_at_constant_speed_between_keys(rng):
    clip = make_clip(rng, mode="clamp")
    t = clip.times[3] + np.array([0.25, 0.5, 0.75]) / 30.0
    pose = clip.sample(t, method="slerp")
    full = Q.quat_angle(clip.rotations[4], clip.rotations[3])
    for k, frac in enumerate((0.25, 0.5, 0.75)):
        np.testing.assert_allclose(Q.quat_angle(pose.rotations[k], clip.rotations[3]), frac * full, atol=1e-7)
    nl = clip.sample(t, method="nlerp")
    assert Q.quat_angle(nl.rotations, pose.rotations).max() > 1e-4  # nlerp is not slerp: the test can tell


def test_loop_wraps_rotations_and_carries_the_root_forward(rng):
    clip = make_clip(rng)
    t = rng.uniform(0, clip.duration, 50)
    a, b = clip.sample(t), clip.sample(t + 2 * clip.duration)
    assert Q.quat_angle(a.rotations, b.rotations).max() < 1e-12
    step = clip.root_translation[-1] - clip.root_translation[0]
    step[1] = 0.0  # the root climbs nothing per cycle, only moves horizontally
    np.testing.assert_allclose(b.root_translation - a.root_translation, np.broadcast_to(2 * step, (50, 3)), atol=1e-12)


def test_in_place_loop_stays_in_place(rng):
    clip = make_clip(rng, in_place=True)
    t = rng.uniform(0, clip.duration, 50)
    a, b = clip.sample(t), clip.sample(t + 3 * clip.duration)
    np.testing.assert_allclose(a.root_translation, b.root_translation, atol=1e-12)
    start, end = clip.sample(np.array([0.0, clip.duration])).root_translation
    np.testing.assert_allclose(start[[0, 2]], end[[0, 2]], atol=1e-12)


def test_pingpong_and_clamp(rng):
    clip = make_clip(rng, mode="pingpong")
    x = rng.uniform(0, clip.duration, 40)
    fwd, back = clip.sample(x), clip.sample(2 * clip.duration - x)
    assert Q.quat_angle(fwd.rotations, back.rotations).max() < 1e-12
    later = clip.sample(x + 4 * clip.duration)
    np.testing.assert_allclose(later.rotations, fwd.rotations, atol=1e-12)
    clamped = make_clip(rng, mode="clamp")
    last = clamped.sample(np.array([clamped.duration, clamped.duration + 5.0]))
    np.testing.assert_allclose(last.rotations[0], last.rotations[1])
    t_map, cycles = playback_time(np.array([-1.0, 0.5, 2.5]), 1.0, "loop")
    np.testing.assert_allclose(t_map, [0.0, 0.5, 0.5])
    np.testing.assert_allclose(cycles, [-1.0, 0.0, 2.0])


def test_resample_keeps_original_keys_and_end(rng):
    clip = make_clip(rng, n_keys=31, rate=30.0)
    fine = clip.resample(120.0)
    assert fine.n_keys == 121
    assert Q.quat_angle(fine.rotations[::4], clip.rotations).max() < 1e-12
    coarse = clip.resample(7.0)
    np.testing.assert_allclose(coarse.times[-1], clip.duration)
    mid = clip.sample(coarse.times[:-1], method="slerp")  # (a loop maps its end time to the start)
    assert Q.quat_angle(coarse.rotations[:-1], mid.rotations).max() < 1e-12
    assert Q.quat_angle(coarse.rotations[-1], clip.rotations[-1]).max() < 1e-12


def test_invalid_clips_are_rejected(rng):
    skeleton = biped()
    rot = random_rotations(rng, (3, skeleton.n_joints))
    with pytest.raises(ValueError, match="strictly increasing"):
        KeyframeClip(skeleton, [0.0, 0.1, 0.1], rot, np.zeros((3, 3)))
    with pytest.raises(ValueError, match="expected rotations"):
        KeyframeClip(skeleton, [0.0, 0.1, 0.2], rot[:, :4], np.zeros((3, 3)))
    with pytest.raises(ValueError, match="playback mode"):
        KeyframeClip(skeleton, [0.0, 0.1, 0.2], rot, np.zeros((3, 3)), mode="bounce")
    with pytest.raises(ValueError, match="fewer than 2 keys"):
        make_clip(rng).segment(0.05, 0.06)


def test_closed_loop_repeats_the_first_key_and_keeps_the_motion_close(rng):
    clip = make_clip(rng, n_keys=31)
    closed = clip.closed_loop()
    assert Q.quat_angle(closed.rotations[-1], closed.rotations[0]).max() < 1e-12
    np.testing.assert_allclose(closed.root_translation[-1, 1], closed.root_translation[0, 1], atol=1e-15)
    # The first key is untouched; key k moves by at most k/(K-1) of the mismatch.
    assert Q.quat_angle(closed.rotations[0], clip.rotations[0]).max() < 1e-12
    mismatch = Q.quat_angle(clip.rotations[-1], clip.rotations[0])
    moved = Q.quat_angle(closed.rotations, clip.rotations)
    assert np.all(moved <= (clip.times / clip.duration)[:, None] * mismatch + 1e-12)
