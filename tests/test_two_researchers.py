"""Issue 25's scenario, on SQLite and PostgreSQL: two researchers A and B, neither an admin, on one server.  A's
uploaded animation is A's: B can neither use it nor see its name or any server path (API answers and errors);
once A shares it with B by name, B's study over it opens, and A changing the upload's frames and rebuilding
leaves B's participants every video byte for byte and B's results as they were."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select
from sqlalchemy.orm import Session

from server.app import create_app
from server.config import Settings
from server.db import migrate, session_factory
from server.jobs.models import BuildJob
from server.media.manifest import read_render_manifest
from server.pipeline import jobs as build_job
from server.researchers.service import create_researcher
from server.studies.design import Design
from server.studies.models import Study
from tests.conftest import DATABASES, _fresh_engine
from tests.server_fixtures import answer_all, start, study_file
from tests.test_stimulus_sets import PASSWORD, build_and_render
from tests.test_uploads import SECRET, excerpt, login

A, B = "a@example.org", "b@example.org"


def run_build(engine, settings: Settings, study_id: int) -> BuildJob:
    """The build job of a study's uploads, run here (the server runs the same function in its own process)."""
    with Session(engine, expire_on_commit=False) as db:
        job = BuildJob(study_id=study_id)
        db.add(job)
        db.commit()
    build_job.run(settings, session_factory(engine), job.id)
    with Session(engine) as db:
        return db.get(BuildJob, job.id)


def create(client: TestClient, headers: dict, slug: str, animations: list[str]):
    design = Design(reference="keyframe", conditions=["hybrid0"], animations=animations, catch_trials=1)
    return client.post("/api/v1/studies", json=study_file(design, slug=slug).model_dump(mode="json"),
                       headers=headers)


