"""Locomotion that turns or travels (issue 35): what ``clips inspect`` suggests builds, no clip walks backwards.

The turning walk is made here from the shipped CMU walk of the thesis clip set (``12_03_walk``, frames 1..565): a
yaw growing steadily to 96 degrees over the take is added to the root rotation, and the root's path is curved with
it (each step turned by the yaw reached there), as an elderly walk turning 96 degrees left would be captured.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from anim_core.clips.build import ConfigError
from anim_core.clips.measure import clip_warnings
from anim_core.clips.sources import inspect_source
from anim_core.io.bvh import clip_from_bvh, format_bvh, read_bvh
from anim_core.math.quat import quat_from_axis_angle, quat_mul, rotate
from anim_core.methods.hybrid import build_gait
from server.cli import main
from server.clipset.build import build_clip_set
from server.clipset.config import CharacterConfig, clip_set_config, inline_config

WALK = "mocap/cmu/12_03_walk.bvh.gz"
TURN_DEG = 96.0
HYBRIDS = [{"id": f"hybrid{i}", "method": "hybrid", "params": {"increment": i}} for i in range(3)]
CONDITIONS = [{"id": "keyframe", "method": "keyframe"}, *HYBRIDS]
MOVING_MPS = 0.05  # the root moves: faster than this horizontally


def _turned(rot: np.ndarray, root: np.ndarray, turn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Poses with the root turned by ``turn (F,)`` rad about the vertical and the root path's steps turned along."""
    rot = np.array(rot)
    rot[:, 0] = quat_mul(quat_from_axis_angle([0.0, 1.0, 0.0], turn), rot[:, 0])
    steps = rotate(quat_from_axis_angle([0.0, 1.0, 0.0], 0.5 * (turn[1:] + turn[:-1])), np.diff(root, axis=0))
    return rot, np.concatenate([root[:1], root[:1] + np.cumsum(steps, axis=0)])


@pytest.fixture(scope="module")
def turning_walk(data, tmp_path_factory) -> Path:
    bvh = read_bvh(data / WALK)
    rot, root = bvh.pose_arrays()
    rot, root = rot[1:], root[1:]  # frame 0 is CMU's T-pose
    turn = np.radians(TURN_DEG) * np.arange(len(rot)) / (len(rot) - 1)
    path = tmp_path_factory.mktemp("turning") / "turning_walk.bvh"
    path.write_text(format_bvh(bvh.with_poses(*_turned(rot, root, turn))))
    return path


def heading(positions: np.ndarray, skeleton) -> np.ndarray:
    """``(T,)`` rad: the way the hips face, ``atan2(x, z)`` of (right hip -> left hip) x up (computed here, not by the
    code under test)."""
    left = positions[:, skeleton.index("LeftUpLeg")] - positions[:, skeleton.index("RightUpLeg")]
    forward = np.cross(left, [0.0, 1.0, 0.0])
    return np.arctan2(forward[:, 0], forward[:, 2])


def _facing(clip) -> np.ndarray:
    """``(T, 3)`` unit horizontal direction the hips face, per frame."""
    sk = clip.character.skeleton
    left = clip.world_positions[:, sk.index("LeftUpLeg")] - clip.world_positions[:, sk.index("RightUpLeg")]
    forward = np.cross(left, [0.0, 1.0, 0.0])
    forward[:, 1] = 0.0
    return forward / np.linalg.norm(forward, axis=-1, keepdims=True)


def backwards(clip) -> tuple[int, int, float]:
    """(frames where the root moves, of them frames where it moves against the way the hips face, the smallest
    cosine between root velocity and facing), over one playback period with the wrap."""
    root = clip.root_positions
    step = (np.roll(root, -1, axis=0) - root)[:-1] * clip.fps
    step[:, 1] = 0.0
    speed = np.linalg.norm(step, axis=-1)
    moving = speed > MOVING_MPS
    cos = np.sum(step * _facing(clip)[:-1], axis=-1)[moving] / speed[moving]
    return int(moving.sum()), int((cos <= 0.0).sum()), float(cos.min())


def bone_directions_in_heading_frame(clip, frames: np.ndarray) -> np.ndarray:
    """``(K, J - 1, 3)`` world bone directions at ``frames``, each frame turned so the hips face +Z."""
    sk = clip.character.skeleton
    pos = clip.world_positions[frames]
    psi = heading(pos, sk)
    pos = rotate(quat_from_axis_angle([0.0, 1.0, 0.0], -psi)[:, None], pos)
    child = np.flatnonzero(sk.parents >= 0)
    bones = pos[:, child] - pos[:, sk.parents[child]]
    length = np.linalg.norm(bones, axis=-1, keepdims=True)
    return np.where(length > 1e-9, bones / np.maximum(length, 1e-12), 0.0)


def _build(data, path: Path, entry: dict, conditions=CONDITIONS):
    return build_clip_set(data, inline_config({"turn": {"source": str(path), **entry}}, conditions, "test"))


