"""Uploading motion files into a draft study's assets (``POST /api/v1/studies/{slug}/assets``): stored only when
the file inspects cleanly, within the size limit (declared or streamed), for the study's researcher, while it is a
draft; listed, changed and deleted."""

from __future__ import annotations

import gzip
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from server.app import create_app
from server.config import Settings
from server.deps import get_session
from server.jobs.control import active_jobs
from server.jobs.models import BuildJob, BuildState
from server.researchers.service import create_researcher
from server.studies.models import StudyState
from server.uploads.models import StudyAsset
from tests.server_fixtures import RESEARCHER, make_study

SECRET = "test-secret-0123456789abcdef0123456789"
IDLE = "mocap/cmu/113_21_idle_30fps.bvh.gz"


def excerpt(data: Path, name: str = IDLE, frames: int = 45, start: int = 0) -> bytes:
    """The first ``frames`` frames (from ``start``) of a shipped CMU BVH, as an uploadable plain BVH."""
    lines = gzip.decompress((data / name).read_bytes()).decode().splitlines()
    at = lines.index("MOTION")
    body = lines[at + 3 + start: at + 3 + start + frames]
    return ("\n".join([*lines[: at + 1], f"Frames: {len(body)}", lines[at + 2], *body]) + "\n").encode()


@pytest.fixture
def app_settings(tmp_path, data):
    return Settings(var_dir=tmp_path / "var", data_dir=data, secret_key=SECRET, upload_max_bytes=120_000)


@pytest.fixture
def uclient(db, engine, app_settings):
    app = create_app(app_settings, engine, run_migrations=False)
    app.dependency_overrides[get_session] = lambda: db
    with TestClient(app) as client:
        yield client


def login(client: TestClient, email: str, password: str) -> dict[str, str]:
    r = client.post("/api/v1/auth/token", data={"username": email, "password": password})
    assert r.status_code == 200, r.text
    return {"Authorization": f"Bearer {r.json()['access_token']}"}


@pytest.fixture
def admin(db, uclient):
    create_researcher(db, *RESEARCHER, admin=True)
    return login(uclient, *RESEARCHER)


@pytest.fixture
def draft(db):
    return make_study(db, slug="mine", state=StudyState.draft)


def upload(client: TestClient, headers: dict, body: bytes | object, filename: str = "idle45.bvh",
           slug: str = "mine", **params: str):
    return client.post(f"/api/v1/studies/{slug}/assets", params={"filename": filename, **params}, content=body,
                       headers={**headers, "Content-Type": "application/octet-stream"})


def stored_files(settings: Settings) -> list[Path]:
    root = settings.assets_dir
    return sorted(p for p in root.rglob("*") if p.is_file()) if root.exists() else []


def asset_rows(db) -> int:
    return db.scalar(select(func.count(StudyAsset.id)))


def test_upload_is_inspected_stored_and_listed(uclient, admin, draft, data, app_settings, db):
    body = excerpt(data)
    r = upload(uclient, admin, body)
    assert r.status_code == 201, r.text
    asset = r.json()
    assert (asset["name"], asset["filename"], asset["size_bytes"]) == ("idle45", "idle45.bvh", len(body))
    report = asset["report"]
    assert (report["joints"], report["convention"], report["units"], report["up_axis"]) == (31, "CMU", "cmu", "y")
    assert report["frames"] == 45 and report["fps"] == pytest.approx(30, abs=1e-3)
    assert report["suggested"]["kind"] == "idle" and report["suggested"]["frames"] == [0, 44]
    assert (asset["kind"], asset["frames"]) == ("idle", [0, 44])
    assert {m["joint"] for m in report["mapping"]} >= {"Hips", "LeftUpLeg", "RightHand"}
    path = app_settings.assets_dir / str(draft.id) / "idle45.bvh"
    assert path.read_bytes() == body
    assert stored_files(app_settings) == [path]  # nothing left in .incoming
    listed = uclient.get("/api/v1/studies/mine/assets", headers=admin).json()
    assert [a["name"] for a in listed["assets"]] == ["idle45"] and listed["build"] is None
    assert listed["assets"][0]["report"] == report

    # another name for the same file is another asset; the same file or animation name again is refused
    assert upload(uclient, admin, body, "idle45.bvh").status_code == 409
    assert upload(uclient, admin, body, "other.bvh", name="idle45").status_code == 409
    r = upload(uclient, admin, body, "Idle Take 2.bvh")
    assert r.status_code == 201 and r.json()["name"] == "idle_take_2"
    assert asset_rows(db) == 2


