"""Ladders of the clip-set file (issue 38): ``[[ladders]]`` expanded into one condition per level, every bad ladder
refused naming the field and the level, a built ladder's clips in the manifest with their level, run-time cost and
render settings; a level that builds the same clip as another is refused."""

import dataclasses
import textwrap

import numpy as np
import pytest

from anim_core.clips.build import ConfigError, distinct_levels
from anim_core.methods.conditions import get_method
from server.clipset.build import build_clip_set
from server.clipset.config import load_config
from server.clipset.manifest import read_clip_manifest, write_clip_set
from server.media.plan import identical_clips

HEAD = """
fps = 30
[character]
relocate = ["LHipJoint", "RHipJoint"]

[animations.walk]
kind = "gait"
source = "mocap/cmu/12_03_walk.bvh.gz"
frames = [1, 565]

[[conditions]]
id = "keyframe"
method = "keyframe"
"""


def config(tmp_path, ladders, extra=""):
    path = tmp_path / "ladders.toml"
    path.write_text(textwrap.dedent(HEAD + extra + ladders), encoding="utf-8")
    return load_config(path)


def test_a_ladder_expands_into_one_condition_per_level(tmp_path):
    cfg = config(tmp_path, """
        [[ladders]]
        id = "pps"
        method = "update_rate"
        levels = [4, 6, 8, 12, 16, 24]

        [[ladders]]
        id = "eps"
        method = "reduced"
        levels = [0.5, 2.0, 5]

        [[ladders]]
        id = "q"
        method = "quantized"
        levels = [6, 8, 12]
        params = { reduced_epsilon_deg = 1.0 }

        [[ladders]]
        id = "inc"
        method = "hybrid_ik"
        param = "increment"
        levels = [0, 1, 2]
        params = { contact_source = "reference" }
        """)
    got = [(c.id, c.method, c.ladder, c.level, c.params_dict()) for c in cfg.conditions[1:]]
    assert got[:6] == [(f"pps{r}", "update_rate", "pps", r, {"rate": r}) for r in (4, 6, 8, 12, 16, 24)]
    assert [g[0] for g in got[6:9]] == ["eps0_5", "eps2", "eps5"]
    assert [g[4]["epsilon_deg"] for g in got[6:9]] == [0.5, 2.0, 5]
    assert got[9][4] == {"bits": 6, "reduced_epsilon_deg": 1.0}
    assert got[12][0] == "inc0" and got[12][4]["increment"] == 0 and got[12][4]["contact_source"] == "reference"
    assert cfg.conditions[0].ladder is None and cfg.conditions[0].level is None
    assert [get_method(m).graded for m in ("reduced", "quantized", "hybrid", "update_rate", "bone_lod",
                                             "skin_influences")] == [
        "epsilon_deg", "bits", "increment", "rate", "depth", "influences"]


