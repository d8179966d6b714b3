"""Stimulus sets (issue 25): what a study shows is pinned when it opens.  A rebuild of the clip set with other
frames (what an upload's rebuild does) leaves an open study every video byte for byte and its results as they
were; each exported vote names the sha256 of what was shown; opening an incomplete set is refused with what is
missing; ``gc`` deletes exactly the files nothing uses."""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import io
import time
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session

from server import cli
from server.app import create_app
from server.cli.study import _study_session
from server.clipset.build import build_clip_set
from server.clipset.config import load_config
from server.clipset.manifest import write_clip_set
from server.config import Settings
from server.db import migrate
from server.deps import get_session
from server.media.build import render_media
from server.media.manifest import read_render_manifest
from server.media.plan import MEDIA_NAME
from server.media.scene import RenderSettings
from server.participants.service import update_study
from server.pipeline.stimuli import render_manifest_dirs
from server.researchers.service import create_researcher
from server.stimuli import service as stimulus_sets
from server.studies import service
from server.studies.design import Design
from server.studies.service import clip_set_index, required_pairs
from server.studies.studyfile import parse_study_text
from tests.conftest import DATABASES, _fresh_engine
from tests.server_fixtures import RESEARCHER, answer_all, fake_media, start, study_file, write_fake_media
from tests.test_uploads import SECRET, excerpt, login

TINY = RenderSettings(width=64, height=48, shadows=False)
PASSWORD = "correct horse battery"
DESIGN = Design(reference="keyframe", conditions=["hybrid0"], animations=["base"], catch_trials=1)
CLIPSET = """fps = 30
[character]
relocate = ["LHipJoint", "RHipJoint"]
[animations.base]
kind = "idle"
source = "{source}"
frames = [{first}, {last}]
[[conditions]]
id = "keyframe"
method = "keyframe"
[[conditions]]
id = "hybrid0"
method = "hybrid"
params = {{ increment = 0 }}
"""


def build_and_render(settings: Settings, tmp_path: Path, frames: tuple[int, int]) -> None:
    """Build the clip set (animation ``base`` from ``frames`` of a CMU excerpt) and render what DESIGN shows, as
    `animstudy clips build` + `render` (and an upload's rebuild) do."""
    source = tmp_path / "base.bvh"
    source.write_bytes(excerpt(settings.data, frames=120))
    config = tmp_path / "base.toml"
    config.write_text(CLIPSET.format(source=source, first=frames[0], last=frames[1]), encoding="utf-8")
    write_clip_set(build_clip_set(settings.data, load_config(config)), settings.clips_dir)
    render_media(settings.data, settings.clips_dir, settings.media_dir, settings.secret, TINY,
                 pairs=required_pairs(DESIGN, clip_set_index(settings.clips_dir)), workers=1)