def test_change_and_delete(uclient, admin, draft, data, app_settings):
    assert upload(uclient, admin, excerpt(data)).status_code == 201
    r = uclient.patch("/api/v1/studies/mine/assets/idle45", json={"kind": "crouch", "frames": [2, 40]},
                      headers=admin)
    assert r.status_code == 200, r.text
    assert (r.json()["kind"], r.json()["frames"]) == ("crouch", [2, 40])
    for bad in ({"kind": "dance"}, {"frames": [10, 45]}, {"frames": [20, 10]}, {"colour": "red"}):
        assert uclient.patch("/api/v1/studies/mine/assets/idle45", json=bad, headers=admin).status_code == 422
    assert uclient.delete("/api/v1/studies/mine/assets/nothing", headers=admin).status_code == 404
    assert uclient.delete("/api/v1/studies/mine/assets/idle45", headers=admin).status_code == 204
    assert uclient.get("/api/v1/studies/mine/assets", headers=admin).json()["assets"] == []
    assert stored_files(app_settings) == []


def chunks(body: bytes, size: int = 8192):
    for i in range(0, len(body), size):
        yield body[i:i + size]


def test_over_the_limit_is_413_and_stores_nothing(uclient, admin, draft, data, app_settings, db):
    body = excerpt(data, "mocap/cmu/12_03_walk.bvh.gz", frames=200)  # over the 120 000 bytes of these settings
    assert len(body) > app_settings.upload_max_bytes
    r = upload(uclient, admin, body)  # declared length: refused before the body is read
    assert r.status_code == 413 and "120000 bytes" in r.json()["detail"]
    r = upload(uclient, admin, chunks(body))  # chunked, no length: refused when the limit is passed
    assert r.status_code == 413, r.text
    assert "ANIMSTUDY_UPLOAD_MAX_BYTES" in r.json()["detail"]
    assert stored_files(app_settings) == [] and asset_rows(db) == 0
    # within the limit (and over the 64 KiB of every other body), declared and chunked
    within = excerpt(data, frames=120)
    assert 64 * 1024 < len(within) < app_settings.upload_max_bytes
    assert upload(uclient, admin, within).status_code == 201
    assert upload(uclient, admin, chunks(within), "second.bvh").status_code == 201


def test_the_default_limit_is_50_mb_and_configurable(monkeypatch):
    assert Settings().upload_max_bytes == 50 * 2**20
    monkeypatch.setenv("ANIMSTUDY_UPLOAD_MAX_BYTES", "1000")
    assert Settings().upload_max_bytes == 1000


def test_other_bodies_keep_the_64_kib_limit(uclient, admin, draft):
    r = uclient.post("/api/v1/studies/file", content=b"x" * 70_000, headers={**admin, "Content-Type": "text/plain"})
    assert r.status_code == 413


@pytest.mark.parametrize(("content", "needle"), [
    (b"", "empty"),
    (b"HIERARCHY\nROOT Hips\n{\n", "idle45.bvh"),  # truncated
    (b"\x89PNG\r\n\x1a\n" + bytes(100), "idle45.bvh"),
    ("nan", "idle45.bvh"),
])
def test_invalid_files_are_422_and_store_nothing(uclient, admin, draft, data, app_settings, db, content, needle):
    if content == "nan":  # a finite-looking file with one NaN channel value
        text = excerpt(data).decode().splitlines()
        text[-1] = "nan " + text[-1].split(" ", 1)[1]
        content = ("\n".join(text) + "\n").encode()
    r = upload(uclient, admin, content)
    assert r.status_code == 422, r.text
    assert needle in str(r.json()["detail"])
    assert stored_files(app_settings) == [] and asset_rows(db) == 0


