"""Joint mapping of common rigs, mirror partners per convention, units and up axis: the real CMU files renamed,
scaled and turned must retarget to the very same character poses."""

import numpy as np
import pytest

from anim_core.io.bvh import Bvh, read_bvh
from anim_core.math.quat import quat_conj, quat_from_axis_angle, quat_mul, rotate
from anim_core.math.skeleton import Skeleton
from anim_core.rig.character import retarget
from anim_core.rig.mirror import mirror_partners
from anim_core.rig.normalize import normalize_bvh
from anim_core.rig.rigmap import CANONICAL_NAMES, RigMapError, map_skeleton, read_mapping_file
from server.assets import character as load_character

CMU = CANONICAL_NAMES

# CMU name -> name in each convention.  Joints a convention has no name for get helper-like names that say
# nothing about what they carry, so the hierarchy and lengths must place them.
_SIDED = {  # CMU name of each central and left joint -> its name in the convention (right ones by _right)
    "mixamo": {"Hips": "Hips", "LHipJoint": "LeftHipHelper", "LeftUpLeg": "LeftUpLeg", "LeftLeg": "LeftLeg",
               "LeftFoot": "LeftFoot", "LeftToeBase": "LeftToeBase", "LowerBack": "Spine", "Spine": "Spine1",
               "Spine1": "Spine2", "Neck": "Neck", "Neck1": "Neck1", "Head": "Head",
               "LeftShoulder": "LeftShoulder", "LeftArm": "LeftArm", "LeftForeArm": "LeftForeArm",
               "LeftHand": "LeftHand", "LeftFingerBase": "LeftHandPalm", "LeftHandIndex1": "LeftHandIndex1",
               "LThumb": "LeftHandThumb1"},
    "unreal": {"Hips": "pelvis", "LHipJoint": "hip_helper_l", "LeftUpLeg": "thigh_l", "LeftLeg": "calf_l",
               "LeftFoot": "foot_l", "LeftToeBase": "ball_l", "LowerBack": "spine_01", "Spine": "spine_02",
               "Spine1": "spine_03", "Neck": "neck_01", "Neck1": "neck_02", "Head": "head",
               "LeftShoulder": "clavicle_l", "LeftArm": "upperarm_l", "LeftForeArm": "lowerarm_l",
               "LeftHand": "hand_l", "LeftFingerBase": "palm_l", "LeftHandIndex1": "index_01_l",
               "LThumb": "thumb_01_l"},
    "blender": {"Hips": "hips", "LHipJoint": "pelvis.L", "LeftUpLeg": "thigh.L", "LeftLeg": "shin.L",
                "LeftFoot": "foot.L", "LeftToeBase": "toe.L", "LowerBack": "spine", "Spine": "spine.001",
                "Spine1": "chest", "Neck": "neck", "Neck1": "neck.001", "Head": "head",
                "LeftShoulder": "shoulder.L", "LeftArm": "upper_arm.L", "LeftForeArm": "forearm.L",
                "LeftHand": "hand.L", "LeftFingerBase": "palm.L", "LeftHandIndex1": "f_index.01.L",
                "LThumb": "thumb.01.L"},
    "blender_underscore": {"Hips": "Hips", "LHipJoint": "Pelvis_L", "LeftUpLeg": "Thigh_L", "LeftLeg": "Shin_L",
                           "LeftFoot": "Foot_L", "LeftToeBase": "Toe_L", "LowerBack": "Spine", "Spine": "Spine2",
                           "Spine1": "Chest", "Neck": "Neck", "Neck1": "Neck2", "Head": "Head",
                           "LeftShoulder": "Clavicle_L", "LeftArm": "UpperArm_L", "LeftForeArm": "LowerArm_L",
                           "LeftHand": "Hand_L", "LeftFingerBase": "Palm_L", "LeftHandIndex1": "Index1_L",
                           "LThumb": "Thumb1_L"},
    "suffix_words": {"Hips": "Pelvis", "LHipJoint": "HipJointLeft", "LeftUpLeg": "ThighLeft",
                     "LeftLeg": "CalfLeft", "LeftFoot": "FootLeft", "LeftToeBase": "ToeLeft", "LowerBack": "Waist",
                     "Spine": "Spine", "Spine1": "Chest", "Neck": "Neck", "Neck1": "NeckUpper", "Head": "Head",
                     "LeftShoulder": "CollarLeft", "LeftArm": "UpperArmLeft", "LeftForeArm": "ForeArmLeft",
                     "LeftHand": "HandLeft", "LeftFingerBase": "PalmLeft", "LeftHandIndex1": "IndexLeft",
                     "LThumb": "ThumbLeft"},
    "l_prefix": {"Hips": "Hips", "LHipJoint": "L_HipJoint", "LeftUpLeg": "L_UpperLeg", "LeftLeg": "L_LowerLeg",
                 "LeftFoot": "L_Foot", "LeftToeBase": "L_Toe", "LowerBack": "Spine0", "Spine": "Spine1",
                 "Spine1": "Chest", "Neck": "Neck", "Neck1": "Neck1", "Head": "Head",
                 "LeftShoulder": "L_Clavicle", "LeftArm": "L_UpperArm", "LeftForeArm": "L_Forearm",
                 "LeftHand": "L_Hand", "LeftFingerBase": "L_Palm", "LeftHandIndex1": "L_Index1",
                 "LThumb": "L_Thumb1"},
    "poser_daz": {"Hips": "hip", "LHipJoint": "lPelvis", "LeftUpLeg": "lThigh", "LeftLeg": "lShin",
                  "LeftFoot": "lFoot", "LeftToeBase": "lToe", "LowerBack": "abdomen", "Spine": "abdomen2",
                  "Spine1": "chest", "Neck": "neck", "Neck1": "neck2", "Head": "head",
                  "LeftShoulder": "lCollar", "LeftArm": "lShldr", "LeftForeArm": "lForeArm",
                  "LeftHand": "lHand", "LeftFingerBase": "lPalm", "LeftHandIndex1": "lIndex1",
                  "LThumb": "lThumb1"},
    "smpl": {"Hips": "Pelvis", "LHipJoint": "L_Pelvis", "LeftUpLeg": "L_Hip", "LeftLeg": "L_Knee",
             "LeftFoot": "L_Ankle", "LeftToeBase": "L_Foot", "LowerBack": "Spine1", "Spine": "Spine2",
             "Spine1": "Spine3", "Neck": "Neck", "Neck1": "Neck_Helper", "Head": "Head",
             "LeftShoulder": "L_Collar", "LeftArm": "L_Shoulder", "LeftForeArm": "L_Elbow",
             "LeftHand": "L_Wrist", "LeftFingerBase": "L_Hand", "LeftHandIndex1": "L_Index1",
             "LThumb": "L_Thumb1"},
}
_RIGHT = {"Left": "Right", "left": "right", "_l": "_r", ".L": ".R", "_L": "_R", "L_": "R_", "lP": "rP", "lT": "rT",
          "lS": "rS", "lF": "rF", "lC": "rC", "lH": "rH", "lI": "rI"}


