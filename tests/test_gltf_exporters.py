"""glTF as exporters write it (issue 35): a file laid out the way COLLADA2GLTF writes one -- nodes without names, one
animation per joint (``animation0`` .. ``animation30``) on a shared time base, constant translation keys on every
joint 0-3 mm off its rest value, scale keys of 1, a skinned mesh of a 1.51 m figure in metres -- inspects, builds a
clip set and is read as a character, with no mapping: its unnamed joints are mapped by structure, left and right
from the bind pose's geometry (whatever order the file numbers them in); a file that does not map prints its joints.
"""

import base64
import json

import numpy as np
import pytest

from anim_core.clips.sources import inspect_source, read_motions
from anim_core.io.bvh import read_bvh
from anim_core.io.gltf import GltfError, read_gltf, write_gltf
from anim_core.math.skeleton import Skeleton
from anim_core.rig.character import retarget
from anim_core.rig.gltf_character import RIG_NAMES, character_from_gltf
from anim_core.rig.rigmap import CANONICAL_NAMES
from server.assets import character as load_character

STATURE_M = 1.51  # the figure's height (its mesh's bounding box), metres
JITTER_M = 0.003  # constant translation keys up to this far off the rest value
STEP = 4  # every 4th frame of the 120 fps CMU walk: 30 fps, as an exporter samples it
#: World bone directions of the motion read back against the source's, degrees, on bones of 10 cm and more: the
#: 3 mm constant offsets the file keys turn such a bone by up to 2 * atan(3 / 100) = 3.4 degrees (both ends moved
#: across it); measured: median 0.41, max 0.95 degrees (the collar bone).
BONE_TOLERANCE_DEG = 2.0
_CHEST = CANONICAL_NAMES.index("Spine1")


@pytest.fixture(scope="module")
def walk(data):
    """The CMU walk retargeted onto the shipped character, scaled to a 1.51 m figure."""
    character = load_character(data)
    bvh = read_bvh(data / "mocap" / "cmu" / "02_01_walk.bvh.gz")
    rt = retarget(character, bvh.posed_skeleton(), bvh.end_sites)
    rot, root = bvh.pose_arrays()
    rot, root = rot[::STEP], root[::STEP] * rt.root_scale
    k = STATURE_M / float(np.ptp(rt.mesh.vertices[:, 1]))
    sk = rt.skeleton
    skeleton = Skeleton(sk.names, sk.parents, sk.offsets * k, sk.rest_rotations)
    return rt, skeleton, rot, root * k, k, STEP * bvh.frame_time