@pytest.mark.parametrize("ladder, message", [
    ('id = "pps"\nmethod = "update_rate"\nlevels = [4, 8]',
     r"\[\[ladders\]\] id = 'pps' levels: a list of at least 3 levels, got \[4, 8\]"),
    ('id = "pps"\nmethod = "update_rate"\nlevels = [4, 12, 8]',
     r"id = 'pps' levels: level 8 is out of order"),
    ('id = "pps"\nmethod = "update_rate"\nlevels = [4, 8, 8, 12]',
     r"id = 'pps' levels: level 8 is repeated"),
    ('id = "pps"\nmethod = "update_rate"\nlevels = [12, 24, 30]',
     r"id = 'pps' level 30: rate 30 poses/s is at or above the clips' own rate of 30 keys/s"),
    ('id = "pps"\nmethod = "update_rate"\nlevels = [4, 8, true]',
     r"id = 'pps' levels: level True is not a number"),
    ('id = "q"\nmethod = "quantized"\nlevels = [1, 4, 8]',
     r"id = 'q' level 1: params of method 'quantized': bits: Input should be greater than or equal to 2"),
    ('id = "q"\nmethod = "quantized"\nlevels = [4, 8.5, 9]',
     r"id = 'q' level 8.5: params of method 'quantized': bits: Input should be a valid integer"),
    ('id = "skin"\nmethod = "skin_influences"\nlevels = [2, 3, 5]',
     r"id = 'skin' level 5: params of method 'skin_influences': influences: Input should be less than or equal "
     r"to 4"),
    ('id = "k"\nmethod = "keyframe"\nlevels = [1, 2, 3]', r"id = 'k' method: 'keyframe' is the reference"),
    ('id = "x"\nmethod = "squash"\nlevels = [1, 2, 3]', r"id = 'x' method: unknown method 'squash'"),
    ('id = "p"\nmethod = "update_rate"\nparam = "speed"\nlevels = [1, 2, 3]',
     r"id = 'p' param: method 'update_rate' has no parameter 'speed'; it has rate"),
    ('id = "p"\nmethod = "update_rate"\nlevels = [1, 2, 3]\nparams = { rate = 2 }',
     r"id = 'p' params: 'rate' is the graded parameter"),
    ('id = "Bad-id"\nmethod = "update_rate"\nlevels = [1, 2, 3]', r"\[\[ladders\]\] #1 id: 1..32 lower-case"),
    ('id = "p"\nmethod = "update_rate"\nlevels = [1, 2, 3]\nstep = 2', r"\[\[ladders\]\] #1: unknown field 'step'"),
])
def test_bad_ladders_are_refused_naming_the_field_and_the_level(tmp_path, ladder, message):
    with pytest.raises(ConfigError, match=message):
        config(tmp_path, "\n[[ladders]]\n" + ladder + "\n")


def test_ladder_ids_may_not_clash_with_explicit_conditions_or_other_ladders(tmp_path):
    explicit = '\n[[conditions]]\nid = "pps8"\nmethod = "hybrid"\nparams = { increment = 0 }\n'
    ladder = '\n[[ladders]]\nid = "pps"\nmethod = "update_rate"\nlevels = [4, 8, 12]\n'
    with pytest.raises(ConfigError, match=r"id = 'pps' levels: level 8 makes the condition id 'pps8', which "
                                          r"\[\[conditions\]\] has already"):
        config(tmp_path, ladder, explicit)
    twice = ladder + '\n[[ladders]]\nid = "pps"\nmethod = "update_rate"\nlevels = [2, 3, 4]\n'
    with pytest.raises(ConfigError, match=r"level 4 makes the condition id 'pps4', which \[\[ladders\]\] id = 'pps' "
                                          r"has already"):
        config(tmp_path, twice)


LADDERS = """
[[ladders]]
id = "pps"
method = "update_rate"
levels = [4, 6, 12]

[[ladders]]
id = "depth"
method = "bone_lod"
levels = [5, 6, 7]

[[ladders]]
id = "skin"
method = "skin_influences"
levels = [1, 2, 4]
"""


@pytest.fixture(scope="module")
def built(data, tmp_path_factory):
    folder = tmp_path_factory.mktemp("ladders")
    path = folder / "ladders.toml"
    path.write_text(textwrap.dedent(HEAD + LADDERS), encoding="utf-8")
    clips = build_clip_set(data, load_config(path))
    write_clip_set(clips, folder / "clips")
    return folder / "clips", clips


