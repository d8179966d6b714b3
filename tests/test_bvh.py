"""Tests of ``anim_core.io.bvh``: parsing, writing, pose conversion and error reporting, on real CMU files and on
small hierarchies written out below."""

from __future__ import annotations

import gzip
import re
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from anim_core.io.bvh import Bvh, BvhError, format_bvh, parse_bvh, read_bvh, write_bvh
from anim_core.math.quat import quat_angle

CMU_JOINTS = (
    "Hips LHipJoint LeftUpLeg LeftLeg LeftFoot LeftToeBase RHipJoint RightUpLeg RightLeg RightFoot "
    "RightToeBase LowerBack Spine Spine1 Neck Neck1 Head LeftShoulder LeftArm LeftForeArm LeftHand "
    "LeftFingerBase LeftHandIndex1 LThumb RightShoulder RightArm RightForeArm RightHand RightFingerBase "
    "RightHandIndex1 RThumb"
).split()

# Mixed indentation (spaces, tabs, both), a blank line, CRLF when joined below; channel orders XYZ, YXZ, a
# 6-channel joint in odd order (constant positions), a 1-channel joint and a 0-channel joint, End Sites at
# two depths.  19 channels per frame.
SYNTHETIC_LINES = [
    "HIERARCHY",
    "ROOT Root",
    "{",
    "  OFFSET 1 2 3",
    "  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation",
    "  JOINT A",
    "  {",
    "\tOFFSET 0 1.5 0",
    "\tCHANNELS 3 Xrotation Yrotation Zrotation",
    "\tJOINT B",
    "\t{",
    "\t   OFFSET\t0  2 0",
    "\t   CHANNELS 6 Yrotation Xposition Zrotation Zposition Xrotation Yposition",
    "",
    "\t   End Site",
    "\t   {",
    "\t      OFFSET 0 0.5 0",
    "\t   }",
    "\t}",
    "  }",
    "  JOINT C",
    "  {",
    "    OFFSET 1 0 0",
    "    CHANNELS 3 Yrotation Xrotation Zrotation",
    "    JOINT D",
    "    {",
    "      OFFSET 1 0 0",
    "      CHANNELS 1 Yrotation",
    "      JOINT E",
    "      {",
    "        OFFSET 0 0 1",
    "        CHANNELS 0",
    "        End Site",
    "        {",
    "          OFFSET 0 0 0.25",
    "        }",
    "      }",
    "    }",
    "  }",
    "}",
    "MOTION",
    "Frames: 3",
    "Frame Time: 0.04",
    "0.5 -1 2   10 20 30   5 -15 25   40 0.1 -50 -0.2 60 0.3   -35 12 70   30",
    "",
    "\t0.25 -1.5 2.5 -10 -20 -30\t-5 15 -25 -40 0.1 50 -0.2 -60 0.3 35 -12 -70 -45 ",
    "1 0 -2 170 -80 175 100 60 -120 0 0.1 0 -0.2 0 0.3 80 45 -160 90",
]
SYNTHETIC = "\r\n".join(SYNTHETIC_LINES) + "\r\n"


def line_of(text: str, fragment: str) -> int:
    """1-based number of the first line of ``text`` containing ``fragment``."""
    return next(n for n, line in enumerate(text.split("\n"), 1) if fragment in line)


def replace_line(text: str, number: int, new: str | None) -> str:
    """``text`` with line ``number`` (1-based) replaced by ``new``, or removed when ``new`` is None."""
    lines = text.split("\r\n")
    lines[number - 1 : number] = [] if new is None else [new]
    return "\r\n".join(lines)