def _right(name: str) -> str:
    if name.startswith("L_"):
        return "R_" + name[2:]
    for a, b in _RIGHT.items():
        if a in name:
            return name.replace(a, b, 1)
    raise AssertionError(name)


def convention_table(convention: str, prefix: str = "") -> dict[str, str]:
    """CMU name -> name in ``convention`` for all 31 joints."""
    left = _SIDED[convention]
    table: dict[str, str] = {}
    for cmu in CMU:
        mirrored = cmu.replace("Right", "Left").replace("RH", "LH").replace("RT", "LT")
        name = left[mirrored]
        if mirrored != cmu:
            name = _right(name)
        table[cmu] = prefix + name
    assert len(set(table.values())) == 31, convention
    return table


CASES = [("mixamo", "mixamorig:"), ("mixamo", "mixamorig_"), ("mixamo", "Armature_mixamorig"),
         ("unreal", ""), ("blender", ""), ("blender_underscore", ""), ("suffix_words", ""), ("l_prefix", ""),
         ("poser_daz", ""), ("smpl", "")]


def renamed(bvh: Bvh, table: dict[str, str]) -> Bvh:
    s = bvh.skeleton
    return Bvh(Skeleton([table[n] for n in s.names], s.parents, s.offsets), bvh.channels, bvh.end_sites,
               bvh.frame_time, bvh.motion, bvh.source)