@pytest.fixture(scope="module")
def suggested_build(data, turning_walk):
    (report,) = inspect_source(turning_walk)
    entry = {"kind": report.kind, "frames": list(report.frames), "in_place": False}
    if report.kind == "other":
        entry["playback"] = report.playback
    return report, _build(data, turning_walk, entry)


def test_a_turning_walk_builds_as_inspect_suggests_and_never_walks_backwards(suggested_build):
    report, clips = suggested_build
    print(f"suggested {report.kind} {report.frames} ({report.reason})")
    assert report.kind in ("gait", "other")
    assert [c.condition for c in clips] == ["keyframe", "hybrid0", "hybrid1", "hybrid2"]
    for c in clips:
        moving, back, cos = backwards(c)
        print(f"{c.id}: {c.key_times.size} keys, root moves in {moving} of {c.n_frames} frames, backwards in {back}, "
              f"smallest cos(velocity, facing) {cos:.3f}")
        assert moving > 0.8 * c.n_frames  # it walks (not in place)
        assert back == 0
    print("reference source:", {k: v for k, v in clips[0].source.items() if k != "character"})


def test_the_hybrids_keyed_frames_are_the_reference_in_the_heading_frame(suggested_build):
    _, clips = suggested_build
    reference = clips[0]
    for c in clips[1:]:
        times = c.key_times[c.key_times < reference.duration_s / 2 - 1e-9] if c.kind == "gait" else c.key_times
        frames = np.round(times * c.fps).astype(np.intp)
        a = bone_directions_in_heading_frame(reference, frames)
        b = bone_directions_in_heading_frame(c, frames)
        angle = np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))
        print(f"{c.id}: {frames.size} keyed frames, largest bone direction difference {angle.max():.4f} deg")
        assert angle.max() <= 1.0


def test_build_gait_mirrors_a_walk_off_the_mirror_plane_in_its_heading_frame(data):
    """The CMU walk turned 60 and 90 degrees about the vertical (both walk across the default mirror plane, x = 0):
    each builds, walking its own direction, and the two hybrids are one another turned by the 30 degrees between
    them (each was mirrored in its own heading frame)."""
    walk = clip_from_bvh(read_bvh(data / WALK), first_frame=1, name="walk")
    keys, period = [walk.times[373], walk.times[412]], walk.times[533] - walk.times[373]
    o = walk.skeleton.offsets[0]

    def turned(deg):
        q = quat_from_axis_angle([0.0, 1.0, 0.0], np.radians(deg))
        rot = np.array(walk.rotations)
        rot[:, 0] = quat_mul(q, rot[:, 0])
        return type(walk)(walk.skeleton, walk.times, rot, rotate(q, walk.root_translation + o) - o, walk.mode,
                          walk.in_place, walk.up_axis, walk.name)

    h60, h90 = (build_gait(turned(deg), keys, period) for deg in (60.0, 90.0))
    for h, deg in ((h60, 60.0), (h90, 90.0)):
        direction = np.degrees(np.arctan2(h.velocity[0], h.velocity[2]))
        straight = np.degrees(np.arctan2(build_gait(walk, keys, period).velocity[0],
                                         build_gait(walk, keys, period).velocity[2]))
        print(f"turned {deg:g}: the hybrid walks at {direction:.2f} deg (the walk's own {straight:.2f} + {deg:g})")
        assert abs(direction - straight - deg) < 1e-6
    t = np.linspace(0.0, 2 * period, 97)
    a = walk.skeleton.forward_kinematics(*h60.sample(t))[1]
    b = walk.skeleton.forward_kinematics(*h90.sample(t))[1]
    err = np.abs(rotate(quat_from_axis_angle([0.0, 1.0, 0.0], np.radians(30.0)), a) - b).max()
    print(f"hybrid of the walk turned 90 vs that turned 60, turned 30 more: {err:.2e} (file units)")
    assert err < 1e-6


def test_a_traveling_other_take_is_refused_as_pingpong_naming_the_field(data, turning_walk):
    with pytest.raises(ConfigError, match=r"\[animations\.turn\] playback: the root travels [\d.]+ m .*"
                                          r"playback = \"loop\""):
        _build(data, turning_walk, {"kind": "other", "frames": [0, 564], "playback": "pingpong",
                                    "tolerance_mm": 50}, CONDITIONS[:2])