@pytest.mark.slow  # tens of seconds (the parallel run's slowest; still run by `make test`)
@pytest.mark.parametrize("kind", DATABASES)
def test_two_researchers(kind, tmp_path, tmp_path_factory, data):
    engine = _fresh_engine(kind, tmp_path_factory, database="test_animstudy_two_researchers")
    settings = Settings(var_dir=tmp_path / "var", data_dir=data, secret_key=SECRET)
    try:
        migrate(engine)
        build_and_render(settings, tmp_path, (40, 100))  # the server's clip set: animation "base", anyone's
        with Session(engine) as db:
            create_researcher(db, A, PASSWORD)
            create_researcher(db, B, PASSWORD)
        with TestClient(create_app(settings, engine, run_migrations=False)) as client:
            a, b = login(client, A, PASSWORD), login(client, B, PASSWORD)
            assert create(client, a, "astudy", ["base"]).status_code == 201
            r = client.post("/api/v1/studies/astudy/assets", params={"filename": "Private Sway.bvh"},
                            content=excerpt(data, frames=60), headers=a)
            assert r.status_code == 201, r.text
            assert r.json()["name"] == "private_sway"
            with Session(engine) as db:
                astudy_id = db.scalar(select(Study.id).where(Study.slug == "astudy"))
            built = run_build(engine, settings, astudy_id)
            assert built.state == "done", built.error
            assert "private_sway" in client.get("/api/v1/studies/astudy/definition", headers=a).json()[
                "design"]["animations"]

            # B can neither use nor see A's animation, nor any server path.
            r = create(client, b, "bstudy", ["private_sway"])
            assert r.status_code == 422, r.text
            detail = r.text
            assert "unknown animation(s) private_sway (the clip set has base)" in detail
            r = create(client, b, "bstudy", ["base"])
            assert r.status_code == 201, r.text
            r = client.patch("/api/v1/studies/bstudy", json={"design": {"animations": ["base", "private_sway"]}},
                             headers=b)
            assert r.status_code == 422 and "(the clip set has base)" in r.text
            results = client.get("/api/v1/studies/bstudy/results", headers=b).json()
            assert {c["animation"] for c in results["clips"]} == {"base"}
            seen = [client.get("/api/v1/studies", headers=b).text, str(results)]
            for path in ("/api/v1/studies/astudy/assets", "/api/v1/studies/astudy/results",
                         "/api/v1/studies/astudy/assets/private_sway/shares", "/api/v1/studies/astudy/definition"):
                r = client.get(path, headers=b)
                assert r.status_code == 404, path  # another's study answers as an unknown one
                seen.append(r.text)
            r = client.post("/api/v1/studies/astudy/assets/private_sway/shares", json={"email": B}, headers=b)
            assert r.status_code == 404  # only A shares A's upload (B is told nothing of A's study)
            for text in seen:
                assert "private_sway" not in text and "Private Sway" not in text
            for text in [*seen, detail, r.text]:
                assert A not in text and str(settings.var) not in text and str(tmp_path) not in text
            assert client.delete("/api/v1/studies/bstudy", headers=b).status_code == 204

            # B names an upload as A's private animation: B's build is refused with what it says for any name B
            # cannot take (here the server's "base"), nothing of A's.
            assert create(client, b, "bnames", ["base"]).status_code == 201
            with Session(engine) as db:
                bnames_id = db.scalar(select(Study.id).where(Study.slug == "bnames"))
            errors = {}
            for name in ("private_sway", "base"):
                r = client.post("/api/v1/studies/bnames/assets", params={"filename": "mine.bvh", "name": name},
                                content=excerpt(data, frames=60, start=20), headers=b)
                assert r.status_code == 201, r.text
                failed = run_build(engine, settings, bnames_id)
                assert failed.state == "failed", failed.error
                errors[name] = failed.error
                assert client.delete(f"/api/v1/studies/bnames/assets/{name}", headers=b).status_code == 204
            assert errors["private_sway"] == errors["base"].replace("'base'", "'private_sway'"), errors
            for word in ("already", "exists", A, "astudy", "Private Sway", str(settings.var)):
                assert word not in errors["private_sway"], errors
            assert client.delete("/api/v1/studies/bnames", headers=b).status_code == 204

            # A shares it with B by name: now B's study over it is created and opened.
            r = client.post("/api/v1/studies/astudy/assets/private_sway/shares", json={"email": B}, headers=a)
            assert r.status_code == 200 and r.json()["shared_with"] == [B], r.text
            assert create(client, b, "bstudy", ["base", "private_sway"]).status_code == 201
            assert client.post("/api/v1/studies/bstudy/open", headers=b).status_code == 200
            sid, headers = start(client, "bstudy")
            trials = answer_all(client, sid, headers)
            shown = {t["video_url"]: client.get(t["video_url"]).content for t in trials}
            assert all(len(v) > 1000 for v in shown.values())
            results = client.get("/api/v1/studies/bstudy/results", headers=b).json()
            export = client.get("/api/v1/studies/bstudy/export.csv", headers=b).text

            # A changes the frames of the upload and rebuilds.
            sway_before = {v for (left, _), v in read_render_manifest(settings.media_dir).pair_videos().items()
                           if left.startswith("private_sway")}
            r = client.patch("/api/v1/studies/astudy/assets/private_sway", json={"frames": [10, 50]}, headers=a)
            assert r.status_code == 200, r.text
            built = run_build(engine, settings, astudy_id)
            assert built.state == "done", built.error
            sway_after = {v for (left, _), v in read_render_manifest(settings.media_dir).pair_videos().items()
                          if left.startswith("private_sway")}
            assert sway_after and sway_after.isdisjoint(sway_before)  # other frames, other videos
            for url, content in shown.items():
                r = client.get(url)
                assert r.status_code == 200 and r.content == content, url
            sid2, headers2 = start(client, "bstudy")
            assert {t["video_url"] for t in answer_all(client, sid2, headers2)} <= set(shown)
            after = client.get("/api/v1/studies/bstudy/results", headers=b).json()
            assert after["clips"] == results["clips"]
            assert client.get("/api/v1/studies/bstudy/export.csv", headers=b).text.startswith(export)

            # A build that fails says why without a server path.
            (settings.assets_dir / str(astudy_id) / "Private Sway.bvh").write_text("HIERARCHY\nnot a bvh\n")
            failed = run_build(engine, settings, astudy_id)
            assert failed.state == "failed" and failed.error
            assert str(settings.var) not in failed.error and str(tmp_path) not in failed.error, failed.error
    finally:
        engine.dispose()
