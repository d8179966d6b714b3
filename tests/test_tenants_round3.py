"""Tenants, round three (issue 36, findings 1, 2, 9, 10, 12, 14), each as it was reproduced, on SQLite and (with
TEST_DATABASE_URL) PostgreSQL: one researcher's inline study does not break the other builds of the server; a
deleted draft's id and preview link open nothing of another researcher; build slots are per researcher and the
409 names no other researcher's study; a preview link that opens nothing answers as an unknown study does; two
animations whose clips come out identical render; ``study create --owner`` on SQLite does not lock the database.
"""

from __future__ import annotations

import fcntl
import os
import threading
import time
from datetime import timedelta
from pathlib import Path

import jwt
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select
from sqlalchemy.orm import Session

from server import cli
from server.app import create_app
from server.clipset.build import build_clip_set
from server.clipset.config import load_config
from server.clipset.manifest import write_clip_set
from server.config import Settings
from server.db import migrate, session_factory, utcnow
from server.errors import Conflict
from server.jobs.models import BuildJob, BuildState, JobKind
from server.media.build import render_media
from server.media.manifest import read_render_manifest
from server.pipeline import jobs as build_job
from server.researchers.models import Researcher
from server.researchers.service import create_researcher
from server.studies.design import Design
from server.studies.models import Study, StudyState
from server.studies.service import new_draft
from server.uploads.models import StudyAsset
from tests.conftest import DATABASES, _fresh_engine
from tests.server_fixtures import make_study, study_file, write_fake_media
from tests.test_pilot import preview
from tests.test_stimulus_sets import PASSWORD, TINY, api_study_text, build_and_render, wait_for
from tests.test_uploads import SECRET, excerpt, login

A, B = "a@example.org", "b@example.org"
THESIS = Path(__file__).resolve().parents[1] / "studies" / "thesis.toml"


def fresh(kind: str, tmp_path_factory: pytest.TempPathFactory, name: str, tmp_path: Path, data: Path,
          **settings: object) -> tuple[object, Settings]:
    engine = _fresh_engine(kind, tmp_path_factory, database=f"test_animstudy_tenants3_{name}")
    migrate(engine)
    # the settings name the engine's database: the commands run in a job open it again from them
    return engine, Settings(var_dir=tmp_path / "var", data_dir=data, secret_key=SECRET,
                            database_url=engine.url.render_as_string(hide_password=False), **settings)


def researchers(engine: object) -> dict[str, int]:
    with Session(engine) as db:  # type: ignore[call-overload]
        return {email: create_researcher(db, email, PASSWORD).id for email in (A, B)}


# --- 1: an inline study's clips are its owner's clip set, and other builds never ask for them ---------------------

@pytest.mark.parametrize("kind", DATABASES)
def test_an_inline_study_leaves_the_server_clip_set_and_its_renders_alone(kind, tmp_path, tmp_path_factory, data):
    """A's study file with inline [clips] (a private animation name) is built; then `animstudy render` and `study
    create` over the server's clip set still work (they failed: "pair (alicesprivatewalk-keyframe, ...) names a
    clip that is not in the clip set")."""
    engine, settings = fresh(kind, tmp_path_factory, "inline", tmp_path, data)
    try:
        build_and_render(settings, tmp_path, (40, 100))  # the server's clip set: animation "base"
        researchers(engine)
        text = api_study_text("alice", frames="[40, 80]").replace("clips.animations.idle", "clips.animations."
                                                                  "alicesprivatewalk").replace(
            'animations = ["idle"]', 'animations = ["alicesprivatewalk"]')
        with TestClient(create_app(settings, engine, run_migrations=False)) as client:
            a = login(client, A, PASSWORD)
            r = client.post("/api/v1/studies/file", content=text.encode(), headers=a)
            assert r.status_code == 202, r.text
            job = wait_for(client, "alice", a)
            assert job["state"] == "done", job
        # the inline clips are A's clip set, not the server's
        assert "alicesprivatewalk" not in (settings.clips_dir / "manifest.json").read_text()

        rendered = build_job.run_in_this_process(settings, JobKind.render, {
            "out": str(settings.media_dir), "clips_dir": str(settings.clips_dir), "studies": [], "workers": 1,
            "every_clip": False, "settings": {"width": 64, "height": 48, "shadows": False}}, echo=lambda _m: None)
        assert (rendered.state, rendered.error) == (BuildState.done, None)
        study = tmp_path / "over-server.toml"
        study.write_text(thesis_over_base("over-server"), encoding="utf-8")
        created = build_job.run_in_this_process(settings, JobKind.study, {
            "file": str(study), "owner_id": None, "open": False, "settings": None}, echo=lambda _m: None)
        assert (created.state, created.error) == (BuildState.done, None)
    finally:
        engine.dispose()


