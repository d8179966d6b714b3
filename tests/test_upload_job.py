"""The build job of a study's uploaded assets, end to end on a real (small) upload: a CMU excerpt uploaded into a
draft study whose design shows one animation of a small clip set; the job (its own process) builds the clips,
renders the videos and adds the animation to the design, and its progress is visible through the API."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session

from anim_core.clips.build import METRES_PER_CMU_UNIT
from anim_core.io.bvh import format_bvh, read_bvh
from server.app import create_app
from server.assets import character as load_makehuman
from server.clipset.build import build_clip_set
from server.clipset.config import load_config
from server.clipset.manifest import read_clip_manifest, write_clip_set
from server.config import Settings
from server.db import migrate
from server.media.build import render_media
from server.media.manifest import read_render_manifest
from server.media.scene import RenderSettings
from server.researchers.service import create_researcher
from server.studies.design import Design
from server.studies.service import clip_set_index, create_study, required_pairs
from tests.conftest import DATABASES, _fresh_engine
from tests.server_fixtures import RESEARCHER, fake_media, study_file
from tests.test_gltf_character import export
from tests.test_rigmap import Z_UP, convention_table, renamed, scaled, turned
from tests.test_uploads import SECRET, excerpt, login

TINY = RenderSettings(width=64, height=48, shadows=False)
BASE_CLIPSET = """fps = 30
[character]
relocate = ["LHipJoint", "RHipJoint"]
{character}
[animations.base]
kind = "idle"
source = "{source}"
frames = [40, 100]
[[conditions]]
id = "keyframe"
method = "keyframe"
[[conditions]]
id = "hybrid0"
method = "hybrid"
params = {{ increment = 0 }}
"""


def small_site(settings: Settings, engine: object, tmp_path: Path, gltf_character: bool = False) -> None:
    """A small clip set in the var directory (animation ``base``, conditions keyframe and hybrid0; for the
    MakeHuman character or, with ``gltf_character``, for it exported as a glTF body), rendered at 64x48 without
    shadows, and a draft study ``own`` over it owned by :data:`RESEARCHER` (not an admin)."""
    source = tmp_path / "base.bvh"
    source.write_bytes(excerpt(settings.data, frames=120))
    character = ""
    if gltf_character:
        character = f'gltf = "{export(load_makehuman(settings.data), tmp_path / "body.glb")}"'
    config = tmp_path / "base.toml"
    config.write_text(BASE_CLIPSET.format(source=source, character=character), encoding="utf-8")
    write_clip_set(build_clip_set(settings.data, load_config(config)), settings.clips_dir)
    design = Design(reference="keyframe", conditions=["hybrid0"], animations=["base"], catch_trials=1)
    render_media(settings.data, settings.clips_dir, settings.media_dir, settings.secret, TINY,
                 pairs=required_pairs(design, clip_set_index(settings.clips_dir)), workers=1)
    with Session(engine, expire_on_commit=False) as db:  # type: ignore[call-overload]
        owner = create_researcher(db, *RESEARCHER)
        create_study(db, read_render_manifest(settings.media_dir), study_file(design, slug="own"), owner=owner)


@pytest.mark.parametrize("kind", DATABASES)
def test_build_job_runs_to_completion(kind, tmp_path, tmp_path_factory, data):
    engine = _fresh_engine(kind, tmp_path_factory, database="test_animstudy_upload_job")
    settings = Settings(var_dir=tmp_path / "var", data_dir=data, secret_key=SECRET)
    try:
        migrate(engine)
        small_site(settings, engine, tmp_path, gltf_character=True)

        body = read_clip_manifest(settings.clips_dir).character
        assert body is not None and body.gltf == str(tmp_path / "body.glb")  # the clip set's glTF body
        app = create_app(settings, engine, run_migrations=False)
        with TestClient(app) as client:
            headers = login(client, *RESEARCHER)
            r = client.post("/api/v1/studies/own/assets", params={"filename": "Sway 45.bvh"},
                            content=excerpt(data, frames=45), headers=headers)
            assert r.status_code == 201, r.text
            assert r.json()["name"] == "sway_45"
            # the same kind of motion from a Mixamo rig (names, centimetres, Z up): inspected and built alike
            r = client.post("/api/v1/studies/own/assets", params={"filename": "mixamo_sway.bvh"},
                            content=mixamo(excerpt(data, frames=45, start=60), tmp_path), headers=headers)
            assert r.status_code == 201, r.text
            report = r.json()["report"]
            assert ("Mixamo" in report["convention"], report["units"], report["up_axis"]) == (True, "cm", "z")
            r = client.patch("/api/v1/studies/own/assets/mixamo_sway", json={"kind": "other"}, headers=headers)
            assert r.status_code == 200 and r.json()["kind"] == "other", r.text  # keys picked generically
            r = client.post("/api/v1/studies/own/assets/build", headers=headers)
            assert r.status_code == 202, r.text
            assert r.json()["state"] == "queued"
            # one build at a time, and the assets are fixed while it runs
            assert client.post("/api/v1/studies/own/assets/build", headers=headers).status_code == 409
            assert client.delete("/api/v1/studies/own/assets/sway_45", headers=headers).status_code == 409
            seen = []
            deadline = time.monotonic() + 900
            while True:
                job = client.get("/api/v1/studies/own/assets/build", headers=headers).json()
                seen.append((job["state"], job["stage"], job["done"], job["total"]))
                if job["state"] in ("done", "failed") or time.monotonic() > deadline:
                    break
                time.sleep(0.5)
            log = (settings.assets_dir / "1" / "build.log").read_text()
            assert job["state"] == "done", (job, log)
            assert job["error"] is None and job["finished_at"]
            stages = [s for _, s, _, _ in seen]
            assert "rendering" in stages or "building" in stages, seen  # progress was visible while it ran
            assert client.get("/api/v1/studies/own/assets", headers=headers).json()["build"]["state"] == "done"

            # the clips, with every condition of the clip set; the videos; the study's design
            clips = read_clip_manifest(settings.clips_dir)
            assert {(c.animation, c.condition) for c in clips.clips} == {
                (a, c) for a in ("base", "sway_45", "mixamo_sway") for c in ("keyframe", "hybrid0")}
            assert clips.character == body  # built for the clip set's character, which the manifest keeps
            mine = [c for c in clips.clips if c.animation == "sway_45"]
            assert all(c.source["file"].endswith("Sway 45.bvh") and c.kind == "idle" for c in mine)
            assert {c.kind for c in clips.clips if c.animation == "mixamo_sway"} == {"other"}
            media = read_render_manifest(settings.media_dir)
            assert {c.animation for c in media.clips.values()} == {"base", "sway_45", "mixamo_sway"}
            for clip in media.clips.values():
                assert (settings.media_dir / clip.video).stat().st_size > 0
            assert media.settings["width"] == 64  # the videos there already kept their settings
            definition = client.get("/api/v1/studies/own/definition", headers=headers).json()
            assert definition["design"]["animations"] == ["base", "sway_45", "mixamo_sway"]
            studies = client.get("/api/v1/studies", headers=headers).json()
            assert studies[0]["trials_total"] == 3 * 2 + 1
            assert not (settings.assets_dir / "1" / "clipset.toml").exists()  # typed, not written and parsed
    finally:
        engine.dispose()


def wait_for(client: TestClient, headers: dict, timeout_s: float = 300) -> dict:
    """The study ``own``'s latest build job once it has ended (or the timeout passed)."""
    deadline = time.monotonic() + timeout_s
    while (job := client.get("/api/v1/studies/own/assets/build", headers=headers).json())["state"] in (
            "queued", "running") and time.monotonic() < deadline:
        time.sleep(0.3)
    return job


