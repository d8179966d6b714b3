"""Issue 15 in the clip set: animations of kind "other", sources of any common rig (BVH) or glTF, export of a built
clip as glTF and BVH, and a study built end to end from a BVH that is not on the CMU skeleton.

The non-CMU sources are the real CMU files renamed to Mixamo names, in centimetres and Z up (the renamer of
tests/test_rigmap.py): after mapping they must give the very clips the CMU files give."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from anim_core.clips.build import ConfigError
from anim_core.io.bvh import format_bvh, read_bvh
from anim_core.io.gltf import GltfAnimation, read_gltf, write_gltf
from anim_core.rig.character import retarget
from server.assets import AssetError
from server.assets import character as load_character
from server.cli import main
from server.clipset.build import build_clip_set
from server.clipset.config import load_config
from server.clipset.manifest import read_clip_manifest, write_clip_set
from tests.test_rigmap import Z_UP, convention_table, renamed, scaled, turned

CMU = "mocap/cmu"
WALK, CROUCH = "02_01_walk.bvh.gz", "115_06_crouch_first164.bvh.gz"
CM_PER_CMU_UNIT = 100 * 0.0254 / 0.45
CONDITIONS = """
[[conditions]]
id = "keyframe"
method = "keyframe"

[[conditions]]
id = "hybrid0"
method = "hybrid"
params = { increment = 0 }
"""


def mixamo_cm_z_up(data: Path, name: str, out: Path) -> Path:
    """The CMU file ``name`` as a Mixamo rig would export it: ``mixamorig:`` names, centimetres, Z up."""
    bvh = read_bvh(data / CMU / name)
    source = turned(scaled(renamed(bvh, convention_table("mixamo", "mixamorig:")), CM_PER_CMU_UNIT), Z_UP)
    path = out / f"mixamo_{name.removesuffix('.gz')}"
    path.write_text(format_bvh(source))
    return path


def clip_set_file(path: Path, animations: str, conditions: str = CONDITIONS) -> Path:
    path.write_text(f"fps = 30\n{animations}\n{conditions}", encoding="utf-8")
    return path


@pytest.fixture(scope="module")
def sources(data, tmp_path_factory):
    folder = tmp_path_factory.mktemp("byo")
    return folder, mixamo_cm_z_up(data, WALK, folder), mixamo_cm_z_up(data, CROUCH, folder)


def animations(walk: str, squat: str, squat_extra: str = "") -> str:
    return f"""
[animations.walk]
kind = "gait"
source = "{walk}"
frames = [0, 342]

[animations.squat]
kind = "other"
source = "{squat}"
frames = [1, 163]
tolerance_mm = 25
{squat_extra}
"""


@pytest.fixture(scope="module")
def built(data, sources):
    """The same clip set from the renamed files (absolute paths) and from the CMU originals (data directory)."""
    folder, walk, squat = sources
    byo = load_config(clip_set_file(folder / "byo.toml", animations(str(walk), str(squat))))
    cmu = load_config(clip_set_file(folder / "cmu.toml", animations(f"{CMU}/{WALK}", f"{CMU}/{CROUCH}")))
    return build_clip_set(data, byo), build_clip_set(data, cmu)


def test_other_from_a_mixamo_bvh_gives_the_clips_of_its_cmu_original(built):
    byo, cmu = built
    assert [c.id for c in byo] == ["walk-keyframe", "walk-hybrid0", "squat-keyframe", "squat-hybrid0"]
    for a, b in zip(byo, cmu, strict=True):
        assert a.id == b.id and a.n_frames == b.n_frames and a.key_times.size == b.key_times.size
        err = np.abs(a.world_positions - b.world_positions).max()
        assert err < 1e-6, (a.id, err)
    squat = {c.condition: c for c in byo if c.animation == "squat"}
    assert squat["keyframe"].kind == "other" and squat["keyframe"].playback == "pingpong"


def test_other_hybrid_stays_within_its_tolerance(built):
    """The hybrid through the picked keys, as built and placed, against the reference: every joint, every frame."""
    byo, _ = built
    squat = {c.condition: c for c in byo if c.animation == "squat"}
    ref, hybrid = squat["keyframe"], squat["hybrid0"]
    err_mm = np.linalg.norm(hybrid.world_positions - ref.world_positions, axis=-1).max() * 1000
    info = hybrid.source
    print(f"squat: {hybrid.key_times.size} keys of {ref.key_times.size}, largest error {err_mm:.1f} mm "
          f"(stated {info['key_error_mm']} mm, tolerance {info['tolerance_mm']} mm)")
    assert info["tolerance_mm"] == 25 and err_mm <= 25 + 1e-6
    assert 2 < hybrid.key_times.size < ref.key_times.size / 3
    # The keys are source frames of the configured range, first and last at its ends (ping-pong turns there).
    keys = info["key_frames"]
    assert keys[0] == 1 and keys[-1] == 163 and keys == sorted(keys) and len(keys) == hybrid.key_times.size


def test_other_loop_with_given_keys_and_the_other_methods(data, sources):
    """A loop with given keys, and a ping-pong one with picked keys, under every registered method."""
    folder, _, squat = sources
    text = f"""
