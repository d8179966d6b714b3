"""The thesis clip set built from the real data: clips, keys, metrics, files, errors."""

import json
import re
import shutil

import numpy as np
import pytest

from anim_core.clips.build import ConfigError
from anim_core.math import quat as Q
from anim_core.math.skeleton import Skeleton
from anim_core.rig.character import FEET
from server.assets import AssetError
from server.cli import main
from server.clipset.build import build_clip_set
from server.clipset.config import load_config
from server.clipset.manifest import MANIFEST, write_clip_set

ANIMATIONS = ("walk", "run", "crouch", "idle")
KEY_COUNTS = {"walk": [4, 8, 16], "run": [4, 8, 16], "crouch": [2, 3, 5], "idle": [2, 3, 5]}


@pytest.fixture(scope="module")
def clips(built_clip_set):
    return built_clip_set()


@pytest.fixture(scope="module")
def by_id(clips):
    return {c.id: c for c in clips}


def test_sixteen_clips_with_the_thesis_key_counts(clips):
    assert [c.id for c in clips] == [f"{a}-{m}" for a in ANIMATIONS
                                     for m in ("keyframe", "hybrid0", "hybrid1", "hybrid2")]
    for c in clips:
        if c.method == "hybrid":
            assert c.key_times.size == KEY_COUNTS[c.animation][c.params["increment"]]
        else:  # dense: 30 keys per second
            assert c.key_times.size >= c.fps * c.duration_s / (2 if c.playback == "pingpong" else 1) - 1


def test_hybrids_share_the_keyframe_clips_period_and_grid(clips):
    for animation in ANIMATIONS:
        group = [c for c in clips if c.animation == animation]
        assert len({(c.n_frames, c.fps, c.playback) for c in group}) == 1
        for c in group:
            np.testing.assert_allclose(c.times, np.arange(c.n_frames) / c.fps)
            assert c.duration_s == c.n_frames / c.fps
            if animation != "crouch":  # crouch keys fall where the spring reaches them
                np.testing.assert_allclose(c.key_times * c.fps, np.round(c.key_times * c.fps), atol=1e-9)


def test_hybrid_samples_equal_their_keys(by_id):
    for animation in ("walk", "run", "idle"):
        for inc in (0, 1, 2):
            c = by_id[f"{animation}-hybrid{inc}"]
            sampled = c.clip.sample(c.key_times).rotations
            assert Q.quat_angle(sampled, c.key_rotations).max() < 1e-9
            # The first keys (all of them for idle, the first half for a gait) are the keyframe clip's poses.
            keyframe = by_id[f"{animation}-keyframe"]
            own = c.key_times.size // 2 if animation != "idle" else c.key_times.size
            mocap = keyframe.clip.sample(c.key_times[:own]).rotations
            assert Q.quat_angle(sampled[:own], mocap).max() < 1e-9


def test_crouch_starts_standing_and_turns_at_the_overshoot_peak(by_id):
    keyframe = by_id["crouch-keyframe"]
    standing, deepest = keyframe.source["key_frames"]
    for inc in (0, 1, 2):
        c = by_id[f"crouch-hybrid{inc}"]
        half = c.duration_s / 2
        start = c.clip.sample(np.array([0.0])).rotations[0]
        assert np.degrees(Q.quat_angle(start, keyframe.clip.sample(np.array([0.0])).rotations[0]).max()) < 0.1
        u = c.clip.path_parameter(np.array([half - 1e-3, half, half + 1e-3]))
        assert u[1] > 1.04  # the pose is beyond the crouch key at the turn: the overshoot stays
        assert abs(u[0] - u[1]) < 1e-5 and abs(u[2] - u[1]) < 1e-5  # and at rest there: no bounce
    assert 90 < deepest < 110  # SOURCE.md: deepest crouch at t = 0.82 s (frame ~99)
    assert 40 < standing < 60  # the mocap stands still for about 0.4 s first


def test_keyframe_walk_keeps_its_feet_planted(by_id):
    walk = by_id["walk-keyframe"]
    print({k: round(v, 3) for k, v in walk.metrics.items() if v is not None})
    assert walk.metrics["foot_skate_ratio"] <= walk.metrics["source_foot_skate_ratio"] + 0.01
    assert walk.metrics["penetration_mm"] < 5
    assert 0.7 < walk.root_speed_mps < 1.0  # SOURCE.md: ~0.85 m/s


def test_metrics_are_complete_and_plausible(clips, by_id):
    names = {"foot_skate_ratio", "foot_slide_mm", "penetration_mm", "floating_mm", "mpjpe_mm",
             "key_velocity_jump_rad_s", "key_accel_jump_rad_s2", "max_global_error_deg", "jerk_mean", "bytes",
             "source_foot_skate_ratio", "seam_jump_mm",
             "median_step_mm", "phase_hips_r", "phase_hips_lag", "phase_knee_r", "phase_knee_lag",
             # the fidelity gate's figures (anim_core.clips.fidelity)
             "upright_m", "foot_reach_m", "under_floor_m", "handedness", "pose_error_deg", "unfaithful",
             # ... measured on every clip (issue 35)
             "bone_error_deg", "hip_width_ratio", "shoulder_width_ratio", "knees_forward", "landing_m",
             "mirror_error_deg"}
    for c in clips:
        assert set(c.metrics) == names
        assert (c.metrics["mpjpe_mm"] is None) == (c.method == "keyframe")
        assert (c.metrics["max_global_error_deg"] is None) == (c.method == "keyframe")
        assert c.metrics["bytes"] == c.key_times.size * (31 * 4 + 4) * 4
    for animation in ANIMATIONS:
        keyframe = by_id[f"{animation}-keyframe"]
        # Dense piecewise-linear keys jump in angular velocity at every key; SQUAD does not.
        if animation != "crouch":
            for inc in (0, 1, 2):
                assert by_id[f"{animation}-hybrid{inc}"].metrics["key_velocity_jump_rad_s"] < 0.05
        assert keyframe.metrics["key_velocity_jump_rad_s"] > 0.05
        # More keys follow the mocap more closely.
        errors = [by_id[f"{animation}-hybrid{i}"].metrics["mpjpe_mm"] for i in (0, 1, 2)]
        if animation != "crouch":  # the crouch hybrid holds the crouch while the mocap stands up again
            assert errors[2] < errors[0]