def reference_positions(bvh: Bvh, frame: int) -> np.ndarray:
    """Joint positions ``(J, 3)`` by a plain loop over 4x4 matrices with scipy's intrinsic Euler rotations."""
    values = bvh.motion[frame]
    start = 0
    world: list[np.ndarray] = []
    for j, names in enumerate(bvh.channels):
        by_name = dict(zip(names, values[start : start + len(names)], strict=True))
        start += len(names)
        axes = "".join(n[0] for n in names if n.endswith("rotation"))
        local = np.eye(4)
        if axes:
            angles = np.array([by_name[a + "rotation"] for a in axes])
            local[:3, :3] = Rotation.from_euler(axes, angles, degrees=True).as_matrix().reshape(3, 3)
        local[:3, 3] = bvh.skeleton.offsets[j] + [by_name.get(a + "position", 0.0) for a in "XYZ"]
        parent = bvh.skeleton.parents[j]
        world.append(local if parent < 0 else world[parent] @ local)
    return np.array([m[:3, 3] for m in world])


def assert_same_bvh(a: Bvh, b: Bvh) -> None:
    assert a.skeleton.names == b.skeleton.names
    assert np.array_equal(a.skeleton.parents, b.skeleton.parents)
    assert np.array_equal(a.skeleton.offsets, b.skeleton.offsets)
    assert a.channels == b.channels
    assert a.end_sites.keys() == b.end_sites.keys()
    assert all(np.array_equal(a.end_sites[j], b.end_sites[j]) for j in a.end_sites)
    assert a.frame_time == b.frame_time
    assert a.motion.shape == b.motion.shape
    # Bit patterns, so that even the sign of zero survives.
    assert np.array_equal(a.motion.view(np.uint64), b.motion.view(np.uint64))


@pytest.fixture(scope="session")
def real(bvh_paths: list[Path]) -> dict[str, Bvh]:
    return {p.name: read_bvh(p) for p in bvh_paths}


# ---- real data ---------------------------------------------------------------------------------------------

def test_walk_12_03_matches_its_description(data: Path) -> None:
    bvh = read_bvh(data / "mocap" / "cmu" / "12_03_walk.bvh.gz")
    assert bvh.n_frames == 566
    assert bvh.frame_time == 0.0083333
    assert bvh.fps == pytest.approx(120, rel=1e-5)
    assert bvh.skeleton.names == tuple(CMU_JOINTS)
    assert bvh.channels[0] == ("Xposition", "Yposition", "Zposition", "Zrotation", "Yrotation", "Xrotation")
    assert set(bvh.channels[1:]) == {("Zrotation", "Yrotation", "Xrotation")}
    assert bvh.motion.shape == (566, 96)
    assert np.array_equal(bvh.motion[0, :4], [-1.4385, 16.4063, -26.0539, 0.0])  # first line of MOTION
    assert np.array_equal(bvh.skeleton.offsets[2], [2.10660, -1.59283, 1.11709])  # LeftUpLeg
    assert sorted(bvh.skeleton.names[j] for j in bvh.end_sites) == sorted(
        ["LeftToeBase", "RightToeBase", "Head", "LeftHandIndex1", "LThumb", "RightHandIndex1", "RThumb"])


def test_real_files_round_trip_exactly(real: dict[str, Bvh], tmp_path: Path) -> None:
    assert len(real) >= 5
    for name, bvh in real.items():
        text = format_bvh(bvh)
        assert "\r" not in text and "\n\t" in text, name
        again = parse_bvh(text, name)
        assert_same_bvh(bvh, again)
        assert format_bvh(again) == text, name
        path = tmp_path / name
        write_bvh(bvh, path)
        assert path.read_bytes()[:2] == b"\x1f\x8b", name  # really gzip
        assert gzip.decompress(path.read_bytes()).decode() == text, name
        assert_same_bvh(bvh, read_bvh(path))


def test_real_files_pose_round_trip(real: dict[str, Bvh]) -> None:
    for name, bvh in real.items():
        rotations, translation = bvh.pose_arrays()
        assert rotations.shape == (bvh.n_frames, 31, 4) and translation.shape == (bvh.n_frames, 3), name
        assert np.allclose(np.linalg.norm(rotations, axis=-1), 1.0, atol=1e-12), name
        assert np.array_equal(translation, bvh.motion[:, :3]), name
        again = bvh.with_poses(rotations, translation)
        rotations2, translation2 = again.pose_arrays()
        assert quat_angle(rotations2, rotations).max() < 1e-9, name
        assert np.abs(translation2 - translation).max() <= 1e-12, name


