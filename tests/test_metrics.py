"""Motion-quality metrics against values derived by hand from synthetic motions."""

import numpy as np
import pytest

from anim_core.clips import metrics
from anim_core.clips.metrics import (
    CONTACT_CLEARANCE_M,
    SKATE_SPEED_MPS,
    angular_velocity_jumps,
    foot_metrics,
    jerk_mean,
    mpjpe_mm,
    storage_bytes,
)
from anim_core.math import quat as Q

FPS = 30.0
T = 30
ANKLE, TOE = 0.08, 0.02  # flat-standing heights of an ankle and a toe joint


def foot_track(clearance, velocity_xz=(0.0, 0.0), height=ANKLE, n=T, fps=FPS):
    """(n, 3) positions of one joint at constant clearance (m) moving horizontally at ``velocity_xz`` (m/s)."""
    t = np.arange(n) / fps
    p = np.zeros((n, 3))
    p[:, 0] = 0.3 + velocity_xz[0] * t
    p[:, 2] = -0.1 + velocity_xz[1] * t
    p[:, 1] = height + np.broadcast_to(clearance, (n,))
    return p


def metrics_of(*tracks, heights=None, periodic=False, fps=FPS):
    """Metrics of feet tracked by one joint each."""
    feet = np.stack(tracks, axis=1)[:, :, None]
    heights = np.full(feet.shape[1], ANKLE) if heights is None else np.asarray(heights)
    return foot_metrics(feet, heights[:, None], fps, periodic=periodic)


def test_constants():
    assert CONTACT_CLEARANCE_M == 0.05
    assert SKATE_SPEED_MPS == 0.5


@pytest.mark.parametrize("periodic", [False, True])
def test_planted_foot_is_clean(periodic):
    m = metrics_of(foot_track(0.0), foot_track(0.0, height=TOE, n=T), heights=[ANKLE, TOE], periodic=periodic)
    assert m == {"foot_skate_ratio": 0.0, "foot_slide_mm": 0.0, "penetration_mm": 0.0, "floating_mm": 0.0}


def test_penetration_of_a_foot_below_the_floor():
    m = metrics_of(foot_track(-0.01))
    assert m["penetration_mm"] == pytest.approx(10.0, rel=1e-12)
    assert m["floating_mm"] == 0.0


def test_hovering_foot_floats_and_is_still_in_contact():
    # 3 cm above its flat height is within the 5 cm contact clearance: sliding fast there is skating.
    m = metrics_of(foot_track(0.03, velocity_xz=(1.0, 0.0)))
    assert m["floating_mm"] == pytest.approx(30.0, rel=1e-12)
    assert m["penetration_mm"] == 0.0
    assert m["foot_skate_ratio"] == 1.0
    assert m["foot_slide_mm"] == pytest.approx(1000.0 / FPS, rel=1e-12)


def test_penetration_and_floating_use_the_lowest_joint():
    m = metrics_of(foot_track(-0.01), foot_track(0.03, height=TOE), heights=[ANKLE, TOE])
    assert m["penetration_mm"] == pytest.approx(10.0, rel=1e-12)
    assert m["floating_mm"] == 0.0
    m = metrics_of(foot_track(0.04), foot_track(0.03, height=TOE), heights=[ANKLE, TOE])
    assert m["floating_mm"] == pytest.approx(30.0, rel=1e-12)


def test_fast_slide_on_the_floor_skates_every_frame():
    # 1 m/s along a diagonal in x-z: both horizontal axes count.
    v = np.array([0.6, 0.8])
    m = metrics_of(foot_track(0.0, velocity_xz=v))
    assert m["foot_skate_ratio"] == 1.0
    assert m["foot_slide_mm"] == pytest.approx(1.0 / FPS * 1000.0, rel=1e-12)


def test_slow_slide_is_sliding_but_not_skating():
    m = metrics_of(foot_track(0.0, velocity_xz=(0.0, 0.2)))
    assert m["foot_skate_ratio"] == 0.0
    assert m["foot_slide_mm"] == pytest.approx(0.2 / FPS * 1000.0, rel=1e-12)


@pytest.mark.parametrize("clearance", [0.06, 0.2])  # just above the 5 cm contact band, and well in the air
def test_fast_foot_in_the_air_is_not_counted(clearance):
    m = metrics_of(foot_track(clearance, velocity_xz=(3.0, 0.0)))
    assert m["foot_skate_ratio"] == 0.0
    assert m["foot_slide_mm"] == 0.0  # no in-contact samples at all
    assert m["floating_mm"] == pytest.approx(clearance * 1000.0, rel=1e-12)