def test_a_bvh_of_the_wrong_rig_is_422(uclient, admin, draft, data, app_settings, db):
    text = excerpt(data).decode()
    for joint in ("LeftUpLeg", "LeftLeg", "LeftFoot"):  # no left leg any more
        text = text.replace(f"JOINT {joint}\n", f"JOINT Stick{joint[4:]}\n")
    r = upload(uclient, admin, text.encode())
    assert r.status_code == 422 and "left leg" in r.json()["detail"], r.text
    assert stored_files(app_settings) == [] and asset_rows(db) == 0


@pytest.mark.parametrize("filename", ["../idle.bvh", "/etc/idle.bvh", "a/../../idle.bvh", "..\\idle.bvh",
                                      "idle\x00.bvh", ".idle.bvh", "idle.txt", "idle.bvh.gz", "idle.bvh/", "",
                                      "idle\n.bvh"])
def test_path_tricks_and_wrong_extensions_are_refused(uclient, admin, draft, data, app_settings, db, filename):
    r = upload(uclient, admin, excerpt(data), filename)
    assert r.status_code == 422, (filename, r.text)
    assert stored_files(app_settings) == [] and asset_rows(db) == 0
    assert not (app_settings.var.parent / "idle.bvh").exists()


def test_bad_animation_names_are_refused(uclient, admin, draft, data):
    for name in ("Walk", "a-b", "", "x" * 33):
        assert upload(uclient, admin, excerpt(data), name=name).status_code == 422


def test_researchers_only_and_drafts_only(uclient, admin, draft, data, db, app_settings):
    body = excerpt(data)
    assert upload(uclient, {}, body).status_code == 401
    assert uclient.get("/api/v1/studies/mine/assets").status_code == 401
    create_researcher(db, "other@example.org", "another good password")
    other = login(uclient, "other@example.org", "another good password")
    assert upload(uclient, other, body).status_code == 404  # not their study
    assert uclient.get("/api/v1/studies/mine/assets", headers=other).status_code == 404
    assert uclient.post("/api/v1/studies/mine/assets/build", headers=other).status_code == 404
    assert upload(uclient, admin, body, slug="nope").status_code == 404
    make_study(db, slug="running", state=StudyState.open)
    r = upload(uclient, admin, body, slug="running")
    assert r.status_code == 409 and "draft" in r.json()["detail"]
    assert uclient.post("/api/v1/studies/running/assets/build", headers=admin).status_code == 409
    assert stored_files(app_settings) == [] and asset_rows(db) == 0


def test_build_needs_assets(uclient, admin, draft):
    r = uclient.post("/api/v1/studies/mine/assets/build", headers=admin)
    assert r.status_code == 409 and "no assets" in r.json()["detail"]
    assert uclient.get("/api/v1/studies/mine/assets/build", headers=admin).json() is None


def test_a_lost_build_process_reads_as_failed(db, uclient, admin):
    """A job that says it runs while its process is gone (killed, server restarted) is failed, and a new build
    may start."""
    study = make_study(db, slug="mine", state=StudyState.draft)
    db.add(BuildJob(study_id=study.id, state=BuildState.running, stage="rendering", pid=2**22 + 12345))
    db.commit()
    job = uclient.get("/api/v1/studies/mine/assets/build", headers=admin).json()
    assert job["state"] == "failed" and "ended unexpectedly" in job["error"]
    assert active_jobs(db) == []
    assert db.scalar(select(BuildJob.state)) == "failed"