def test_a_turning_take_as_other_loop_never_walks_backwards_and_a_dense_hybrid_is_called_so(data, turning_walk):
    """As a loop of kind ``other`` the turning take is straightened too (closing the loop would otherwise unwind
    the turn while the path still curves), and a hybrid with most of the reference's keys is said to be nearly
    the reference."""
    clips = _build(data, turning_walk, {"kind": "other", "frames": [0, 564], "playback": "loop",
                                        "in_place": False, "tolerance_mm": 20},
                   [CONDITIONS[0], HYBRIDS[0], HYBRIDS[2]])
    for c in clips:
        moving, back, cos = backwards(c)
        print(f"{c.id}: {c.key_times.size} keys, backwards in {back} of {moving} moving frames (cos >= {cos:.3f})")
        assert moving > 0.8 * c.n_frames and back == 0
    warnings = clip_warnings(clips)
    print("\n".join(warnings))
    # Played, the loop adds its travel each cycle: its seam is measured so (not as a jump of the whole stride).
    assert not [w for w in warnings if "seam jumps" in w]
    assert all(c.metrics["seam_jump_mm"] < 3 * c.metrics["median_step_mm"] + 5 for c in clips)
    ratio = clips[2].key_times.size / clips[0].key_times.size
    assert ratio >= 0.5
    assert any(w.startswith(f"turn-hybrid2: nearly its reference, not a cheap condition: {clips[2].key_times.size} "
                            f"of the reference's {clips[0].key_times.size} keys (key ratio {ratio:.2f}")
               for w in warnings)


@pytest.fixture(scope="module")
def slow_walk(data, tmp_path_factory) -> Path:
    """Two seconds of the CMU walk played 4 times slower: too slow for a gait (0.3 m/s), but it travels."""
    bvh = read_bvh(data / WALK)
    text = format_bvh(bvh)
    lines = text.split("\n")
    motion = lines.index("MOTION")
    lines[motion + 1] = "Frames: 241"
    lines[motion + 2] = f"Frame Time: {4 * bvh.frame_time:.6f}"
    lines = lines[:motion + 3] + lines[motion + 4:motion + 4 + 241]  # frames 1..241 (frame 0 is the T-pose)
    path = tmp_path_factory.mktemp("slow") / "slow_walk.bvh"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_inspect_suggests_a_loop_for_a_traveling_other_and_its_tolerance_builds(data, slow_walk, capsys):
    code = main(["clips", "inspect", str(slow_walk)])
    out = capsys.readouterr().out
    assert code == 0
    print(out[out.index("suggested"):out.index("mapping (")])
    m = re.search(r'kind = "other", frames (\d+)\.\.(\d+), playback = "loop"', out)
    assert m, out
    t = re.search(r"tolerance_mm = (\d+)  \(built: the hybrid \(increment 0\) has (\d+) of the reference's (\d+) keys",
                  out)
    assert t, out
    config = inline_config({"slow": {"kind": "other", "source": str(slow_walk), "frames": [int(m[1]), int(m[2])],
                                     "playback": "loop", "tolerance_mm": int(t[1])}}, CONDITIONS[:2], "test")
    reference, hybrid = build_clip_set(data, config)
    assert (hybrid.key_times.size, reference.key_times.size) == (int(t[2]), int(t[3]))


def test_max_keys_is_a_clip_set_field(data, turning_walk):
    entry = {"kind": "other", "source": str(turning_walk), "frames": [0, 564], "playback": "loop",
             "tolerance_mm": 20, "max_keys": 5}
    config = clip_set_config({"turn": entry}, CONDITIONS[:2], 30, (), CharacterConfig(), "test")
    assert config.animations["turn"].max_keys == 5
    with pytest.raises(ConfigError, match=r"\[animations\.turn\] tolerance_mm: 5 keys reproduce the motion within "
                                          r"[\d.]+ mm only, not 20\.0 mm; allow more keys \(max_keys, now 5\)"):
        build_clip_set(data, config)
    with pytest.raises(ConfigError, match="only an animation of kind 'other' has max_keys"):
        gait = {k: v for k, v in entry.items() if k != "tolerance_mm"}
        clip_set_config({"w": {**gait, "kind": "gait"}}, CONDITIONS[:2], 30, (), CharacterConfig(), "test")
    with pytest.raises(ConfigError, match=r"max_keys: the most keys the picking may take, a whole number 2\.\.1000"):
        clip_set_config({"w": {**entry, "max_keys": 1}}, CONDITIONS[:2], 30, (), CharacterConfig(), "test")


def test_a_suggested_tolerance_is_one_that_max_keys_reaches(data, slow_walk):
    """With few keys allowed, the tolerances they do not reach are skipped: the one suggested builds."""
    from anim_core.clips.build import AnimationConfig, suggest_tolerance
    from server.assets import character as load_character
    from server.clipset.build import load_source

    config = AnimationConfig("slow", "other", str(slow_walk), (0, 240), "loop", False, max_keys=12)
    source = load_source(data, load_character(data), config, ())
    suggestion = suggest_tolerance(source, 30)
    print(suggestion.describe())
    assert suggestion.tolerance_mm > 20 and suggestion.keys <= 12
    entry = {"kind": "other", "source": str(slow_walk), "frames": [0, 240], "playback": "loop", "max_keys": 12,
             "tolerance_mm": suggestion.tolerance_mm}
    reference, hybrid = build_clip_set(data, inline_config({"slow": entry}, CONDITIONS[:2], "test"))
    assert (hybrid.key_times.size, reference.key_times.size) == (suggestion.keys, suggestion.reference_keys)
