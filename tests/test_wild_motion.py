"""Motion from the wild (issue 24): rigs whose rest pose and local joint frames are not CMU's, BVH files as tools
write them, and the fidelity gate.  Every rig here is made from the real CMU motion by the test itself: same world
motion, other joint frames, rest pose, root, channels, up axis and units."""

import dataclasses
import json

import numpy as np
import pytest

from anim_core.clips import fidelity
from anim_core.clips.build import AnimationConfig, ConfigError, build_animation, source_from_bvh
from anim_core.io.bvh import Bvh, format_bvh, parse_bvh, read_bvh
from anim_core.math.quat import euler_from_quat, quat_conj, quat_from_axis_angle, quat_mul, quat_normalize, rotate
from anim_core.math.skeleton import Skeleton
from anim_core.methods.conditions import Condition
from anim_core.rig.character import retarget
from anim_core.rig.normalize import normalize_bvh
from server.assets import character as load_character

X, Y, Z = np.eye(3)
Z_UP = quat_from_axis_angle(X, np.pi / 2)  # Y up -> Z up


@pytest.fixture(scope="module")
def character(data):
    return load_character(data)


@pytest.fixture(scope="module")
def walk(data) -> Bvh:
    bvh = read_bvh(data / "mocap" / "cmu" / "02_01_walk.bvh.gz")
    return dataclasses.replace(bvh, motion=bvh.motion[1:241])  # 2 s after the T-pose frame: fast, two steps


