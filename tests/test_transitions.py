"""Composite motion (issue 39): transitions, layers, parametric blends.  Expected values are written by hand or
taken from the source clips, never from the code under test; random inputs are seeded."""

from __future__ import annotations

import numpy as np
import pytest

from anim_core.clips.metrics import foot_metrics
from anim_core.math import quat as Q
from anim_core.math.clip import KeyframeClip
from anim_core.methods.transition_feet import FeetLock, landings
from anim_core.methods.transitions import (
    CompositeError,
    TransitionSpec,
    additive,
    additive_delta,
    blend_weights,
    compose_sequence,
    joint_mask,
    override,
    parametric,
    quintic_offset,
)
from tests.synthetic import biped, random_rotations

FPS = 30
BIPED_SETS = {"upper_body": (("Spine",), ()), "lower_body": (("Hips",), ("Spine",)),
              "left_leg": (("LeftUpLeg",), ())}


def _swing(amplitude: float, period: float, speed: float, seconds: float = 2.0, phase: float = 0.0,
           in_place: bool = False) -> KeyframeClip:
    """A looping biped clip: legs and spine swing sinusoidally about X, the root moving at ``speed`` m/s along Z."""
    sk = biped()
    t = np.arange(round(seconds * 120) + 1) / 120
    angle = amplitude * np.sin(2 * np.pi * t / period + phase)
    rot = np.tile(Q.identity((sk.n_joints,)), (t.size, 1, 1))
    for j, sign in ((3, 1), (4, 0.5), (6, -1), (7, -0.5), (1, 0.3)):
        rot[:, j] = Q.quat_from_axis_angle([1, 0, 0], sign * angle)
    root = np.stack([np.zeros_like(t), 0.05 * np.cos(4 * np.pi * t / period), speed * t], axis=-1)
    return KeyframeClip(sk, t, rot, root, "loop", in_place, 1, "swing")


def _circle(amplitude: float = 0.5, speed: float = 1.4) -> KeyframeClip:
    """A 1.0 s looping biped clip whose pose is different at every phase (the left hip swings as sin, the right as
    cos of 2 pi t), unlike :func:`_swing`, whose poses repeat mirrored in time within a cycle."""
    sk = biped()
    t = np.arange(121) / 120
    rot = np.tile(Q.identity((sk.n_joints,)), (t.size, 1, 1))
    rot[:, 3] = Q.quat_from_axis_angle([1, 0, 0], amplitude * np.sin(2 * np.pi * t))
    rot[:, 6] = Q.quat_from_axis_angle([1, 0, 0], amplitude * np.cos(2 * np.pi * t))
    root = np.stack([np.zeros_like(t), np.full_like(t, 0.9), speed * t], axis=-1)
    return KeyframeClip(sk, t, rot, root, "loop", False, 1, "circle")


def test_weights_by_hand() -> None:
    # 100 ms at 30 fps: frames 0..3 after the switch are 0, 1/3, 2/3, 1.
    u = np.arange(5) / FPS
    assert np.allclose(blend_weights(u, 0.1), [0, 1 / 3, 2 / 3, 1, 1], atol=1e-12)
    # smoothstep 3s^2 - 2s^3 at s = 1/3, 2/3: 7/27, 20/27
    assert np.allclose(blend_weights(u, 0.1, "smoothstep"), [0, 7 / 27, 20 / 27, 1, 1], atol=1e-12)
    assert np.array_equal(blend_weights(np.array([-0.01, 0.0, 0.2]), 0.0), [0, 1, 1])


@pytest.mark.parametrize("curve", ["linear", "smoothstep"])
def test_crossfade_weights_exact_at_every_frame(curve: str) -> None:
    walk, run = _swing(0.5, 1.0, 1.4), _swing(0.9, 0.7, 3.0, phase=1.0)
    comp = compose_sequence([(walk, 1.0), (run, 1.0)], FPS, TransitionSpec("crossfade", 0.25, curve))  # type: ignore[arg-type]
    u = (np.arange(60) % 30) / FPS  # seconds since the switch (at frames 0 and 30)
    s = np.clip(u / 0.25, 0, 1)
    expected = s if curve == "linear" else 3 * s**2 - 2 * s**3
    assert comp.switch_frames == (0, 30)
    assert np.allclose(comp.weights, expected, atol=1e-12)
    # Where the weight is 1, the pose is the incoming clip's own (bit for bit).
    settled = np.flatnonzero(comp.weights[30:] == 1.0) + 30
    assert np.array_equal(comp.rotations[settled], run.sample((settled - 30) / FPS).rotations)
    # Where it is 0 (the switch frame), the outgoing clip's own pose at its segment's end.
    assert np.array_equal(comp.rotations[30], walk.sample(np.array([1.0])).rotations[0])