def scaled(bvh: Bvh, factor: float) -> Bvh:
    s = bvh.skeleton
    motion = bvh.motion.copy()
    start = 0
    for names in bvh.channels:
        for k, n in enumerate(names):
            if n.endswith("position"):
                motion[:, start + k] *= factor
        start += len(names)
    return Bvh(Skeleton(s.names, s.parents, s.offsets * factor), bvh.channels,
               {j: e * factor for j, e in bvh.end_sites.items()}, bvh.frame_time, motion, bvh.source)


def turned(bvh: Bvh, q: np.ndarray) -> Bvh:
    """The same motion in a world turned by ``q``: offsets and root path rotated, local rotations conjugated."""
    s = bvh.skeleton
    rot, root = bvh.pose_arrays()
    frame = Bvh(Skeleton(s.names, s.parents, rotate(q, s.offsets)), bvh.channels,
                {j: rotate(q, e) for j, e in bvh.end_sites.items()}, bvh.frame_time, bvh.motion, bvh.source)
    return frame.with_poses(quat_mul(quat_mul(q, rot), quat_conj(q)), rotate(q, root))


Z_UP = quat_from_axis_angle(np.array([1.0, 0.0, 0.0]), np.pi / 2)  # Y up -> Z up, facing -Y (Blender)
QUARTER = quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), np.pi / 2)  # then turned to face +X


@pytest.fixture(scope="module")
def character(data):
    return load_character(data)


@pytest.fixture(scope="module")
def walks(data):
    return [read_bvh(data / "mocap" / "cmu" / name) for name in ("02_01_walk.bvh.gz", "115_06_crouch_first164.bvh.gz")]


def character_positions(character, bvh: Bvh) -> np.ndarray:
    rt = retarget(character, bvh.posed_skeleton(), bvh.end_sites)
    rot, root = bvh.pose_arrays()
    return rt.skeleton.forward_kinematics(rot, root * rt.root_scale)[1]


@pytest.mark.parametrize(("convention", "prefix"), CASES)
def test_renamed_scaled_and_turned_cmu_retargets_to_the_same_character_poses(character, walks, convention, prefix):
    table = convention_table(convention, prefix)
    transforms = [("cm", 100 * 0.0254 / 0.45, None), ("m", 0.0254 / 0.45, Z_UP),
                  ("inch", 1 / 0.45, quat_mul(QUARTER, Z_UP))]
    for bvh in walks:
        expected = character_positions(character, bvh)
        source = renamed(bvh, table)
        for units, factor, q in transforms:
            variant = scaled(source, factor)
            if q is not None:
                variant = turned(variant, q)
            out = normalize_bvh(variant)
            assert out.units == units
            assert out.up_axis == ("y" if q is None else "z")
            assert out.mapping.as_dict() == {c: table[c] for c in CMU}, out.mapping.decisions
            got = character_positions(character, out.bvh)
            err = np.abs(got - expected).max()
            assert err < 1e-6, (convention, units, err)


def test_cmu_itself_is_unchanged(walks):
    for bvh in walks:
        out = normalize_bvh(bvh)
        assert out.units == "cmu" and out.up_axis == "y" and out.facing_angle == 0
        assert out.mapping.convention == "CMU" and out.mapping.unmapped == ()
        r0, t0 = bvh.pose_arrays()
        r1, t1 = out.bvh.pose_arrays()
        np.testing.assert_allclose(np.abs(np.sum(r0 * r1, axis=-1)), 1.0, atol=1e-12)
        np.testing.assert_allclose(t1, t0, atol=1e-12)


def with_helper(bvh: Bvh, child: str, fraction: float, name: str) -> Bvh:
    """Insert a joint without rotation on the bone ending at ``child``, ``fraction`` of the way from its parent."""
    s = bvh.skeleton
    c = s.index(child)
    p = int(s.parents[c])
    names = [*s.names[:c], name, *s.names[c:]]
    old_to_new = np.array([j + (j >= c) for j in range(s.n_joints)])
    parents = [int(old_to_new[q]) if q >= 0 else -1 for q in s.parents]
    parents = [*parents[:c], int(old_to_new[p]), *parents[c:]]
    parents[c + 1] = c
    offsets = [*s.offsets[:c], s.offsets[c] * fraction, *s.offsets[c:]]
    offsets[c + 1] = s.offsets[c] * (1 - fraction)
    channels = [*bvh.channels[:c], ("Zrotation", "Yrotation", "Xrotation"), *bvh.channels[c:]]
    start = sum(len(ch) for ch in bvh.channels[:c])
    motion = np.concatenate([bvh.motion[:, :start], np.zeros((bvh.n_frames, 3)), bvh.motion[:, start:]], axis=1)
    return Bvh(Skeleton(names, parents, np.array(offsets)), channels,
               {int(old_to_new[j]): e for j, e in bvh.end_sites.items()}, bvh.frame_time, motion, bvh.source)