@pytest.fixture
def site(db, engine, tmp_path, data):
    settings = Settings(var_dir=tmp_path / "var", data_dir=data, secret_key=SECRET)
    app = create_app(settings, engine, run_migrations=False)
    app.dependency_overrides[get_session] = lambda: db
    with TestClient(app) as client:
        yield settings, client


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def test_a_rebuild_leaves_an_open_study_its_videos_and_results(site, db, tmp_path):
    settings, client = site
    build_and_render(settings, tmp_path, (40, 100))
    create_researcher(db, "b@example.org", PASSWORD)
    b = login(client, "b@example.org", PASSWORD)
    r = client.post("/api/v1/studies", json=study_file(DESIGN, slug="bstudy").model_dump(mode="json"), headers=b)
    assert r.status_code == 201, r.text
    assert client.post("/api/v1/studies/bstudy/open", headers=b).status_code == 200
    sid, headers = start(client, "bstudy")
    trials = answer_all(client, sid, headers)
    shown = {t["video_url"]: client.get(t["video_url"]).content for t in trials}
    assert len(shown) >= 2 and all(len(v) > 1000 for v in shown.values())
    results = client.get("/api/v1/studies/bstudy/results", headers=b).json()
    assert {(c["animation"], c["condition"]) for c in results["clips"]} == {("base", "keyframe"),
                                                                             ("base", "hybrid0")}
    rendered_before = read_render_manifest(settings.media_dir).pair_videos()

    build_and_render(settings, tmp_path, (50, 110))  # other frames: other clips, other videos

    assert set(read_render_manifest(settings.media_dir).pair_videos().values()).isdisjoint(
        rendered_before.values())  # the rebuild did change what a new study would show
    for url, content in shown.items():
        r = client.get(url)
        assert r.status_code == 200, url
        assert r.content == content
    sid2, headers2 = start(client, "bstudy")  # a participant who starts now sees the pinned videos too
    assert {t["video_url"] for t in answer_all(client, sid2, headers2)} <= set(shown)
    after = client.get("/api/v1/studies/bstudy/results", headers=b).json()
    assert after["clips"] == results["clips"]  # the metrics of the clips participants saw, not the rebuild's

    # Every exported vote names the bytes it was given on.
    rows = list(csv.DictReader(io.StringIO(client.get("/api/v1/studies/bstudy/export.csv", headers=b).text)))
    assert len(rows) == 2 * len(trials)
    by_sha = {sha(content): url for url, content in shown.items()}
    study = service.get_study(db, "bstudy")
    clip_video = {s.condition: s.video for s in study.stimuli}
    for row in rows:
        assert row["pair_video"] in by_sha
        assert row["stimulus_set"] == study.stimulus_set.digest
        left = row["reference_condition"] if row["reference_side"] == "left" else row["test_condition"]
        right = row["test_condition"] if row["reference_side"] == "left" else row["reference_condition"]
        assert row["left_video"] == sha((settings.media_dir / clip_video[left]).read_bytes())
        assert row["right_video"] == sha((settings.media_dir / clip_video[right]).read_bytes())
    # the set's digest is the sha256 of its content, which records every file's sha256
    assert study.stimulus_set.digest == stimulus_sets.content_digest(study.stimulus_set.content)

    # gc keeps what the open study and the render manifest use, and has nothing else to delete here.
    assert stimulus_sets.garbage(db, settings.media_dir).files == []


def test_opening_an_incomplete_set_is_refused_with_what_is_missing(db, tmp_path):
    media_dir = tmp_path / "media"
    media = write_fake_media(media_dir)
    study = service.create_study(db, media, study_file(slug="partial"), media_dir=media_dir)
    pair = study.comparisons[0]
    (media_dir / pair.video_reference_right).unlink()
    (media_dir / study.stimuli[0].video).write_bytes(b"other bytes")
    with pytest.raises(service.Conflict) as caught:
        service.open_study(db, study, media_dir)
    message = caught.value.detail
    assert "stimulus set is incomplete" in message
    assert f"{study.stimuli[0].animation} {study.stimuli[0].condition}: its file has other bytes" in message
    assert "is not rendered" in message
    assert str(media_dir) not in message and ".mp4" not in message  # no server path, no file name
    assert study.state == "draft"


def test_a_draft_rebuilds_its_set_and_an_opened_study_keeps_it(db, tmp_path):
    media_dir = tmp_path / "media"
    media = write_fake_media(media_dir)
    study = service.create_study(db, media, study_file(slug="draft"), media_dir=media_dir)
    first = study.stimulus_set.digest
    smaller = {"design": {**study.design, "animations": ["walk", "run"]}}
    update_study(db, study, smaller, media, media_dir)
    assert study.stimulus_set.digest != first
    assert {c.animation for c in stimulus_sets.content_of(study.stimulus_set).clips} == {"walk", "run"}
    service.open_study(db, study, media_dir)
    pinned = study.stimulus_set.digest
    with pytest.raises(service.Conflict):
        update_study(db, study, {"design": {**study.design, "animations": ["walk"]}}, media, media_dir)
    assert study.stimulus_set.digest == pinned


