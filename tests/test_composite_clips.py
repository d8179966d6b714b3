"""Composite clips built from the sample takes (issue 39): server/clipset/transitions.toml's sequence with every
transition, and an override and an additive layer on the walk (the idle's upper body stands in for a layer here;
the captured wave's layers are tests/test_layers_study.py's).  Expected values come from the take clips, never
from the composite code."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from anim_core.clips import fidelity
from anim_core.math.quat import quat_conj, quat_mul
from anim_core.methods.transitions import joint_mask
from server.clipset.build import build_clip_set
from server.clipset.config import load_config
from tests.poses import mesh_local, same

CONFIG = Path(__file__).resolve().parents[1] / "server" / "clipset" / "transitions.toml"
LAYERS = """
[animations.walk_arms]
base = "walk"
layers = [{ animation = "idle", joints = "upper_body", mode = "override" }]

[animations.walk_rest_arms]
base = "walk"
layers = [{ animation = "idle", joints = "arms", mode = "additive", reference_pose = "rest" }]

[animations.walk_still]
base = "walk"
layers = [{ animation = "walk", joints = "arms", mode = "additive", reference_pose = "first" }]
"""
# The 250 ms crossfade without its feet held, to see what the lock changes.
FREE = """
[[conditions]]
id = "crossfade250free"
method = "crossfade"
params = { duration_ms = 250, curve = "smoothstep", foot_lock = false }
"""
# A parametric blend of the walk and the run, at 0, 0.5 and 1.
BLEND = """
[animations.walk_run]
blend = ["walk", "run"]