def test_mixed_rig_with_helpers_is_mapped_by_lengths(character, walks):
    """Mixamo names with Poser/DAZ limbs: a "LeftLeg" helper just below the hip, the knee on "lShin", a
    "LeftShoulder" that is the upper arm under a separate "lCollar", twist bones on the arms."""
    bvh = walks[0]
    table = convention_table("mixamo", "mixamorig:")
    table |= {"LeftLeg": "lShin", "RightLeg": "rShin", "LeftShoulder": "lCollar", "RightShoulder": "rCollar",
              "LeftArm": "mixamorig:LeftShoulder", "RightArm": "mixamorig:RightShoulder",
              "LeftForeArm": "lForeArm", "RightForeArm": "rForeArm"}
    source = renamed(bvh, table)
    for side in ("Left", "Right"):
        source = with_helper(source, f"{side[0].lower()}Shin", 0.08, f"mixamorig:{side}Leg")
        source = with_helper(source, f"{side[0].lower()}ForeArm", 0.5, f"mixamorig:{side}ArmTwist")
        source = with_helper(source, f"mixamorig:{side}Hand", 0.5, f"{side[0].lower()}ForeArmTwist")
    assert source.skeleton.n_joints == 37
    out = normalize_bvh(scaled(source, 100 * 0.0254 / 0.45))
    assert out.units == "cm"
    assert "Mixamo" in out.mapping.convention and "Poser/DAZ" in out.mapping.convention
    decided = out.mapping.as_dict()
    assert decided["LeftLeg"] == "lShin" and decided["LeftUpLeg"] == "mixamorig:LeftUpLeg"
    assert decided["LeftArm"] == "mixamorig:LeftShoulder" and decided["LeftShoulder"] == "lCollar"
    assert decided["RightForeArm"] == "rForeArm"
    assert set(out.mapping.unmapped) == {f"mixamorig:{s}Leg" for s in ("Left", "Right")} | \
        {f"mixamorig:{s}ArmTwist" for s in ("Left", "Right")} | {"lForeArmTwist", "rForeArmTwist"}
    reasons = {d.canonical: d.reason for d in out.mapping.decisions}
    assert "splits the limb" in reasons["LeftLeg"]
    err = np.abs(character_positions(character, out.bvh) - character_positions(character, bvh)).max()
    assert err < 1e-6


def _skeleton(parents_by_name: dict[str, tuple[str | None, tuple[float, float, float]]]) -> Skeleton:
    names = list(parents_by_name)
    parents = [names.index(p) if p else -1 for p, _ in parents_by_name.values()]
    return Skeleton(names, parents, np.array([o for _, o in parents_by_name.values()]))


def smpl_24() -> Skeleton:
    """SMPL's 24 joints with roughly its rest offsets (metres, Y up)."""
    j: dict[str, tuple[str | None, tuple[float, float, float]]] = {"Pelvis": (None, (0, 0.9, 0))}
    for s, x in (("L", 1), ("R", -1)):
        j |= {f"{s}_Hip": ("Pelvis", (0.06 * x, -0.09, 0)), f"{s}_Knee": (f"{s}_Hip", (0.04 * x, -0.38, 0)),
              f"{s}_Ankle": (f"{s}_Knee", (-0.01 * x, -0.4, -0.04)),
              f"{s}_Foot": (f"{s}_Ankle", (0.02 * x, -0.06, 0.12))}
    j |= {"Spine1": ("Pelvis", (0, 0.11, -0.02)), "Spine2": ("Spine1", (0, 0.14, 0.01)),
          "Spine3": ("Spine2", (0, 0.06, 0)), "Neck": ("Spine3", (0, 0.21, -0.03)), "Head": ("Neck", (0, 0.09, 0.05))}
    for s, x in (("L", 1), ("R", -1)):
        j |= {f"{s}_Collar": ("Spine3", (0.08 * x, 0.12, -0.02)), f"{s}_Shoulder": (f"{s}_Collar", (0.12 * x, 0.05, 0)),
              f"{s}_Elbow": (f"{s}_Shoulder", (0.26 * x, 0, 0)), f"{s}_Wrist": (f"{s}_Elbow", (0.25 * x, 0, 0)),
              f"{s}_Hand": (f"{s}_Wrist", (0.08 * x, 0, 0))}
    return _skeleton(j)