def _xyzw(q):
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def collada2gltf(walk, path, rng, mirror=False):
    """The walk as COLLADA2GLTF lays a file out (see the module docstring).  ``mirror``: the hips' and the chest's
    children in reverse order, so that depth-first numbering meets the right leg and the right arm first."""
    rt, skeleton, rot, root, k, frame_time = walk
    n = skeleton.n_joints
    ib = np.array(rt.mesh.inverse_bind)
    ib[:, :, 3] *= k
    write_gltf(path, skeleton, rt.mesh.vertices * k, rt.mesh.normals, rt.faces, rt.mesh.joints, rt.mesh.weights, ib)
    doc = json.loads(path.read_text())
    head, data = doc["buffers"][0]["uri"].split(",", 1)
    blob = bytearray(base64.b64decode(data))

    def add(values, kind):
        raw = np.ascontiguousarray(values, np.float32)
        while len(blob) % 4:
            blob.append(0)
        doc["bufferViews"].append({"buffer": 0, "byteOffset": len(blob), "byteLength": raw.nbytes})
        blob.extend(raw.tobytes())
        accessor = {"bufferView": len(doc["bufferViews"]) - 1, "componentType": 5126, "count": len(raw),
                    "type": kind}
        if kind == "SCALAR":
            accessor |= {"min": [float(raw.min())], "max": [float(raw.max())]}
        doc["accessors"].append(accessor)
        return len(doc["accessors"]) - 1

    frames = len(rot)
    times = add(np.arange(frames) * frame_time, "SCALAR")
    direction = rng.normal(size=(n, 3))
    jitter = direction / np.linalg.norm(direction, axis=1, keepdims=True) * rng.uniform(0, JITTER_M, (n, 1))
    animations = []
    for j in range(n):
        moved = root + skeleton.offsets[0] if j == 0 else np.tile(skeleton.offsets[j] + jitter[j], (frames, 1))
        outputs = [("rotation", add(_xyzw(rot[:, j]), "VEC4")), ("translation", add(moved, "VEC3")),
                   ("scale", add(np.ones((frames, 3)), "VEC3"))]
        animations.append({
            "samplers": [{"input": times, "output": out, "interpolation": "LINEAR"} for _, out in outputs],
            "channels": [{"sampler": s, "target": {"node": j, "path": what}} for s, (what, _) in enumerate(outputs)]})
    doc["animations"] = animations
    for node in doc["nodes"]:
        node.pop("name", None)
    if mirror:
        for j in (0, _CHEST):
            doc["nodes"][j]["children"] = doc["nodes"][j]["children"][::-1]
    doc["buffers"][0] = {"byteLength": len(blob), "uri": head + "," + base64.b64encode(bytes(blob)).decode()}
    path.write_text(json.dumps(doc))
    return path, jitter


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def bone_errors(walk, normalized):
    """Per frame and bone, the angle (degrees) between the world bone directions of ``normalized`` and the source
    walk's, on the canonical bones of 10 cm or more in the source (joint to its canonical parent)."""
    _, skeleton, rot, root, _, _ = walk
    source = skeleton.forward_kinematics(rot, root)[1]
    bvh = normalized.bvh
    got = bvh.posed_skeleton().forward_kinematics(*bvh.pose_arrays())[1]
    assert bvh.skeleton.names == CANONICAL_NAMES == tuple(skeleton.names)
    parents = bvh.skeleton.parents
    bones = [c for c in range(1, len(CANONICAL_NAMES))
             if normalized.mapping.source_index[c] >= 0 and np.linalg.norm(source[0, c] - source[0, parents[c]]) > 0.1]
    cos = np.sum(_unit(source[:, bones] - source[:, parents[bones]]) * _unit(got[:, bones] - got[:, parents[bones]]),
                 axis=-1)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))), [CANONICAL_NAMES[c] for c in bones]


@pytest.mark.parametrize("mirror", [False, True], ids=["file-order", "mirrored-numbering"])
def test_a_collada2gltf_file_inspects_with_no_mapping_and_left_stays_left(walk, tmp_path, rng, mirror):
    path, _ = collada2gltf(walk, tmp_path / "collada.gltf", rng, mirror)
    asset = read_gltf(path)
    assert asset.skeleton.names == tuple(f"joint{k}" for k in range(31))
    (anim,) = asset.animations  # 31 one-joint animations, one motion
    assert anim.name == "animation0..animation30" and len(anim.parts) == 31
    (report,) = inspect_source(path)
    n = report.normalized
    assert n.units == "m" and n.up_axis == "y" and n.facing_angle == 0.0, (n.units, n.up_axis, n.facing_angle)
    assert report.kind == "gait", report.reason
    # Left stays left: every joint mapped is the file's joint of that name before the names were taken out
    # (node i is CANONICAL_NAMES[i]; the reader numbers it skin_order[i], depth-first), whatever order the file
    # numbers them in; and the left leg and arm are at +X of the bind pose.
    mapping = n.mapping.as_dict()
    truth = {name: f"joint{asset.skin_order[i]}" for i, name in enumerate(CANONICAL_NAMES)}
    wrong = {c: (f, truth[c]) for c, f in mapping.items() if f != truth[c]}
    assert not wrong and len(mapping) == 25, (wrong, sorted(set(CANONICAL_NAMES) - set(mapping)))
    if mirror:
        assert mapping["LeftUpLeg"] != "joint2" and mapping["RightArm"] == "joint5"  # right ones numbered first
    rest = asset.skeleton.rest_global()[1]
    index = {name: i for i, name in enumerate(asset.skeleton.names)}
    for side, sign in (("Left", 1), ("Right", -1)):
        for part in ("UpLeg", "Foot", "Arm", "Hand"):
            assert sign * rest[index[mapping[side + part]], 0] > 0.05, (side + part, mapping[side + part])
    errors, bones = bone_errors(walk, n)
    print(f"{'mirrored' if mirror else 'file order'}: world bone directions vs the source over {len(bones)} bones "
          f"x {len(errors)} frames: median {np.median(errors):.2f}, max {errors.max():.2f} deg "
          f"({bones[int(np.argmax(errors.max(axis=0)))]})")
    assert errors.max() < BONE_TOLERANCE_DEG