def test_cut_is_the_incoming_clip_and_root_does_not_jump() -> None:
    walk, run = _swing(0.5, 1.0, 1.4), _swing(0.9, 0.7, 3.0, phase=1.0)
    comp = compose_sequence([(walk, 1.0), (run, 1.0)], FPS, TransitionSpec("cut"))
    assert np.array_equal(comp.rotations[30:60], run.sample(np.arange(30) / FPS).rotations)
    step = np.diff(comp.clip.root_translation[:, 2])
    # Root moves 1.4 m/s * 1/30 s = 46.7 mm per frame on the walk, 100 mm on the run: never more than the run's.
    assert step.max() <= 3.0 / FPS + 1e-6
    assert step.min() >= 1.4 / FPS * 0.99


def test_inertialization_continuous_in_position_and_velocity() -> None:
    fps = 1200  # fine grid: differences approximate the derivatives
    walk, run = _swing(0.5, 1.0, 1.4), _swing(0.9, 0.7, 3.0, phase=1.0)
    comp = compose_sequence([(walk, 1.0), (run, 1.0)], fps, TransitionSpec("inertialization", 0.25))
    f = fps  # the switch walk -> run
    h = 1.0 / fps
    q = Q.make_continuous(comp.clip.rotations, axis=0)
    a = walk.sample(np.array([1.0 - h, 1.0, 1.0 + h])).rotations
    a = Q.align_hemisphere(a, q[f])
    # position: the pose at the switch is the outgoing clip's (to rounding)
    assert np.abs(q[f] - a[1]).max() < 1e-9
    # velocity: second-order one-sided differences after the switch against the outgoing clip's central ones,
    # within 1 % of the largest component velocity (the differences' O(h^2) error at 1200 fps)
    v_out = (-3 * q[f] + 4 * q[f + 1] - q[f + 2]) / (2 * h)
    v_src = (a[2] - a[0]) / (2 * h)
    v_scale = np.abs(v_src).max()
    assert np.abs(v_out - v_src).max() < 0.01 * v_scale
    # a cut at the same switch has a velocity jump well above that tolerance (the test can fail)
    cut = Q.make_continuous(compose_sequence([(walk, 1.0), (run, 1.0)], fps, TransitionSpec("cut")).clip.rotations)
    assert np.abs((-3 * cut[f] + 4 * cut[f + 1] - cut[f + 2]) / (2 * h) - v_src).max() > 0.2 * v_scale
    # after the duration the offset is gone: the pose is the run's
    late = f + int(0.3 * fps)
    assert np.allclose(comp.clip.rotations[late], run.sample(np.array([0.3])).rotations[0], atol=1e-12)


def test_quintic_by_hand() -> None:
    # x(0) = x0, x'(0) = v0, x(d) = x'(d) = x''(d) = 0
    d, x0, v0 = 0.25, np.array([0.3, -0.2]), np.array([1.0, 0.5])
    u = np.array([0.0, 1e-7, d - 1e-7, d, 0.4])
    x = quintic_offset(x0, v0, u, d)
    assert np.allclose(x[0], x0, atol=0)
    assert np.allclose((x[1] - x[0]) / 1e-7, v0, atol=1e-5)
    assert np.abs(x[2]).max() < 1e-12 and np.array_equal(x[3:], np.zeros((2, 2)))


def test_zero_additive_delta_leaves_base_bit_identical() -> None:
    rng = np.random.default_rng(39)
    sk = biped()
    base = random_rotations(rng, (20, sk.n_joints))
    mask = joint_mask(sk, "upper_body", BIPED_SETS)
    out = additive(base, Q.identity((20, sk.n_joints)), mask)
    assert np.array_equal(out, base)
    layer = random_rotations(rng, (20, sk.n_joints))
    out = additive(base, additive_delta(layer, layer), mask)  # a layer against itself: zero delta
    assert np.array_equal(out, base)
    # a non-zero delta does move the set's joints (and only those)
    moved = additive(base, additive_delta(layer, layer[0]), mask)
    assert not np.array_equal(moved[1:, mask], base[1:, mask])
    assert np.array_equal(moved[:, ~mask], base[:, ~mask])


