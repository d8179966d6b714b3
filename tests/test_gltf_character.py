"""A skinned glTF character in place of the MakeHuman body: the MakeHuman character exported as glTF (renamed to
Mixamo, centimetres, Z up) comes back as the same character, its clips skin to the same vertices, it renders, the
manifest records it, and bad files fail clearly."""

import hashlib
import json
import shutil

import numpy as np
import pytest
from PIL import Image

from anim_core.io.bvh import read_bvh
from anim_core.io.gltf import read_gltf, write_gltf
from anim_core.math.clip import Pose
from anim_core.math.quat import identity, rotate
from anim_core.math.skeleton import Skeleton
from anim_core.rig.character import bind_mesh, retarget
from anim_core.rig.gltf_character import RIG_NAMES, character_from_gltf
from anim_core.rig.rigmap import CANONICAL_NAMES, CANONICAL_PARENTS
from server.assets import AssetError
from server.assets import character as load_makehuman
from server.clipset.build import build_clip_set
from server.clipset.config import ConfigError, load_config
from server.clipset.manifest import read_clip_manifest, write_clip_set
from server.errors import MediaError
from server.media.build import render_media
from server.media.manifest import MANIFEST
from server.media.scene import RenderSettings
from tests.test_rigmap import Z_UP, convention_table

VERTEX_TOLERANCE_M = 1e-5  # float32 in the file: ~1e-7 m at these sizes; 10 um leaves room for the retarget
SMALL = RenderSettings(width=160, height=120, shadows=False)
SECRET = b"test secret"


@pytest.fixture(scope="module")
def makehuman(data):
    return load_makehuman(data)


def export_rig(path, names, parents, positions, vertices, normals, faces, joints, weights):
    """A skinned glTF whose bind pose is the mesh: joints at ``positions`` with identity bind rotations."""
    offsets = positions.copy()
    offsets[1:] -= positions[parents[1:]]
    inverse_bind = np.concatenate([np.broadcast_to(np.eye(3), (len(positions), 3, 3)), -positions[:, :, None]],
                                  axis=2)
    write_gltf(path, Skeleton(names, parents, offsets), vertices, normals, faces, joints, weights, inverse_bind)
    return path


def export(character, path, names=None, scale=1.0, turn=None, vertices=None):
    """``character`` as a skinned glTF: its 31 joints (renamed by ``names``) at their heads plus an end joint
    at each leaf's tail (as Mixamo's ``HeadTop_End``), bind pose = the mesh, lengths times ``scale``, turned by
    ``turn``."""
    names = names or {n: n for n in character.names}
    turn = identity() if turn is None else turn
    leaves = [j for j in range(len(character.names)) if not np.any(character.parents == j)]
    pos = rotate(turn, np.concatenate([character.heads, character.tails[leaves]])) * scale
    v = character.vertices if vertices is None else vertices
    return export_rig(path, [names[n] for n in character.names] + [names[character.names[j]] + "_End" for j in leaves],
                      np.concatenate([character.parents, leaves]), pos, rotate(turn, v) * scale,
                      rotate(turn, character.normals), character.faces, character.joints, character.weights)


def mixamo_names(character):
    table = convention_table("mixamo", "mixamorig:")  # CMU name -> Mixamo name
    cmu = dict(zip(RIG_NAMES, CANONICAL_NAMES, strict=True))
    return {n: table[cmu[n]] for n in character.names}


def dense_weights(character, order):
    """``(V, 31)`` weight per joint, joints in ``order`` (names)."""
    column = np.array([order.index(n) for n in character.names])
    w = np.zeros((len(character.vertices), len(order)))
    rows = np.repeat(np.arange(len(w)), character.joints.shape[1])
    np.add.at(w, (rows, column[character.joints].ravel()), character.weights.ravel())
    return w


@pytest.mark.parametrize(("name", "mixamo", "scale", "z_up", "units", "up"), [
    ("plain.gltf", False, 1.0, False, "m", "y"), ("mixamo_cm_zup.glb", True, 100.0, True, "cm", "z")])