def test_smpl_24_joints_map_without_helpers():
    s = smpl_24()
    assert s.n_joints == 24
    m = map_skeleton(s)
    assert m.convention == "SMPL"
    d = m.as_dict()
    assert (d["LeftUpLeg"], d["LeftLeg"], d["LeftFoot"], d["LeftToeBase"]) == ("L_Hip", "L_Knee", "L_Ankle", "L_Foot")
    assert (d["LeftShoulder"], d["LeftArm"], d["LeftForeArm"], d["LeftHand"]) == \
        ("L_Collar", "L_Shoulder", "L_Elbow", "L_Wrist")
    assert (d["LowerBack"], d["Spine"], d["Spine1"], d["Neck1"], d["Head"]) == \
        ("Spine1", "Spine2", "Spine3", "Neck", "Head")
    assert d["LeftFingerBase"] == "L_Hand"
    assert "LHipJoint" not in d and "Neck" not in d and m.unmapped == ()


def test_explicit_mapping_overrides_and_completes(tmp_path, walks):
    names = {n: f"b{k:02d}" for k, n in enumerate(CMU)}  # names that say nothing
    source = renamed(walks[0], names)
    # The structure maps them (issue 35: hips and chest by their branches, left and right from the rest pose)...
    auto = map_skeleton(source.skeleton).as_dict()
    assert len(auto) == 25 and all(auto[c] == names[c] for c in auto), auto
    # ... unless it does not tell (here the left arm hangs from the hips): the error names the parts.
    s = source.skeleton
    parents = s.parents.copy()
    parents[CMU.index("LeftShoulder")] = 0
    with pytest.raises(RigMapError) as info:
        map_skeleton(Skeleton(s.names, parents, s.offsets))
    message = str(info.value)
    for part in ("hips", "spine", "left leg", "right arm"):
        assert part in message
    path = tmp_path / "mapping.toml"
    path.write_text("[mapping]\n" + "".join(f'{c} = "{s}"\n' for c, s in names.items()))
    mapping = read_mapping_file(path)
    m = map_skeleton(source.skeleton, mapping)
    assert m.as_dict() == names and {d.reason for d in m.decisions} == {"explicit mapping"}
    # Completing: names resolve most joints; the explicit entry moves the knee onto another joint.
    table = convention_table("unreal")
    s = renamed(walks[0], table).skeleton
    with pytest.raises(RigMapError, match="not below"):
        map_skeleton(s, {"LeftLeg": "calf_r"})
    with pytest.raises(RigMapError, match="not a joint"):
        map_skeleton(s, {"LeftLeg": "knee_l"})
    m = map_skeleton(s, {"LeftLeg": "foot_l", "LeftFoot": "ball_l", "LeftToeBase": ""})
    assert m.as_dict()["LeftLeg"] == "foot_l" and "LeftToeBase" not in m.as_dict()


def test_missing_parts_are_named(walks):
    s = walks[0].skeleton
    keep = [j for j, n in enumerate(s.names) if "Right" not in n and n not in ("RHipJoint", "RThumb")]
    sub = Skeleton([s.names[j] for j in keep], [keep.index(s.parents[j]) if j else -1 for j in keep],
                   s.offsets[keep])
    with pytest.raises(RigMapError, match=r"right leg, right arm of the skeleton \(missing right leg: RightUpLeg, "
                                          r"RightLeg, RightFoot; right arm: RightArm, RightForeArm, RightHand\)"):
        map_skeleton(sub)


@pytest.mark.parametrize(("convention", "prefix"), CASES)
def test_mirror_partners_per_convention(convention, prefix):
    table = convention_table(convention, prefix)
    names = [table[n] for n in CMU]
    perm = mirror_partners(names)
    cmu_perm = mirror_partners(CMU)
    assert perm.tolist() == cmu_perm.tolist()
    assert sum(perm != np.arange(31)) == 24  # 12 pairs: hip joint, leg, knee, foot, toe, collar, arm, ..., thumb


