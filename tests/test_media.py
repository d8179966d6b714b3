"""Pre-rendered videos: decodable, framed, synchronized, seamless, blind, deterministic, cached, leak-free.

The whole clip set is rendered once at 160x120 (the pipeline is the same as at 640x480, only cheaper); stills of
a few frames are saved under var/test-artifacts/ for a person to look at.
"""

import gc
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from anim_core.rig.character import bind_mesh
from server.assets import character as load_character
from server.clipset.manifest import write_clip_set
from server.errors import MediaError
from server.media.build import PeakMemory, render_media
from server.media.manifest import MANIFEST
from server.media.plan import BODY_PADDING_M, MEDIA_NAME, grid_spacing, read_clip_set
from server.media.renderer import ClipRenderer
from server.media.scene import RenderSettings, frame_motion
from server.media.video import FILE_TIME, decode, probe, yuv420
from server.studies.service import clip_set_index, required_pairs
from server.studies.studyfile import thesis_study

SMALL = RenderSettings(width=160, height=120)
SECRET = b"test secret"
WORDS = re.compile(r"walk|run|crouch|idle|hybrid|keyframe|increment|mocap|squad", re.IGNORECASE)
WHOLE_WORDS = re.compile(rf"\b({WORDS.pattern})\b", re.IGNORECASE)
ARTIFACTS = Path(__file__).resolve().parents[1] / "var" / "test-artifacts" / "media"


@pytest.fixture(scope="module")
def clips_dir(built_clip_set, tmp_path_factory):
    out = tmp_path_factory.mktemp("clips")
    write_clip_set(built_clip_set(), out)
    return out


@pytest.fixture(scope="module")
def pairs(clips_dir):
    """The pairs the default (thesis) study shows: what `animstudy render` renders by default."""
    return required_pairs(thesis_study().design, clip_set_index(clips_dir))


@pytest.fixture(scope="module")
def media(data, clips_dir, pairs, tmp_path_factory):
    out = tmp_path_factory.mktemp("media")
    messages = []
    render_media(data, clips_dir, out, SECRET, SMALL, pairs=pairs, workers=2, progress=messages.append)
    manifest = json.loads((out / MANIFEST).read_text())
    return out, manifest, messages


@pytest.mark.slow  # tens of seconds (the parallel run's slowest; still run by `make test`)
def test_every_video_decodes_with_the_expected_frames(media, clips_dir):
    out, manifest, _ = media
    clips = {c.id: c for c in read_clip_set(clips_dir)}
    assert len(manifest["clips"]) == 16 and len(manifest["pairs"]) == 16
    # The server finds stimuli by (animation, condition): every clip entry says both, as the clip set does.
    assert {(e["animation"], e["condition"]) for e in manifest["clips"].values()} == {
        (c.animation, c.condition) for c in clips.values()}
    for entry in [*manifest["clips"].values(), *manifest["pairs"]]:
        info = probe(out / entry["video"])
        clip = clips[entry.get("clip") or entry["left"]]
        width = SMALL.width if "clip" in entry else 2 * SMALL.width + 4
        assert (info["frames"], info["fps"], info["width"], info["height"]) == (clip.frames, 30.0, width, 120)
        assert (info["codec"], info["pix_fmt"]) == ("h264", "yuv420p")
        with Image.open(out / entry["poster"]) as poster:
            assert poster.size == (width, 120)


def body_mask(frames, background):
    """Pixels that differ from the empty scene (the character and its shadow)."""
    return np.abs(frames.astype(int) - background.astype(int)).max(axis=-1) > 24


def clip_renderer(character, clips: list, animation: str) -> ClipRenderer:
    """A ClipRenderer for ``animation``, set up like the pipeline's (same framing and bounds)."""
    files = [c for c in clips if c.animation == animation]
    group = [np.load(c.path) for c in files]
    pos = np.concatenate([g["world_positions"] for g in group])
    mesh = bind_mesh(character, [str(n) for n in group[0]["joint_names"]], group[0]["bind_rotations"],
                     group[0]["bind_positions"])
    bounds = np.array([pos.reshape(-1, 3).min(axis=0) - 0.3, pos.reshape(-1, 3).max(axis=0) + 0.3])
    return ClipRenderer(mesh, character.faces, frame_motion(pos, SMALL, BODY_PADDING_M), SMALL, bounds,
                        grid_spacing(files[0], SMALL))