def test_forward_kinematics_matches_scipy_matrix_reference(real: dict[str, Bvh]) -> None:
    bvh = real["12_03_walk.bvh.gz"]
    _, positions = bvh.skeleton.forward_kinematics(*bvh.pose_arrays())
    for frame in (0, 1, 137, 400, 565):
        np.testing.assert_allclose(positions[frame], reference_positions(bvh, frame), rtol=0, atol=1e-9)


def test_errors_in_real_file_name_the_file(data: Path, tmp_path: Path) -> None:
    text = gzip.decompress((data / "mocap" / "cmu" / "12_03_walk.bvh.gz").read_bytes()).decode()
    cut = "".join(text.splitlines(keepends=True)[:40])  # line 40 is the '{' of RightUpLeg
    with pytest.raises(BvhError, match=r"^walk\.bvh, unexpected end of file after line 40: expected "
                                       r"'OFFSET x y z' in joint 'RightUpLeg'$"):
        parse_bvh(cut, "walk.bvh")
    cut = "".join(text.splitlines(keepends=True)[:42])
    with pytest.raises(BvhError, match=r"after line 42: expected '\}' closing joint 'RightUpLeg'"):
        parse_bvh(cut, "walk.bvh")
    path = tmp_path / "broken.bvh.gz"
    path.write_bytes(gzip.compress(text.replace("OFFSET 2.10660", "OFSET 2.10660").encode()))
    with pytest.raises(BvhError, match=r"^broken\.bvh\.gz, line 12: expected 'OFFSET x y z', found "
                                       r"'OFSET 2\.10660 -1\.59283 1\.11709'$"):
        read_bvh(path)


# ---- synthetic hierarchies ---------------------------------------------------------------------------------

def test_synthetic_parse_results() -> None:
    bvh = parse_bvh(SYNTHETIC)
    s = bvh.skeleton
    assert s.names == ("Root", "A", "B", "C", "D", "E")
    assert s.parents.tolist() == [-1, 0, 1, 0, 3, 4]
    assert s.offsets.tolist() == [[1, 2, 3], [0, 1.5, 0], [0, 2, 0], [1, 0, 0], [1, 0, 0], [0, 0, 1]]
    assert np.array_equal(s.rest_rotations, np.tile([1.0, 0, 0, 0], (6, 1)))
    assert bvh.channels == (
        ("Xposition", "Yposition", "Zposition", "Zrotation", "Yrotation", "Xrotation"),
        ("Xrotation", "Yrotation", "Zrotation"),
        ("Yrotation", "Xposition", "Zrotation", "Zposition", "Xrotation", "Yposition"),
        ("Yrotation", "Xrotation", "Zrotation"),
        ("Yrotation",),
        (),
    )
    assert sorted(bvh.end_sites) == [2, 5]
    assert bvh.end_sites[2].tolist() == [0, 0.5, 0] and bvh.end_sites[5].tolist() == [0, 0, 0.25]
    assert bvh.frame_time == 0.04 and bvh.fps == 25.0 and bvh.n_frames == 3
    assert bvh.motion.shape == (3, 19)
    assert bvh.motion[0].tolist() == [float(v) for v in SYNTHETIC_LINES[-4].split()]
    assert bvh.motion[1, 18] == -45.0
    # LF, spaces only and no blank lines give the same result.
    plain = parse_bvh("\n".join(" ".join(line.split()) for line in SYNTHETIC_LINES if line.strip()))
    assert_same_bvh(bvh, plain)


def test_synthetic_round_trip() -> None:
    bvh = parse_bvh(SYNTHETIC)
    text = format_bvh(bvh)
    assert "\r" not in text and "  " not in text
    assert "\n\t\t\tJOINT E\n" in text and "\n\t\t\tEnd Site\n" in text  # tabs per depth
    assert "Frame Time: 0.04\n" in text
    assert_same_bvh(bvh, parse_bvh(text))