[animations.sway]
kind = "other"
source = "{squat}"
frames = [20, 120]
playback = "loop"
in_place = true
keys = [20, 50, 80]
accept_unfaithful = true  # the C2 spline through 3 keys of a squat lifts a foot out of a stance: the gate marks it

[animations.squat]
kind = "other"
source = "{squat}"
frames = [1, 163]
"""
    conditions = CONDITIONS + """
[[conditions]]
id = "c2"
method = "hybrid_c2"
params = { increment = 0 }

[[conditions]]
id = "ik"
method = "hybrid_ik"
params = { increment = 0 }

[[conditions]]
id = "reduced"
method = "reduced"
params = { epsilon_deg = 2.0 }

[[conditions]]
id = "quantized"
method = "quantized"
params = { bits = 12 }
"""
    built = build_clip_set(data, load_config(clip_set_file(folder / "loop.toml", text, conditions)))
    clips = {c.id: c for c in built}
    assert len(clips) == 12
    ref, hybrid = clips["sway-keyframe"], clips["sway-hybrid0"]
    assert ref.fidelity.ok and hybrid.fidelity.ok
    assert "the left foot never lands in the reference's contact" in clips["sway-c2"].fidelity.problems[0]
    assert ref.playback == "loop" and ref.n_frames == ref.key_times.size  # one loop, the closing key not stored
    assert hybrid.key_times.size == clips["sway-c2"].key_times.size == 3
    # The hybrid passes through the reference's poses at its keys (grid frames of source frames 20, 50, 80).
    frames = np.rint(hybrid.key_times * 30).astype(int)
    assert frames[0] == 0 and np.allclose(frames, [0, 0.3 * ref.n_frames, 0.6 * ref.n_frames], atol=1)
    np.testing.assert_allclose(hybrid.world_positions[frames], ref.world_positions[frames], atol=1e-9)
    # Seams no larger than twice the median step + 5 mm (the warning limit of `clips build`).
    for c in built:
        if c.condition != "c2" or c.animation != "sway":  # C2 through 3 keys of a crouch: the spline's own seam
            assert c.metrics["seam_jump_mm"] <= 2 * c.metrics["median_step_mm"] + 5, c.id
    assert clips["squat-c2"].key_times.size == clips["squat-hybrid0"].key_times.size > 2


def test_a_loop_through_straight_legs_does_not_flip(data, tmp_path):
    """The middle of the CMU crouch (frames 20-120, both feet down, the right knee passing through straight) as a
    loop: the foot planting keeps each knee on its hinge, so no joint flips (before: thighs and feet twisted by
    167 degrees in one frame, a `clips build` warning).  The largest frame-to-frame turn is 33 degrees where the
    right knee, hyper-extended in the mocap, is bent forwards through straight (18 degrees unplanted)."""
    from anim_core.clips.measure import clip_warnings
    from anim_core.math.quat import quat_angle

    text = (f'[animations.middle]\nkind = "other"\nsource = "{CMU}/{CROUCH}"\nframes = [20, 120]\n'
            f'playback = "loop"\n')
    clips = build_clip_set(data, load_config(clip_set_file(tmp_path / "m.toml", text)))
    assert not [w for w in clip_warnings(clips) if "flip" in w]
    for c in clips:
        turn = np.degrees(quat_angle(np.roll(c.local_rotations, -1, axis=0), c.local_rotations))  # the wrap too
        assert turn.max() < 40.0, (c.id, c.character.skeleton.names[int(np.argmax(turn.max(axis=0)))])


def test_gltf_animation_by_name_and_index(data, tmp_path):
    """A glTF holding the crouch on the character (second of two animations) is a source, picked by name or index;
    its clips are those of the CMU file (float32 in the file)."""
    character = load_character(data)
    bvh = read_bvh(data / CMU / CROUCH)
    rot, root = bvh.pose_arrays()
    # bound to the frames the clip set below plays, as its build binds the CMU file (the pelvis as the take holds it)
    rt = retarget(character, bvh.posed_skeleton(), bvh.end_sites, motion=rot[1:164])
    times = np.arange(bvh.n_frames) * bvh.frame_time
    still = GltfAnimation("still", times[:5], rot[:5], root[:5] * rt.root_scale)
    path = tmp_path / "crouch.glb"
    write_gltf(path, rt.skeleton, rt.mesh.vertices, rt.mesh.normals, rt.faces, rt.mesh.joints, rt.mesh.weights,
               rt.mesh.inverse_bind, (still, GltfAnimation("Squat", times, rot, root * rt.root_scale)))

    def squat(source: str, extra: str) -> str:
        return f'[animations.squat]\nkind = "other"\nsource = "{source}"\nframes = [1, 163]\n{extra}\n'

    cmu = build_clip_set(data, load_config(clip_set_file(tmp_path / "c.toml", squat(f"{CMU}/{CROUCH}", ""))))
    for extra in ('animation = "Squat"', "animation = 1"):
        clips = build_clip_set(data, load_config(clip_set_file(tmp_path / "g.toml", squat(str(path), extra))))
        for a, b in zip(clips, cmu, strict=True):
            assert a.key_times.size == b.key_times.size
            err = np.abs(a.world_positions - b.world_positions).max()
            assert err < 1e-4, (extra, a.id, err)
    for extra, message in (('animation = "Jump"', r"holds no animation 'Jump'; it holds 'still', 'Squat'"),
                           ("animation = 2", r"index 2, but .* holds 2 animation")):
        with pytest.raises(AssetError, match=rf"\[animations.squat\] animation: .*{message}"):
            build_clip_set(data, load_config(clip_set_file(tmp_path / "g.toml", squat(str(path), extra))))


def test_mapping_units_and_up_overrides(data, sources, tmp_path):
    _, walk, _ = sources
    mapping = tmp_path / "map.json"
    mapping.write_text(json.dumps({"LeftToeBase": "mixamorig:LeftToeBase"}))
    text = (f'[animations.walk]\nkind = "gait"\nsource = "{walk}"\nframes = [0, 342]\nunits = "cm"\nup_axis = "z"\n'
            f'mapping = "{mapping}"\n')
    clips = build_clip_set(data, load_config(clip_set_file(tmp_path / "o.toml", text)))
    assert [c.id for c in clips] == ["walk-keyframe", "walk-hybrid0"]
    # The overrides are taken as given: a wrong unit is the mocap's scale, a wrong up axis lays the walk down.
    from server.clipset.build import load_source

    mm = load_config(clip_set_file(tmp_path / "o.toml", text.replace('"cm"', '"mm"'))).animations["walk"]
    assert load_source(data, load_character(data), mm, ()).metres_per_unit == 0.001
    # (A walk laid down is no longer refused by the mirroring, which turns a walk into its own heading frame: the
    # fidelity gate refuses it.)
    with pytest.raises(ConfigError, match=r"\[animations\.walk\] .*fails the fidelity gate"):
        y_up = text.replace('up_axis = "z"', 'up_axis = "y"')
        build_clip_set(data, load_config(clip_set_file(tmp_path / "o.toml", y_up)))
    broken = tmp_path / "broken.json"
    broken.write_text("{")
    with pytest.raises(AssetError, match=r"\[animations.walk\] mapping: .*broken\.json"):
        build_clip_set(data, load_config(clip_set_file(tmp_path / "o.toml", text.replace(str(mapping),
                                                                                           str(broken)))))
    missing = text.replace(str(walk), str(tmp_path / "nowhere.bvh"))
    with pytest.raises(AssetError, match=r"missing file .*nowhere\.bvh"):
        build_clip_set(data, load_config(clip_set_file(tmp_path / "o.toml", missing)))
    bad = tmp_path / "bad.bvh"
    bad.write_text(walk.read_text()[:3000])
    with pytest.raises(AssetError, match=r"\[animations.walk\] source: .*bad\.bvh"):
        build_clip_set(data, load_config(clip_set_file(tmp_path / "o.toml", text.replace(str(walk), str(bad)))))


@pytest.mark.parametrize(("entry", "message"), [
    ('kind = "dance"', r"kind must be 'gait', 'crouch', 'idle', 'other', got 'dance'"),
    ('kind = "gait"\ntolerance_mm = 5', r"only an animation of kind 'other' has tolerance_mm"),
    ("tolerance_mm = 0", r"tolerance_mm: a distance in millimetres"),
    ('tolerance_mm = "5"', r"tolerance_mm: a distance in millimetres"),
    ('animation = "Walk"', r"animation: only a glTF source"),
    ('units = "feet"', r"units: one of 'm', 'inch', 'cm', 'mm', 'cmu', got 'feet'"),
    ('up_axis = "x"', r"up_axis: 'y' or 'z', got 'x'"),
    ('mapping = "map.yaml"', r"mapping: a .toml or .json mapping file"),
    ("keys = [3, 100]", r"keys: the first key is the first frame \(1\), got 3"),
    ("keys = [1, 100]", r"keys: a ping-pong clip turns at its last key, the last frame \(163\)"),
    ('playback = "loop"\nkeys = [1, 163]', r"keys: a loop's last frame \(163\) is its first again"),
    ("in_place = true", r"in_place takes out the travel of a loop"),
    ('playback = "clamp"', r"playback must be 'loop' or 'pingpong'"),
    ("cycle = [1, 100]", r"only a gait has a cycle"),
])
def test_config_errors_name_the_entry_and_field(tmp_path, entry, message):
    fields = {"kind": '"other"', "source": '"x.bvh"', "frames": "[1, 163]"}
    lines = [f"{k} = {v}" for k, v in fields.items() if not entry.startswith(f"{k} =")]
    path = clip_set_file(tmp_path / "clips.toml", "[animations.squat]\n" + "\n".join([*lines, entry]) + "\n")
    with pytest.raises(ConfigError, match=rf"clips\.toml \[animations.squat\]:? {message}"):
        load_config(path)


def test_a_method_that_cannot_build_an_other_names_animation_and_condition(data, sources, tmp_path):
    """Every registered method builds kind "other"; one that needs a gait must fail naming both."""
    from anim_core.clips.build import build_animation
    from anim_core.math.clip import KeyframeClip
    from anim_core.methods.conditions import Animation, Condition, Params, register
    from server.clipset.build import load_source

    @register("test_gait_only", Params)
    def gait_only(animation: Animation, params: Params) -> KeyframeClip:
        if animation.kind != "gait":
            raise ValueError(f"needs a gait, got a {animation.kind}")
        return animation.reference

    _, _, squat = sources
    cfg = load_config(clip_set_file(tmp_path / "s.toml", f'[animations.squat]\nkind = "other"\nsource = "{squat}"\n'
                                                          f'frames = [1, 163]\n')).animations["squat"]
    conditions = [Condition.parse("keyframe", "keyframe"), Condition.parse("gaitonly", "test_gait_only")]
    with pytest.raises(ConfigError, match=r"\[\[conditions\]\] 'gaitonly' on animation 'squat': needs a gait, got a "
                                          r"other"):
        build_animation(load_source(data, load_character(data), cfg, ()), 30, conditions)


def test_source_must_be_a_motion_file(tmp_path):
    path = clip_set_file(tmp_path / "clips.toml", '[animations.squat]\nkind = "other"\nsource = "x.fbx"\n'
                                                  'frames = [1, 163]\n')
    with pytest.raises(ConfigError, match=r"clips\.toml \[animations.squat\] source: 'x.fbx' is not a motion file"):
        load_config(path)


# --- export -------------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def clips_dir(built, tmp_path_factory):
    out = tmp_path_factory.mktemp("clips")
    write_clip_set(built[0], out)
    return out


@pytest.mark.parametrize("clip_id", ["squat-hybrid0", "walk-keyframe"])
def test_export_then_import_gives_the_clips_skeleton_and_poses(data, clips_dir, tmp_path, capsys, clip_id):
    """glTF: float32 in the file, so joint positions agree within 1e-5 m; BVH: text of exact reprs, 1e-9 m."""
    with np.load(clips_dir / f"{clip_id}.npz") as z:
        expected = {k: z[k] for k in z.files}
    entry = next(c for c in read_clip_manifest(clips_dir).clips if c.id == clip_id)
    names = [str(n) for n in expected["joint_names"]]
    for suffix, tolerance in ((".glb", 1e-5), (".gltf", 1e-5), (".bvh", 1e-9)):
        out = tmp_path / f"{clip_id}{suffix}"
        assert main(["clips", "export", clip_id, "--clips", str(clips_dir), "--out", str(out)]) == 0
        assert f"wrote {out} ({entry.frames} frames at 30 fps" in capsys.readouterr().out
        if suffix == ".bvh":
            bvh = read_bvh(out)
            skeleton, (rot, root), frame_time = bvh.posed_skeleton(), bvh.pose_arrays(), bvh.frame_time
        else:
            asset = read_gltf(out)
            (anim,) = asset.animations
            assert anim.name == clip_id
            skeleton, rot, root, frame_time = asset.skeleton, anim.rotations, anim.root_translation, anim.frame_time
            character = load_character(data)
            assert np.array_equal(asset.faces, character.faces)
            np.testing.assert_allclose(asset.vertices, character.vertices, atol=1e-6)
        assert list(skeleton.names) == names and skeleton.parents.tolist() == expected["parents"].tolist()
        np.testing.assert_allclose(skeleton.offsets, expected["offsets"], atol=tolerance)
        assert len(rot) == entry.frames and abs(frame_time - 1 / 30) < 1e-6
        positions = skeleton.forward_kinematics(rot, root)[1]
        err = np.abs(positions - expected["world_positions"]).max()
        assert err < tolerance, (suffix, err)


def test_export_uses_the_clip_sets_gltf_character(data, tmp_path, capsys):
    """Clips built for a glTF character (the MakeHuman body exported as Mixamo, cm, Z up, its mesh made 10 % wider
    so that it differs) export with that body, not MakeHuman's."""
    from anim_core.rig.gltf_character import character_from_gltf
    from tests.test_gltf_character import Z_UP as GLTF_Z_UP
    from tests.test_gltf_character import export, mixamo_names

    makehuman = load_character(data)
    wide = makehuman.vertices * np.array([1.1, 1.0, 1.1])
    glb = export(makehuman, tmp_path / "wide.glb", mixamo_names(makehuman), 100.0, GLTF_Z_UP, vertices=wide)
    text = (f'[character]\ngltf = "{glb}"\n[animations.sway]\nkind = "idle"\nsource = "mocap/cmu/'
            f'113_21_idle_30fps.bvh.gz"\nframes = [0, 59]\n')
    clips = build_clip_set(data, load_config(clip_set_file(tmp_path / "c.toml", text)))
    write_clip_set(clips, tmp_path / "clips")
    out = tmp_path / "sway.glb"
    assert main(["clips", "export", "sway-hybrid0", "--clips", str(tmp_path / "clips"), "--out", str(out)]) == 0
    capsys.readouterr()
    asset = read_gltf(out)
    body = character_from_gltf(read_gltf(glb)).character
    np.testing.assert_allclose(asset.vertices, body.vertices, atol=1e-6)
    assert np.abs(asset.vertices - makehuman.vertices).max() > 0.01
    (anim,) = asset.animations
    positions = asset.skeleton.forward_kinematics(anim.rotations, anim.root_translation)[1]
    assert np.abs(positions - clips[1].world_positions).max() < 1e-5