def _arc(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    axis = np.cross(a, b)
    if np.linalg.norm(axis) < 1e-9:
        axis = np.cross(a, X if abs(a[0]) < 0.9 else Y)
        return quat_from_axis_angle(axis, 0.0 if a @ b > 0 else np.pi)
    return quat_from_axis_angle(axis, np.arctan2(np.linalg.norm(np.cross(a, b)), a @ b))


def wild_rig(bvh: Bvh, rng: np.random.Generator, frames: str, *, scale: float = 1.0, world: np.ndarray | None = None,
             static_root: bool = False, six_channels: bool = False, order: str = "ZYX") -> Bvh:
    """The CMU motion on a BVH rig with other local joint frames (identity rest rotations, as BVH has):

    ``frames`` "random": every joint frame turned by a seeded random rotation; "x-bones": each joint's frame turned
    so its (first) child bone lies along local X, twisted at random about it (the all-zero pose then lies in a
    heap); "a-pose": the arms' frames turned 45 degrees down (the zero pose is an A-pose).  ``scale`` (units),
    ``world`` (a turn of the whole world, e.g. Z up), ``static_root`` (a still ``joint_Root`` above the hips, whose
    position channels hold the hips' place), ``six_channels`` (position channels on every joint, equal to the
    OFFSET), ``order`` (Euler order of every joint's rotation channels)."""
    s = bvh.posed_skeleton()
    rot, root = bvh.pose_arrays()
    n = s.n_joints
    q_world = np.array([1.0, 0, 0, 0]) if world is None else world
    if frames == "random":
        c = quat_normalize(rng.normal(size=(n, 4)))
    elif frames == "x-bones":
        c = np.empty((n, 4))
        for j in range(n):
            kids = [k for k in s.children(j) if np.linalg.norm(s.offsets[k]) > 1e-9]
            bone = s.offsets[kids[0]] if kids else rng.normal(size=3)
            twist = quat_from_axis_angle(X, rng.uniform(-np.pi, np.pi))
            c[j] = quat_mul(_arc(X, bone), twist)  # local X -> the bone (CMU rest frames are world-aligned)
    elif frames == "a-pose":
        c = np.tile([1.0, 0, 0, 0], (n, 1))
        for j, name in enumerate(s.names):
            if name.startswith(("Left", "Right")) and any(k in name for k in ("Arm", "Hand")):
                c[j] = quat_from_axis_angle(Z, -np.pi / 4 if name.startswith("Left") else np.pi / 4)
    else:
        raise ValueError(frames)
    # New globals W G C: local rotations C_parent^-1 L C (the root's W L C), offsets C_parent^-1 o.
    parent_c = np.where((s.parents >= 0)[:, None], c[np.maximum(s.parents, 0)], quat_conj(q_world))
    offsets = rotate(quat_conj(parent_c), s.offsets) * scale
    local = quat_mul(quat_mul(quat_conj(parent_c)[None], rot), c[None])
    root_t = rotate(q_world, root) * scale
    ends = {j: rotate(quat_conj(c[j]), e) * scale for j, e in bvh.end_sites.items()}
    names = list(s.names)
    parents = list(s.parents)
    if static_root:
        names, parents = ["joint_Root", *names], [-1] + [p + 1 for p in parents]
        hips_place = offsets[0] + root_t  # the hips' position channels hold their place
        offsets = np.concatenate([[np.zeros(3)], [[0.0, 93.9 * scale / 100, -3.0 * scale / 100]], offsets[1:]])
        local = np.concatenate([np.tile([1.0, 0, 0, 0], (len(local), 1, 1)), local], axis=1)
        ends = {j + 1: e for j, e in ends.items()}
        moving, root_values = 1, hips_place
    else:
        moving, root_values = 0, root_t
    rotation = tuple(f"{a}rotation" for a in order)
    position = ("Xposition", "Yposition", "Zposition")
    channels, columns = [], []
    for j in range(len(names)):
        angles = np.degrees(euler_from_quat(local[:, j], order))
        if j == moving:
            channels.append(position + rotation)
            columns.append(np.concatenate([root_values, angles], axis=1))
        elif six_channels or (static_root and j == 0):
            channels.append(position + rotation)
            columns.append(np.concatenate([np.tile(offsets[j], (len(local), 1)), angles], axis=1))
        else:
            channels.append(rotation)
            columns.append(angles)
    rig = Bvh(Skeleton(names, parents, offsets), tuple(channels), ends, bvh.frame_time,
              np.concatenate(columns, axis=1), "wild.bvh")
    return parse_bvh(format_bvh(rig), "wild.bvh")  # through the text, as a file would come


def character_positions(character, bvh: Bvh) -> np.ndarray:
    rt = retarget(character, bvh.posed_skeleton(), bvh.end_sites)
    rot, root = bvh.pose_arrays()
    return rt.skeleton.forward_kinematics(rot, root * rt.root_scale)[1]


VARIANTS = {
    "random frames, cm": dict(frames="random", scale=100 * 0.0254 / 0.45),
    "bones along X, lying zero pose, Z up, inches": dict(frames="x-bones", scale=1 / 0.45, world=Z_UP),
    "static root above the hips, 6 channels, ZXY, cm": dict(frames="x-bones", scale=100 * 0.0254 / 0.45,
                                                           static_root=True, six_channels=True, order="ZXY"),
    "random frames, Z up, static root, 6 channels, YXZ, inches": dict(
        frames="random", scale=1 / 0.45, world=Z_UP, static_root=True, six_channels=True, order="YXZ"),
}


@pytest.mark.parametrize("variant", VARIANTS)
def test_rest_pose_and_joint_frames_do_not_change_the_character(character, walk, rng, variant):
    """The character's world joint positions from a rig that differs only in rest pose, local joint frames, root,
    channels, up axis and units equal those from the plain CMU file taken relative to the same standing
    reference frame of the motion, to 1e-6 m.  (Against the plain CMU build, whose rest is CMU's T-pose, they
    differ by up to 16.5 mm in the joints the character hangs off zero-length CMU bones:
    :func:`test_wild_rigs_against_the_plain_t_pose_build` says why.)"""
    options = VARIANTS[variant]
    rig = wild_rig(walk, rng, **options)
    out = normalize_bvh(rig)  # no flags: units, up axis and rest pose all come from the motion
    assert out.units == ("cm" if options["scale"] > 3 else "inch")
    assert out.up_axis == ("z" if "world" in options else "y")
    assert out.reference_frame is not None
    plain = normalize_bvh(walk, rest="motion")
    assert out.reference_frame == plain.reference_frame
    err = np.abs(character_positions(character, out.bvh) - character_positions(character, plain.bvh)).max()
    assert err < 1e-6, err


#: CMU joints with a zero-length bone to their parent: the character hangs its own pelvis, lower back, neck, collar
#: and palm geometry off them, turned with the parent's rest frame.
HUNG = ("LHipJoint", "RHipJoint", "LowerBack", "Neck", "LeftShoulder", "RightShoulder", "LeftFingerBase", "LThumb",
        "RightFingerBase", "RThumb")


@pytest.mark.parametrize("variant", [None, *VARIANTS])
def test_wild_rigs_against_the_plain_t_pose_build(character, walk, rng, variant):
    """Against the plain CMU build (its T-pose as rest) every wild rig, and the plain file taken relative to a
    frame of the motion, give every bone of the character the same world direction (1e-6); the joint positions
    differ by up to 16.5 mm, and only through the joints of :data:`HUNG`.

    Why that is inherent: a zero-length source bone has no direction to carry over, so the character's own
    geometry there (e.g. its pelvis, from the hips to the thigh heads) is bound in the parent's *rest* frame.  A
    rig whose zero pose does not stand has no T-pose; its rest is the motion's most upright frame (frame 110 of
    this walk), and the geometry is bound to the pelvis as it is in that frame: the hips are turned 4.7 degrees
    and the CMU pelvis joints 5.0 degrees from the T-pose there, which moves the thigh heads (and the legs below
    them) by up to 16.5 mm; the thumbs (turned 50 degrees at that frame) by 13.5 mm, the finger bases 6.6 mm, the
    chest 5.2 mm (the lower back 6.9 degrees).  Any rig without a T-pose gives the second answer, and every such
    rig gives the same one to 1e-6 m (the test above): which frame the geometry is bound in is a convention, not
    information the file holds."""
    plain = character_positions(character, walk)
    out = normalize_bvh(walk, rest="motion") if variant is None else normalize_bvh(wild_rig(walk, rng,
                                                                                            **VARIANTS[variant]))
    # The reference frame's hips may face another quarter of the world than the T-pose's: turn back.
    moved = rotate(quat_from_axis_angle(Y, -out.facing_angle), character_positions(character, out.bvh))
    sk = walk.skeleton
    directed = [j for j in range(1, sk.n_joints) if np.linalg.norm(sk.offsets[j]) > 1e-9]

    def directions(p: np.ndarray) -> np.ndarray:
        d = p[:, directed] - p[:, sk.parents[directed]]
        return d / np.linalg.norm(d, axis=-1, keepdims=True)
    assert np.abs(directions(plain) - directions(moved)).max() < 1e-6
    diff = np.linalg.norm(plain - moved, axis=-1).max(axis=0)  # per joint
    assert 0.010 < diff.max() < 0.017, diff.max()
    # Where the displacement arises (a joint moved against its parent): at the hung joints only; the hips stay.
    shift = moved - plain
    arises = np.linalg.norm(shift[:, 1:] - shift[:, sk.parents[1:]], axis=-1).max(axis=0) > 1e-6
    assert {sk.names[j + 1] for j in np.flatnonzero(arises)} <= set(HUNG)
    assert np.abs(shift[:, 0]).max() < 1e-6


def test_a_pose_zero_pose_gives_the_plain_cmu_build(character, walk, rng):
    """A standing zero pose (an A-pose) stays the rest pose: every joint the bones place is where the plain CMU
    build puts it (1e-6 m); the palm and thumb joints, which hang off the hand by the character's own hand geometry
    (zero-length CMU bones), turn with the hand's bind and move by under 2 mm.  Taken relative to the motion's
    reference frame, both agree to 1e-6 m everywhere."""
    rig = wild_rig(walk, rng, "a-pose", scale=100 * 0.0254 / 0.45)
    out = normalize_bvh(rig)
    assert out.reference_frame is None and out.units == "cm"
    diff = np.abs(character_positions(character, out.bvh) - character_positions(character, walk)).max(axis=(0, 2))
    hung = [walk.skeleton.index(n) for n in ("LeftFingerBase", "LThumb", "RightFingerBase", "RThumb",
                                             "LeftHandIndex1", "RightHandIndex1")]
    assert np.delete(diff, hung).max() < 1e-6, diff
    assert diff[hung].max() < 0.002, diff[hung]
    err = np.abs(character_positions(character, normalize_bvh(rig, rest="motion").bvh)
                 - character_positions(character, normalize_bvh(walk, rest="motion").bvh)).max()
    assert err < 1e-6, err


def test_old_zero_pose_retargeting_of_a_lying_rig_is_what_broke(character, walk, rng):
    """The bug of the issue, kept as a fact: taking the all-zero pose of a rig with bones along X as the rest pose
    (what the code did before) puts the hips in the wrong place; the gate's pose check sees it."""
    rig = wild_rig(walk, rng, "x-bones", scale=100 * 0.0254 / 0.45)
    broken = normalize_bvh(rig, rest="zero", units="cm", up_axis="y")
    good = normalize_bvh(rig)
    assert np.abs(character_positions(character, broken.bvh)
                  - character_positions(character, good.bvh)).max() > 0.05
    positions = character_positions(character, broken.bvh)
    check = fidelity.check_reference(positions - [0, positions[..., 1].min(), 0], np.zeros(31),
                                     broken.source_positions)
    assert not check.ok and "not faithful" in " ".join(check.problems)


def test_animated_position_channels_below_the_root_are_refused_with_the_joint_named(walk, rng):
    rig = wild_rig(walk, rng, "random", scale=100 * 0.0254 / 0.45, six_channels=True)
    motion = rig.motion.copy()
    start = sum(len(c) for c in rig.channels[:rig.skeleton.index("LeftLeg")])
    motion[:, start] += np.linspace(0, 10, len(motion))  # the knee slides 10 cm down the thigh
    slid = dataclasses.replace(rig, motion=motion)
    with pytest.raises(ValueError, match=r"wild\.bvh: joint 'LeftLeg' has animated position channels.*"
                                         r"only the body's root \('Hips'\) may translate"):
        normalize_bvh(slid)
    motion[:, start] = motion[0, start] + 1e-3 * np.sin(np.arange(len(motion)))  # rounding noise: kept
    assert normalize_bvh(dataclasses.replace(rig, motion=motion)).units == "cm"


# --- the fidelity gate on builds -----------------------------------------------------------------------------

CONDITIONS = (Condition.parse("keyframe", "keyframe", {}), Condition.parse("hybrid1", "hybrid", {"increment": 1}))


# A broken body has no gait cycle to find; the walk travels, so it loops (refused as ping-pong).
BROKEN = {"kind": "other", "playback": "loop", "in_place": False}


def _build(character, bvh: Bvh, **config):
    out = normalize_bvh(bvh)
    cfg = AnimationConfig(**{"name": "walk", "kind": "gait", "source": bvh.source, "frames": (0, bvh.n_frames - 1),
                             "playback": "loop", "in_place": True, **config})
    source = source_from_bvh(out.bvh, character, cfg, ("LHipJoint", "RHipJoint"), out.metres_per_unit,
                             out.source_positions)
    return build_animation(source, 30, CONDITIONS)


def test_gate_passes_the_shipped_walk_and_a_wild_rig(character, walk, rng):
    for bvh in (walk, wild_rig(walk, rng, "x-bones", scale=100 * 0.0254 / 0.45, static_root=True,
                                six_channels=True, order="ZXY")):
        clips = _build(character, bvh)
        for c in clips:
            assert c.fidelity is not None and c.fidelity.ok, (c.id, c.fidelity)
            assert c.metrics["unfaithful"] == 0.0
        assert clips[0].metrics["pose_error_deg"] < 10.0
        assert clips[0].metrics["handedness"] == 1.0


def _swapped(bvh: Bvh) -> Bvh:
    swap = {"Left": "Right", "Right": "Left", "LHip": "RHip", "RHip": "LHip", "LThumb": "RThumb", "RThumb": "LThumb"}

    def name(n: str) -> str:
        for a, b in swap.items():
            if n.startswith(a):
                return b + n[len(a):]
        return n
    s = bvh.skeleton
    return dataclasses.replace(bvh, skeleton=Skeleton([name(n) for n in s.names], s.parents, s.offsets))


def _thigh_turned(bvh: Bvh) -> Bvh:
    rot, root = bvh.pose_arrays()
    j = bvh.skeleton.index("LeftUpLeg")
    rot[:, j] = quat_mul(quat_from_axis_angle(X, -np.pi / 2), rot[:, j])
    return bvh.with_poses(rot, root)


@pytest.mark.parametrize(("broken", "message"), [
    (_swapped, "left and right swapped"),
    (_thigh_turned, "the left foot never comes lower"),
])
def test_gate_refuses_broken_sources_naming_what_and_where(character, walk, broken, message):
    with pytest.raises(ConfigError, match=rf"\[animations\.walk\].*the reference fails the fidelity gate: .*{message}"):
        _build(character, broken(walk), **BROKEN)
    clips = _build(character, broken(walk), accept_unfaithful=True, **BROKEN)  # the override builds, marked
    assert clips[0].metrics["unfaithful"] == 1.0 and message in " ".join(clips[0].fidelity.problems)


def test_a_condition_that_flips_the_body_is_an_error_naming_it():
    rng = np.random.default_rng(1)
    reference = rng.normal(scale=0.05, size=(20, 31, 3))
    reference[:, :, 1] += 1.0
    reference[:, fidelity._I["Head"], 1] += 0.6
    flipped = reference.copy()
    flipped[8:12, :, 1] = 2.0 - flipped[8:12, :, 1]  # upside down for four frames
    check = fidelity.check_condition(flipped, np.zeros(31), reference)
    assert "flips the body: the head is under the hips at frames 8..11" in check.problems[0]
    assert fidelity.check_condition(reference, np.zeros(31), reference).ok


# --- glTF as exporters write it --------------------------------------------------------------------------------

def test_gltf_with_one_influence_set_unnamed_joints_and_partial_animation(character, walk, tmp_path):
    """What Blender and most exporters write: only JOINTS_0/WEIGHTS_0 (<= 4 influences; before the fix an
    AttributeError on JOINTS_1), joints without names (given by a mapping file), an animation that keys only some
    joints.  The motion read from it drives the character as the same file written by our exporter does."""
    from anim_core.clips.sources import read_motions
    from anim_core.io.gltf import GltfAnimation, read_gltf, write_gltf
    from anim_core.rig.rigmap import CANONICAL_NAMES, read_mapping_file

    rt = retarget(character, walk.posed_skeleton(), walk.end_sites)
    rot, root = walk.pose_arrays()
    rot, root = rot[:60], root[:60] * rt.root_scale
    held = [rt.skeleton.index(n) for n in ("LThumb", "RThumb", "LeftFingerBase", "RightFingerBase")]
    rot[:, held] = [1.0, 0, 0, 0]  # the file will not key these: they stay at rest
    ours = tmp_path / "ours.gltf"
    write_gltf(ours, rt.skeleton, rt.mesh.vertices, rt.mesh.normals, rt.faces, rt.mesh.joints, rt.mesh.weights,
               rt.mesh.inverse_bind, (GltfAnimation("walk", np.arange(60) * walk.frame_time, rot, root),))
    doc = json.loads(ours.read_text())
    for mesh in doc["meshes"]:
        for prim in mesh["primitives"]:
            assert "JOINTS_1" in prim["attributes"]  # ours writes two sets; the exporter below does not
            del prim["attributes"]["JOINTS_1"], prim["attributes"]["WEIGHTS_1"]
    joint_nodes = doc["skins"][0]["joints"]
    for node in joint_nodes:
        doc["nodes"][node].pop("name", None)
    anim = doc["animations"][0]
    held_nodes = {joint_nodes[rt.skeleton.index(CANONICAL_NAMES[j])] for j in held}
    anim["channels"] = [c for c in anim["channels"] if c["target"]["node"] not in held_nodes]
    theirs = tmp_path / "exported.gltf"
    theirs.write_text(json.dumps(doc))

    asset = read_gltf(theirs)
    assert asset.joints.shape[1] == 8 and np.all(asset.joints[:, 4:] == 0) and np.all(asset.weights[:, 4:] == 0)
    assert asset.skeleton.names[0] == "joint0"
    mapping = tmp_path / "mapping.toml"
    names = asset.skeleton.names
    # The skin lists joints in node order; our writer wrote them in skeleton order, so joint k is canonical k.
    mapping.write_text("\n".join(f'{c} = "{names[k]}"' for k, c in enumerate(rt.skeleton.names)) + "\n")
    (name, out), = read_motions(theirs, read_mapping_file(mapping))
    assert name == "walk" and out.units == "m"
    (_, same), = read_motions(ours)  # the file as our exporter wrote it, joints named
    err = np.abs(character_positions(character, out.bvh) - character_positions(character, same.bvh)).max()
    assert err < 1e-6, err


def test_a_one_cycle_take_cut_just_before_a_passing_builds_every_hybrid(character, data):
    """A take of exactly one gait cycle (its last pose its first), at 30 fps, cut one frame before the left foot
    falls behind the right, as the Bandai Namco run is: the passing is the very next frame, and keys one frame apart
    left the hybrid's increment 1 nothing to insert ("keys ... fall on the same source frames").  The second key is
    the first passing or full extension at least two frames on: every hybrid of the thesis builds."""
    bvh = read_bvh(data / "mocap" / "cmu" / "02_01_walk.bvh.gz")
    bvh = dataclasses.replace(bvh, motion=bvh.motion[1::4], frame_time=4 * bvh.frame_time)  # 30 fps
    rot, root = bvh.pose_arrays()
    pos = bvh.posed_skeleton().forward_kinematics(rot, root)[1]
    sk = bvh.skeleton
    lead = pos[:, sk.index("LeftFoot"), 2] - pos[:, sk.index("RightFoot"), 2]  # CMU 02_01 walks along +z
    behind = np.flatnonzero((lead[:-1] > 0) & (lead[1:] <= 0))
    a, b = int(behind[0]), int(behind[1])  # the frames just before two passings: one whole cycle
    rot, root = rot[a:b + 1].copy(), root[a:b + 1]
    rot[-1] = rot[0]  # the take's last pose is its first again
    take = bvh.with_poses(rot, root)
    conditions = (*CONDITIONS[:1], *(Condition.parse(f"hybrid{i}", "hybrid", {"increment": i}) for i in range(3)))
    out = normalize_bvh(take)
    cfg = AnimationConfig("take", "gait", take.source, (0, take.n_frames - 1), "loop", True)
    source = source_from_bvh(out.bvh, character, cfg, ("LHipJoint", "RHipJoint"), out.metres_per_unit,
                             out.source_positions)
    clips = build_animation(source, 30, conditions)
    assert [c.condition for c in clips] == ["keyframe", "hybrid0", "hybrid1", "hybrid2"]
    start, passing, end = clips[0].source["key_frames"][0], clips[0].source["key_frames"][1], b - a
    assert start == 0 and passing >= 2 and clips[0].source["cycle_frames"] == [0, end]
    assert all(c.fidelity.ok for c in clips), [(c.id, c.fidelity) for c in clips]