def test_built_ladder_clips_carry_level_cost_and_render_settings(built):
    out, _clips = built
    manifest = read_clip_manifest(out)
    by = {e.condition: e for e in manifest.clips}
    assert [e.condition for e in manifest.clips] == [
        "keyframe", "pps4", "pps6", "pps12", "depth5", "depth6", "depth7", "skin1", "skin2", "skin4"]
    assert (by["pps6"].ladder, by["pps6"].level, by["keyframe"].ladder) == ("pps", 6, None)
    assert by["skin2"].render is not None and by["skin2"].render.skin_influences == 2
    assert by["keyframe"].render is None and by["pps4"].render is None
    for e in manifest.clips:
        assert e.metrics["cost_ms_per_1000"] > 0 and e.metrics["bytes"] > 0
    for k in ("keyframe", "skin1", "skin2", "skin4"):
        assert by[k].metrics["skin_ms_per_1000"] > 0
    # Weights blended: one per vertex at 1 influence (the body's 13,380 vertices), more with more, most at full.
    blended = [by[k].metrics["skin_weights"] for k in ("skin1", "skin2", "skin4", "keyframe")]
    assert blended[0] == 13380 and blended == sorted(set(blended))
    # The held-update path poses about 4/60 of the crowd a frame: cheaper than posing everyone, really measured.
    assert by["pps4"].metrics["cost_ms_per_1000"] < 0.6 * by["keyframe"].metrics["cost_ms_per_1000"]
    # Fewer updates store fewer keys: a 40-frame loop updated 4 times a second has 6 (frames 0, 8, 15, 23, 30, 38).
    assert (by["pps4"].key_count, by["keyframe"].key_count) == (6, 40)
    assert by["pps4"].metrics["bytes"] < by["pps12"].metrics["bytes"] < by["keyframe"].metrics["bytes"]
    # The skin levels are the reference's motion, yet each is its own video.
    ids = identical_clips(manifest.clips)
    assert [ids[f"walk-{c}"] for c in ("skin1", "skin2", "keyframe")] == ["walk-skin1", "walk-skin2",
                                                                          "walk-keyframe"]
    assert len({by[c].digest for c in ("keyframe", "skin1", "skin2", "skin4")}) == 4


def test_built_levels_hold_reference_poses_and_bone_lod_leaves_others_bit_identical(built):
    _, clips = built
    by = {c.condition: c for c in clips}
    ref = by["keyframe"]
    held = by["pps6"]
    # 30 fps / 6 updates a second: each of the reference's frames 0, 5, 10, ... is shown for 5 frames.
    shown = np.arange(ref.n_frames) // 5 * 5
    np.testing.assert_allclose(held.local_rotations, ref.local_rotations[shown], atol=1e-12)
    lod = by["depth6"]
    names = list(ref.character.skeleton.names)
    held_joints = {"LeftHand", "RightHand", "LeftFingerBase", "RightFingerBase", "LThumb", "RThumb",
                   "LeftHandIndex1", "RightHandIndex1"}
    keep = np.array([n not in held_joints for n in names])
    assert np.array_equal(lod.local_rotations[:, keep], ref.local_rotations[:, keep])
    assert not np.allclose(lod.local_rotations[:, ~keep], ref.local_rotations[:, ~keep])
    assert np.ptp(lod.local_rotations[:, ~keep], axis=0).max() == 0.0  # held: one pose throughout


def test_a_level_making_the_same_clip_as_another_is_refused(built, tmp_path, data):
    _, clips = built
    by = {c.condition: c for c in clips}
    weights = by["keyframe"].character.mesh.weights
    # A body with at most 2 influences per vertex: skin levels 2 and 4 both keep every weight (the full skin).
    two = np.where(np.arange(weights.shape[1]) < 2, weights, 0.0)
    with pytest.raises(ConfigError, match=r"\[\[ladders\]\] id = 'skin' level 2 \(skin_influences\): on animation "
                                          r"'walk' it makes the same clip as the reference"):
        distinct_levels("walk", [by["keyframe"], by["skin1"], by["skin2"]], two)
    same = dataclasses.replace(by["pps12"], local_rotations=by["pps6"].local_rotations,
                               root_positions=by["pps6"].root_positions)
    with pytest.raises(ConfigError, match=r"id = 'pps' level 12 \(update_rate\): on animation 'walk' it makes the "
                                          r"same clip as condition 'pps6'"):
        distinct_levels("walk", [by["keyframe"], by["pps6"], same], weights)
    # Built: depth 7 holds exactly the fingers, as an explicit condition does.
    path = tmp_path / "same.toml"
    path.write_text(HEAD + '[[conditions]]\nid = "fingers"\nmethod = "bone_lod"\nparams = { joints = "fingers" }\n'
                    + '[[ladders]]\nid = "depth"\nmethod = "bone_lod"\nlevels = [5, 6, 7]\n', encoding="utf-8")
    with pytest.raises(ConfigError, match=r"id = 'depth' level 7 \(bone_lod\): on animation 'walk' it makes the "
                                          r"same clip as condition 'fingers'"):
        build_clip_set(data, load_config(path))


