"""`animstudy clips inspect FILE`: the report of real and renamed files, and the bad-input list of issue 15."""

import gzip
import json
import re
from pathlib import Path

import numpy as np
import pytest

from anim_core.io.bvh import format_bvh, read_bvh
from anim_core.io.gltf import GltfAnimation, write_gltf
from anim_core.math.skeleton import Skeleton
from server.cli import main
from tests.test_rigmap import Z_UP, convention_table, renamed, scaled, turned


def run(argv, capsys):
    code = main(argv)
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture(scope="module")
def walk_text(data):
    text = gzip.decompress((data / "mocap" / "cmu" / "02_01_walk.bvh.gz").read_bytes()).decode()
    return text.replace("\r\n", "\n")


def test_inspect_real_walk(data, capsys):
    code, out, err = run(["clips", "inspect", str(data / "mocap" / "cmu" / "02_01_walk.bvh.gz")], capsys)
    assert code == 0 and err == ""
    assert "convention  CMU" in out and "units       cmu" in out and "up axis     Y" in out
    assert "frames      343" in out and "fps         120" in out
    assert re.search(r'suggested   kind = "gait", frames \d+\.\.\d+', out)
    assert "LeftUpLeg        <- LeftUpLeg" in out


def test_inspect_crouch_and_idle(data, capsys):
    _, out, _ = run(["clips", "inspect", str(data / "mocap" / "cmu" / "115_06_crouch_first164.bvh.gz")], capsys)
    assert 'kind = "crouch", frames 1..163' in out and "T-pose" in out
    _, out, _ = run(["clips", "inspect", str(data / "mocap" / "cmu" / "113_21_idle_30fps.bvh.gz")], capsys)
    assert 'kind = "idle"' in out


def test_inspect_renamed_z_up_mixamo_in_cm(data, tmp_path, capsys):
    bvh = read_bvh(data / "mocap" / "cmu" / "02_01_walk.bvh.gz")
    source = turned(scaled(renamed(bvh, convention_table("mixamo", "mixamorig:")), 100 * 0.0254 / 0.45), Z_UP)
    path = tmp_path / "mixamo_walk.bvh"
    path.write_text(format_bvh(source))
    code, out, _ = run(["clips", "inspect", str(path)], capsys)
    assert code == 0
    assert "convention  Mixamo" in out and "units       cm" in out and "up axis     Z" in out
    assert "LeftUpLeg        <- mixamorig:LeftUpLeg" in out
    assert 'kind = "gait"' in out
    # The override is taken as given (a wrong unit is the user's call; the report shows it).
    _, out, _ = run(["clips", "inspect", str(path), "--units", "mm", "--up", "z"], capsys)
    assert "units       mm" in out
    mapping = tmp_path / "map.json"
    mapping.write_text(json.dumps({"LeftToeBase": ""}))
    _, out, _ = run(["clips", "inspect", str(path), "--mapping", str(mapping)], capsys)
    assert "LeftToeBase      <- (none): left out by the explicit mapping" in out


def test_inspect_gltf(data, tmp_path, capsys):
    s = Skeleton(["Hips"], [-1], np.zeros((1, 3)))
    path = tmp_path / "tiny.glb"
    write_gltf(path, s, np.eye(3), np.eye(3), np.array([[0, 1, 2]]), np.zeros((3, 1), int), np.ones((3, 1)),
               np.eye(4)[None], (GltfAnimation("a", np.arange(3) / 30, np.tile([1.0, 0, 0, 0], (3, 1, 1)),
                                               np.zeros((3, 3))),))
    code, _, err = run(["clips", "inspect", str(path)], capsys)
    assert code == 2 and err.startswith("error: ") and "cannot find the" in err and "left leg" in err


def _joint_chain(n: int) -> str:
    lines = ["HIERARCHY", "ROOT j0", "{", "OFFSET 0 0 0", "CHANNELS 3 Xposition Yposition Zposition"]
    for k in range(1, n):
        lines += [f"JOINT j{k}", "{", "OFFSET 0 1 0", "CHANNELS 0"]
    lines += ["}"] * n
    lines += ["MOTION", "Frames: 1", "Frame Time: 0.033", "0 0 0"]
    return "\n".join(lines) + "\n"