def test_upper_body_override_leaves_lower_body_bit_identical() -> None:
    rng = np.random.default_rng(40)
    sk = biped()
    base, layer = random_rotations(rng, (15, sk.n_joints)), random_rotations(rng, (15, sk.n_joints))
    upper = joint_mask(sk, "upper_body", BIPED_SETS)
    lower = joint_mask(sk, "lower_body", BIPED_SETS)
    assert upper.tolist() == [False, True, True, False, False, False, False, False, False]  # Spine, Head
    assert not np.any(upper & lower) and np.all(upper | lower)
    for space in ("local", "model"):
        out = override(base, layer, upper, sk, space)  # type: ignore[arg-type]
        assert np.array_equal(out[:, lower], base[:, lower])
    # local: the set's joints are the layer's; model: the set's top joint keeps the layer's model rotation
    assert np.array_equal(override(base, layer, upper)[:, upper], layer[:, upper])
    g_out, _ = sk.forward_kinematics(override(base, layer, upper, sk, "model"))
    g_layer, _ = sk.forward_kinematics(layer)
    assert np.abs(Q.quat_angle(g_out[:, 1:3], g_layer[:, 1:3])).max() < 1e-6  # the head rides on the layer's spine


def test_joint_sets_of_the_character() -> None:
    from anim_core.math.skeleton import Skeleton

    with pytest.raises(CompositeError, match="joints: unknown joint set 'tail'"):
        joint_mask(biped(), "tail", BIPED_SETS)
    with pytest.raises(CompositeError, match="needs joint 'LowerBack'"):
        joint_mask(biped(), "upper_body")
    names = ("Hips", "LowerBack", "Spine", "LeftShoulder", "LeftArm", "LHipJoint", "LeftUpLeg")
    sk = Skeleton(names, (-1, 0, 1, 2, 3, 0, 5), np.zeros((7, 3)))
    assert joint_mask(sk, "upper_body").tolist() == [0, 1, 1, 1, 1, 0, 0]
    assert joint_mask(sk, "lower_body").tolist() == [1, 0, 0, 0, 0, 1, 1]
    assert joint_mask(sk, "left_arm").tolist() == [0, 0, 0, 1, 1, 0, 0]


def test_parametric_of_a_take_with_itself_is_the_take() -> None:
    walk = _swing(0.5, 1.0, 1.4, seconds=1.0)
    for w in (0.0, 0.3, 1.0):
        mixed = parametric(walk, walk, w, 120)
        assert np.allclose(mixed.times, walk.times, atol=1e-12)
        assert np.abs(Q.quat_angle(mixed.rotations, walk.rotations)).max() < 1e-7  # radians
        assert np.allclose(mixed.root_translation, walk.root_translation, atol=1e-12)
    # two different takes: halfway is halfway in duration
    run = _swing(0.9, 0.7, 3.0, seconds=0.7)
    assert parametric(walk, run, 0.5, 120).duration == pytest.approx(0.85, abs=1 / 120)


def test_parametric_of_takes_played_in_place_keeps_their_speed() -> None:
    walk = _swing(0.5, 1.0, 1.4, seconds=1.0, in_place=True)
    run = _swing(0.9, 0.7, 3.0, seconds=0.7, in_place=True)
    mixed = parametric(walk, run, 0.5, 120)
    # travel per cycle 1.4 m and 2.1 m, halfway 1.75 m, over (1.0 + 0.7) / 2 s; played in place as the walk is
    assert mixed.in_place and mixed.velocity[2] == pytest.approx(1.75 / 0.85, rel=1e-9)
    with pytest.raises(CompositeError, match="blend"):
        parametric(walk, KeyframeClip(run.skeleton, run.times, run.rotations, run.root_translation, "pingpong"),
                   0.5, 120)