def test_exported_makehuman_comes_back_as_the_same_character(makehuman, tmp_path, name, mixamo, scale, z_up,
                                                            units, up):
    names = mixamo_names(makehuman) if mixamo else None
    path = export(makehuman, tmp_path / name, names, scale, Z_UP if z_up else None)
    mapped = character_from_gltf(read_gltf(path))
    c = mapped.character
    assert (mapped.units, mapped.up_axis) == (units, up)
    assert mapped.mapping.convention == ("Mixamo" if mixamo else "CMU")
    assert c.names == RIG_NAMES and np.array_equal(c.parents, CANONICAL_PARENTS)
    perm = [makehuman.index(n) for n in c.names]
    np.testing.assert_allclose(c.heads, makehuman.heads[perm], atol=1e-6)
    leaves = [k for k in range(31) if not np.any(c.parents == k)]
    np.testing.assert_allclose(c.tails[leaves], makehuman.tails[perm][leaves], atol=1e-6)
    np.testing.assert_allclose(c.vertices, makehuman.vertices, atol=1e-6)
    assert np.array_equal(c.faces, makehuman.faces)
    np.testing.assert_allclose(dense_weights(c, RIG_NAMES), dense_weights(makehuman, RIG_NAMES), atol=1e-6)
    assert mapped.folded == {}  # the end joints carry no weight


def test_unmapped_joints_pass_their_weights_to_their_mapped_ancestors(makehuman, tmp_path):
    """A rig with a root above the hips, a twist bone in the upper arm and a middle finger, each taking half of
    its mapped ancestor's weights: imported, the weights are the MakeHuman ones again."""
    c = makehuman
    arm, hand, hips = c.index("LeftArm"), c.index("LeftHand"), c.index("Hips")
    twist_at = 0.5 * (c.heads[arm] + c.heads[c.index("LeftForeArm")])
    middle_at = c.heads[hand] + 0.8 * (c.heads[c.index("LeftFingerBase")] - c.heads[hand])
    # Root first (index 0), then the character's joints shifted by one, then the twist and the middle finger.
    names = ["Root", *c.names, "LeftArmTwist", "LeftHandMiddle1"]
    parents = np.array([-1, *(np.where(c.parents >= 0, c.parents + 1, 0)), arm + 1, hand + 1])
    positions = np.concatenate([[[0.0, 0.0, 0.0]], c.heads, [twist_at, middle_at]])
    joints, weights = c.joints + 1, c.weights.copy()
    n = len(c.names)
    for source, helper in ((hips, -1), (arm, n + 1), (hand, n + 2)):  # half of each slot's weight to the helper
        rows, cols = np.nonzero((c.joints == source) & (c.weights > 0))
        free = np.argmin(weights[rows] > 0, axis=1)  # an empty slot on the same vertex
        assert np.all(weights[rows, free] == 0)
        weights[rows, cols] *= 0.5
        joints[rows, free], weights[rows, free] = (0 if helper < 0 else helper), weights[rows, cols]
    path = export_rig(tmp_path / "helpers.glb", names, parents, positions, c.vertices, c.normals, c.faces, joints,
                      weights)
    mapped = character_from_gltf(read_gltf(path))
    assert mapped.folded == {"Root": "Hips", "LeftArmTwist": "LeftArm", "LeftHandMiddle1": "LeftHand"}
    assert {"Root", "LeftArmTwist", "LeftHandMiddle1"} <= set(mapped.mapping.unmapped)
    np.testing.assert_allclose(dense_weights(mapped.character, RIG_NAMES), dense_weights(c, RIG_NAMES), atol=1e-6)