def test_mirror_partners_of_mixed_and_odd_names():
    names = ["Hips", "mixamorig:LeftArm", "mixamorig:RightArm", "lCollar", "rCollar", "thigh_l", "thigh_r",
             "LOD", "Lthing", "ThighLeft", "ThighRight", "left_hip", "right_hip", "hand.L", "hand.R"]
    perm = mirror_partners(names)
    assert [names[i] for i in perm] == ["Hips", "mixamorig:RightArm", "mixamorig:LeftArm", "rCollar", "lCollar",
                                        "thigh_r", "thigh_l", "LOD", "Lthing", "ThighRight", "ThighLeft",
                                        "right_hip", "left_hip", "hand.R", "hand.L"]
    with pytest.raises(ValueError, match="no partner 'thigh_r'"):
        mirror_partners(["Hips", "thigh_l"])
    assert mirror_partners(["Hips", "A", "B"], overrides={"A": "B"}).tolist() == [0, 2, 1]


def test_units_and_up_axis_overrides_and_errors(walks):
    bvh = walks[0]
    out = normalize_bvh(bvh, units="m", up_axis="y")
    assert out.units == "m" and out.metres_per_unit == 1.0
    with pytest.raises(RigMapError, match="not a human height"):
        normalize_bvh(scaled(bvh, 0.3))
    with pytest.raises(RigMapError, match="units must be"):
        normalize_bvh(bvh, units="furlong")
    with pytest.raises(RigMapError, match="up axis"):
        normalize_bvh(bvh, up_axis="x")


def rig_with_turned_frames(bvh: Bvh, rng: np.random.Generator):
    """The motion on a glTF-like rig: Mixamo names, metres, every joint frame turned at random in the rest pose
    (same world motion).  Returns the skeleton, local rotations, root translation and end sites."""
    from anim_core.math.quat import quat_normalize

    s = bvh.posed_skeleton()
    rot, root = bvh.pose_arrays()
    g_rot, _ = s.forward_kinematics(rot, root)
    g0 = quat_normalize(rng.normal(size=(s.n_joints, 4)))  # random global rest frames
    par = np.maximum(s.parents, 0)
    g0_parent = np.where((s.parents >= 0)[:, None], g0[par], [1.0, 0, 0, 0])
    rest_local = quat_mul(quat_conj(g0_parent), g0)
    offsets = rotate(quat_conj(g0_parent), s.offsets)  # world rest offsets, expressed in the parent's frame
    offsets[0] = s.offsets[0]
    g = quat_mul(g_rot, g0)  # the same world motion of the turned frames
    local = g.copy()
    local[:, 1:] = quat_mul(quat_conj(g[:, s.parents[1:]]), g[:, 1:])
    table = convention_table("mixamo", "mixamorig:")
    metres = 0.0254 / 0.45
    rig = Skeleton([table[n] for n in s.names], s.parents, offsets * metres, rest_local)
    ends = {j: rotate(quat_conj(g0[j]), e) * metres for j, e in bvh.end_sites.items()}
    return rig, local, root * metres, ends


def test_rig_with_joint_frames_not_aligned_to_the_world(character, walks, rng):
    """Removing the rest pose of a rig whose joint frames are turned must give the very same character poses."""
    from anim_core.rig.normalize import normalize_motion

    bvh = walks[0]
    rig, local, root, ends = rig_with_turned_frames(bvh, rng)
    out = normalize_motion(rig, local, root, bvh.frame_time, ends, "turned.glb")
    assert out.units == "m"
    err = np.abs(character_positions(character, out.bvh) - character_positions(character, bvh)).max()
    assert err < 1e-6, err


def _biped(spec: list[tuple[str, str | None, tuple[float, float, float]]]) -> Skeleton:
    names = [n for n, _, _ in spec]
    return Skeleton(names, [names.index(p) if p else -1 for _, p, _ in spec], np.array([o for _, _, o in spec]))


def _mirror_spec(spec, left: str, right: str):
    out = []
    for name, parent, (x, y, z) in spec:
        out.append((name, parent, (x, y, z)))
        if left in name:
            out.append((name.replace(left, right), parent.replace(left, right) if parent else parent, (-x, y, z)))
    return out