def test_export_errors_are_one_line_and_write_nothing(clips_dir, tmp_path, capsys):
    out = tmp_path / "x.glb"
    assert main(["clips", "export", "swim-keyframe", "--clips", str(clips_dir), "--out", str(out)]) == 2
    assert "has no clip 'swim-keyframe'; it has walk-keyframe, walk-hybrid0" in capsys.readouterr().err
    assert main(["clips", "export", "walk-keyframe", "--clips", str(clips_dir), "--out", str(tmp_path / "x.fbx")]) == 2
    assert "export writes .glb, .gltf, .bvh or .bvh.gz" in capsys.readouterr().err
    assert main(["clips", "export", "walk-keyframe", "--clips", str(tmp_path / "none"), "--out", str(out)]) == 2
    assert "no clip manifest" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


# --- end to end ---------------------------------------------------------------------------------------------------

STUDY_DESIGN = """[design]
reference = "keyframe"
conditions = ["hybrid0"]
animations = ["walk", "squat"]
repeats = 1
catch_trials = 0
"""


def test_a_study_from_a_mixamo_bvh_end_to_end(data, sources, tmp_path, monkeypatch, capsys):
    """clips build (Mixamo walk as gait, Mixamo crouch as "other") -> render --study -> study create --open ->
    a participant is served the pair videos of those clips."""
    from fastapi.testclient import TestClient

    from server.app import create_app
    from server.config import Settings
    from server.db import make_engine
    from server.media.manifest import read_render_manifest
    from tests.server_fixtures import answer_all, start

    _, walk, squat = sources
    var = tmp_path / "var"
    monkeypatch.setenv("ANIMSTUDY_DATA_DIR", str(data))
    monkeypatch.setenv("ANIMSTUDY_VAR_DIR", str(var))
    monkeypatch.setenv("ANIMSTUDY_SECRET_KEY", "byo-test-secret-0123456789abcdef0123")
    monkeypatch.delenv("ANIMSTUDY_DATABASE_URL", raising=False)
    monkeypatch.delenv("DATABASE_URL", raising=False)
    config = clip_set_file(tmp_path / "byo.toml", animations(str(walk), str(squat)))
    assert main(["clips", "build", "--config", str(config), "--out", str(var / "clips")]) == 0
    assert "4 clips" in capsys.readouterr().out
    thesis = (Path(__file__).resolve().parents[1] / "studies" / "thesis.toml").read_text(encoding="utf-8")
    head, _, tail = thesis.partition("[design]")
    study = tmp_path / "byo-study.toml"
    study.write_text(head.replace('slug = "thesis"', 'slug = "byo"') + STUDY_DESIGN + tail[tail.index("\n["):],
                     encoding="utf-8")
    assert main(["render", "--study", str(study), "--clips", str(var / "clips"), "--out", str(var / "media"),
                 "--width", "96", "--height", "72", "--no-shadows", "--workers", "1"]) == 0
    rendered = read_render_manifest(var / "media")
    assert rendered.settings["width"] == 96 and set(rendered.clips) == {
        "walk-keyframe", "walk-hybrid0", "squat-keyframe", "squat-hybrid0"}
    capsys.readouterr()
    assert main(["study", "create", str(study), "--open"]) == 0
    out = capsys.readouterr().out
    assert "0 to render" in out and "created study 'byo' (open, 4 trials per participant)" in out
    pair_videos = read_render_manifest(var / "media").pair_videos()
    expected = {pair_videos[(f"{a}-{x}", f"{a}-{y}")] for a in ("walk", "squat")
                for x, y in (("keyframe", "hybrid0"), ("hybrid0", "keyframe"))}

    settings = Settings.from_env()
    engine = make_engine(settings.sqlalchemy_url)
    try:
        with TestClient(create_app(settings, engine, run_migrations=False)) as client:
            sid, headers = start(client, "byo", PROLIFIC_PID="p1", STUDY_ID="s1", SESSION_ID="x1")
            trials = answer_all(client, sid, headers)
            served = {t["video_url"].removeprefix("/media/") for t in trials}
            assert served == expected  # each pair of the Mixamo clips, in both side orders
            r = client.get(trials[0]["video_url"])
            assert r.status_code == 200 and r.content == (var / "media" / trials[0]["video_url"][7:]).read_bytes()
    finally:
        engine.dispose()