def test_the_renderer_skins_each_clip_with_its_render_settings(built):
    from anim_core.methods.lod import max_influences
    from server.media.worker import clip_mesh

    out, clips = built
    by = {e.condition: e for e in read_clip_manifest(out).clips}
    mesh = clips[0].character.mesh
    assert clip_mesh(mesh, by["keyframe"]) is mesh and clip_mesh(mesh, by["pps4"]) is mesh
    for k in (1, 2, 4):
        skinned = clip_mesh(mesh, by[f"skin{k}"])
        assert max_influences(skinned.weights) == k
        np.testing.assert_allclose(skinned.weights.sum(axis=1), 1.0, atol=1e-12)


def test_a_skin_level_renders_other_pixels_only_where_weights_were_dropped(built, data):
    """One frame of the walk rendered small without shadows: with every weight kept (7 influences, the body's
    most) it is the full skin's frame pixel for pixel; with 1 influence pixels change, and every changed pixel lies
    in the screen box (1 px wider) of a triangle with a vertex that lost weights."""
    from anim_core.bench.cost import skinned_mesh
    from anim_core.rig.character import bind_mesh
    from server.assets import character as load_character
    from server.media.plan import BODY_PADDING_M
    from server.media.renderer import ClipRenderer
    from server.media.scene import RenderSettings, frame_motion
    from server.media.worker import clip_mesh

    out, _ = built
    by = {e.condition: e for e in read_clip_manifest(out).clips}
    a = np.load(by["keyframe"].path)
    body = load_character(data)
    mesh = bind_mesh(body, [str(n) for n in a["joint_names"]], a["bind_rotations"], a["bind_positions"])
    settings = RenderSettings(width=160, height=120, shadows=False)
    pos = a["world_positions"]
    framing = frame_motion(pos, settings, BODY_PADDING_M)
    bounds = np.array([pos.reshape(-1, 3).min(axis=0) - 0.3, pos.reshape(-1, 3).max(axis=0) + 0.3])
    renderer = ClipRenderer(mesh, body.faces, framing, settings, bounds)
    frame = slice(10, 11)
    try:
        def render(skin):
            (image,) = renderer.render(a["world_rotations"][frame], a["world_positions"][frame], mesh=skin)
            return image.astype(int)

        full, kept, cut = render(mesh), render(skinned_mesh(mesh, 7)), render(clip_mesh(mesh, by["skin1"]))
    finally:
        renderer.close()
    assert np.array_equal(kept, full)
    changed = np.abs(cut - full).max(axis=-1) > 0
    assert changed.sum() > 20
    # Where the weights were dropped, projected: the camera looks down -Z of its pose, pyrender's perspective.
    one = clip_mesh(mesh, by["skin1"])
    matrices = mesh.skinning_matrices(a["world_rotations"][10], a["world_positions"][10])
    v_full, _ = mesh.skin(matrices)
    v_cut, _ = one.skin(one.skinning_matrices(a["world_rotations"][10], a["world_positions"][10]))
    dropped = np.count_nonzero(mesh.weights, axis=1) > 1
    faces = body.faces[dropped[body.faces].any(axis=1)]
    world_to_camera = np.linalg.inv(framing.pose())
    ty = np.tan(np.radians(settings.yfov_deg) / 2)
    tx = ty * settings.width / settings.height
    allowed = np.zeros_like(changed)
    for v in (v_full, v_cut):
        cam = v @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
        col = (cam[:, 0] / -cam[:, 2] / tx + 1) / 2 * settings.width
        row = (1 - cam[:, 1] / -cam[:, 2] / ty) / 2 * settings.height
        c, r = col[faces], row[faces]
        for c0, c1, r0, r1 in zip(np.floor(c.min(1)) - 1, np.ceil(c.max(1)) + 1, np.floor(r.min(1)) - 1,
                                  np.ceil(r.max(1)) + 1, strict=True):
            allowed[max(int(r0), 0):max(int(r1), 0) + 1, max(int(c0), 0):max(int(c1), 0) + 1] = True
    assert allowed.mean() < 0.5  # the boxes leave most of the picture out
    assert not (changed & ~allowed).any()