def test_real_mixamo_and_unreal_hierarchies_map_as_expected():
    """Hierarchies as the tools export them (geometry approximate, cm): Mixamo without pelvis bones, three spine
    joints, end joints and four-joint fingers; the UE4 mannequin with a root, twist bones beside the limb chains and
    IK helper bones under the root."""
    mixamo = _mirror_spec([
        ("mixamorig:Hips", None, (0, 100, 0)), ("mixamorig:Spine", "mixamorig:Hips", (0, 10, 0)),
        ("mixamorig:Spine1", "mixamorig:Spine", (0, 12, 0)), ("mixamorig:Spine2", "mixamorig:Spine1", (0, 14, 0)),
        ("mixamorig:Neck", "mixamorig:Spine2", (0, 15, 0)), ("mixamorig:Head", "mixamorig:Neck", (0, 10, 2)),
        ("mixamorig:HeadTop_End", "mixamorig:Head", (0, 18, 0)),
        ("mixamorig:LeftShoulder", "mixamorig:Spine2", (6, 10, 0)),
        ("mixamorig:LeftArm", "mixamorig:LeftShoulder", (12, 0, 0)),
        ("mixamorig:LeftForeArm", "mixamorig:LeftArm", (27, 0, 0)),
        ("mixamorig:LeftHand", "mixamorig:LeftForeArm", (26, 0, 0)),
        ("mixamorig:LeftHandThumb1", "mixamorig:LeftHand", (3, 0, 3)),
        ("mixamorig:LeftHandIndex1", "mixamorig:LeftHand", (9, 0, 2)),
        ("mixamorig:LeftHandIndex2", "mixamorig:LeftHandIndex1", (4, 0, 0)),
        ("mixamorig:LeftUpLeg", "mixamorig:Hips", (9, -5, 0)),
        ("mixamorig:LeftLeg", "mixamorig:LeftUpLeg", (0, -42, 0)),
        ("mixamorig:LeftFoot", "mixamorig:LeftLeg", (0, -42, 0)),
        ("mixamorig:LeftToeBase", "mixamorig:LeftFoot", (0, -8, 12)),
        ("mixamorig:LeftToe_End", "mixamorig:LeftToeBase", (0, 0, 8)),
    ], "Left", "Right")
    m = map_skeleton(_biped(mixamo))
    d = m.as_dict()
    assert m.convention == "Mixamo"
    assert (d["LowerBack"], d["Spine"], d["Spine1"], d["Neck1"], d["Head"]) == tuple(
        "mixamorig:" + n for n in ("Spine", "Spine1", "Spine2", "Neck", "Head"))
    assert (d["LeftShoulder"], d["LeftArm"], d["LeftForeArm"], d["LeftHand"]) == tuple(
        "mixamorig:" + n for n in ("LeftShoulder", "LeftArm", "LeftForeArm", "LeftHand"))
    assert (d["RightUpLeg"], d["RightLeg"], d["RightFoot"], d["RightToeBase"]) == tuple(
        "mixamorig:" + n for n in ("RightUpLeg", "RightLeg", "RightFoot", "RightToeBase"))
    assert d["LThumb"] == "mixamorig:LeftHandThumb1" and d["LeftHandIndex1"] == "mixamorig:LeftHandIndex1"
    assert "LHipJoint" not in d and "mixamorig:HeadTop_End" in m.unmapped

    unreal = _mirror_spec([
        ("root", None, (0, 0, 0)), ("pelvis", "root", (0, 100, 0)), ("spine_01", "pelvis", (0, 10, 0)),
        ("spine_02", "spine_01", (0, 14, 0)), ("spine_03", "spine_02", (0, 14, 0)),
        ("neck_01", "spine_03", (0, 16, 0)), ("head", "neck_01", (0, 10, 0)),
        ("clavicle_l", "spine_03", (4, 10, 0)), ("upperarm_l", "clavicle_l", (15, 0, 0)),
        ("upperarm_twist_01_l", "upperarm_l", (14, 0, 0)), ("lowerarm_l", "upperarm_l", (28, 0, 0)),
        ("lowerarm_twist_01_l", "lowerarm_l", (13, 0, 0)), ("hand_l", "lowerarm_l", (26, 0, 0)),
        ("index_01_l", "hand_l", (10, 0, 2)), ("thumb_01_l", "hand_l", (3, 0, 3)),
        ("thigh_l", "pelvis", (9, -4, 0)), ("thigh_twist_01_l", "thigh_l", (0, -20, 0)),
        ("calf_l", "thigh_l", (0, -43, 0)), ("calf_twist_01_l", "calf_l", (0, -20, 0)),
        ("foot_l", "calf_l", (0, -42, 0)), ("ball_l", "foot_l", (0, -8, 13)),
        ("ik_foot_root", "root", (0, 0, 0)), ("ik_foot_l", "ik_foot_root", (9, 8, 0)),
    ], "_l", "_r")
    m = map_skeleton(_biped(unreal))
    d = m.as_dict()
    assert m.convention == "Unreal"
    assert (d["Hips"], d["LowerBack"], d["Spine"], d["Spine1"], d["Neck1"], d["Head"]) == \
        ("pelvis", "spine_01", "spine_02", "spine_03", "neck_01", "head")
    assert (d["LeftShoulder"], d["LeftArm"], d["LeftForeArm"], d["LeftHand"]) == \
        ("clavicle_l", "upperarm_l", "lowerarm_l", "hand_l")
    assert (d["RightUpLeg"], d["RightLeg"], d["RightFoot"], d["RightToeBase"]) == \
        ("thigh_r", "calf_r", "foot_r", "ball_r")
    assert {"upperarm_twist_01_l", "thigh_twist_01_r", "ik_foot_l", "root"} <= set(m.unmapped)
    assert mirror_partners(m.source_names)[m.source_names.index("upperarm_twist_01_l")] == \
        m.source_names.index("upperarm_twist_01_r")