[animations.walk_run_walk]
root_motion = "travel"
sequence = [{ animation = "walk", seconds = 2 }, { animation = "run", seconds = 2 }]
"""
PARAMETRIC = "".join(f"""
[[conditions]]
id = "parametric{round(100 * w)}"
method = "parametric"
params = {{ weight = {w} }}
""" for w in (0.0, 0.5, 1.0)) + """
[[conditions]]
id = "parametric50phase"
method = "parametric"
params = { weight = 0.5, sync = "phase" }
"""
LEGS = ("LeftUpLeg", "LeftLeg", "LeftFoot", "RightUpLeg", "RightLeg", "RightFoot")


@pytest.fixture(scope="module")
def by_id(data: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    text = CONFIG.read_text(encoding="utf-8").replace("[[conditions]]", LAYERS + BLEND + "\n[[conditions]]", 1)
    text += FREE + PARAMETRIC
    path = tmp_path_factory.mktemp("composites") / "set.toml"
    path.write_text(text, encoding="utf-8")
    return {c.id: c for c in build_clip_set(data, load_config(path))}


def test_every_condition_that_applies_and_no_other(by_id: dict) -> None:
    sequence = {"keyframe", "cut", "crossfade100", "crossfade250", "inertialization250", "crossfade250free"}
    assert {i.split("-")[1] for i in by_id if i.startswith("idle_walk_run-")} == sequence
    assert {i.split("-")[1] for i in by_id if i.startswith("walk_run_walk-")} == sequence
    assert {i.split("-")[1] for i in by_id if i.startswith("walk-")} == {"keyframe"}
    assert {i.split("-")[1] for i in by_id if i.startswith("walk_arms-")} == {"keyframe"}
    assert {i.split("-")[1] for i in by_id if i.startswith("walk_rest_arms-")} == {"keyframe"}
    assert {i.split("-")[1] for i in by_id if i.startswith("walk_run-")} == {
        "keyframe", "parametric0", "parametric50", "parametric100", "parametric50phase"}


def test_transition_metrics(by_id: dict) -> None:
    cut, fade = by_id["idle_walk_run-cut"].metrics, by_id["idle_walk_run-crossfade250"].metrics
    inert, free = by_id["idle_walk_run-inertialization250"].metrics, by_id["idle_walk_run-crossfade250free"].metrics
    for m in (cut, fade, inert):
        assert {"transition_foot_skate_ratio", "switch_velocity_jump_rad_s", "switch_accel_jump_rad_s2",
                "settle_s", "transition_foot_slide_mm"} <= set(m)
    # A blend smooths the switch: the angular velocity jump is at most half the cut's (seen: 54.5 vs 21 rad/s).
    assert fade["switch_velocity_jump_rad_s"] < 0.5 * cut["switch_velocity_jump_rad_s"]
    assert inert["switch_velocity_jump_rad_s"] < 0.5 * cut["switch_velocity_jump_rad_s"]
    # Without held feet a crossfade settles within its 250 ms (and a frame); held, the legs settle once the held
    # foot has lifted and been let go over its swing (seen: 1.10 s, the walk's left foot down 0.8 s after the switch).
    assert cut["settle_s"] == 0.0 and 0.0 < free["settle_s"] <= 0.25 + 1 / 30 + 1e-9
    assert free["settle_s"] < fade["settle_s"] < 1.5


def test_blends_skate_no_more_than_their_sources(by_id: dict) -> None:
    # issue 39: "no more foot skate during a blend than the sources have"; the window of every switch, the worst
    # (walk -> run among them).  Without the lock the 250 ms crossfade skates more (seen: 0.304 against 0.146).
    for condition in ("crossfade100", "crossfade250", "inertialization250"):
        m = by_id[f"idle_walk_run-{condition}"].metrics
        assert m["transition_foot_skate_ratio"] <= m["source_foot_skate_ratio"], condition
    free = by_id["idle_walk_run-crossfade250free"].metrics
    assert free["transition_foot_skate_ratio"] > free["source_foot_skate_ratio"]



def test_on_walk_run_walk_the_lock_is_what_keeps_a_blend_within_its_sources(by_id: dict) -> None:
    # Walk -> run -> walk loops back from the run into the walk.  Before the loop's own switch was matched the walk
    # was entered at its time 0 there, the run's swing foot came down into the walk's toe-off, and the 100 ms
    # crossfade skated in 0.304 of its window, the cut 0.348, against the sources' 0.261 (seen); matched, every
    # condition is within it (test_the_like_for_like_source_yardstick).  Without the lock the 250 ms crossfade
    # skates more than its sources (seen: 0.391).
    free = by_id["walk_run_walk-crossfade250free"].metrics
    assert free["transition_foot_skate_ratio"] > free["source_window_foot_skate_ratio"]


def test_the_lock_moves_the_legs_only_and_nothing_before_a_switch(by_id: dict) -> None:
    held, free = by_id["idle_walk_run-crossfade250"], by_id["idle_walk_run-crossfade250free"]
    legs = np.isin(held.character.skeleton.names, LEGS)
    same = np.abs(np.abs(np.sum(held.local_rotations * free.local_rotations, axis=-1)) - 1) < 1e-12  # (T, J)
    assert same[:, ~legs].all()
    assert not same[:, legs].all()
    for s in held.clip.switch_times:  # the 8 frames before each switch (the first is the loop's seam)
        f = round(s * held.fps)
        assert same[np.arange(f - 8, f) % held.n_frames].all()
    assert np.array_equal(held.floor_travel, free.floor_travel)  # the root is the blend's


def test_the_cut_plays_each_take_as_built(by_id: dict) -> None:
    seq, run = by_id["idle_walk_run-cut"], by_id["run-keyframe"]
    # The run starts 5 s in (idle 2 s, walk 3 s), entered at the frame of its cycle in the walk's leg phase
    # (entry = "matched", the default): its first second is the run clip's own motion from that frame on, as the
    # mesh shows it (the sequence plays on the idle's skeleton, each take bound on its own: mesh_local).
    cycle = mesh_local(run, run.clip.sample(np.arange(round(run.clip.duration * 30)) / 30).rotations)
    shown = mesh_local(seq, seq.local_rotations)
    k = int(np.argmin(np.abs(np.abs(np.sum(cycle * shown[150], axis=-1)) - 1).max(axis=1)))
    frames = np.arange(150, 180)
    expected = mesh_local(run, run.clip.sample((k + frames - 150) / 30).rotations)
    assert same(shown[frames], expected) < 1e-12
    # and so its feet: where they are against the hips is the run's own (played unchanged on the idle's skeleton
    # they were up to 0.31 m off, seen)
    feet, hips = run.character.skeleton.indices(["LeftToeBase", "RightToeBase", "LeftFoot", "RightFoot"]), 0
    got = seq.world_positions[frames][:, feet] - seq.world_positions[frames][:, [hips]]
    run_pose = run.clip.sample((k + frames - 150) / 30)
    want = run.character.skeleton.forward_kinematics(*run_pose)[1]
    want = want[:, feet] - want[:, [hips]]
    assert np.abs(got - want).max() < 1e-9


def test_layers_leave_the_rest_of_the_base(by_id: dict) -> None:
    walk, arms, still = by_id["walk-keyframe"], by_id["walk_arms-keyframe"], by_id["walk_still-keyframe"]
    lower = joint_mask(walk.character.skeleton, "lower_body")
    assert np.array_equal(np.abs(arms.local_rotations[:, lower]), np.abs(walk.local_rotations[:, lower]))
    # the walk's own arms against its first frame, added onto the walk: the arms move, the rest is the walk's
    upper = joint_mask(walk.character.skeleton, "arms")
    assert np.array_equal(np.abs(still.local_rotations[:, ~upper]), np.abs(walk.local_rotations[:, ~upper]))
    assert not np.allclose(np.abs(still.local_rotations[:, upper]), np.abs(walk.local_rotations[:, upper]))
    assert arms.metrics["foot_skate_ratio"] == walk.metrics["foot_skate_ratio"]


def test_an_additive_rest_reference_is_the_layer_takes_own_rest_pose(by_id: dict) -> None:
    # The idle's arms against the idle's rest pose, added to the walk: as the mesh shows it, the walk's arm turned
    # by the idle's turn away from its own rest (M_walk M_rest^-1 M_idle); the idle is bound on its own, so its rest
    # is not the walk skeleton's identity (against that the arms were 0.0061 off, 1 - |<q, q'>|, seen).
    walk, idle, layered = by_id["walk-keyframe"], by_id["idle-keyframe"], by_id["walk_rest_arms-keyframe"]
    arms = joint_mask(walk.character.skeleton, "arms")
    shown_idle = mesh_local(idle, idle.clip.sample(np.arange(walk.n_frames) / walk.fps).rotations)
    rest = mesh_local(idle, np.asarray(idle.character.skeleton.rest_rotations)[None])
    expected = quat_mul(mesh_local(walk, walk.local_rotations), quat_mul(quat_conj(rest), shown_idle))
    assert same(mesh_local(layered, layered.local_rotations)[:, arms], expected[:, arms]) < 1e-12


def test_a_travelling_sequence_is_stored_in_place_with_its_floor_travel(by_id: dict) -> None:
    seq, walk, run = by_id["idle_walk_run-crossfade250"], by_id["walk-keyframe"], by_id["run-keyframe"]
    # shown in place: the body stays within 0.75 m of its place (surge, sway, the smoothing lag at a change of pace;
    # seen: 0.54 m)
    assert np.ptp(seq.root_positions[:, 2]) < 0.75
    travel = seq.floor_travel
    assert travel is not None and np.diff(travel).min() > -0.002  # the ground moves backwards by < 2 mm a frame
    # 3 s of walk and 3 s of run at their speeds, within the 2 x 0.25 s of blending (speeds from the take clips)
    expected = 3 * walk.root_speed_mps + 3 * run.root_speed_mps
    assert abs(travel[-1] - expected) < 0.5 * (walk.root_speed_mps + run.root_speed_mps) * 0.25 + 0.1
    assert "floor_travel_m" in seq.arrays() and "floor_travel_m" not in walk.arrays()


def test_parametric_mixes_the_two_takes_after_aligning_their_cycles(by_id: dict) -> None:
    walk, run = by_id["walk-keyframe"], by_id["run-keyframe"]
    ref, p0, p50, p100 = (by_id[f"walk_run-{c}"] for c in ("keyframe", "parametric0", "parametric50", "parametric100"))
    # the blend's reference and weight 0 are the walk
    assert np.array_equal(ref.local_rotations, walk.local_rotations)
    assert np.abs(np.abs(np.sum(p0.local_rotations * walk.local_rotations, axis=-1)) - 1).max() < 1e-9
    # weight 1 is the run's cycle entered elsewhere: every frame is the run's frame a fixed shift later, as the
    # mesh shows it (the blend plays on the walk's skeleton: mesh_local)
    run_shown, p100_shown = mesh_local(run, run.local_rotations), mesh_local(p100, p100.local_rotations)
    shift = int(np.argmin(np.abs(np.abs(np.sum(run_shown * p100_shown[0], axis=-1)) - 1).max(axis=1)))
    expected = run_shown[(np.arange(run.n_frames) + shift) % run.n_frames]
    assert p100.n_frames == run.n_frames
    assert same(p100_shown, expected) < 1e-9
    # and it stands where the run stands: each blend is placed on the floor by its own feet (placed by the walk's,
    # weight 1 floated 18-24 mm over the floor, seen)
    # (the feet and the head; CMU's zero-length hip joints are placed per take: 2 cm apart)
    joints = run.character.skeleton.indices(["LeftFoot", "LeftToeBase", "RightFoot", "RightToeBase", "Head"])
    heights = run.world_positions[(np.arange(run.n_frames) + shift) % run.n_frames][:, joints, 1]
    assert np.abs(p100.world_positions[:, joints, 1] - heights).max() < 1e-6
    # halfway: half way in length and speed (from the take clips: 40 and 24 frames, 1.1 and 3.3 m/s or so)
    assert p50.n_frames == round((walk.n_frames + run.n_frames) / 2)
    speed = 0.5 * (walk.clip.velocity * walk.clip.duration + run.clip.velocity * run.clip.duration) / p50.clip.duration
    np.testing.assert_allclose(p50.clip.velocity, speed, atol=1e-9)


def test_a_parametric_blend_lands_its_feet_together_and_skates_no_more_than_its_takes(by_id: dict) -> None:
    # Synced by the feet's landings (sync = "feet", the default), the walk/run blend skates no more than either
    # take (seen: 0.000 against the walk's 0.075 and the run's 0.042); on one linear phase the walk's foot is still
    # planted where the run's swings, and the mixed foot slides (seen: 0.125).
    walk, run = by_id["walk-keyframe"].metrics, by_id["run-keyframe"].metrics
    synced, linear = by_id["walk_run-parametric50"].metrics, by_id["walk_run-parametric50phase"].metrics
    takes = max(walk["foot_skate_ratio"], run["foot_skate_ratio"])
    assert synced["foot_skate_ratio"] <= takes
    assert linear["foot_skate_ratio"] > takes


def test_every_composite_clip_passes_the_gate_against_its_takes(by_id: dict) -> None:
    # The gate holds a composite against its takes, each on its own skeleton: a sequence's frames that show one take
    # alone (the cut everywhere, a transition once settled) are poses of that take (seen: 0.0 in the cuts, at most
    # 1.0 after settling; limit TAKE_POSE_DEG).
    composites = [c for c in by_id.values() if c.animation in ("idle_walk_run", "walk_run_walk", "walk_run",
                                                                "walk_arms", "walk_rest_arms", "walk_still")]
    assert len(composites) == 20
    for c in composites:
        assert c.fidelity is not None and c.fidelity.ok, (c.id, c.fidelity)
        if c.animation in ("idle_walk_run", "walk_run_walk"):
            assert c.fidelity.bone_error_deg <= fidelity.TAKE_POSE_DEG, c.id
            if c.condition in ("keyframe", "cut"):
                assert c.fidelity.bone_error_deg < 1e-3, c.id


def test_the_gate_fails_a_take_played_on_another_takes_skeleton(by_id: dict) -> None:
    # The defect the gate missed before: the run's rotations played unchanged on the idle's skeleton (each take is
    # bound on its own); its bones are then 21 degrees from any pose of the run (seen).
    run, idle = by_id["run-keyframe"], by_id["idle-keyframe"]
    played = idle.character.skeleton.forward_kinematics(run.local_rotations, run.root_positions)[1]
    frames = np.arange(run.n_frames)
    check = fidelity.check_composite(played, run.character.contact_heights, idle.world_positions,
                                     [("run", frames, run.world_positions)])
    assert any("not its takes" in p for p in check.problems), check.problems
    assert check.bone_error_deg > 10
    own = fidelity.check_composite(run.world_positions, run.character.contact_heights, idle.world_positions,
                                   [("run", frames, run.world_positions)])
    assert own.ok and own.bone_error_deg < 1e-3


def test_worst_window_of_a_loop() -> None:
    from anim_core.clips.reference import worst_window

    flags = np.array([1, 0, 0, 0, 1, 1, 0, 0], bool)
    assert worst_window(flags, 3) == pytest.approx(2 / 3)
    assert worst_window(flags, 8) == worst_window(flags, 20) == pytest.approx(3 / 8)
    assert worst_window(np.array([1, 0, 0, 0, 0, 1], bool), 2) == 1.0  # across the loop's seam


def test_the_like_for_like_source_yardstick(by_id: dict) -> None:
    # Per switch, the worst window of the switch's length in its two takes' own frames: never below the takes'
    # whole-span skate (a window's worst is at least its mean).  Against it every condition skates no more than
    # its sources on both sequences (seen on walk -> run -> walk: 0.087, 0.130, 0.174, 0.130 against 0.261).
    for name in ("idle_walk_run", "walk_run_walk"):
        for condition in ("cut", "crossfade100", "crossfade250", "inertialization250"):
            m = by_id[f"{name}-{condition}"].metrics
            assert m["source_window_foot_skate_ratio"] >= m["source_foot_skate_ratio"] - 1e-12
            assert m["transition_foot_skate_ratio"] <= m["source_window_foot_skate_ratio"], (name, condition)


def test_a_sequences_switches_are_no_seam_or_flip_warnings_but_a_flip_between_them_is(by_id: dict) -> None:
    from dataclasses import replace

    from anim_core.clips.measure import clip_warnings
    from anim_core.math.quat import quat_from_axis_angle

    # The cut's switches turn a forearm by 96 degrees and its loop's seam is the run -> idle switch (seen: a flip
    # warning at frame 149 -> 150 and a 527 mm seam warning); the switch metrics measure those.
    cut = by_id["idle_walk_run-cut"]
    assert clip_warnings([cut]) == []
    rot = cut.local_rotations.copy()
    rot[100, 5] = quat_mul(quat_from_axis_angle([1.0, 0.0, 0.0], np.radians(120.0)), rot[100, 5])
    warnings = clip_warnings([replace(cut, local_rotations=rot)])
    assert len(warnings) == 1 and "from frame 99 to 100" in warnings[0], warnings