@pytest.fixture(scope="module")
def renderers(data, clips_dir):
    """A ClipRenderer per animation."""
    character, clips = load_character(data), read_clip_set(clips_dir)
    made = {animation: clip_renderer(character, clips, animation) for animation in ("walk", "run", "crouch", "idle")}
    yield made
    for r in made.values():
        r.close()


def test_the_character_is_in_frame_and_not_clipped(media, renderers, clips_dir):
    out, manifest, _ = media
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    for animation, renderer in renderers.items():
        renderer.body.mesh.is_visible = False
        first = np.load(next(c.path for c in read_clip_set(clips_dir) if c.id == f"{animation}-keyframe"))
        (background,) = renderer.render(first["world_rotations"][:1], first["world_positions"][:1])
        renderer.body.mesh.is_visible = True
        for method in ("keyframe", "hybrid0", "hybrid1", "hybrid2"):
            frames = decode(out / manifest["clips"][f"{animation}-{method}"]["video"])
            picks = [0, len(frames) // 2, len(frames) - 1]
            stills = []
            for f in picks:
                mask = body_mask(frames[f], background)
                assert mask.sum() > 300, f"{animation}-{method} frame {f}: no character"
                # Not cut off: nothing of the character touches the left, right or top border.
                assert not mask[:2].any() and not mask[:, :2].any() and not mask[:, -2:].any(), (
                    f"{animation}-{method} frame {f} touches the border")
                stills.append(frames[f])
            Image.fromarray(np.concatenate(stills, axis=1)).save(ARTIFACTS / f"{animation}-{method}.png")


def test_side_by_side_halves_match_the_single_videos(media):
    out, manifest, _ = media
    for pair in manifest["pairs"]:
        both = decode(out / pair["video"]).astype(int)
        left = decode(out / manifest["clips"][pair["left"]]["video"]).astype(int)
        right = decode(out / manifest["clips"][pair["right"]]["video"]).astype(int)
        assert both.shape[0] == left.shape[0] == right.shape[0]
        # Same frame index, same pose: only codec noise between the pair's halves and the single videos.
        assert np.abs(both[:, :, :160] - left).mean() < 2.5
        assert np.abs(both[:, :, -160:] - right).mean() < 2.5
        # And the halves are not simply the same picture (the hybrid differs from the mocap somewhere).
        assert np.abs(both[:, :, :160] - both[:, :, -160:]).mean() > 0.05


def test_loops_are_seamless(media):
    out, manifest, _ = media
    for clip_id, entry in manifest["clips"].items():
        frames = decode(out / entry["video"]).astype(np.int16)
        steps = np.abs(np.diff(frames, axis=0)).mean(axis=(1, 2, 3))
        seam = np.abs(frames[0] - frames[-1]).mean()
        assert seam <= 1.5 * steps.max() + 0.5, f"{clip_id}: loop seam {seam:.2f} vs steps up to {steps.max():.2f}"


def test_video_wraps_are_no_larger_than_three_median_steps(media):
    """Issue 14: mean |last - first| frame difference at most 3 x the median neighbour-frame difference."""
    out, manifest, _ = media
    for clip_id, entry in manifest["clips"].items():
        frames = decode(out / entry["video"]).astype(np.int16)
        steps = np.abs(np.diff(frames, axis=0)).mean(axis=(1, 2, 3))
        seam = np.abs(frames[0] - frames[-1]).mean()
        assert seam <= 3 * np.median(steps), f"{clip_id}: wrap {seam:.2f} vs median step {np.median(steps):.2f}"


def test_nothing_names_the_content(media):
    out, manifest, _ = media
    for f in out.iterdir():
        if f.name == MANIFEST:
            continue
        assert MEDIA_NAME.match(f.name), f.name
        assert not WORDS.search(f.name)
        if f.suffix == ".mp4":
            info = probe(f)
            assert not any(WORDS.search(f"{k} {v}") for k, v in info["metadata"].items()), info["metadata"]
        # No readable text in the file names the method or animation (container tags, encoder comments).  Text:
        # runs of 16+ printable bytes and whole words, so compressed picture data that happens to spell "rUn" in
        # a few random bytes does not count (that failed this test with runs of 8: "]+wD<ruN}K", once in CI).  A
        # random run of 16 printable bytes is about as likely as (95/256)^16, 1e-7 per byte of video.
        text_runs = [r.decode() for r in re.findall(rb"[\x20-\x7e]{16,}", f.read_bytes())]
        assert not [r for r in text_runs if WHOLE_WORDS.search(r)]
        if f.suffix == ".mp4":  # the check reads the encoder's own comment, so it would see words put there
            assert any("x264" in r and "options:" in r for r in text_runs)
    # Nor when, or in which order, the files were written (the hybrid-left video of a pair was written just
    # before the hybrid-right one, increment 0 before increment 1): every file has the same modification time.
    assert {f.stat().st_mtime for f in out.iterdir() if f.name != MANIFEST} == {FILE_TIME}
    # One opaque name per video, different for each side order.
    names = [p["video"] for p in manifest["pairs"]] + [c["video"] for c in manifest["clips"].values()]
    assert len(set(names)) == len(names)


def test_second_run_renders_nothing_and_settings_change_names(media, data, clips_dir, pairs):
    out, manifest, messages = media
    assert any("0 up to date, 32 to render" in m for m in messages)
    before = {f.name: f.stat().st_mtime_ns for f in out.iterdir()}
    again: list[str] = []
    render_media(data, clips_dir, out, SECRET, SMALL, pairs=pairs, workers=2, progress=again.append)
    assert any("32 up to date, 0 to render" in m for m in again)
    assert {f.name: f.stat().st_mtime_ns for f in out.iterdir() if f.name != MANIFEST} == {
        k: v for k, v in before.items() if k != MANIFEST}
    assert json.loads((out / MANIFEST).read_text()) == manifest
    # Another secret gives other names for the same content.
    other = out.parent / "other-secret"
    shutil.copytree(out, other)
    from server.media.plan import plan
    p = plan(data, clips_dir, other, SMALL, b"another secret", pairs)
    assert {o.name for o in p.outputs}.isdisjoint({Path(c["video"]).stem for c in manifest["clips"].values()})


def test_without_every_clip_only_the_clips_of_the_pairs_get_a_video(media, data, clips_dir, tmp_path):
    """The thesis study shows no hybrid2: without every_clip (the commands' default) its clips get no video
    (none is missing afterwards), an existing up-to-date one is kept; a clip with the arrays of another shares its
    video and is not rendered."""
    from server.media.plan import plan

    out, manifest, _ = media
    pairs = [("walk-keyframe", "walk-hybrid0"), ("walk-hybrid0", "walk-keyframe")]
    empty = plan(data, clips_dir, tmp_path / "nothing", SMALL, SECRET, pairs, every_clip=False)
    assert set(empty.clip_outputs) == {"walk-keyframe", "walk-hybrid0"}
    assert sorted(o.clips for j in empty.jobs for o in j.outputs) == sorted([*pairs, ("walk-keyframe",),
                                                                             ("walk-hybrid0",)])
    # Every clip's video exists in `out`: all are kept, none is due.
    kept = plan(data, clips_dir, out, SMALL, SECRET, pairs, every_clip=False)
    assert set(kept.clip_outputs) == set(manifest["clips"]) and not kept.jobs
    # A second clip set in which walk-copy is walk-keyframe under another condition id.
    twin = tmp_path / "twin"
    shutil.copytree(clips_dir, twin)
    doc = json.loads((twin / "manifest.json").read_text())
    entry = next(c for c in doc["clips"] if c["id"] == "walk-keyframe")
    doc["clips"].append({**entry, "id": "walk-copy", "condition": "copy", "file": "walk-copy.npz"})
    (twin / "manifest.json").write_text(json.dumps(doc))
    shutil.copy(twin / entry["file"], twin / "walk-copy.npz")
    p = plan(data, twin, tmp_path / "twin-media", SMALL, SECRET, [("walk-keyframe", "walk-copy"),
                                                                   ("walk-copy", "walk-keyframe")], every_clip=False)
    assert p.clip_outputs["walk-copy"].name == p.clip_outputs["walk-keyframe"].name
    names = {o.name for j in p.jobs for o in j.outputs}
    assert len(names) == 2 and sum(len(j.outputs) for j in p.jobs) == 2  # one clip video, one pair video
    assert all("walk-copy" not in o.clips for j in p.jobs for o in j.outputs)  # never rendered itself


def test_a_closed_renderer_leaves_the_next_one_in_the_thread_alone(data, clips_dir):
    # close() frees the GL objects and the context without pyrender's full gc.collect(): the renderers made after
    # it in the same thread (one open while the closed one is collected) render the same pixels (shadows on).
    character, clips = load_character(data), read_clip_set(clips_dir)
    clip = np.load(next(c.path for c in clips if c.id == "walk-keyframe"))

    def frames(renderer: ClipRenderer) -> list:
        return list(renderer.render(clip["world_rotations"][:3], clip["world_positions"][:3]))

    first = clip_renderer(character, clips, "walk")
    reference = frames(first)
    second = clip_renderer(character, clips, "walk")
    first.close()
    del first
    gc.collect()
    assert all(np.array_equal(x, y) for x, y in zip(frames(second), reference, strict=True))
    second.close()
    third = clip_renderer(character, clips, "walk")
    del second
    gc.collect()
    assert all(np.array_equal(x, y) for x, y in zip(frames(third), reference, strict=True))
    third.close()


def test_rendering_is_deterministic(renderers, clips_dir, pairs, data, tmp_path):
    clip = np.load(next(c.path for c in read_clip_set(clips_dir) if c.id == "run-hybrid0"))
    a = list(renderers["run"].render(clip["world_rotations"][:5], clip["world_positions"][:5]))
    b = list(renderers["run"].render(clip["world_rotations"][:5], clip["world_positions"][:5]))
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    # Whole files too: the same inputs give byte-identical videos.
    first, second = tmp_path / "a", tmp_path / "b"
    for out in (first, second):
        render_media(data, clips_dir, out, SECRET, SMALL, pairs=pairs, workers=1, animations=["run"])
    files = sorted(f.name for f in first.iterdir())
    assert files == sorted(f.name for f in second.iterdir())
    assert all((first / f).read_bytes() == (second / f).read_bytes() for f in files)


def test_pingpong_clips_are_their_own_reverse(clips_dir):
    """Rendering only the first half of a ping-pong period relies on this."""
    for c in read_clip_set(clips_dir):
        if c.playback == "pingpong":
            rot = np.load(c.path)["world_rotations"]
            t = len(rot)
            np.testing.assert_allclose(rot[1:t // 2], rot[t - 1:t // 2:-1], atol=1e-12)


def rss_mib():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def test_memory_stays_flat_over_300_frames(renderers, clips_dir):
    renderer = renderers["walk"]
    clip = np.load(next(c.path for c in read_clip_set(clips_dir) if c.id == "walk-keyframe"))
    rot = np.resize(clip["world_rotations"], (300, *clip["world_rotations"].shape[1:]))
    pos = np.resize(clip["world_positions"], (300, *clip["world_positions"].shape[1:]))
    usage = []
    for f, _ in enumerate(renderer.render(rot, pos)):
        if f in (50, 299):
            usage.append(rss_mib())
    print(f"RSS after 50 frames {usage[0]:.0f} MiB, after 300 {usage[1]:.0f} MiB")
    assert usage[1] - usage[0] < 20  # the unpatched pyrender/PyOpenGL leak is ~4 MB per frame


def test_render_takes_its_pairs_from_a_study_file(clips_dir, pairs, tmp_path, monkeypatch, capsys):
    """`animstudy render` renders the pairs of the study file it is given (default: the thesis study's 16); a bad
    study file or one naming what the clip set lacks is one error line, and nothing is rendered."""
    from server.cli import main

    assert len(pairs) == 16 and all({left, right} & {f"{a}-keyframe" for a in ("walk", "run", "crouch", "idle")}
                                    for left, right in pairs)
    monkeypatch.setenv("ANIMSTUDY_VAR_DIR", str(tmp_path / "var"))
    out = tmp_path / "media"
    bad = tmp_path / "bad.toml"
    bad.write_text('slug = "x"\n', encoding="utf-8")
    assert main(["render", "--clips", str(clips_dir), "--out", str(out), "--study", str(bad)]) == 2
    assert "bad.toml is not a valid study file" in capsys.readouterr().err
    unknown = tmp_path / "unknown.toml"
    text = (Path(__file__).resolve().parents[1] / "studies" / "example.toml").read_text(encoding="utf-8")
    unknown.write_text(text.replace('animations = ["walk", "run"]', 'animations = ["walk", "swim"]'), encoding="utf-8")
    assert main(["render", "--clips", str(clips_dir), "--out", str(out), "--study", str(unknown)]) == 2
    assert "unknown animation(s) swim" in capsys.readouterr().err
    assert not out.exists() or not any(out.iterdir())


def test_render_of_another_clip_set_needs_a_study_or_every_clip(clips_dir, tmp_path, monkeypatch, capsys):
    """The default study (the thesis's) names the server's clip set's animations: `render --clips OTHER` alone is
    one error line saying what to give, not the thesis study's "unknown animation(s)" (issue 37), and renders
    nothing."""
    from server.cli import main

    monkeypatch.setenv("ANIMSTUDY_VAR_DIR", str(tmp_path / "var"))
    out = tmp_path / "media"
    assert main(["render", "--clips", str(clips_dir), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "is not the server's clip set" in err and "--study FILE" in err and "--every-clip" in err
    assert "unknown animation" not in err
    assert not out.exists()


def test_the_clip_index_is_read_from_the_manifest_not_from_the_clip_files(clips_dir, tmp_path):
    """Knowing what a clip set has reads its manifest only; rendering it reads (and checks) every clip file."""
    copy = tmp_path / "clips"
    shutil.copytree(clips_dir, copy)
    expected = clip_set_index(clips_dir)
    for f in copy.glob("*.npz"):
        f.write_bytes(b"not an npz file")  # any read of a clip file fails now
    assert clip_set_index(copy) == expected
    assert len(expected) == len(list(clips_dir.glob("*.npz")))
    with pytest.raises(MediaError, match="unreadable"):
        read_clip_set(copy)


def test_a_render_is_cut_per_video_only_where_the_workers_outnumber_what_per_animation_keeps_busy(
        data, clips_dir, pairs, tmp_path):
    """The thesis study (four animations, a reference and two conditions): on 2 workers one Dask task per animation
    (each clip rendered once); on 64 workers one per video (a clip rendered once per video that shows it, on
    workers that would otherwise wait)."""
    from server.media.build import render_tasks
    from server.media.plan import plan

    p = plan(data, clips_dir, tmp_path, SMALL, SECRET, pairs)
    videos = sum(len(j.outputs) for j in p.jobs)
    assert len(p.jobs) == 4 and videos > 4
    assert [t.animation for t in render_tasks(p, 2)] == [j.animation for j in p.jobs]
    per_video = render_tasks(p, 64)
    assert len(per_video) == videos and all(len(t.outputs) == 1 for t in per_video)
    assert sum(t.n_frames for t in per_video) > 2 * sum(j.n_frames for j in p.jobs)  # the price of cutting finer


def test_peak_memory_counts_a_child_started_after_it_began():
    """The render's "peak memory (all processes)": a child that touches 300 MiB after the sampler started (the
    members are looked up again every ``rescan`` seconds) is counted, and nothing is counted after the exit."""
    child_mib = 300
    with PeakMemory(interval=0.05, rescan=0.2) as memory:
        time.sleep(0.1)
        before = memory.peak_bytes
        child = subprocess.Popen([sys.executable, "-c", f"b = bytearray({child_mib} * 2**20); print(1, flush=True); "
                                  "import sys; sys.stdin.read()"], stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        try:
            assert child.stdout.readline() == b"1\n"
            time.sleep(0.6)  # past a rescan and several samples
        finally:
            child.communicate(b"")
    assert before > 0
    assert memory.peak_bytes >= before + child_mib * 2**20 * 0.95, (before / 2**20, memory.peak_bytes / 2**20)


def test_yuv420_with_a_kept_reformatter_is_a_fresh_conversion_at_every_size(rng):
    """yuv420 keeps one swscale context per thread: frames of other sizes in between still convert as a new
    context converts them."""
    import av

    for h, w in [(120, 160), (240, 320), (120, 160), (2, 4), (480, 640), (120, 160)]:
        rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        packed = av.VideoFrame.from_ndarray(rgb, format="rgb24").reformat(format="yuv420p").to_ndarray()
        y, u, v = yuv420(rgb)
        assert y.shape == (h, w) and u.shape == v.shape == (h // 2, w // 2)
        np.testing.assert_array_equal(np.concatenate([y.ravel(), u.ravel(), v.ravel()]), packed.ravel())