def test_a_chunked_upload_is_refused_while_it_is_still_sending(tmp_path, tmp_path_factory, data):
    """Over a real connection: the 413 arrives as soon as the limit is passed, while the client has more to send
    (the rest is never read), and nothing is stored."""
    import socket

    from server.db import migrate, session_factory
    from tests.conftest import _fresh_engine
    from tests.server_fixtures import live_server

    settings = Settings(var_dir=tmp_path / "var", data_dir=data, secret_key=SECRET, upload_max_bytes=100_000)
    engine = _fresh_engine("sqlite", tmp_path_factory)
    migrate(engine)
    with session_factory(engine)() as db:
        make_study(db, slug="mine", state=StudyState.draft)
        create_researcher(db, *RESEARCHER, admin=True)
    try:
        with live_server(create_app(settings, engine, run_migrations=False)) as base:
            with TestClient(create_app(settings, engine, run_migrations=False)) as client:
                token = login(client, *RESEARCHER)["Authorization"]
            host, port = base.removeprefix("http://").split(":")
            with socket.create_connection((host, int(port)), timeout=30) as sock:
                sock.sendall(f"POST /api/v1/studies/mine/assets?filename=big.bvh HTTP/1.1\r\nHost: {host}\r\n"
                             f"Authorization: {token}\r\nContent-Type: application/octet-stream\r\n"
                             f"Transfer-Encoding: chunked\r\n\r\n".encode())
                chunk = b"x" * 10_000
                for _ in range(11):  # 110 000 bytes: past the limit, and the body is not finished
                    sock.sendall(b"%x\r\n%s\r\n" % (len(chunk), chunk))
                answer = b""
                while b"\r\n\r\n" not in answer:
                    answer += sock.recv(4096)
            assert answer.startswith(b"HTTP/1.1 413"), answer[:200]
        assert stored_files(settings) == []
        with session_factory(engine)() as db:
            assert asset_rows(db) == 0
    finally:
        engine.dispose()


def test_the_clip_set_description_of_the_assets(tmp_path):
    """The job's clip-set description (typed, no file written to be read back): every condition of the richest
    shipped clip set (ints, floats, strings in params), the assets' kinds, absolute sources with spaces and
    frames, validated as a clip-set file is."""
    from anim_core.clips.build import ConfigError
    from server.clipset.config import CharacterConfig, load_config
    from server.pipeline.assets import BaseClipSet, assets_config

    shipped = load_config(Path("server/clipset/conditions16.toml"))
    conditions = [(c.id, c.method, c.params_dict()) for c in shipped.conditions]
    assets = [StudyAsset(id=1, name="sway", filename="Sway 1.bvh", kind="idle", first_frame=3, last_frame=40),
              StudyAsset(id=2, name="walk2", filename='we"ird.bvh', kind="gait", first_frame=0, last_frame=99)]
    files = {1: tmp_path / "a b" / "Sway 1.bvh", 2: tmp_path / 'we"ird.bvh'}
    character = CharacterConfig(gltf="/data/bodies/Mine 2.glb", units="cm")
    base = BaseClipSet(24, ("LHipJoint",), character, conditions)
    config = assets_config(assets, lambda a: files[a.id], base)
    assert (config.fps, config.relocate, config.character) == (24, ("LHipJoint",), character)
    assert [(c.id, c.method, c.params_dict()) for c in config.conditions] == conditions
    assert {n: (a.kind, a.source, a.frames) for n, a in config.animations.items()} == {
        "sway": ("idle", str(files[1]), (3, 40)), "walk2": ("gait", str(files[2]), (0, 99))}
    assert not list(tmp_path.rglob("*.toml"))
    bad = [StudyAsset(id=1, name="sway", filename="Sway 1.bvh", kind="idle", first_frame=40, last_frame=3)]
    with pytest.raises(ConfigError, match=r"the study's assets \[animations.sway\] frames"):
        assets_config(bad, lambda a: files[a.id], base)


def test_an_unreadable_clip_set_stops_the_build(tmp_path):
    from server.jobs.progress import BuildError
    from server.pipeline.assets import current_clip_set, merge_clips

    assert current_clip_set(tmp_path) is None
    (tmp_path / "manifest.json").write_text('{"version": 1, "clips": []}')
    with pytest.raises(BuildError, match="version 1"):
        merge_clips(tmp_path, [])
    assert (tmp_path / "manifest.json").read_text() == '{"version": 1, "clips": []}'


def test_uploads_left_over_by_a_killed_server_are_cleaned_up(app_settings):
    import os
    import time

    from server.uploads.service import STALE_INCOMING_S, incoming_path

    old = incoming_path(app_settings, "a.bvh")
    old.write_bytes(b"x")
    recent = incoming_path(app_settings, "b.bvh")
    long_ago = time.time() - STALE_INCOMING_S - 60
    os.utime(old.parent, (long_ago, long_ago))
    fresh = incoming_path(app_settings, "c.bvh")
    assert not old.parent.exists() and recent.parent.is_dir() and fresh.parent.is_dir()