def thesis_over_base(slug: str) -> str:
    """studies/thesis.toml over the small clip set of :func:`build_and_render` (animation base, DESIGN)."""
    return THESIS.read_text().replace('slug = "thesis"', f'slug = "{slug}"').replace(
        'conditions = ["hybrid0", "hybrid1"]\nanimations = ["walk", "run", "crouch", "idle"]\nrepeats = 1\n'
        'catch_trials = 0', 'conditions = ["hybrid0"]\nanimations = ["base"]\nrepeats = 1\ncatch_trials = 1')


# --- 2: ids are never reused; a preview link is bound to its study --------------------------------------------

@pytest.mark.parametrize("kind", DATABASES)
def test_a_deleted_drafts_id_and_preview_link_open_nothing_of_another_researcher(kind, tmp_path, tmp_path_factory,
                                                                                 data):
    """A's draft, its preview link and A deleting it; B's next draft gets another id and A's link opens it not
    (SQLite gave it the same id: 200 with B's title and a pilot session)."""
    engine, settings = fresh(kind, tmp_path_factory, "ids", tmp_path, data)
    try:
        researchers(engine)
        write_fake_media(settings.media_dir)
        with TestClient(create_app(settings, engine, run_migrations=False)) as client:
            a, b = login(client, A, PASSWORD), login(client, B, PASSWORD)
            r = client.post("/api/v1/studies", json=study_file(slug="adraft").model_dump(mode="json"),
                            headers=a)
            assert r.status_code == 201, r.text
            token = preview(client, a, "adraft")
            with Session(engine) as db:
                a_id = db.scalar(select(Study.id).where(Study.slug == "adraft"))
            assert client.delete("/api/v1/studies/adraft", headers=a).status_code == 204
            r = client.post("/api/v1/studies", json=study_file(slug="bdraft").model_dump(mode="json"),
                            headers=b)
            assert r.status_code == 201, r.text
            with Session(engine) as db:
                assert db.scalar(select(Study.id).where(Study.slug == "bdraft")) > a_id
            r = client.get("/api/v1/studies/bdraft", params={"preview": token})
            assert r.status_code == 404 and "title" not in r.json(), r.text
            r = client.post("/api/v1/studies/bdraft/sessions", json={"consent": True, "preview": token})
            assert r.status_code == 404, r.text
    finally:
        engine.dispose()


def test_a_preview_link_names_its_study_by_more_than_its_id(client, db, researcher_headers):
    """A study given the id of a deleted one (as a restored database could) is not opened by the old link."""
    make_study(db, state=StudyState.draft, slug="old")
    token = preview(client, researcher_headers, "old")
    old = db.scalar(select(Study).where(Study.slug == "old"))
    old_id = old.id
    db.delete(old)
    db.commit()
    again = new_draft(db, study_file(slug="again"), None)
    again.id = old_id  # the same id, another study
    db.add(again)
    db.commit()
    assert db.get(Study, old_id).slug == "again"
    assert client.get("/api/v1/studies/again", params={"preview": token}).status_code == 404
    fresh_token = preview(client, researcher_headers, "again")
    assert client.get("/api/v1/studies/again", params={"preview": fresh_token}).status_code == 200


# --- 9: build slots per researcher ---------------------------------------------------------------------------

def running_job(db: Session, study: Study) -> BuildJob:
    """A build of ``study`` running in a live process (this one)."""
    job = BuildJob(study_id=study.id, state=BuildState.running, stage="rendering", message="", pid=os.getpid())
    db.add(job)
    db.commit()
    return job