def mixamo(bvh: bytes, folder: Path) -> bytes:
    """The same motion as a Mixamo rig exports it: ``mixamorig:`` names (with a helper pelvis joint per side),
    centimetres, Z up (the renamings of ``tests/test_rigmap.py``)."""
    path = folder / "cmu.bvh"
    path.write_bytes(bvh)
    source = renamed(read_bvh(path), convention_table("mixamo", "mixamorig:"))
    return format_bvh(turned(scaled(source, 100 * METRES_PER_CMU_UNIT), Z_UP)).encode()


@pytest.mark.parametrize("kind", DATABASES)
def test_a_failed_build_says_why(kind, tmp_path, tmp_path_factory, data):
    """A build that cannot be done stops with a message naming the asset and why; the job's error is visible and
    the assets can change again."""
    engine = _fresh_engine(kind, tmp_path_factory, database="test_animstudy_upload_job")
    settings = Settings(var_dir=tmp_path / "var", data_dir=data, secret_key=SECRET)
    try:
        migrate(engine)
        with Session(engine, expire_on_commit=False) as db:
            owner = create_researcher(db, *RESEARCHER)
            create_study(db, fake_media(), study_file(slug="own"), owner=owner)
        with TestClient(create_app(settings, engine, run_migrations=False)) as client:
            headers = login(client, *RESEARCHER)
            # a file gone from the assets folder behind the server's back: the build names it
            r = client.post("/api/v1/studies/own/assets", params={"filename": "idle.bvh"},
                            content=excerpt(data, frames=45), headers=headers)
            assert r.status_code == 201, r.text
            (settings.assets_dir / "1" / "idle.bvh").unlink()
            assert client.post("/api/v1/studies/own/assets/build", headers=headers).status_code == 202
            job = wait_for(client, headers)
            assert job["state"] == "failed" and "idle.bvh" in job["error"] and "missing" in job["error"], job
            assert job["stage"] == "building" and job["finished_at"]
            assert not (settings.clips_dir / "manifest.json").exists()  # nothing was built
            assert client.delete("/api/v1/studies/own/assets/idle", headers=headers).status_code == 204
    finally:
        engine.dispose()