def test_gc_deletes_exactly_the_unreferenced_files(db, tmp_path, monkeypatch, capsys):
    media_dir = tmp_path / "media"
    media = write_fake_media(media_dir)
    study = service.create_study(db, media, study_file(slug="kept"), media_dir=media_dir)
    service.open_study(db, study, media_dir)
    shown = {n for s in study.stimuli for n in (s.video, s.poster)}
    for c in study.comparisons:
        for v in (c.video_reference_left, c.video_reference_right):
            shown |= {v, v.replace(".mp4", ".jpg")}
    # A later render whose manifest lists only the walk clips, and files of an earlier render nothing lists.
    walk = fake_media().model_copy(update={
        "clips": {k: v for k, v in media.clips.items() if v.animation == "walk"},
        "pairs": [p for p in media.pairs if p.left.startswith("walk-") and p.right.startswith("walk-")]})
    (media_dir / "manifest.json").write_text(walk.model_dump_json())
    listed = {n for v in [*walk.clips.values(), *walk.pairs] for n in (v.video, v.poster)}
    orphans = {f"{hashlib.sha256(str(i).encode()).hexdigest()[:24]}.mp4" for i in range(3)}
    for name in orphans:
        (media_dir / name).write_bytes(b"old")
    (media_dir / "notes.txt").write_text("not a media file")
    everything = {f.name for f in media_dir.iterdir() if MEDIA_NAME.match(f.name)}
    expected = everything - shown - listed
    assert orphans <= expected and len(expected) > len(orphans)  # the unlisted pairs of the other animations too

    dry = stimulus_sets.collect(db, media_dir, dry_run=True)
    assert {f.name for f in dry.files} == expected
    assert {f.name for f in media_dir.iterdir() if MEDIA_NAME.match(f.name)} == everything  # nothing deleted
    done = stimulus_sets.collect(db, media_dir)
    assert {f.name for f in done.files} == expected
    left = {f.name for f in media_dir.iterdir()}
    assert left == (everything - expected) | {"manifest.json", "notes.txt"}
    assert shown <= left
    assert stimulus_sets.missing(stimulus_sets.content_of(study.stimulus_set), media_dir) == []