def test_one_researchers_build_neither_blocks_nor_is_named_to_another(db, engine, tmp_path, data):
    """A's long build (study 'long2') runs: B's build is not refused for it and never reads its name (it read
    "a build is running (study 'long2')", 17 of 17 times); A's second build is refused, naming A's own; with the
    server's cap reached B is refused, naming no study."""
    from server.jobs.control import check_build_slot

    owner_a, owner_b = (create_researcher(db, email, PASSWORD) for email in (A, B))
    long2 = make_study(db, slug="long2", state=StudyState.draft, owner=owner_a)
    other_a = make_study(db, slug="again", state=StudyState.draft, owner=owner_a)
    mine = make_study(db, slug="bstudy", state=StudyState.draft, owner=owner_b)
    db.add(StudyAsset(study_id=mine.id, name="sway", filename="sway.bvh", size_bytes=1, sha256="0" * 64,
                      kind="idle", first_frame=0, last_frame=10, report={}))
    db.add(StudyAsset(study_id=other_a.id, name="sway", filename="sway.bvh", size_bytes=1, sha256="0" * 64,
                      kind="idle", first_frame=0, last_frame=10, report={}))
    db.commit()
    running_job(db, long2)

    settings = Settings(var_dir=tmp_path / "var", data_dir=data, secret_key=SECRET)
    check_build_slot(db, settings, owner_b.id)  # B's build may start beside A's
    with pytest.raises(Conflict) as own:
        check_build_slot(db, settings, owner_a.id)
    assert "long2" in own.value.detail

    capped = Settings(var_dir=tmp_path / "var", data_dir=data, secret_key=SECRET, builds_max=1)
    app = create_app(capped, engine, run_migrations=False)
    from server.deps import get_session

    app.dependency_overrides[get_session] = lambda: db
    with TestClient(app) as client:
        b = login(client, B, PASSWORD)
        r = client.post("/api/v1/studies/bstudy/assets/build", headers=b)
        assert r.status_code == 409 and "long2" not in r.text and "as many builds" in r.text, r.text
        a = login(client, A, PASSWORD)
        r = client.post("/api/v1/studies/again/assets/build", headers=a)
        assert r.status_code == 409 and "long2" in r.text, r.text  # A's own