def test_full_precision_values_round_trip_bit_identically(rng: np.random.Generator) -> None:
    bvh = parse_bvh(SYNTHETIC)
    motion = rng.normal(scale=100.0, size=(50, 19)) * 10.0 ** rng.integers(-12, 12, size=(50, 19))
    motion[0, :5] = [-0.0, 1e-300, 5e-324, 1.7976931348623157e308, 0.1 + 0.2]
    noisy = Bvh(bvh.skeleton, bvh.channels, bvh.end_sites, 1 / 120, motion)
    text = format_bvh(noisy)
    assert "Frame Time: 0.008333333333333333\n" in text
    again = parse_bvh(text)
    assert again.frame_time == 1 / 120
    assert_same_bvh(noisy, again)
    # Whole numbers are written compactly.
    assert format_bvh(bvh).splitlines()[-1].startswith("1 0 -2 170 -80 175 100 60 -120 0 0.1 0 ")


def test_synthetic_pose_values_and_fk_reference() -> None:
    bvh = parse_bvh(SYNTHETIC)
    rotations, translation = bvh.pose_arrays()
    assert np.array_equal(translation, bvh.motion[:, :3])
    half = np.radians(30.0) / 2  # D: Yrotation 30 in frame 0
    np.testing.assert_allclose(rotations[0, 4], [np.cos(half), 0, np.sin(half), 0], atol=1e-15)
    assert np.array_equal(rotations[:, 5], np.tile([1.0, 0, 0, 0], (3, 1)))  # E has no channels
    posed = bvh.posed_skeleton()
    assert posed.offsets[2].tolist() == [0.1, 2.3, -0.2]  # B: OFFSET + constant position channels
    assert np.array_equal(bvh.skeleton.offsets[2], [0, 2, 0])  # the file's offsets stay as they were
    _, positions = posed.forward_kinematics(rotations, translation)
    for frame in range(3):
        np.testing.assert_allclose(positions[frame], reference_positions(bvh, frame), rtol=0, atol=1e-12)


def test_synthetic_with_poses_reproduces_channel_values() -> None:
    bvh = parse_bvh(SYNTHETIC)
    again = bvh.with_poses(*bvh.pose_arrays())
    # No gimbal lock here, so each joint's decomposition in its own order gives back the file's angles.
    np.testing.assert_allclose(again.motion, bvh.motion, rtol=0, atol=1e-9)
    assert again.channels == bvh.channels and again.skeleton is bvh.skeleton
    shorter = bvh.with_poses(*(a[:2] for a in bvh.pose_arrays()))
    assert shorter.n_frames == 2


def test_with_poses_rejects_axes_without_channels() -> None:
    bvh = parse_bvh(SYNTHETIC)
    rotations, translation = bvh.pose_arrays()
    tilted = rotations.copy()
    tilted[1, 4] = [np.cos(0.1), np.sin(0.1), 0, 0]  # D (Yrotation only) turned about X
    with pytest.raises(BvhError, match="joint 'D' has no Xrotation channel"):
        bvh.with_poses(tilted, translation)
    tilted = rotations.copy()
    tilted[2, 5] = [np.cos(0.1), 0, 0, np.sin(0.1)]  # E has no channels at all
    with pytest.raises(BvhError, match="joint 'E' has no Zrotation channel"):
        bvh.with_poses(tilted, translation)
    tilted = rotations.copy()
    tilted[:, 4] = [np.cos(1.2), 0, np.sin(1.2), 0]  # a pure Y rotation is fine
    assert np.allclose(bvh.with_poses(tilted, translation).motion[:, 18], np.degrees(2.4))


SMALL = """HIERARCHY
ROOT Pelvis
{
OFFSET 0 0 0
CHANNELS 3 Xposition Zposition Yrotation
JOINT Slider
{
OFFSET 0 1 0
CHANNELS 2 Yposition Zrotation
End Site
{
OFFSET 0 1 0
}
}
}
MOTION
Frames: 2
Frame Time: 0.5
1 2 30 0.5 10
1 2 30 0.5 20
"""