def _warped_circle(amplitude: float = 0.5) -> KeyframeClip:
    """:func:`_circle`'s poses over 0.8 s with its phase warped: phase 0.25 at 0.24 s, 0.75 at 0.56 s (linear
    between, and across the wrap), where the circle has them at 0.25 s and 0.75 s."""
    c = _circle(amplitude)
    t = np.arange(97) / 120
    phase = np.interp(t / 0.8, [0.0, 0.3, 0.7, 1.0], [0.0, 0.25, 0.75, 1.0])
    rot = np.tile(Q.identity((c.skeleton.n_joints,)), (t.size, 1, 1))
    rot[:, 3] = Q.quat_from_axis_angle([1, 0, 0], amplitude * np.sin(2 * np.pi * phase))
    rot[:, 6] = Q.quat_from_axis_angle([1, 0, 0], amplitude * np.cos(2 * np.pi * phase))
    root = np.stack([np.zeros_like(t), np.full_like(t, 0.9), 1.4 * t], axis=-1)
    return KeyframeClip(c.skeleton, t, rot, root, "loop", False, 1, "warped")


def test_parametric_synced_by_markers_mixes_like_poses() -> None:
    # Both takes go round the same circle of poses (left hip A sin, right hip A cos of the phase), the second with a
    # warped phase. Synced at the marker phases 0.25 and 0.75, every frame mixes two poses of one phase: the hips
    # stay on the circle (radius A). On one linear phase the takes are up to 0.05 of a cycle apart and the mix
    # cuts inside it (seen: 1.2 % short).
    a, b = _circle(), _warped_circle()
    for w in (0.25, 0.5, 0.75):
        for markers, on_circle in ((((0.25, 0.75), (0.24, 0.56)), True), (None, False)):
            mixed = parametric(a, b, w, 120, markers=markers)
            assert mixed.duration == pytest.approx((1 - w) * 1.0 + w * 0.8, abs=1 / 120)
            left = Q.quat_angle(mixed.rotations[:, 3], Q.identity())
            right = Q.quat_angle(mixed.rotations[:, 6], Q.identity())
            radius = np.hypot(left, right) / 0.5
            assert (np.abs(radius - 1).max() < 1e-3) == on_circle, (w, markers, np.abs(radius - 1).max())
    # weight 0 is the first take, at its own times, markers or not
    same = parametric(a, b, 0.0, 120, markers=((0.25, 0.75), (0.24, 0.56)))
    assert np.abs(Q.quat_angle(same.rotations, a.rotations)).max() < 1e-9
    with pytest.raises(CompositeError, match="different orders"):
        parametric(a, b, 0.5, 120, markers=((0.25, 0.75, 0.9), (0.24, 0.7, 0.56)))
    with pytest.raises(CompositeError, match="as many sync markers"):
        parametric(a, b, 0.5, 120, markers=((0.25, 0.75), (0.24,)))


def test_a_take_that_does_not_step_has_no_landings() -> None:
    # Standing still, each foot is down over the whole loop: no landing to sync on (the blend's builder then asks
    # for sync = "phase").
    still = _circle(amplitude=0.0, speed=0.0)
    sk = still.skeleton
    lock = FeetLock(((3, 4, 5), (6, 7, 8)), ((sk.index("LeftFoot"),), (sk.index("RightFoot"),)))
    assert landings(still, lock) is None


@pytest.mark.parametrize(("spec", "message"), [
    (TransitionSpec("crossfade", 1.5), "duration"),
    (TransitionSpec("crossfade", -0.1), "duration"),
    (TransitionSpec("inertialization", 0.0), "duration"),
])
def test_bad_transitions(spec: TransitionSpec, message: str) -> None:
    walk, run = _swing(0.5, 1.0, 1.4), _swing(0.9, 0.7, 3.0)
    with pytest.raises(CompositeError, match=message):
        compose_sequence([(walk, 1.0), (run, 1.0)], FPS, spec)


def test_bad_sequences() -> None:
    walk, run = _swing(0.5, 1.0, 1.4), _swing(0.9, 0.7, 3.0, in_place=True)
    with pytest.raises(CompositeError, match="root_motion"):
        compose_sequence([(walk, 1.0), (run, 1.0)], FPS, TransitionSpec())
    with pytest.raises(CompositeError, match="seconds"):
        compose_sequence([(walk, -1.0), (run, 1.0)], FPS, TransitionSpec(), "travel")
    with pytest.raises(CompositeError, match="seconds"):
        compose_sequence([(walk, float("inf")), (run, 1.0)], FPS, TransitionSpec(), "travel")
    comp = compose_sequence([(walk, 1.0), (run, 1.0)], FPS, TransitionSpec(), "travel")
    assert np.ptp(comp.clip.root_translation[:, 2]) > 3.0  # both travel: 1.4 m + 3 m