@pytest.mark.parametrize("kind", DATABASES)
def test_a_build_into_a_busy_clip_set_waits_its_turn(kind, tmp_path, tmp_path_factory, data):
    """While another build holds the server's clip set, a job waits (it failed at once: "another build is
    running on this server") and runs when the other has finished."""
    engine, settings = fresh(kind, tmp_path_factory, "turns", tmp_path, data)
    try:
        ids = researchers(engine)
        with Session(engine, expire_on_commit=False) as db:
            study = make_study(db, slug="bstudy", state=StudyState.draft, owner=db.get(Researcher, ids[B]))
            job = BuildJob(study_id=study.id, state=BuildState.queued, stage="queued", message="starting")
            db.add(job)
            db.commit()
        lock_path = settings.assets_dir / ".build.lock"
        lock_path.parent.mkdir(parents=True, exist_ok=True)
        factory = session_factory(engine)
        with lock_path.open("w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)  # A's build, into the server's clip set
            worker = threading.Thread(target=build_job.run, args=(settings, factory, job.id))
            worker.start()
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline:
                with factory() as db:
                    waiting = db.get(BuildJob, job.id)
                if waiting.message.startswith("waiting"):
                    break
                time.sleep(0.05)
            assert (waiting.state, waiting.message) == (BuildState.queued, "waiting for another build into the "
                                                                          "same clip set to finish")
            time.sleep(0.3)
            assert worker.is_alive()
        worker.join(60)
        with factory() as db:
            ran = db.get(BuildJob, job.id)
        assert (ran.state, ran.error) == (BuildState.failed, "the study has no assets")  # it ran: its own reason
    finally:
        engine.dispose()


# --- 10: a preview link that opens nothing ------------------------------------------------------------------

def test_a_preview_link_tells_an_existing_draft_from_an_unknown_slug_not(client, db, researcher_headers):
    make_study(db, state=StudyState.draft, slug="secret-draft")
    make_study(db, state=StudyState.draft, slug="mine")
    token = preview(client, researcher_headers, "mine")
    expired = jwt.encode({"typ": "preview", "study": 1, "exp": utcnow() - timedelta(days=1)}, SECRET)
    for bad in ("x", token, token[:-4] + "AAAA", expired):
        answers = []
        for slug in ("secret-draft", "no-such-study"):
            for r in (client.get(f"/api/v1/studies/{slug}", params={"preview": bad}),
                      client.post(f"/api/v1/studies/{slug}/sessions", json={"consent": True, "preview": bad})):
                answers.append((r.status_code, r.text.replace(slug, "SLUG")))
        assert len(set(answers)) == 1 and answers[0][0] == 404, answers
    assert client.get("/api/v1/studies/mine", params={"preview": token}).status_code == 200


# --- 12: two animations whose clips come out identical ---------------------------------------------------------

TWINS = """fps = 30
[character]
relocate = ["LHipJoint", "RHipJoint"]
[animations.first]
kind = "idle"
source = "{source}"
frames = [40, 70]
[animations.second]
kind = "idle"
source = "{source}"
frames = [40, 70]
[[conditions]]
id = "keyframe"
method = "keyframe"
[[conditions]]
id = "hybrid0"
method = "hybrid"
params = {{ increment = 0 }}
"""


def test_two_animations_whose_clips_are_identical_render(tmp_path, data):
    """The same motion under two names (an upload of the shipped walk): every clip renders (it failed with
    ``KeyError: 'first-hybrid0'``); each animation's videos are its own clips'."""
    source = tmp_path / "twin.bvh"
    source.write_bytes(excerpt(data, frames=100))
    config = tmp_path / "twins.toml"
    config.write_text(TWINS.format(source=source), encoding="utf-8")
    clips_dir, media_dir = tmp_path / "clips", tmp_path / "media"
    write_clip_set(build_clip_set(data, load_config(config)), clips_dir)
    design = Design(reference="keyframe", conditions=["hybrid0"], animations=["first", "second"], catch_trials=0)
    from server.studies.service import clip_set_index, required_pairs

    render_media(data, clips_dir, media_dir, SECRET.encode(), TINY,
                 pairs=required_pairs(design, clip_set_index(clips_dir)), workers=1, every_clip=True)
    media = read_render_manifest(media_dir)
    assert set(media.clips) == {f"{a}-{c}" for a in ("first", "second") for c in ("keyframe", "hybrid0")}
    assert all((media_dir / c.video).is_file() for c in media.clips.values())
    assert len(media.pairs) == 4


# --- 14: study create --owner on SQLite -------------------------------------------------------------------------

@pytest.mark.parametrize("kind", DATABASES)
def test_study_create_with_an_owner_does_not_lock_the_database(kind, tmp_path, tmp_path_factory, data, monkeypatch,
                                                               capsys):
    """`animstudy study create FILE --owner EMAIL` (it ended after 30 s in "database is locked", a traceback)."""
    engine, settings = fresh(kind, tmp_path_factory, "owner", tmp_path, data)
    try:
        build_and_render(settings, tmp_path, (40, 100))
        ids = researchers(engine)
        monkeypatch.setenv("ANIMSTUDY_VAR_DIR", str(settings.var))
        monkeypatch.setenv("ANIMSTUDY_DATA_DIR", str(data))
        monkeypatch.setenv("ANIMSTUDY_SECRET_KEY", SECRET)
        monkeypatch.delenv("ANIMSTUDY_DATABASE_URL", raising=False)
        monkeypatch.setenv("DATABASE_URL", engine.url.render_as_string(hide_password=False))  # type: ignore[attr-defined]
        path = tmp_path / "owned.toml"
        path.write_text(thesis_over_base("owned"), encoding="utf-8")
        started = time.monotonic()
        assert cli.main(["study", "create", str(path), "--owner", A]) == 0, capsys.readouterr()
        assert time.monotonic() - started < 25
        assert "created study 'owned'" in capsys.readouterr().out
        with Session(engine) as db:  # type: ignore[call-overload]
            assert db.scalar(select(Study.owner_id).where(Study.slug == "owned")) == ids[A]
    finally:
        engine.dispose()