def test_position_channels_outside_the_root() -> None:
    bvh = parse_bvh(SMALL)
    rotations, translation = bvh.pose_arrays()
    assert translation.tolist() == [[1, 0, 2], [1, 0, 2]]
    assert bvh.posed_skeleton().offsets[1].tolist() == [0, 1.5, 0]
    with pytest.raises(BvhError, match="lacks a position channel"):
        bvh.with_poses(rotations, translation + np.array([0, 1e-6, 0]))
    animated = parse_bvh(SMALL.replace("30 0.5 20", "30 0.7 20"), "slide.bvh")
    with pytest.raises(BvhError, match=r"slide\.bvh: joint 'Slider' has animated position channels"):
        animated.pose_arrays()
    with pytest.raises(BvhError, match="joint 'Slider' has animated position channels"):
        animated.posed_skeleton()


# ---- malformed input ---------------------------------------------------------------------------------------

def _cut_after(text: str, number: int) -> str:
    return "\r\n".join(text.split("\r\n")[:number]) + "\r\n"


S = SYNTHETIC
L_MOTION = line_of(S, "MOTION")
L_FRAMES = line_of(S, "Frames:")
L_D_OPEN = line_of(S, "JOINT D") + 1
L_C_CHANNELS = line_of(S, "CHANNELS 3 Yrotation")
L_FRAME0 = line_of(S, "0.5 -1 2")
L_FRAME1 = line_of(S, "0.25 -1.5")
L_FRAME2 = line_of(S, "1 0 -2 170")