def test_joints_the_rig_lacks_are_placed_between_their_neighbours(makehuman, data, tmp_path):
    """Without LHipJoint, RHipJoint, LowerBack, Neck1 and Spine (as some rigs): their weights went to their
    parents; the character places the missing joints as the CMU skeleton has them (the one neck joint left is read
    as Neck1, the joint below the head, so Neck is the one placed, on Spine1; Spine midway); a CMU walk retargets
    onto it with the body about where the MakeHuman's is."""
    c = makehuman
    drop = [c.index(n) for n in ("LHipJoint", "RHipJoint", "LowerBack", "Neck1", "Spine")]
    keep = [j for j in range(len(c.names)) if j not in drop]
    up = c.parents.copy()
    for j in range(len(c.names)):
        while up[j] in drop:
            up[j] = c.parents[up[j]]
    new_index = {j: k for k, j in enumerate(keep)}
    joints = np.array([new_index[j] for j in np.where(np.isin(np.arange(len(c.names)), drop), up,
                                                        np.arange(len(c.names)))])[c.joints]
    parents = np.array([new_index[up[j]] if up[j] >= 0 else -1 for j in keep])
    path = export_rig(tmp_path / "fewer.glb", [c.names[j] for j in keep], parents, c.heads[keep], c.vertices,
                      c.normals, c.faces, joints, c.weights)
    mine = character_from_gltf(read_gltf(path)).character
    for name, a, b in (("LHipJoint", "Hips", "Hips"), ("LowerBack", "Hips", "Hips"), ("Neck", "Spine1", "Spine1"),
                       ("Spine", "Hips", "Spine1")):
        np.testing.assert_allclose(mine.heads[mine.index(name)],
                                   0.5 * (c.heads[c.index(a)] + c.heads[c.index(b)]), atol=1e-6)
    bvh = read_bvh(data / "mocap" / "cmu" / "12_03_walk.bvh.gz")
    rot, root = bvh.pose_arrays()
    skins, joints = [], []
    for character in (c, mine):
        rc = retarget(character, bvh.skeleton, bvh.end_sites)
        g = rc.skeleton.forward_kinematics(*rc.pose(Pose(rot[1:200:20], root[1:200:20])))
        skins.append(rc.mesh.skin(rc.mesh.skinning_matrices(*g))[0])
        joints.append(g[1])
    worst = np.linalg.norm(skins[1] - skins[0], axis=-1)
    assert np.all(np.isfinite(worst))
    legs = [bvh.skeleton.index(n) for n in ("LeftUpLeg", "LeftLeg", "LeftFoot", "RightUpLeg", "RightFoot")]
    np.testing.assert_allclose(joints[1][:, legs], joints[0][:, legs], atol=1e-6)
    print(f"rig without 5 joints vs MakeHuman: median {np.median(worst):.4f} m, max {worst.max():.4f} m")
    # Not equal: the spine has other bone lengths and the CMU neck rotation turns about other points (an
    # approximation: measured 3.4 cm median, 18 cm at the head), but nothing blows up and the legs are exact.
    assert np.median(worst) < 0.05 and worst.max() < 0.25


def write_clip_set_file(folder, character=""):
    path = folder / "set.toml"
    path.write_text(f"""fps = 30
[character]
{character}
[animations.walk]
kind = "gait"
source = "mocap/cmu/12_03_walk.bvh.gz"
frames = [1, 565]

[animations.idle]
kind = "idle"
source = "mocap/cmu/113_21_idle_30fps.bvh.gz"
frames = [0, 59]

[[conditions]]
id = "keyframe"
method = "keyframe"

[[conditions]]
id = "hybrid0"
method = "hybrid"
params = {{ increment = 0 }}
""")
    return path


@pytest.fixture(scope="module")
def built(data, makehuman, tmp_path_factory):
    """The same clip set built for the MakeHuman character and for it exported as a Mixamo-named, centimetre,
    Z-up glTF (given by absolute path, with a mapping file that restates one automatic choice)."""
    folder = tmp_path_factory.mktemp("gltf_character")
    glb = export(makehuman, folder / "mine.glb", mixamo_names(makehuman), 100.0, Z_UP)
    (folder / "map.toml").write_text('[mapping]\nLeftLeg = "mixamorig:LeftLeg"\n')
    plain = build_clip_set(data, load_config(write_clip_set_file(folder)))
    (folder / "gltf").mkdir()
    config = write_clip_set_file(folder / "gltf", f'gltf = "{glb}"\nmapping = "{folder / "map.toml"}"')
    messages = []
    mine = build_clip_set(data, load_config(config), progress=messages.append)
    return folder, glb, plain, mine, messages