def test_the_bench_times_a_bone_lod_level_by_the_runtime_path_sampling_only_its_animated_joints(built):
    """``animstudy bench`` and the manifest's cost pose a bone-LOD level as the crowd runtime plays it: the frozen
    joints copied from their first (bind-pose) key, never sampled.  Shown by a level whose frozen joints were given
    moving keys: the timed step still holds them at the first key, while every other joint is the keys runtime's."""
    from anim_core.bench import suite
    from anim_core.bench.cost import pose_step
    from anim_core.runtime import animated_joints, runtime_for

    _, clips = built
    by = {c.condition: c for c in clips}
    ref, lod = by["keyframe"], by["depth6"]
    names = list(ref.character.skeleton.names)
    held_joints = {"LeftHand", "RightHand", "LeftFingerBase", "RightFingerBase", "LThumb", "RThumb",
                   "LeftHandIndex1", "RightHandIndex1"}
    assert [n for n, on in zip(names, animated_joints(lod.clip), strict=True) if not on] == [
        n for n in names if n in held_joints]
    assert animated_joints(ref.clip).all()
    # The level with moving keys on its frozen joints after the first (the first is still their bind pose): a path
    # that sampled them would move them; the runtime's holds them at the first key, i.e. the level's own pose.
    frozen = animated_joints(lod.clip) == 0
    rotations = np.array(ref.clip.rotations)
    rotations[0, frozen] = lod.clip.rotations[0, frozen]
    moving = dataclasses.replace(lod.clip, rotations=rotations)
    t = np.linspace(0.1, 1.1, 10)
    expected = runtime_for(lod.clip).pose(t).rotations.copy()  # every joint sampled: the level's keys are constant
    sampled = runtime_for(moving).pose(t).rotations.copy()
    assert not np.allclose(sampled[:, frozen], expected[:, frozen], atol=1e-3)
    runtime = runtime_for(moving)
    for step in (lambda x: suite._runtime_step(runtime, 10, clip=moving)(x, 0), pose_step(moving, 10)):
        got = step(t).rotations
        np.testing.assert_allclose(got, expected, atol=1e-5)
        assert np.array_equal(got[:, ~frozen], sampled[:, ~frozen])


def test_bone_lod_levels_are_timed_beside_keyframe_playback_and_printed_as_ratios(built, capsys):
    """One bench run at 1,000 characters: every level of the depth ladder has a median in the same rounds as the
    keyframe clip and its ratio to it in the printed table."""
    from anim_core.bench import suite
    from server.cli.bench import _print_bench

    _, clips = built
    group = [c for c in clips if c.condition in ("keyframe", "depth5", "depth6", "depth7")]
    doc = suite.run(group, characters=[1000], stages=["pose"], frames=12, warmup=3, variants=["keys"])
    ratios = {r["condition"]: r["ratio"] for r in suite._ratios(doc["results"], "keys")}
    assert set(ratios) == {"depth5", "depth6", "depth7"} and all(r > 0 for r in ratios.values())
    _print_bench(doc)
    out = capsys.readouterr().out
    for level in ("depth5", "depth6", "depth7"):
        line = next(x for x in out.splitlines() if x.startswith(f"walk-{level} "))
        assert f"({ratios[level]:.2f})" in line
