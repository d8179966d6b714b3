"""The MakeHuman character and the retargeting of every CMU clip onto it."""

import gzip
import shutil

import numpy as np
import pytest

from anim_core.io.bvh import read_bvh
from anim_core.math.clip import Pose
from anim_core.rig.character import CharacterError, rebind, retarget
from server.assets import CHARACTER_DIR, AssetError
from server.assets import character as load_character


@pytest.fixture(scope="module")
def character(data):
    return load_character(data)


def test_body_mesh_and_weights(character):
    assert character.vertices.shape == (13380, 3)  # the "body" group only, helper geometry dropped
    assert character.faces.shape == (2 * 13378, 3)  # quads split in two
    assert character.faces.max() == 13379
    np.testing.assert_allclose(character.weights.sum(axis=1), 1.0, atol=1e-9)
    assert character.joints.shape[1] == 8
    height = np.ptp(character.vertices[:, 1])
    assert 1.6 < height < 1.75  # metres (SOURCE.md: ~1.67 m)
    # Faces wound counter-clockwise seen from outside: the signed volume is positive and about a person's
    # (~0.06 m³), so the normals computed from that winding point outwards.
    tri = character.vertices[character.faces]
    volume = np.sum(tri[:, 0] * np.cross(tri[:, 1], tri[:, 2])) / 6.0
    print(f"body volume {volume:.4f} m3")
    assert 0.04 < volume < 0.1
    np.testing.assert_allclose(np.linalg.norm(character.normals, axis=1), 1.0, atol=1e-9)


def test_rig_is_y_up_facing_plus_z(character):
    head = character.heads[character.index("Head")]
    hips = character.heads[character.index("Hips")]
    left = character.heads[character.index("LeftUpLeg")]
    toe = character.heads[character.index("LeftToeBase")]
    ankle = character.heads[character.index("LeftFoot")]
    assert head[1] - hips[1] > 0.5  # up is +Y
    assert left[0] > hips[0] + 0.05  # the character's left is +X
    assert toe[2] > ankle[2] + 0.05  # toes point forward, +Z


def bone_angles(mocap, mocap_pos, char_pos):
    """Angle (degrees) between each mocap bone with a length and the character's same bone, (frames, bones)."""
    bones = [j for j in range(1, mocap.n_joints) if np.linalg.norm(mocap.offsets[j]) > 1e-9]
    parents = mocap.parents[bones]
    a = mocap_pos[:, bones] - mocap_pos[:, parents]
    b = char_pos[:, bones] - char_pos[:, parents]
    cos = np.sum(a * b, axis=-1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))), len(bones)


def test_every_bone_points_as_in_the_mocap_at_every_frame_of_every_clip(character, bvh_paths):
    for path in bvh_paths:
        bvh = read_bvh(path)
        rc = retarget(character, bvh.skeleton, bvh.end_sites)
        rotations, root = bvh.pose_arrays()
        _, mocap_pos = bvh.skeleton.forward_kinematics(rotations, root)
        _, char_pos = rc.skeleton.forward_kinematics(*rc.pose(Pose(rotations, root)))
        angles, n_bones = bone_angles(bvh.skeleton, mocap_pos, char_pos)
        print(f"{path.name}: {bvh.n_frames} frames x {n_bones} bones, worst {angles.max():.1e} deg")
        assert angles.max() < 1.0


def test_bind_pose_reproduces_the_mesh_and_sockets_stay_put(character, data):
    bvh = read_bvh(data / "mocap/cmu/12_03_walk.bvh.gz")
    rc = retarget(character, bvh.skeleton, bvh.end_sites)
    pos, nrm = rc.mesh.skin(rc.mesh.skinning_matrices(rc.bind_rotations, rc.bind_positions))
    np.testing.assert_allclose(pos, character.vertices, atol=1e-12)
    np.testing.assert_allclose(nrm, character.normals, atol=1e-12)
    # The hip sockets are where the mesh has them, though the pelvis bones take the mocap's direction.
    for name in ("LeftUpLeg", "RightUpLeg"):
        np.testing.assert_allclose(rc.bind_positions[rc.skeleton.index(name)], character.heads[character.index(name)],
                                   atol=1e-12)
    # Feet: ankles ~7 cm and toes ~2 cm above the soles when standing.
    contact = dict(zip(rc.skeleton.names, rc.contact_heights, strict=True))
    assert 0.04 < contact["LeftFoot"] < 0.1 and 0.0 < contact["LeftToeBase"] < 0.04