def skinned(clip, character, frames):
    a = clip.arrays()
    mesh = bind_mesh(character, [str(n) for n in a["joint_names"]], a["bind_rotations"], a["bind_positions"])
    return mesh.skin(mesh.skinning_matrices(a["world_rotations"][frames], a["world_positions"][frames]))[0]


def test_clips_on_the_gltf_character_skin_to_the_makehuman_vertices(built, data, makehuman):
    _, glb, plain, mine, messages = built
    assert any("character" in m and "Mixamo names, cm, z up" in m for m in messages), messages
    character = character_from_gltf(read_gltf(glb)).character
    assert [c.id for c in mine] == [c.id for c in plain]
    worst = 0.0
    for a, b in zip(plain, mine, strict=True):
        assert a.n_frames == b.n_frames
        frames = np.linspace(0, a.n_frames - 1, 7).astype(int)
        err = np.abs(skinned(b, character, frames) - skinned(a, makehuman, frames)).max()
        worst = max(worst, err)
        assert err < VERTEX_TOLERANCE_M, (a.id, err)
    print(f"glTF character vs MakeHuman: max skinned vertex difference {worst:.2e} m over {len(plain)} clips")


def test_the_manifest_records_the_character(built, tmp_path):
    folder, glb, plain, mine, _ = built
    write_clip_set(mine, tmp_path / "mine")
    record = read_clip_manifest(tmp_path / "mine").character
    assert record.gltf == str(glb) and record.mapping == str(folder / "map.toml")

    assert record.files == {str(glb): hashlib.sha256(glb.read_bytes()).hexdigest(),
                            str(folder / "map.toml"): hashlib.sha256((folder / "map.toml").read_bytes()).hexdigest()}
    assert "character" not in json.loads((tmp_path / "mine" / "manifest.json").read_text())["clips"][0]["source"]
    write_clip_set(plain, tmp_path / "plain")
    default = read_clip_manifest(tmp_path / "plain").character
    assert default.gltf is None and len(default.files) == 3


def test_a_clip_renders_with_the_gltf_character(built, data, makehuman, tmp_path):
    """The renderer draws the recorded character's mesh: the exported MakeHuman renders as the MakeHuman does; a
    character with a wider mesh (same skeleton) renders wider; a glTF changed after the build is refused."""
    folder, glb, plain, mine, _ = built
    idle = lambda clips: [c for c in clips if c.id == "idle-keyframe"]  # noqa: E731 (one short clip renders)

    def poster(clips, name):
        write_clip_set(clips, tmp_path / name / "clips")
        out = tmp_path / name / "media"
        render_media(data, tmp_path / name / "clips", out, SECRET, SMALL, workers=1)
        (entry,) = json.loads((out / MANIFEST).read_text())["clips"].values()
        with Image.open(out / entry["poster"]) as image:
            return np.asarray(image.convert("RGB"), dtype=int)

    reference, same = poster(idle(plain), "plain"), poster(idle(mine), "mine")
    wide_vertices = makehuman.vertices * [1.25, 1.0, 1.25]
    wide_glb = export(makehuman, folder / "wide.glb", mixamo_names(makehuman), 100.0, Z_UP, wide_vertices)
    (folder / "wide").mkdir()
    wide_clips = build_clip_set(data, load_config(write_clip_set_file(folder / "wide", f'gltf = "{wide_glb}"')))
    wide = poster(idle(wide_clips), "wide")
    background = reference[0, 0]
    body = lambda img: np.abs(img - background).max(axis=-1) > 24  # noqa: E731
    assert body(reference).sum() > 300
    assert np.abs(same - reference).mean() < 1.0  # same mesh, same picture (JPEG noise only)
    assert body(wide).sum() > 1.1 * body(reference).sum()  # the glTF's own (wider) mesh is drawn
    # A character file changed after the clips were built: the renderer refuses it and says to rebuild.
    shutil.copy(glb, folder / "mine.bak")
    try:
        glb.write_bytes(wide_glb.read_bytes())
        with pytest.raises(MediaError, match=r"mine\.glb changed since the clip set was built; rebuild"):
            render_media(data, tmp_path / "mine" / "clips", tmp_path / "mine" / "again", SECRET, SMALL, workers=1)
    finally:
        shutil.copy(folder / "mine.bak", glb)