def test_crossfade_foot_skate_no_worse_than_the_sources() -> None:
    """Root motion across a blend: the feet slide no more during the crossfade than in the sources (measured)."""
    walk, run = _swing(0.5, 1.0, 1.4), _swing(0.7, 1.0, 1.96)  # in phase (a phase jump skates: see the docs)
    comp = compose_sequence([(walk, 1.0), (run, 1.0)], 120, TransitionSpec("crossfade", 0.25), name="x")

    def slide(clip: KeyframeClip, t: np.ndarray) -> float:
        _, pos = clip.skeleton.forward_kinematics(*clip.sample(t))
        feet = pos[:, [5, 8]][:, :, None]  # (T, 2 feet, 1 joint, 3)
        heights = np.full((2, 1), feet[..., 1].min())
        return foot_metrics(feet, heights, 120, periodic=False)["foot_slide_mm"]

    during = slide(comp.clip, 1.0 + np.arange(30) / 120)
    sources = max(slide(walk, np.arange(240) / 120), slide(run, np.arange(240) / 120))
    assert during <= sources * 1.05 + 0.05


def test_the_loops_own_switch_is_matched_too() -> None:
    """The loop's own switch (the last clip back into the first) is matched as well: a looping first clip starts at
    the frame of its cycle whose pose is the last clip's at that switch.  The last clip here holds the first's pose
    at 0.3 s (frame 9 at 30 fps), so the loop starts there (it started at 0 before); a first clip that is no loop
    starts at 0."""
    walk = _circle()
    pose = walk.sample(np.array([0.3, 0.3]))
    hold = KeyframeClip(walk.skeleton, np.array([0.0, 1.0]), pose.rotations, pose.root_translation, "pingpong")
    comp = compose_sequence([(walk, 0.6), (hold, 0.5)], FPS, TransitionSpec("cut"), "travel", entry="matched")
    assert np.abs(np.abs(np.sum(comp.rotations[0] * pose.rotations[0], axis=-1)) - 1).max() < 1e-12
    assert np.abs(np.abs(np.sum(comp.rotations[0] * walk.sample(np.zeros(1)).rotations[0], axis=-1)) - 1).max() > 0.01
    comp = compose_sequence([(hold, 0.5), (walk, 0.6)], FPS, TransitionSpec("cut"), "travel", entry="matched")
    assert np.array_equal(comp.rotations[0], pose.rotations[0])


def test_a_take_entered_matched_after_itself_goes_on_where_it_was() -> None:
    """``entry = "matched"``: a loop entered after itself starts at the frame of its cycle where the outgoing copy
    is at the switch, so a cut between them is seamless (every frame the take's own, as if it had played on); from
    its time 0 ("start") the cut jumps back to the cycle's first pose."""
    walk = _circle()  # a 1.0 s cycle, a different pose at every phase
    matched = compose_sequence([(walk, 0.6), (walk, 0.6)], FPS, TransitionSpec("cut"), entry="matched")
    t = np.arange(36) / FPS
    # The first copy starts where the loop's own switch matches (the test above); from there on, one take playing on.
    cycle = walk.sample(t[:30]).rotations
    b = t[np.argmin(np.abs(np.abs(np.sum(cycle * matched.rotations[0], axis=-1)) - 1).max(axis=1))]
    assert np.abs(np.abs(np.sum(matched.rotations * walk.sample(b + t).rotations, axis=-1)) - 1).max() < 1e-12
    start = compose_sequence([(walk, 0.6), (walk, 0.6)], FPS, TransitionSpec("cut"), entry="start")
    assert np.array_equal(start.rotations[18:], walk.sample(t[:18]).rotations)
    with pytest.raises(CompositeError, match="entry"):
        compose_sequence([(walk, 0.6), (walk, 0.6)], FPS, TransitionSpec("cut"), entry="middle")  # type: ignore[arg-type]