def test_gc_command(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("ANIMSTUDY_VAR_DIR", str(tmp_path / "var"))
    monkeypatch.setenv("ANIMSTUDY_SECRET_KEY", "gc-test-secret-0123456789abcdef0123")
    monkeypatch.delenv("ANIMSTUDY_DATABASE_URL", raising=False)
    monkeypatch.delenv("DATABASE_URL", raising=False)
    settings = Settings.from_env()
    media = write_fake_media(settings.media_dir)
    with _study_session(settings) as db:
        study = service.create_study(db, media, study_file(slug="kept"), media_dir=settings.media_dir)
        service.open_study(db, study, settings.media_dir)
    (settings.media_dir / "manifest.json").unlink()  # nothing but the study keeps files now
    used = stimulus_sets.content_of(study.stimulus_set).hashes()
    unused = {f.name for f in settings.media_dir.iterdir()} - set(used)
    assert cli.main(["gc", "--dry-run"]) == 0
    out, err = capsys.readouterr()
    assert set(out.split()) == unused and f"would delete {len(unused)} unreferenced files" in err
    assert cli.main(["gc"]) == 0
    assert {f.name for f in settings.media_dir.iterdir()} == set(used)


FUTURE_WORK = Path(__file__).resolve().parents[1] / "studies" / "future-work.toml"


@pytest.mark.slow  # tens of seconds (the serial run's slowest; still run by `make test`)
def test_study_create_builds_and_renders_the_clip_set_a_study_file_names(tmp_path, monkeypatch, capsys, data):
    """`study create studies/future-work.toml` on a fresh server: its [clips] set (conditions16.toml) is built for
    the study's animations and conditions and rendered, in one command; a second study over the same clip set
    finds everything done."""
    monkeypatch.setenv("ANIMSTUDY_VAR_DIR", str(tmp_path / "var"))
    monkeypatch.setenv("ANIMSTUDY_DATA_DIR", str(data))
    monkeypatch.setenv("ANIMSTUDY_SECRET_KEY", "future-work-secret-0123456789abcdef01")
    monkeypatch.delenv("ANIMSTUDY_DATABASE_URL", raising=False)
    monkeypatch.delenv("DATABASE_URL", raising=False)
    size = ["--width", "96", "--height", "72", "--no-shadows"]
    assert cli.main(["study", "create", str(FUTURE_WORK), "--open", *size]) == 0
    out = capsys.readouterr().out
    assert "[1/2] walk: building 4 clips" in out and "clips: 8 built into the clip set" in out
    assert "created study 'future-work' (open" in out
    settings = Settings.from_env()
    assert not (settings.clips_dir / "manifest.json").exists()  # the server's clip set was not needed
    with _study_session(settings) as db:
        study = service.get_study(db, "future-work")
        content = stimulus_sets.content_of(study.stimulus_set)
        assert {(c.animation, c.condition) for c in content.clips} == {
            (a, c) for a in ("walk", "crouch") for c in ("keyframe", "hybrid0", "hybrid_ik0", "hybrid_c2_0")}
        assert all(c.metrics and c.method for c in content.clips)  # from the clip set's manifest
        assert stimulus_sets.missing(content, settings.media_dir) == []
        assert content.render["width"] == 96
    # A second study file over the same clip set: nothing to build or render.
    second = tmp_path / "second.toml"
    second.write_text(FUTURE_WORK.read_text().replace('slug = "future-work"', 'slug = "future-work-2"').replace(
        'set = "../server/clipset/conditions16.toml"', f'set = "{FUTURE_WORK.parent}/../server/clipset/'
                                                       'conditions16.toml"'))
    assert cli.main(["study", "create", str(second)]) == 0
    out = capsys.readouterr().out
    assert "clips: all 8 the design needs are built" in out and ", 0 to render" in out


def test_study_create_builds_conditions_given_inline(tmp_path, monkeypatch, capsys, data):
    """A study file with its conditions inline ([[clips.conditions]]) on the default motions: built and rendered
    by `study create`; an inline set that lacks a design's condition is refused with the condition named."""
    monkeypatch.setenv("ANIMSTUDY_VAR_DIR", str(tmp_path / "var"))
    monkeypatch.setenv("ANIMSTUDY_DATA_DIR", str(data))
    monkeypatch.setenv("ANIMSTUDY_SECRET_KEY", "inline-clips-secret-0123456789abcdef01")
    monkeypatch.delenv("ANIMSTUDY_DATABASE_URL", raising=False)
    monkeypatch.delenv("DATABASE_URL", raising=False)
    text = FUTURE_WORK.read_text().replace('slug = "future-work"', 'slug = "inline"')
    text = text.replace('animations = ["walk", "crouch"]', 'animations = ["walk"]').replace(
        'conditions = ["hybrid0", "hybrid_ik0", "hybrid_c2_0"]', 'conditions = ["hybrid_c2_0"]')
    text = text.replace('set = "../server/clipset/conditions16.toml"', '''conditions = [
  { id = "keyframe", method = "keyframe" },
  { id = "hybrid_c2_0", method = "hybrid_c2", params = { increment = 0 } },
]''')
    study = tmp_path / "inline.toml"
    study.write_text(text)
    assert cli.main(["study", "validate", str(study)]) == 0
    assert cli.main(["study", "create", str(study), "--width", "96", "--height", "72", "--no-shadows"]) == 0
    out = capsys.readouterr().out
    assert "clip set given in the study file" in out and "[1/1] walk: building 2 clips" in out
    with _study_session(Settings.from_env()) as db:
        content = stimulus_sets.content_of(service.get_study(db, "inline").stimulus_set)
    assert {(c.animation, c.condition, c.method) for c in content.clips} == {
        ("walk", "keyframe", "keyframe"), ("walk", "hybrid_c2_0", "hybrid_c2")}
    lacking = tmp_path / "lacking.toml"
    lacking.write_text(text.replace('slug = "inline"', 'slug = "lacking"').replace(
        'conditions = ["hybrid_c2_0"]', 'conditions = ["hybrid_ik0"]'))
    assert cli.main(["study", "create", str(lacking)]) == 2
    assert "hybrid_ik0 are not in the study's clip set" in capsys.readouterr().err


@pytest.mark.parametrize("how", ["merge", "rebuild"])
def test_a_build_killed_halfway_leaves_the_previous_clip_set(tmp_path, data, monkeypatch, how):
    """A rebuild of the clip set (other frames of its animation) that dies after writing its first clip: the
    manifest and every file it names keep their bytes and load; the next build goes through."""
    from server.clipset import manifest as clip_manifest
    from server.clipset.manifest import MANIFEST, merge_clip_set, read_clip, read_clip_manifest

    source = tmp_path / "base.bvh"
    source.write_bytes(excerpt(data, frames=120))

    def clips(first: int, last: int) -> list:
        config = tmp_path / f"base{first}.toml"
        config.write_text(CLIPSET.format(source=source, first=first, last=last), encoding="utf-8")
        return build_clip_set(data, load_config(config))

    clips_dir = tmp_path / "clips"
    write_clip_set(clips(40, 100), clips_dir)

    def hashes() -> dict[str, str]:
        return {f.name: sha(f.read_bytes()) for f in clips_dir.iterdir() if not f.name.startswith(".")}

    before = hashes()
    assert len(before) == 3  # the manifest and two clips
    rebuilt = clips(30, 110)
    write = merge_clip_set if how == "merge" else write_clip_set
    real, calls = clip_manifest.np.savez_compressed, []

    def dies_on_the_second(*args, **kwargs):
        calls.append(args[0])
        if len(calls) == 2:
            raise KeyboardInterrupt("killed")  # as SIGINT would
        return real(*args, **kwargs)

    monkeypatch.setattr(clip_manifest.np, "savez_compressed", dies_on_the_second)
    with pytest.raises(KeyboardInterrupt):
        write(clips_dir, rebuilt) if how == "merge" else write(rebuilt, clips_dir)
    monkeypatch.setattr(clip_manifest.np, "savez_compressed", real)
    assert {k: v for k, v in hashes().items() if k in before} == before
    old = read_clip_manifest(clips_dir)
    assert [read_clip(clips_dir, c.id)[0] for c in old.clips] == list(old.clips)

    write(clips_dir, rebuilt) if how == "merge" else write(rebuilt, clips_dir)
    new = read_clip_manifest(clips_dir)
    assert new.clips != old.clips and (clips_dir / MANIFEST).read_bytes() != b""
    for c in new.clips:
        _, arrays = read_clip(clips_dir, c.id)
        assert arrays["times"].shape == (c.frames,)
    files = {f.name for f in clips_dir.iterdir() if f.suffix == ".npz" and not f.name.startswith(".")}
    # the previous files are removed once the new manifest is in place (leftovers of the killed build aside)
    assert {c.file for c in new.clips} <= files and not files & ({c.file for c in old.clips} - {c.file for c in
                                                                                              new.clips})


# --- the API builds too ---------------------------------------------------------------------------------------------

API_CLIPS = '''[clips.animations.idle]
kind = "idle"
source = "{source}"
frames = {frames}

[[clips.conditions]]
id = "keyframe"
method = "keyframe"

[[clips.conditions]]
id = "hybrid0"
method = "hybrid"
params = {{ increment = 0 }}
'''


def api_study_text(slug: str, source: str = "mocap/cmu/113_21_idle_30fps.bvh.gz", frames: str = "[40, 100]",
                   condition: str = "hybrid0") -> str:
    """future-work.toml with the idle motion of the data directory and its conditions inline."""
    text = FUTURE_WORK.read_text().replace('slug = "future-work"', f'slug = "{slug}"')
    text = text.replace('animations = ["walk", "crouch"]', 'animations = ["idle"]').replace(
        'conditions = ["hybrid0", "hybrid_ik0", "hybrid_c2_0"]', f'conditions = ["{condition}"]')
    return text.replace('[clips]\nset = "../server/clipset/conditions16.toml"\n',
                        API_CLIPS.format(source=source, frames=frames))


def wait_for(client: TestClient, slug: str, headers: dict) -> dict:
    deadline = time.monotonic() + 600
    while True:
        job = client.get(f"/api/v1/studies/{slug}/assets/build", headers=headers).json()
        if job["state"] in ("done", "failed") or time.monotonic() > deadline:
            return job
        time.sleep(0.5)


@pytest.mark.parametrize("kind", DATABASES)
def test_the_api_creates_a_study_whose_clips_are_given_inline(kind, tmp_path, tmp_path_factory, data):
    """POST /studies/file with inline [clips]: 202 with the draft and its build job, which builds the clips and
    renders the videos in its own process; then the study opens with them.  Bad [clips] are a 422 naming the
    field (nothing created) or a failed job with the reason and no server path."""
    engine = _fresh_engine(kind, tmp_path_factory, database="test_animstudy_api_clips")
    settings = Settings(var_dir=tmp_path / "var", data_dir=data, secret_key=SECRET)
    try:
        migrate(engine)
        # the server's videos are 64x48 without shadows: the study's are rendered alike
        settings.media_dir.mkdir(parents=True)
        (settings.media_dir / "manifest.json").write_text(fake_media().model_copy(update={
            "settings": dataclasses.asdict(TINY)}
        ).model_dump_json())
        with Session(engine) as db:
            create_researcher(db, *RESEARCHER)
        app = create_app(settings, engine, run_migrations=False)
        with TestClient(app) as client:
            headers = login(client, *RESEARCHER)

            def post(text: str) -> Any:
                return client.post("/api/v1/studies/file", content=text.encode(), headers=headers)

            bad = [(api_study_text("b1", condition="hybrid_ik0"), "hybrid_ik0 are not in the study's clip set"),
                   (api_study_text("b2", source="mocap/none.bvh"), "data directory has no file 'mocap/none.bvh'"),
                   (api_study_text("b3", source=str(data / "mocap/cmu/113_21_idle_30fps.bvh.gz")),
                    "no absolute path"),
                   (api_study_text("b4").replace('[clips.animations.idle]', '[clips.animations.Idle]'),
                    "an animation name is 1..32 lower-case"),
                   (FUTURE_WORK.read_text().replace('"future-work"', '"b5"'), "clips.set: a clip-set file")]
            for text, reason in bad:
                r = post(text)
                assert r.status_code == 422 and reason in r.text, r.text
                assert str(tmp_path) not in r.text and str(data) not in r.text
            # the same through the JSON endpoint
            r = client.post("/api/v1/studies", json=parse_study_text(bad[0][0], "x").model_dump(mode="json"),
                            headers=headers)
            assert r.status_code == 422 and bad[0][1] in r.text, r.text
            assert [s["slug"] for s in client.get("/api/v1/studies", headers=headers).json()] == []

            r = post(api_study_text("idle"))
            assert r.status_code == 202, r.text
            assert r.json()["study"]["slug"] == "idle" and r.json()["build"]["state"] == "queued"
            # one build at a time per researcher: a second study file is refused and not created
            r = post(api_study_text("second"))
            assert r.status_code == 409 and "your build of study 'idle' is running" in r.text, r.text
            assert client.get("/api/v1/studies/second/definition", headers=headers).status_code == 404
            assert client.post("/api/v1/studies/idle/open", headers=headers).status_code == 409  # nothing to show
            job = wait_for(client, "idle", headers)
            log = (settings.assets_dir / "1" / "build.log").read_text()
            assert (job["state"], job["stage"], job["error"]) == ("done", "done", None), (job, log)
            with Session(engine) as db:
                built = stimulus_sets.content_of(service.get_study(db, "idle").stimulus_set)
            # the draft's design changes over its own clip set (the server's has an "idle" of other videos)
            r = client.patch("/api/v1/studies/idle", json={"design": {"practice": "hybrid0"}}, headers=headers)
            assert r.status_code == 200, r.text
            with Session(engine) as db:
                study = service.get_study(db, "idle")
                assert [c.kind for c in study.comparisons] == ["test", "catch", "practice"]
                assert stimulus_sets.content_of(study.stimulus_set).clips == built.clips
            r = client.post("/api/v1/studies/idle/assets", params={"filename": "sway.bvh"},
                            content=excerpt(data, frames=45), headers=headers)
            assert r.status_code == 409 and "its own clip set" in r.text, r.text
            r = client.post("/api/v1/studies/idle/open", headers=headers)
            assert r.status_code == 200, r.text
            with Session(engine) as db:
                study = service.get_study(db, "idle")
                content = stimulus_sets.content_of(study.stimulus_set)
                assert {(c.animation, c.condition) for c in content.clips} == {("idle", "keyframe"),
                                                                              ("idle", "hybrid0")}
                assert stimulus_sets.missing(content, settings.media_dir) == []
                assert content.render["width"] == 64
                assert len(study.comparisons) == 3  # test, catch and practice
            # gc: the study's videos are kept (pinned, and listed by its clip set's render manifest); an orphan goes
            orphan = settings.media_dir / f"{sha(b'orphan')[:24]}.mp4"
            orphan.write_bytes(b"old")
            pinned = set(content.hashes())
            with Session(engine) as db:
                dry = stimulus_sets.collect(db, settings.media_dir, render_manifest_dirs(settings), dry_run=True)
                assert [f.name for f in dry.files] == [orphan.name] and orphan.exists()
                done = stimulus_sets.collect(db, settings.media_dir, render_manifest_dirs(settings))
            assert [f.name for f in done.files] == [orphan.name] and not orphan.exists()
            assert pinned <= {f.name for f in settings.media_dir.iterdir()}
            assert stimulus_sets.missing(content, settings.media_dir) == []

            # frames the file does not have: found by the build, the job fails with the reason, no server path
            r = post(api_study_text("late", frames="[40, 99999]"))
            assert r.status_code == 202, r.text
            job = wait_for(client, "late", headers)
            assert job["state"] == "failed" and "99999" in job["error"], job
            assert str(tmp_path) not in job["error"] and str(data) not in job["error"]
            assert client.post("/api/v1/studies/late/open", headers=headers).status_code == 409
    finally:
        engine.dispose()


def test_gc_collects_the_clip_files_a_killed_build_left_and_waits_for_running_jobs(tmp_path, data, monkeypatch,
                                                                                     capsys):
    """A clip file no manifest names and older than the manifest (a killed build's) is collected; one newer than
    the manifest (a running build's) and every named one are kept; while a job runs gc deletes nothing."""
    import os

    from server.clipset.manifest import MANIFEST, read_clip_manifest
    from server.jobs.models import BuildJob, BuildState, JobKind

    monkeypatch.setenv("ANIMSTUDY_VAR_DIR", str(tmp_path / "var"))
    monkeypatch.setenv("ANIMSTUDY_SECRET_KEY", "gc-clips-secret-0123456789abcdef0123")
    monkeypatch.delenv("ANIMSTUDY_DATABASE_URL", raising=False)
    monkeypatch.delenv("DATABASE_URL", raising=False)
    settings = Settings.from_env()
    source = tmp_path / "base.bvh"
    source.write_bytes(excerpt(data, frames=120))
    config = tmp_path / "base.toml"
    config.write_text(CLIPSET.format(source=source, first=40, last=100), encoding="utf-8")
    write_clip_set(build_clip_set(data, load_config(config)), settings.clips_dir)
    named = {c.file for c in read_clip_manifest(settings.clips_dir).clips}
    some = settings.clips_dir / sorted(named)[0]
    written = (settings.clips_dir / MANIFEST).stat().st_mtime
    left, running = settings.clips_dir / "left.0123456789ab.npz", settings.clips_dir / "new.0123456789ab.npz"
    for f, when in ((left, written - 60), (running, written + 60)):
        f.write_bytes(some.read_bytes())
        os.utime(f, (when, when))

    with _study_session(settings) as db:
        db.add(BuildJob(kind=JobKind.render, state=BuildState.running, stage="rendering", pid=os.getpid()))
        db.commit()
    assert cli.main(["gc"]) == 2
    assert "a job is running (render job" in capsys.readouterr().err
    assert left.is_file()
    with _study_session(settings) as db:
        db.query(BuildJob).delete()
        db.commit()

    assert cli.main(["gc", "--dry-run"]) == 0
    out, err = capsys.readouterr()
    assert out.split() == ["clips/left.0123456789ab.npz"] and "would delete 1 clip files" in err
    assert left.is_file()
    assert cli.main(["gc"]) == 0
    assert {f.name for f in settings.clips_dir.glob("*.npz")} == named | {running.name}