def test_still_translation_keys_are_the_joints_translations(walk, tmp_path, rng):
    """The constant keys, 0-3 mm off the rest, are taken as the joints' translations (as a BVH's constant position
    channels are): the motion read is the one the file plays, to float32."""
    path, jitter = collada2gltf(walk, tmp_path / "collada.gltf", rng)
    (anim,) = read_gltf(path).animations
    skeleton = walk[1]
    expected = skeleton.offsets + np.where(np.arange(31)[:, None] > 0, jitter, 0.0)
    np.testing.assert_allclose(anim.offsets, expected, atol=1e-6)
    ((name, normalized),) = read_motions(path)
    assert name == anim.name and normalized.bvh.n_frames == len(walk[2])
    # Translation keys that move a joint are still refused, with the joint named: the root's (it travels) on joint 3.
    doc = json.loads(path.read_text())
    doc["animations"][3]["samplers"][1]["output"] = doc["animations"][0]["samplers"][1]["output"]
    bad = tmp_path / "moving.gltf"
    bad.write_text(json.dumps(doc))
    with pytest.raises(GltfError, match=r"moving\.gltf: animation 'animation3' translates joint 'joint3' "
                                        r"\(it moves up to .*only the root may translate"):
        read_gltf(bad)
    # Scale keys beyond 1 % of 1 are refused too.
    doc = json.loads(path.read_text())
    doc["animations"][4]["samplers"][2]["output"] = doc["animations"][0]["samplers"][1]["output"]
    bad.write_text(json.dumps(doc))
    with pytest.raises(GltfError, match=r"animation 'animation4' scales joint 'joint4'"):
        read_gltf(bad)


def test_the_animation_field_selects_the_merged_motion(walk, tmp_path, rng, data):
    from server.clipset.build import read_source
    from server.clipset.config import AnimationConfig

    path, _ = collada2gltf(walk, tmp_path / "collada.gltf", rng)
    for wanted in (None, 0, "animation0..animation30"):
        config = AnimationConfig("walk", "gait", str(path), (0, 10), "loop", False, animation=wanted)
        assert read_source(data, config).bvh.n_frames == len(walk[2])


