"""Stimulus sets (issue 25): what a study shows is pinned when it opens.  A rebuild of the clip set with other
frames (what an upload's rebuild does) leaves an open study every video byte for byte and its results as they
were; each exported vote names the sha256 of what was shown; opening an incomplete set is refused with what is
missing; ``gc`` deletes exactly the files nothing uses."""

from __future__ import annotations

import csv
import hashlib
import io
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from server import cli
from server.app import create_app
from server.clipset.build import build_clip_set
from server.clipset.config import load_config
from server.clipset.manifest import write_clip_set
from server.config import Settings
from server.deps import get_session
from server.media.build import MEDIA_NAME, render_media
from server.media.manifest import read_render_manifest
from server.media.scene import RenderSettings
from server.participants.service import update_study
from server.researchers.service import create_researcher
from server.stimuli import service as stimulus_sets
from server.studies import service
from server.studies.design import Design
from server.studies.service import clip_set_index, required_pairs
from tests.server_fixtures import answer_all, fake_media, start, study_file, write_fake_media
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
    with cli._study_session(settings) as db:
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
    with cli._study_session(settings) as db:
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
    with cli._study_session(Settings.from_env()) as db:
        content = stimulus_sets.content_of(service.get_study(db, "inline").stimulus_set)
    assert {(c.animation, c.condition, c.method) for c in content.clips} == {
        ("walk", "keyframe", "keyframe"), ("walk", "hybrid_c2_0", "hybrid_c2")}
    lacking = tmp_path / "lacking.toml"
    lacking.write_text(text.replace('slug = "inline"', 'slug = "lacking"').replace(
        'conditions = ["hybrid_c2_0"]', 'conditions = ["hybrid_ik0"]'))
    assert cli.main(["study", "create", str(lacking)]) == 2
    assert "hybrid_ik0 are not in the study's clip set" in capsys.readouterr().err