def _bad_cases(walk_text: str) -> dict[str, tuple[str, str]]:
    lines = [s.strip() for s in walk_text.split("\n")]
    motion = lines.index("MOTION")
    frame = motion + 3  # first frame line (0-based index)

    def with_line(k, text):
        return "\n".join([*lines[:k], text, *lines[k + 1:]])
    values = lines[frame].split()
    leg = next(i for i, s in enumerate(lines) if s.strip() == "JOINT LeftLeg") + 2
    return {
        "truncated.bvh": (walk_text[: len(walk_text) // 2], r"truncated\.bvh, (line \d+|unexpected end of file)"),
        "nan.bvh": (with_line(frame, " ".join(["nan", *values[1:]])), rf"nan\.bvh, line {frame + 1}: value 1 'nan'"),
        "inf.bvh": (with_line(frame, " ".join([*values[:5], "inf", *values[6:]])),
                    rf"inf\.bvh, line {frame + 1}: value 6 'inf' is not a number"),
        "zero_leg.bvh": (with_line(leg, "OFFSET 0 0 0"),
                         r"zero_leg\.bvh: zero-length bones where the character needs a length: LeftUpLeg-LeftLeg"),
        "duplicate.bvh": (walk_text.replace("JOINT RightLeg", "JOINT LeftLeg"),
                          r"duplicate\.bvh, line \d+: joint name 'LeftLeg' already used on line \d+"),
        "thousands.bvh": (_joint_chain(1500), r"thousands\.bvh: 1500 joints; at most 1000 are supported"),
        "huge.bvh": (_joint_chain(10_050), r"huge\.bvh, line \d+: more than 10000 joints"),
        "millions.bvh": (with_line(motion + 1, "Frames: 5000000"),
                         rf"millions\.bvh, line {motion + 2}: 5000000 frames declared; at most 1000000"),
        "empty.bvh": ("\n".join(lines[: motion + 1]) + "\nFrames: 0\nFrame Time: 0.008333\n",
                      r"empty\.bvh: the MOTION section has no frames"),
        "nomotion.bvh": ("\n".join(lines[: motion]) + "\n", r"nomotion\.bvh, unexpected end of file after line \d+: "
                                                           r"expected 'MOTION'"),
        "cycle.gltf": ("", "cycle"),
        "noskin.gltf": ("", "has no skin"),
        "external.gltf": ("", "external buffer 'gone.bin' does not exist"),
        "quads.gltf": ("", "only triangles"),
    }


def _gltf(path: Path, kind: str) -> None:
    s = Skeleton(["Hips", "Spine"], [-1, 0], np.array([[0.0, 1, 0], [0, 0.3, 0]]))
    write_gltf(path, s, np.eye(3), np.eye(3), np.array([[0, 1, 2]]), np.zeros((3, 1), int), np.ones((3, 1)),
               np.tile(np.eye(4), (2, 1, 1)))
    doc = json.loads(path.read_text())
    if kind == "cycle":
        doc["nodes"][1]["children"] = [0]
    elif kind == "noskin":
        doc.pop("skins")
        doc["nodes"][-1].pop("skin")
    elif kind == "external":
        doc["buffers"][0]["uri"] = "gone.bin"
    else:
        doc["meshes"][0]["primitives"][0]["mode"] = 6  # triangle fan
    path.write_text(json.dumps(doc))


def test_bad_input_gives_one_clear_error_line_and_writes_nothing(walk_text, tmp_path, capsys):
    for name, (text, pattern) in _bad_cases(walk_text).items():
        folder = tmp_path / name.replace(".", "_")
        folder.mkdir()
        path = folder / name
        if name.endswith(".gltf"):
            _gltf(path, name.split(".")[0])
        else:
            path.write_text(text)
        before = sorted(p.name for p in folder.iterdir())
        code, out, err = run(["clips", "inspect", str(path)], capsys)
        assert code == 2, (name, out)
        # One error line; a file that does not map lists its joints after it (issue 35), to write a mapping from.
        lines = err.splitlines()
        assert out == "" and err.startswith("error: ") and (len(lines) == 1 or lines[1].startswith("joints of ")), \
            (name, err)
        assert "Traceback" not in err
        assert re.search(pattern, err), (name, err)
        assert sorted(p.name for p in folder.iterdir()) == before


def test_convert_writes_the_motion_on_the_character(data, tmp_path, capsys):
    import trimesh

    from anim_core.io.gltf import read_gltf
    from anim_core.rig.character import retarget
    from server.assets import character as load_character

    source = data / "mocap" / "cmu" / "12_03_walk.bvh.gz"
    bvh = read_bvh(source)
    rot, root = bvh.pose_arrays()
    rt = retarget(load_character(data), bvh.posed_skeleton(), bvh.end_sites, motion=rot)  # as convert binds it
    expected = rt.skeleton.forward_kinematics(rot, root * rt.root_scale)[1]
    for name in ("walk.glb", "walk.bvh"):
        code, out, err = run(["clips", "convert", str(source), str(tmp_path / name)], capsys)
        assert code == 0 and err == "" and "566 frames" in out
    asset = read_gltf(tmp_path / "walk.glb")
    (anim,) = asset.animations
    got = asset.skeleton.forward_kinematics(anim.rotations, anim.root_translation)[1]
    assert np.abs(got - expected).max() < 1e-5
    back = read_bvh(tmp_path / "walk.bvh")
    got = back.skeleton.forward_kinematics(*back.pose_arrays())[1]
    assert np.abs(got - expected).max() < 1e-9
    # Another reader takes the .glb too: trimesh finds the character's mesh with all its vertices.
    scene = trimesh.load(tmp_path / "walk.glb")
    assert sum(len(g.vertices) for g in scene.geometry.values()) == len(rt.mesh.vertices)
    code, _, err = run(["clips", "convert", str(source), str(tmp_path / "walk.fbx")], capsys)
    assert code == 2 and "walk.fbx: export writes .glb, .gltf, .bvh or .bvh.gz" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["walk.bvh", "walk.glb"]


def test_inspect_suggests_a_tolerance_whose_hybrid_is_cheaper_with_its_measured_ratios(data, tmp_path, capsys):
    """Kind ``other`` (issue 24): the suggested ``tolerance_mm`` is said with the key and byte ratio of the hybrid
    (increment 0) it builds, and building the clip set with it gives those keys and a hybrid that is cheaper."""
    from anim_core.math.quat import quat_from_axis_angle, quat_mul
    from server.clipset.build import build_clip_set
    from server.clipset.config import inline_config

    bvh = read_bvh(data / "mocap" / "cmu" / "113_21_idle_30fps.bvh.gz")
    rot, root = bvh.pose_arrays()
    j = bvh.skeleton.index("RightArm")
    wave = 1.0 * np.sin(np.arange(bvh.n_frames) / bvh.fps * 2 * np.pi * 0.7)  # an arm waving at 0.7 Hz
    rot[:, j] = quat_mul(quat_from_axis_angle([0.0, 0.0, 1.0], wave), rot[:, j])
    path = tmp_path / "wave.bvh"
    path.write_text(format_bvh(bvh.with_poses(rot, root)))
    code, out, err = run(["clips", "inspect", str(path)], capsys)
    assert code == 0 and err == ""
    frames = re.search(r'kind = "other", frames (\d+)\.\.(\d+)', out)
    assert frames, out
    m = re.search(r"tolerance_mm = (\d+)  \(built: the hybrid \(increment 0\) has (\d+) of the reference's (\d+) keys "
                  r"\(key ratio ([\d.]+)\) and stores (\d+) of its (\d+) bytes \(byte ratio ([\d.]+)\)\)", out)
    assert m, out
    tolerance, keys, ref_keys, key_ratio, size, ref_size, byte_ratio = m.groups()
    assert float(byte_ratio) <= 0.5 and float(key_ratio) < 1.0
    config = inline_config({"wave": {"kind": "other", "source": str(path), "tolerance_mm": int(tolerance),
                                     "frames": [int(frames[1]), int(frames[2])]}},
                           [{"id": "keyframe", "method": "keyframe"},
                            {"id": "hybrid0", "method": "hybrid", "params": {"increment": 0}}], "test")
    reference, hybrid = build_clip_set(data, config)
    assert (hybrid.key_times.size, reference.key_times.size) == (int(keys), int(ref_keys))
    assert (hybrid.metrics["bytes"], reference.metrics["bytes"]) == (int(size), int(ref_size))
    assert int(size) < int(ref_size)