def test_a_collada2gltf_file_is_a_character_and_builds_a_clip_set(walk, tmp_path, rng, data):
    """Read as a character from its skin and bind pose (its 31 animations play no part), mapped by structure, in
    metres by its mesh's height; and a clip set with that file as both character and motion builds with no
    mapping."""
    from server.assets import gltf_character
    from server.clipset.build import build_clip_set
    from server.clipset.config import load_config

    path, _ = collada2gltf(walk, tmp_path / "collada.gltf", rng, mirror=True)
    mapped = gltf_character(data, str(path))  # as a clip set's [character] gltf reads it
    assert mapped.mapping.convention == "unknown" and mapped.mapping.source_index[0] == 0
    direct = character_from_gltf(read_gltf(path, animations=False)).character
    np.testing.assert_allclose(direct.heads, mapped.character.heads, atol=1e-12)
    assert mapped.units == "m" and mapped.up_axis == "y"
    c = mapped.character
    assert c.names == RIG_NAMES
    heads = dict(zip(c.names, c.heads, strict=True))
    for side, sign in (("Left", 1), ("Right", -1)):
        for joint in ("UpLeg", "Foot", "Arm", "Hand"):
            rig_name = RIG_NAMES[CANONICAL_NAMES.index(side + joint)]
            assert sign * heads[rig_name][0] > 0.05, rig_name
    stature = float(np.ptp(c.vertices[:, 1]))
    assert abs(stature - STATURE_M) < 1e-3, stature

    (report,) = inspect_source(path)
    lo, hi = report.frames
    config = tmp_path / "set.toml"
    config.write_text(f"""fps = 30
[character]
gltf = "{path}"
[animations.walk]
kind = "{report.kind}"
source = "{path}"
frames = [{lo}, {hi}]

[[conditions]]
id = "keyframe"
method = "keyframe"
""")
    messages = []
    clips = build_clip_set(data, load_config(config), progress=messages.append)
    assert [clip.id for clip in clips] == ["walk-keyframe"], [clip.id for clip in clips]
    print("\n".join(m for m in messages if "character" in m or "fidelity" in m or "walk" in m))


def test_a_failed_inspect_prints_the_joint_list(walk, tmp_path, rng, capsys):
    """A file that does not map (here the left arm hangs from the hips: four branches there) fails with the
    reason, and lists its joints -- index, name, parent, bind position -- to write a mapping file from."""
    from server.cli import main

    path, _ = collada2gltf(walk, tmp_path / "collada.gltf", rng)
    doc = json.loads(path.read_text())
    shoulder = CANONICAL_NAMES.index("LeftShoulder")
    doc["nodes"][_CHEST]["children"].remove(shoulder)
    doc["nodes"][0]["children"].append(shoulder)
    bad = tmp_path / "four.gltf"
    bad.write_text(json.dumps(doc))
    assert main(["clips", "inspect", str(bad)]) == 2
    out = capsys.readouterr()
    assert out.out == "" and "Traceback" not in out.err
    assert out.err.startswith("error: four.gltf animation 'animation0..animation30': cannot find"), out.err
    assert "mapping by structure failed: the hips (joint 0) have 4 branches" in out.err
    lines = out.err.splitlines()
    start = next(k for k, line in enumerate(lines) if line.startswith("joints of four.gltf"))
    table = lines[start + 2:]
    assert len(table) == 31
    bind = np.linalg.inv(read_gltf(bad, animations=False).inverse_bind)[:, :3, 3]
    for k, line in enumerate(table):
        index, name, parent, *position = line.split(None, 3)
        assert int(index) == k and name == f"joint{k}"
        assert parent == "-" if k == 0 else parent.startswith("joint")
        xyz = np.array([float(v) for v in position[0].strip("()").split(",")])
        np.testing.assert_allclose(xyz, bind[k], atol=1e-3)
    print("\n".join(lines[start:start + 6]))


def test_the_human_height_rule_reads_the_mesh(walk, tmp_path, rng):
    """A figure with short legs (knee and ankle bones at 0.6 of the walk's): 1.51 m tall by its mesh, but its legs
    make a standing height of 1.63 leg lengths = 0.71 m, no human height in any unit.  The file's skinned mesh
    gives its height: metres, with no --units."""
    rt, skeleton, rot, root, k, frame_time = walk
    offsets = skeleton.offsets.copy()
    short = [CANONICAL_NAMES.index(f"{side}{part}") for side in ("Left", "Right") for part in ("Leg", "Foot")]
    offsets[short] *= 0.6
    stubby = (rt, Skeleton(skeleton.names, skeleton.parents, offsets, skeleton.rest_rotations), rot, root, k,
              frame_time)
    path, _ = collada2gltf(stubby, tmp_path / "stubby.gltf", rng)
    (report,) = inspect_source(path)
    assert report.normalized.units == "m"
    assert abs(float(np.ptp(read_gltf(path, animations=False).vertices[:, 1])) - STATURE_M) < 1e-3
