"""Hostile input, round two (issue 26), uploads: small files that asked for gigabytes are refused before the memory
is taken, the peak memory of inspecting them stays within 50 × their size + 200 MB (measured in a subprocess), and
the usual glTF export (``JOINTS_0``/``WEIGHTS_0`` only) uploads."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from server.app import create_app
from server.config import Settings
from server.deps import get_session
from server.researchers.service import create_researcher
from server.studies.models import StudyState
from tests.hostile_files import bvh_bomb, gltf_key_bomb, gltf_stride_bomb, write_bombs
from tests.server_fixtures import RESEARCHER, make_study

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def settings(tmp_path, data):
    return Settings(var_dir=tmp_path / "var", data_dir=data, secret_key="test-secret-0123456789abcdef0123456789")


@pytest.fixture
def client(db, engine, settings):
    app = create_app(settings, engine, run_migrations=False)
    app.dependency_overrides[get_session] = lambda: db
    with TestClient(app) as c:
        yield c


@pytest.fixture
def admin(db, client):
    create_researcher(db, *RESEARCHER, admin=True)
    r = client.post("/api/v1/auth/token", data={"username": RESEARCHER[0], "password": RESEARCHER[1]})
    make_study(db, slug="mine", state=StudyState.draft)
    return {"Authorization": f"Bearer {r.json()['access_token']}"}


def upload(client: TestClient, headers: dict, body: bytes, filename: str):
    return client.post("/api/v1/studies/mine/assets", params={"filename": filename}, content=body,
                       headers={**headers, "Content-Type": "application/octet-stream"})


def stored(settings: Settings) -> list[Path]:
    root = settings.assets_dir
    return [p for p in root.rglob("*") if p.is_file()] if root.exists() else []


def test_bvh_of_channel_less_joints_and_many_frames_is_refused_at_its_frames_line(client, admin, data, settings):
    # Before: accepted after 46 s with 2.6 GiB taken (10,000 frames × 1000 joints from 170 KB).
    r = upload(client, admin, bvh_bomb(data), "bomb.bvh")
    assert r.status_code == 422, r.text[:300]
    detail = r.json()["detail"]
    assert "bomb.bvh, line" in detail and "10000 frames of 1000 joints" in detail
    assert stored(settings) == []


@pytest.mark.parametrize("make, message", [
    (lambda p: gltf_key_bomb(p, 1000.0), "30001 frames of 1000 joints"),
    (lambda p: gltf_stride_bomb(p), "byteStride 1, less than the 64 bytes"),
])
def test_gltf_bombs_are_refused_before_allocating(client, admin, settings, tmp_path, make, message):
    path = make(tmp_path / "bomb.glb")
    r = upload(client, admin, path.read_bytes(), "bomb.glb")
    assert r.status_code == 422, r.text[:300]
    assert message in r.json()["detail"]
    assert stored(settings) == []


@pytest.mark.slow  # tens of seconds (the parallel run's slowest; still run by `make test`)
def test_peak_memory_of_inspecting_the_bomb_files_is_within_50_times_their_size_plus_200_mb(data, tmp_path):
    files = write_bombs(tmp_path, data)
    bound_mib = (50 * min(f.stat().st_size for f in files) + 200e6) / 2**20  # the bound
    run = subprocess.run([sys.executable, "-m", "tests.hostile_files", "--inspect", *map(str, files)], cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    lines = [json.loads(x) for x in run.stdout.splitlines()]
    assert run.returncode == 0 and len(lines) == len(files), run.stderr[-2000:]
    # The peak only grows: the last line's added memory bounds the inspection of every file.
    assert lines[-1]["added_mib"] <= bound_mib, lines
    assert all(x["outcome"].startswith("422") for x in lines), lines


def test_a_gltf_with_only_joints_0_and_weights_0_uploads(client, admin, data, settings, tmp_path):
    """The usual export (four influences per vertex).  The reader's fix is issue 24's (h24); until it is merged
    this fails (before: a 500, AttributeError: 'Attributes' object has no attribute 'JOINTS_1'; on this branch the
    glTF reader reports it as a GltfError, 422)."""
    from anim_core.io.bvh import read_bvh
    from anim_core.io.gltf import GltfAnimation, write_gltf
    from anim_core.rig.character import retarget
    from server.assets import character as load_character

    character = load_character(data)
    bvh = read_bvh(data / "mocap" / "cmu" / "02_01_walk.bvh.gz")
    rt = retarget(character, bvh.posed_skeleton(), bvh.end_sites)
    rot, root = bvh.pose_arrays()
    rot, root = rot[1:31], root[1:31] * rt.root_scale
    weights = rt.mesh.weights.copy()
    weights[:, 4:] = 0.0  # four influences, as exporters write them
    path = tmp_path / "walk.gltf"
    write_gltf(path, rt.skeleton, rt.mesh.vertices, rt.mesh.normals, rt.faces, rt.mesh.joints, weights,
               rt.mesh.inverse_bind, (GltfAnimation("walk", np.arange(len(rot)) * bvh.frame_time, rot, root),))
    doc = json.loads(path.read_text())
    for prim in doc["meshes"][0]["primitives"]:
        del prim["attributes"]["JOINTS_1"], prim["attributes"]["WEIGHTS_1"]
    path.write_text(json.dumps(doc))
    r = upload(client, admin, path.read_bytes(), "walk.gltf")
    assert r.status_code == 201, r.text[:500]
    assert r.json()["report"]["frames"] == 30




def test_the_build_job_runs_under_a_memory_ceiling(tmp_path, data, engine):
    """The job's process caps its address space at ``ANIMSTUDY_BUILD_MEMORY_MB`` (passed on by the server): an
    allocation beyond it is a MemoryError (which the job stores as its error), not the server's memory."""
    from server.jobs.control import job_environment

    settings = Settings(var_dir=tmp_path / "var", data_dir=data, build_memory_mb=1024)
    env = job_environment(settings, engine)
    assert env["ANIMSTUDY_BUILD_MEMORY_MB"] == "1024"
    code = ("import numpy as np\nfrom server.config import Settings\nfrom server.jobs.runner import limit_memory\n"
            "limit_memory(Settings().build_memory_mb)\nnp.ones(10**7)\nprint('small ok', flush=True)\n"
            "try:\n    np.ones(2 * 10**8)\nexcept MemoryError:\n    print('MemoryError')\n")
    run = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert run.stdout.split() == ["small", "ok", "MemoryError"], (run.stdout, run.stderr[-1000:])