def test_vertical_motion_in_contact_is_not_skating():
    # Tapping up and down fast (up to ~1.9 m/s vertically) inside the contact band, horizontally still.
    p = foot_track(0.0)
    p[:, 1] += 0.02 + 0.02 * np.sin(2 * np.pi * 15 * np.arange(T) / FPS + 0.5)
    m = metrics_of(p)
    assert m["foot_skate_ratio"] == 0.0
    assert m["foot_slide_mm"] == 0.0


def test_skate_ratio_counts_frames_with_any_skating_contact():
    half = T // 2
    planted = foot_track(0.0)
    sliding = foot_track(0.0, velocity_xz=(1.0, 0.0))
    sliding[half:, 1] += 0.2  # lifted off in the second half: fast but not in contact
    m = metrics_of(planted, sliding)
    assert m["foot_skate_ratio"] == 0.5
    # In contact: T planted samples (speed 0) and `half` sliding samples at 1 m/s.
    assert m["foot_slide_mm"] == pytest.approx(half * 1.0 / (T + half) / FPS * 1000.0, rel=1e-12)
    # Two joints skating in the same frames still count those frames once.
    m = metrics_of(sliding, sliding.copy())
    assert m["foot_skate_ratio"] == 0.5


def test_periodic_velocity_sees_the_jump_at_the_wrap():
    # 0.2 m/s forward over T frames, then back to the start: non-periodic differences never see the return.
    track = foot_track(0.0, velocity_xz=(0.2, 0.0))
    m = metrics_of(track, periodic=False)
    assert m["foot_skate_ratio"] == 0.0
    assert m["foot_slide_mm"] == pytest.approx(200.0 / FPS, rel=1e-12)
    # Periodic central differences at frames 0 and T-1 span the jump back: (0.2/fps * (1 - (T-1))) / (2/fps),
    # i.e. |v| = 0.1 (T - 2) m/s, while the T - 2 inner frames move at 0.2 m/s.
    m = metrics_of(track, periodic=True)
    assert 0.1 * (T - 2) > SKATE_SPEED_MPS
    assert m["foot_skate_ratio"] == pytest.approx(2.0 / T, rel=1e-12)
    mean_speed = ((T - 2) * 0.2 + 2 * 0.1 * (T - 2)) / T
    assert m["foot_slide_mm"] == pytest.approx(mean_speed / FPS * 1000.0, rel=1e-12)


def test_foot_metrics_rejects_bad_shapes():
    with pytest.raises(ValueError):
        foot_metrics(np.zeros((T, 2, 2, 3)), np.zeros((2, 3)), FPS)
    with pytest.raises(ValueError):
        foot_metrics(np.zeros((T, 2, 3)), np.zeros(2), FPS)


def test_a_foot_rolling_over_its_toe_is_not_skating():
    # Heel-off: the ankle moves forward at 1 m/s while the toe stays planted; both are within the contact band.
    ankle = foot_track(0.02, velocity_xz=(0.0, 1.0))
    toe = foot_track(0.0, height=TOE)
    m = foot_metrics(np.stack([ankle, toe], axis=1)[:, None], np.array([[ANKLE, TOE]]), FPS, periodic=False)
    assert m["foot_skate_ratio"] == 0.0
    assert m["foot_slide_mm"] == 0.0
    # The same foot sliding as a whole skates.
    toe_sliding = foot_track(0.0, velocity_xz=(0.0, 1.0), height=TOE)
    m = foot_metrics(np.stack([ankle, toe_sliding], axis=1)[:, None], np.array([[ANKLE, TOE]]), FPS,
                     periodic=False)
    assert m["foot_skate_ratio"] == 1.0
    assert m["foot_slide_mm"] == pytest.approx(1000.0 / FPS, rel=1e-12)


def test_a_foot_is_in_contact_only_when_all_its_joints_are_down():
    # The toe skims the floor fast while the ankle is 8 cm up: a swinging foot, not a planted one.
    ankle = foot_track(0.08, velocity_xz=(0.0, 2.0))
    toe = foot_track(0.01, velocity_xz=(0.0, 2.0), height=TOE)
    m = foot_metrics(np.stack([ankle, toe], axis=1)[:, None], np.array([[ANKLE, TOE]]), FPS, periodic=False)
    assert m["foot_skate_ratio"] == 0.0
    assert m["foot_slide_mm"] == 0.0
    assert m["floating_mm"] == pytest.approx(10.0, rel=1e-9)  # the lowest joint is the toe, 1 cm up


def test_ground_velocity_turns_a_treadmill_foot_into_a_planted_one():
    # In place, a planted foot moves backwards at the walking speed; adding the travel back makes it still.
    back = foot_track(0.0, velocity_xz=(0.0, -1.2))[:, None, None]
    m = foot_metrics(back, np.array([[ANKLE]]), FPS, periodic=False, ground_velocity=[0.0, 0.0, 1.2])
    assert m["foot_skate_ratio"] == 0.0
    assert m["foot_slide_mm"] == pytest.approx(0.0, abs=1e-9)
    m = foot_metrics(back, np.array([[ANKLE]]), FPS, periodic=False)
    assert m["foot_skate_ratio"] == 1.0