# --- bad input -------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def small_gltf(makehuman, tmp_path_factory):
    """The exported MakeHuman as an embedded .gltf (JSON), to edit."""
    return export(makehuman, tmp_path_factory.mktemp("bad") / "base.gltf")


def edited(small_gltf, tmp_path, name, edit):
    doc = json.loads(small_gltf.read_text())
    edit(doc)
    path = tmp_path / name
    path.write_text(json.dumps(doc))
    return path


def _rename_right_leg(doc):
    for node in doc["nodes"]:
        if node.get("name") in ("RightUpLeg", "RightLeg", "RightFoot", "RightToeBase", "RightToeBase_End"):
            node["name"] = "Bone" + node["name"][5:]


def _nan_translation(doc):
    doc["nodes"][3]["translation"] = [float("nan"), 0.0, 0.0]


def _nine_influences(doc):
    attributes = doc["meshes"][0]["primitives"][0]["attributes"]
    attributes["JOINTS_2"], attributes["WEIGHTS_2"] = attributes["JOINTS_1"], attributes["WEIGHTS_1"]


@pytest.mark.parametrize(("name", "edit", "message"), [
    ("noskin.gltf", lambda d: (d.pop("skins"), d["nodes"][-1].pop("skin")), "has no skin"),
    ("lines.gltf", lambda d: d["meshes"][0]["primitives"][0].update(mode=1), "only triangles"),
    ("external.gltf", lambda d: d["buffers"][0].update(uri="missing.bin"), "external buffer 'missing.bin' does not"),
    ("noleg.gltf", _rename_right_leg, "cannot find the right leg of the skeleton .*RightUpLeg, RightLeg, RightFoot"),
    ("nine.gltf", _nine_influences, "more than 8 influences per vertex"),
    ("nan.gltf", _nan_translation, "NaN or infinite"),
])
def test_bad_gltf_characters_fail_clearly(data, small_gltf, tmp_path, name, edit, message):
    path = edited(small_gltf, tmp_path, name, edit)
    config = write_clip_set_file(tmp_path, f'gltf = "{path}"')
    with pytest.raises(AssetError, match=message) as info:
        build_clip_set(data, load_config(config))
    assert str(info.value).startswith(f"glTF character {path}: "), str(info.value)


def test_missing_character_files_and_bad_mapping(data, small_gltf, tmp_path):
    config = write_clip_set_file(tmp_path, 'gltf = "characters/none.glb"')
    with pytest.raises(AssetError, match=r"glTF character file .*characters/none\.glb does not exist"):
        build_clip_set(data, load_config(config))
    (tmp_path / "map.toml").write_text('[mapping]\nLeftLeg = "NoSuchJoint"\n')
    config = write_clip_set_file(tmp_path, f'gltf = "{small_gltf}"\nmapping = "{tmp_path / "map.toml"}"')
    with pytest.raises(AssetError, match=r"base\.gltf: explicit mapping maps 'LeftLeg' to 'NoSuchJoint'"):
        build_clip_set(data, load_config(config))


@pytest.mark.parametrize(("field", "message"), [
    ('gltf = "mine.fbx"', "gltf must name a .glb or .gltf file"),
    ('gltf = "a.glb"\nunits = "feet"', "units must be one of m, inch, cm, mm, cmu"),
    ('gltf = "a.glb"\nup_axis = "x"', "up_axis must be 'y' or 'z'"),
    ('mapping = "map.toml"', "give gltf too"),
    ('body = "x"', "unknown field 'body'"),
    ("gltf = 3", "gltf must be a file path"),
])
def test_character_fields_are_checked(tmp_path, field, message):
    with pytest.raises(ConfigError, match=rf"set\.toml \[character\]: .*{message}"):
        load_config(write_clip_set_file(tmp_path, field))