MALFORMED = {
    "cut mid-hierarchy": (
        _cut_after(S, L_D_OPEN),
        rf"<string>, unexpected end of file after line {L_D_OPEN}: expected 'OFFSET x y z' in joint 'D'$"),
    "cut inside a joint": (
        _cut_after(S, L_C_CHANNELS),
        rf"unexpected end of file after line {L_C_CHANNELS}: expected '\}}' closing joint 'C'$"),
    "cut mid-motion": (
        _cut_after(S, L_FRAME1),
        rf"unexpected end of file after line {L_FRAME1}: expected 3 frames as declared on line {L_FRAMES}, "
        rf"found 2$"),
    "missing value": (
        replace_line(S, L_FRAME1, SYNTHETIC_LINES[L_FRAME1 - 1].replace("-0.2 ", "")),
        rf"line {L_FRAME1}: frame 1 has 18 values, expected 19$"),
    "extra value": (
        replace_line(S, L_FRAME0, SYNTHETIC_LINES[L_FRAME0 - 1] + " 7"),
        rf"line {L_FRAME0}: frame 0 has 20 values, expected 19$"),
    "not a number": (
        replace_line(S, L_FRAME2, SYNTHETIC_LINES[L_FRAME2 - 1].replace(" 100 ", " 1OO ")),
        rf"line {L_FRAME2}: value 7 '1OO' is not a number$"),
    "nan": (
        replace_line(S, L_FRAME2, SYNTHETIC_LINES[L_FRAME2 - 1].replace(" 100 ", " nan ")),
        rf"line {L_FRAME2}: value 7 'nan' is not a number$"),
    "missing MOTION": (
        replace_line(S, L_MOTION, None),
        rf"line {L_MOTION}: expected 'MOTION' after the hierarchy, found 'Frames: 3'$"),
    "CHANNELS count": (
        replace_line(S, L_C_CHANNELS, "CHANNELS 3 Yrotation Xrotation"),
        rf"line {L_C_CHANNELS}: CHANNELS declares 3 channels but lists 2$"),
    "CHANNELS count not a number": (
        replace_line(S, L_C_CHANNELS, "CHANNELS Yrotation Xrotation Zrotation"),
        rf"line {L_C_CHANNELS}: expected 'CHANNELS <count 0..6> <names>', found 'CHANNELS Yrotation"),
    "unknown channel": (
        replace_line(S, L_C_CHANNELS, "CHANNELS 3 Yrotation Xrotaton Zrotation"),
        rf"line {L_C_CHANNELS}: unknown channel 'Xrotaton'"),
    "repeated channel": (
        replace_line(S, L_C_CHANNELS, "CHANNELS 3 Yrotation Xrotation Yrotation"),
        rf"line {L_C_CHANNELS}: channel 'Yrotation' listed twice"),
    "bad Frames": (
        replace_line(S, L_FRAMES, "Frames: three"),
        rf"line {L_FRAMES}: expected 'Frames: <count>', found 'Frames: three'$"),
    "bad Frame Time": (
        replace_line(S, L_FRAMES + 1, "Frame Time: -0.04"),
        rf"line {L_FRAMES + 1}: expected 'Frame Time: <seconds>' with seconds > 0, "
        rf"found 'Frame Time: -0.04'$"),
    "missing Frame Time": (
        replace_line(S, L_FRAMES + 1, None),
        rf"line {L_FRAMES + 1}: expected 'Frame Time: <seconds>' with seconds > 0, found '0.5 -1 2"),
    "more frames than declared": (
        replace_line(S, L_FRAMES, "Frames: 2"),
        rf"line {L_FRAME2}: more frame lines than the 2 declared on line {L_FRAMES}$"),
    "misspelled OFFSET": (
        replace_line(S, 4, "OFSET 1 2 3"),
        r"^<string>, line 4: expected 'OFFSET x y z', found 'OFSET 1 2 3'$"),
    "OFFSET with two values": (
        replace_line(S, 4, "OFFSET 1 2"),
        r"line 4: expected 'OFFSET x y z', found 'OFFSET 1 2'$"),
    "missing closing brace": (
        replace_line(S, L_MOTION - 1, None),
        rf"line {L_MOTION - 1}: expected 'JOINT', 'End Site' or '\}}' in joint 'Root', found 'MOTION'$"),
    "duplicate joint": (
        S.replace("JOINT E", "JOINT A"),
        rf"line {line_of(S, 'JOINT E')}: joint name 'A' already used on line {line_of(S, 'JOINT A')}$"),
    "lower-case keyword": (
        S.replace("JOINT C", "joint C"),
        rf"line {line_of(S, 'JOINT C')}: expected 'JOINT', 'End Site' or '\}}' in joint 'Root', "
        rf"found 'joint C'"),
    "no HIERARCHY": (
        replace_line(S, 1, None),
        r"line 1: expected 'HIERARCHY' at the start, found 'ROOT Root'$"),
    "empty": ("\r\n  \r\n", r"unexpected end of file after line 0: expected 'HIERARCHY'"),
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_input_raises_with_line_number(case: str) -> None:
    text, pattern = MALFORMED[case]
    with pytest.raises(BvhError, match=pattern):
        parse_bvh(text)


def test_any_truncation_or_corruption_gives_bvh_error_only(rng: np.random.Generator) -> None:
    # Every prefix of the text either parses or raises BvhError: no IndexError/ValueError from inside.
    outcomes = set()
    for end in range(len(SYNTHETIC)):
        try:
            parse_bvh(SYNTHETIC[:end])
            outcomes.add("ok")
        except BvhError as e:
            assert re.match(r"<string>, (line \d+|unexpected end of file after line \d+): \S", str(e)), str(e)
            outcomes.add("error")
    assert outcomes == {"ok", "error"}
    tokens = re.split(r"(\s+)", SYNTHETIC)
    junk = ["x", "{", "}", "-", "1e999", "End", "JOINT", "CHANNELS", "OFFSET", "7", "\r\n", "Frames:", ""]
    for _ in range(400):
        corrupted = list(tokens)
        corrupted[2 * rng.integers(len(tokens) // 2)] = junk[rng.integers(len(junk))]
        try:
            parse_bvh("".join(corrupted))
        except BvhError:
            pass