def test_floor_is_under_the_keyframe_feet(by_id):
    for animation in ANIMATIONS:
        c = by_id[f"{animation}-keyframe"]
        feet = np.array([c.character.skeleton.indices(f) for f in FEET])
        clearance = (c.world_positions[:, feet, 1] - c.character.contact_heights[feet]).min(axis=(1, 2))
        assert abs(np.percentile(clearance, 10)) < 1e-9
        assert clearance.min() > -0.02  # nothing sinks more than 2 cm


def test_written_files_follow_the_schema(clips, tmp_path):
    write_clip_set(clips, tmp_path)
    manifest = json.loads((tmp_path / MANIFEST).read_text())
    assert len(manifest["clips"]) == 16
    for entry in manifest["clips"]:
        assert {"id", "animation", "condition", "method", "params", "key_count", "duration_s", "fps", "playback",
                "metrics", "in_place", "root_speed_mps"} <= set(entry)
        assert entry["animation"] in ANIMATIONS and entry["method"] in ("keyframe", "hybrid")
        assert entry["id"] == f"{entry['animation']}-{entry['condition']}"
        assert entry["params"] == ({} if entry["method"] == "keyframe" else {"increment": int(entry["condition"][-1])})
        assert entry["playback"] in ("loop", "pingpong")
        assert (entry["root_speed_mps"] > 0) == entry["in_place"]
        arrays = np.load(tmp_path / entry["file"])
        t = round(entry["duration_s"] * entry["fps"])
        assert arrays["times"].shape == (t,)
        np.testing.assert_allclose(arrays["times"], np.arange(t) / entry["fps"])
        assert arrays["joint_names"].shape == (31,) and arrays["parents"].shape == (31,)
        assert arrays["local_rotations"].shape == (t, 31, 4)
        assert arrays["root_positions"].shape == (t, 3)
        assert arrays["world_positions"].shape == (t, 31, 3)
        assert arrays["key_times"].shape == (entry["key_count"],)
        assert arrays["key_rotations"].shape == (entry["key_count"], 31, 4)
        np.testing.assert_allclose(np.linalg.norm(arrays["local_rotations"], axis=-1), 1.0, atol=1e-9)
        # World positions follow from the stored local rotations, root positions and offsets (metres, Y up).
        sk = Skeleton(tuple(arrays["joint_names"]), arrays["parents"], arrays["offsets"])
        _, pos = sk.forward_kinematics(arrays["local_rotations"], arrays["root_positions"])
        np.testing.assert_allclose(pos, arrays["world_positions"], atol=1e-9)
        assert 0.8 < arrays["world_positions"][:, 0, 1].max() < 1.2 or entry["animation"] == "crouch"


def test_missing_data_directory_is_a_clear_error(tmp_path):
    with pytest.raises(AssetError, match="does not exist; set ANIMSTUDY_DATA_DIR"):
        build_clip_set(tmp_path / "nowhere")


def test_corrupt_motion_file_is_a_clear_error(data, tmp_path):
    copy = tmp_path / "data"
    shutil.copytree(data, copy)
    walk = copy / "mocap/cmu/12_03_walk.bvh.gz"
    walk.chmod(0o644)
    walk.write_bytes(walk.read_bytes()[:-500])
    with pytest.raises(AssetError, match=r"12_03_walk\.bvh\.gz.*corrupt"):
        build_clip_set(copy)


def test_config_errors_name_the_entry(tmp_path):
    bad = tmp_path / "clips.toml"
    bad.write_text('fps = 30\n[animations.walk]\nkind = "gait"\nsource = "x.bvh"\nframes = [10, 5]\n')
    with pytest.raises(ConfigError, match=r"\[animations.walk\] frames must be a list of 2 increasing"):
        load_config(bad)
    bad.write_text("fps = [\n")
    with pytest.raises(ConfigError, match=r"clips\.toml"):
        load_config(bad)
    bad.write_text('[animations.Dance]\nkind = "gait"\n')
    with pytest.raises(ConfigError, match=r"\[animations.Dance\]: an animation name is"):
        load_config(bad)


def test_cli_builds_and_reports(data, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("ANIMSTUDY_DATA_DIR", str(data))
    assert main(["clips", "build", "--out", str(tmp_path / "clips")]) == 0
    out = capsys.readouterr().out
    assert "[4/4] idle" in out and "walk-hybrid2" in out and "16 clips" in out
    assert "hips r" in out and "warning:" not in out  # the comparison table; every pair in phase, no seam jumps
    # The fidelity table names where each clip's largest pose difference is (the reference's with its source frame).
    walk = next(line for line in out.splitlines() if line.startswith("walk-keyframe") and "source" in line)
    assert re.search(r" at frame \d+ \(source frame \d+\) +ok$", walk), walk
    assert (tmp_path / "clips" / MANIFEST).is_file()
    monkeypatch.setenv("ANIMSTUDY_DATA_DIR", str(tmp_path / "nowhere"))
    assert main(["clips", "build", "--out", str(tmp_path / "other")]) == 2
    assert "error: data directory" in capsys.readouterr().err