def test_mpjpe(rng):
    n_frames, n_joints = 20, 7
    a = rng.normal(size=(n_frames, n_joints, 3))
    assert mpjpe_mm(a, a.copy()) == 0.0
    b = a.copy()
    b[:, 3] += (0.003, 0.004, 0.0)  # 5 mm on one non-root joint of n_joints
    assert mpjpe_mm(a, b) == pytest.approx(5.0 / n_joints, rel=1e-9)
    # A different translation of the whole body in every frame changes nothing relative to the root.
    moved = a + rng.normal(size=(n_frames, 1, 3))
    assert mpjpe_mm(a, moved) == pytest.approx(0.0, abs=1e-9)
    # Moving the root alone moves every other joint relative to it: (J - 1) of J joints off by 5 mm.
    c = a.copy()
    c[:, 0] += (0.0, 0.003, 0.004)
    assert mpjpe_mm(a, c) == pytest.approx(5.0 * (n_joints - 1) / n_joints, rel=1e-9)
    # Another root joint: the moved joint 0 is now the only one off.
    assert mpjpe_mm(a, c, root=2) == pytest.approx(5.0 / n_joints, rel=1e-9)


def test_jerk_of_a_cubic_is_six():
    t = np.arange(31) / FPS
    p = np.zeros((t.size, 2, 3))
    p[:, 0, 0] = t**3  # d³/dt³ t³ = 6, and third differences of a cubic are exact
    p[:, 1, 2] = -(t**3)
    assert jerk_mean(p, FPS, periodic=False) == pytest.approx(6.0, rel=1e-6)


def test_jerk_of_a_periodic_sine():
    amplitude, omega, fps = 0.1, 2 * np.pi, 120.0
    n = 120  # exactly one period, no repeated end frame
    t = np.arange(n) / fps
    p = np.zeros((n, 3, 3))
    joints = np.arange(3)
    p[:, joints, joints] = amplitude * np.sin(omega * t[:, None] + np.array([0.0, 0.7, 2.0]))
    # |x'''| = A w³ |cos(w t + phase)|, whose mean over a period is A w³ * 2/pi.
    expected = amplitude * omega**3 * 2.0 / np.pi
    assert jerk_mean(p, fps, periodic=True) == pytest.approx(expected, rel=0.01)


def test_jerk_sees_a_step_at_the_loop_seam():
    n, fps, slope = 40, FPS, 0.002  # m per frame
    ramp = np.zeros((n, 1, 3))
    ramp[:, 0, 0] = slope * np.arange(n)
    # Inside the clip the ramp has no third difference; across the seam it drops by slope * n, which the three
    # wrapping third differences see as -1, +2, -1 times that drop.  Mean over n differences: 4 * slope * fps³.
    assert jerk_mean(ramp, fps, periodic=False) == pytest.approx(0.0, abs=1e-9)
    assert jerk_mean(ramp, fps, periodic=True) == pytest.approx(4.0 * slope * fps**3, rel=1e-9)
    # On top of smooth periodic motion the seam is what dominates.
    t = np.arange(n) / fps
    smooth = np.zeros((n, 1, 3))
    smooth[:, 0, 1] = 0.05 * np.sin(2 * np.pi * t * fps / n)
    assert jerk_mean(smooth + ramp, fps) > 10.0 * jerk_mean(smooth, fps)


def _constant_spin(omega, offset):
    """q(t) = exp(t omega / 2) q0 per joint: constant angular velocity ``omega (J, 3)`` rad/s."""

    def sample(times):
        return Q.quat_mul(Q.quat_exp(times[:, None, None] * omega[None] * 0.5), offset[None])

    return sample


def test_constant_angular_velocity_has_no_jumps(rng):
    n_joints = 4
    omega = rng.normal(scale=3.0, size=(n_joints, 3))
    offset = Q.quat_normalize(rng.normal(size=(n_joints, 4)))
    keys = np.sort(rng.uniform(0.0, 2.0, 6))
    assert angular_velocity_jumps(_constant_spin(omega, offset), keys) < 1e-6


def _switching_spin(w1, w2, t_switch=1.0):
    """Spins at ``w1 (J, 3)`` rad/s until ``t_switch``, then at ``w2`` (both composed on the parent side)."""

    def sample(times):
        at_switch = Q.quat_exp(t_switch * w1 * 0.5)[None]
        early = Q.quat_exp(times[:, None, None] * w1[None] * 0.5)
        late = Q.quat_mul(Q.quat_exp((times - t_switch)[:, None, None] * w2[None] * 0.5), at_switch)
        return np.where((times <= t_switch)[:, None, None], early, late)

    return sample