@pytest.mark.parametrize(("name", "side", "stem", "partner"), [
    ("mixamorig:LeftUpLeg", "L", "upleg", "mixamorig:RightUpLeg"),
    ("Armature_mixamorigLeftShoulder", "L", "shoulder", "Armature_mixamorigRightShoulder"),
    ("mixamorig_RightArm", "R", "arm", "mixamorig_LeftArm"),
    ("thigh_l", "L", "thigh", "thigh_r"), ("hand.R", "R", "hand", "hand.L"), ("Thigh_L", "L", "thigh", "Thigh_R"),
    ("lThigh", "L", "thigh", "rThigh"), ("rShin", "R", "shin", "lShin"), ("lCollar", "L", "collar", "rCollar"),
    ("L_Hip", "L", "hip", "R_Hip"), ("left_hip", "L", "hip", "right_hip"), ("ThighLeft", "L", "thigh", "ThighRight"),
    ("LHipJoint", "L", "hipjoint", "RHipJoint"), ("DEF-thigh.L", "L", "thigh", "DEF-thigh.R"),
    ("Bip01 L Thigh", "L", "thigh", "Bip01 R Thigh"), ("LEFT_ARM", "L", "arm", "RIGHT_ARM"),
    ("Hips", None, "hips", None), ("LowerBack", None, "lowerback", None), ("spine.001", None, "spine001", None),
    ("Lthing", None, "lthing", None),
])
def test_names_read_as_side_and_stem(name, side, stem, partner):
    from anim_core.rig.names import partner_name, split_side

    s = split_side(name)
    assert (s.side, s.stem, partner_name(name)) == (side, stem, partner)


def test_structure_on_noisy_geometry_is_mapped_or_refused_never_a_crash(walks):
    """Joint positions far from a body (the CMU rest pose under seeded Gaussian noise of up to 30 % of its size)
    either give anchors or a RigMapError naming the reason; never numpy's own error (an arm whose first joint is
    already a third of its reach from the chest left no shoulder to pick: "zero-size array", 187 of 2,000 here)."""
    from anim_core.rig.structure import structural_anchors

    skeleton = walks[0].skeleton
    rest = skeleton.forward_kinematics(skeleton.rest_rotations[None])[1][0]
    size = float(np.ptp(rest, axis=0).max())
    rng = np.random.default_rng(0)
    mapped = 0
    for _ in range(600):
        noisy = rest + rng.normal(0.0, size * rng.uniform(0.0, 0.3), rest.shape)
        try:
            structural_anchors(skeleton.parents, noisy)
            mapped += 1
        except RigMapError:
            pass
    assert mapped > 0