def test_root_translation_is_scaled_to_the_leg_length(character, data):
    bvh = read_bvh(data / "mocap/cmu/12_03_walk.bvh.gz")
    rc = retarget(character, bvh.skeleton, bvh.end_sites)
    rotations, root = bvh.pose_arrays()
    # Standing on the mocap's feet, the character's hips are as high above its toes as its leg is long.
    _, pos = rc.skeleton.forward_kinematics(rotations[1:], root[1:] * rc.root_scale)
    toe = pos[:, [rc.skeleton.index("LeftToeBase"), rc.skeleton.index("RightToeBase")], 1].min(axis=1)
    hip_height = np.median(pos[:, 0, 1] - toe)
    leg = sum(np.linalg.norm(rc.skeleton.offsets[rc.skeleton.index(n)]) for n in ("LeftLeg", "LeftFoot"))
    assert 0.85 * leg < hip_height < 1.15 * leg
    assert 0.05 < rc.root_scale < 0.07  # ~ 0.056444 m per CMU unit, adjusted to the character's legs


def copy_character(data, tmp_path):
    target = tmp_path / "data" / CHARACTER_DIR
    shutil.copytree(data / CHARACTER_DIR, target)
    for f in target.iterdir():
        f.chmod(0o644)
    return tmp_path / "data", target


def test_corrupt_or_altered_character_files_give_clear_errors(data, tmp_path):
    load_character(data)  # a character already loaded in the process does not let an altered copy through
    root, folder = copy_character(data, tmp_path)
    weights = folder / "weights.cmu_mb.json.gz"
    weights.write_bytes(weights.read_bytes()[:1000])  # truncated archive
    with pytest.raises(AssetError, match=r"weights\.cmu_mb\.json\.gz.*corrupt"):
        load_character(root)
    rig = folder / "rig.cmu_mb.json"
    shutil.copy(data / CHARACTER_DIR / "weights.cmu_mb.json.gz", weights)
    rig.write_text(rig.read_text().replace("0.0", "0.1", 1))  # a different (edited) rig
    with pytest.raises(AssetError, match=r"rig\.cmu_mb\.json is corrupt or a different version"):
        load_character(root)
    rig.unlink()
    with pytest.raises(AssetError, match=r"missing file .*rig\.cmu_mb\.json"):
        load_character(root)


def test_one_character_is_shared_and_read_only(data, tmp_path):
    shared = load_character(data)
    assert load_character(copy_character(data, tmp_path)[0]) is shared  # verified files have one content
    for name in ("vertices", "normals", "faces", "joints", "weights", "heads", "tails", "parents"):
        with pytest.raises(ValueError, match="read-only"):
            getattr(shared, name)[0] = 0


def test_uncompressed_copies_are_accepted(data, tmp_path):
    root, folder = copy_character(data, tmp_path)
    obj = folder / "base.obj.gz"
    (folder / "base.obj").write_bytes(gzip.decompress(obj.read_bytes()))
    obj.unlink()
    assert load_character(root).vertices.shape == (13380, 3)


def test_retargeting_needs_matching_joints(character, data):
    bvh = read_bvh(data / "mocap/cmu/12_03_walk.bvh.gz")
    with pytest.raises(CharacterError, match="no joints for mocap joints"):
        retarget(character, bvh.skeleton, bvh.end_sites, name_map={})


def test_rebind_moves_the_mesh_as_the_motions_own_binding_does(character, data):
    # issue 39: a composite plays every take on its first take's skeleton. Each take is bound on its own (its rest
    # directions, its pelvis as it holds it), so the run's rotations played unchanged on the idle's binding move the
    # mesh elsewhere (seen: up to 0.32 m); re-expressed by rebind, every vertex lands where the run's own binding
    # puts it.
    run = read_bvh(data / "mocap/cmu/09_11_run.bvh.gz")
    idle = read_bvh(data / "mocap/cmu/113_21_idle_30fps.bvh.gz")
    rot, root = run.pose_arrays()
    rot, root = rot[1:60:6], root[1:60:6]
    mine = retarget(character, run.skeleton, run.end_sites, motion=rot, relocate=("LHipJoint", "RHipJoint"))
    other = retarget(character, idle.skeleton, idle.end_sites, motion=idle.pose_arrays()[0][1:],
                     relocate=("LHipJoint", "RHipJoint"))
    pose = mine.pose(Pose(rot, root))

    def mesh(rc, p):
        g, x = rc.skeleton.forward_kinematics(*p)
        return np.stack([rc.mesh.skin(rc.mesh.skinning_matrices(gi, xi))[0] for gi, xi in zip(g, x, strict=True)])

    want = mesh(mine, pose)
    unchanged = np.linalg.norm(mesh(other, Pose(pose.rotations, pose.root_translation + mine.skeleton.offsets[0]
                                                - other.skeleton.offsets[0])) - want, axis=-1)
    print(f"unchanged: {unchanged.max():.3f} m")
    assert unchanged.max() > 0.1
    assert np.abs(mesh(other, rebind(pose, mine, other)) - want).max() < 1e-9
    assert rebind(pose, mine, mine) is pose