def test_switching_angular_velocity_jumps_by_the_difference():
    w1 = np.array([[0.0, 2.0, 0.0]])
    w2 = np.array([[1.0, 0.0, 0.5]])
    jump = np.linalg.norm(w2 - w1)
    assert angular_velocity_jumps(_switching_spin(w1, w2), [1.0]) == pytest.approx(jump, abs=1e-3)


def test_angular_velocity_jumps_average_over_keys_and_joints(rng):
    w1 = rng.normal(scale=2.0, size=(3, 3))
    w2 = rng.normal(scale=2.0, size=(3, 3))
    # Key 0.5 lies inside the first constant spin (no jump); key 1.0 is the switch.
    expected = np.linalg.norm(w2 - w1, axis=-1).sum() / (2 * 3)
    assert angular_velocity_jumps(_switching_spin(w1, w2), [0.5, 1.0]) == pytest.approx(expected, abs=1e-3)


def test_angular_velocity_jumps_ignore_quaternion_signs(rng):
    w1 = rng.normal(scale=2.0, size=(3, 3))
    w2 = rng.normal(scale=2.0, size=(3, 3))
    inner = _switching_spin(w1, w2)
    keys = np.array([0.5, 1.0])
    reference = angular_velocity_jumps(inner, keys)

    def flipped(times):
        # q and -q are the same rotation: flip signs in a pattern that differs between neighbouring samples.
        sign = np.where(rng.uniform(size=(times.size, 3)) < 0.5, -1.0, 1.0)
        return inner(times) * sign[..., None]

    assert angular_velocity_jumps(flipped, keys) == pytest.approx(reference, abs=1e-9)


def test_angular_velocity_jumps_samples_in_one_call():
    calls = []
    inner = _constant_spin(np.array([[0.0, 1.0, 0.0]]), Q.identity((1,)))

    def sample(times):
        calls.append(np.array(times))
        return inner(times)

    keys = np.array([0.25, 0.5, 0.75])
    angular_velocity_jumps(sample, keys, delta=1e-3)
    assert len(calls) == 1
    np.testing.assert_allclose(np.sort(calls[0]), np.sort(np.concatenate([keys - 1e-3, keys, keys + 1e-3])))


def test_storage_bytes():
    # 31 joints: 31 quaternions (124 floats) + root translation (3) + key time (1) = 128 float32 = 512 bytes per key.
    assert storage_bytes(10, 31) == 10 * 512
    assert storage_bytes(1, 1) == (4 + 3 + 1) * 4
    assert storage_bytes(0, 31) == 0
    assert isinstance(storage_bytes(3, 2), int)


def test_phase_alignment_finds_the_lag_of_a_shifted_signal():
    t = np.arange(80)
    a = np.sin(2 * np.pi * t / 80) + 0.3 * np.sin(6 * np.pi * t / 80)
    assert metrics.phase_alignment(a, a) == (pytest.approx(1.0), 0)
    r0, lag = metrics.phase_alignment(a, np.roll(a, 3))  # other[t] = a[t - 3]: three frames late
    assert lag == 3 and r0 < 0.99
    assert metrics.phase_alignment(a, np.roll(a, -5))[1] == -5
    # Twice per period (a gait's hips): half a period looks like lag 0 unless the search is limited.
    bob = np.cos(4 * np.pi * t / 80)
    assert metrics.phase_alignment(bob, np.roll(bob, 2), max_lag=20)[1] == 2
    # Channels are pooled; a constant channel contributes nothing but does not break the correlation.
    two = np.stack([a, np.full(80, 2.0)], axis=1)
    r, lag = metrics.phase_alignment(two, np.stack([np.roll(a, 1), np.full(80, 5.0)], axis=1))
    assert lag == 1 and 0.4 < r < 0.5  # half of a one-frame-late correlation near 0.99
    with pytest.raises(ValueError, match="same shape"):
        metrics.phase_alignment(a, a[:-1])


def test_seam_jump_is_the_step_across_the_wrap():
    t = np.arange(40) / 40
    p = np.zeros((40, 2, 3))
    p[:, 1, 0] = np.sin(2 * np.pi * t)  # 1 m circle-ish motion: steps of ~157 mm at most
    steps = metrics.frame_steps_mm(p)
    assert steps.shape == (40,)
    assert metrics.seam_jump_mm(p) == pytest.approx(1000 * abs(p[0, 1, 0] - p[-1, 1, 0]))
    assert metrics.seam_jump_mm(p) <= metrics.seam_limit_mm(p)
    popped = p.copy()
    popped[:, 1, 1] = 0.05 * t  # drifts 5 cm over the period and jumps back at the wrap
    assert metrics.seam_jump_mm(popped) > 49
    assert metrics.seam_limit_mm(popped) == pytest.approx(2 * np.median(metrics.frame_steps_mm(popped)[:-1]) + 5)
