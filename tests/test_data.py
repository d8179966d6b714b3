"""The sample data shipped in data/: complete, unchanged, and enough on its own for the default clip set."""

from __future__ import annotations

import gzip
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from server import assets
from tests.conftest import REPO

SHIPPED = REPO / "data"


def test_every_checksummed_file_ships_unchanged():
    for name, expected in assets.CHECKSUMS.items():
        path = assets.verify(SHIPPED, name)  # raises AssetError, naming the file, on any difference
        assert path == SHIPPED / name, f"{name} must ship as {SHIPPED / name}"
        assert expected  # every shipped file is checked, none is listed without a checksum
    readmes = [SHIPPED / "README.md", SHIPPED / "mocap/cmu/README.md", SHIPPED / "character/makehuman_cmu_mb/README.md"]
    assert all(p.is_file() for p in readmes)
    assert "CC0 1.0 Universal" in (SHIPPED / "character/makehuman_cmu_mb/LICENSE-CC0-1.0.md").read_text()
    assert "NSF EIA-0196217" in readmes[1].read_text()


def test_nothing_but_the_sample_set_and_its_documents_ships():
    shipped = {p.relative_to(SHIPPED).as_posix() for p in SHIPPED.rglob("*") if p.is_file()}
    documents = {p for p in shipped if p.endswith(".md")}
    assert shipped - documents == set(assets.CHECKSUMS)


@pytest.fixture
def data_copy(tmp_path: Path) -> Path:
    return Path(shutil.copytree(SHIPPED, tmp_path / "data"))


def test_a_changed_byte_in_a_plain_file_is_reported_by_name(data_copy: Path):
    name = "character/makehuman_cmu_mb/rig.cmu_mb.json"
    path = data_copy / name
    raw = bytearray(path.read_bytes())
    raw[1000] ^= 0x01
    path.write_bytes(bytes(raw))
    with pytest.raises(assets.AssetError, match=r"rig\.cmu_mb\.json is corrupt or a different version"):
        assets.verify(data_copy, name)


def test_a_changed_byte_in_compressed_content_is_reported_by_name(data_copy: Path):
    name = "mocap/cmu/12_03_walk.bvh.gz"
    path = data_copy / name
    text = bytearray(gzip.decompress(path.read_bytes()))
    at = text.index(b"MOTION") + 400  # a digit of a channel value: still a valid BVH, a different motion
    text[at] = ord("7") if text[at] != ord("7") else ord("3")
    path.write_bytes(gzip.compress(bytes(text)))
    with pytest.raises(assets.AssetError, match=r"12_03_walk\.bvh\.gz is corrupt or a different version"):
        assets.verify(data_copy, name)


def test_a_damaged_archive_is_reported_by_name(data_copy: Path):
    name = "character/makehuman_cmu_mb/base.obj.gz"
    path = data_copy / name
    raw = bytearray(path.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    path.write_bytes(bytes(raw))
    with pytest.raises(assets.AssetError, match=r"base\.obj\.gz"):
        assets.verify(data_copy, name)


def test_a_missing_file_is_reported_by_name(data_copy: Path):
    (data_copy / "mocap/cmu/09_11_run.bvh.gz").unlink()
    with pytest.raises(assets.AssetError, match=r"missing file .*09_11_run\.bvh\.gz"):
        assets.verify(data_copy, "mocap/cmu/09_11_run.bvh.gz")


def test_a_copy_of_the_checkout_builds_the_default_clip_set_from_its_own_data(tmp_path: Path):
    """No ANIMSTUDY_DATA_DIR and nothing beside the copy: the default data directory is the shipped folder."""
    checkout = tmp_path / "checkout"
    checkout.mkdir()
    for name in ("anim_core", "server", "migrations", "data", "pyproject.toml"):
        source = REPO / name
        if source.is_dir():
            shutil.copytree(source, checkout / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(source, checkout / name)
    assert not (tmp_path / "shared").exists()
    env = {k: v for k, v in os.environ.items() if k != "ANIMSTUDY_DATA_DIR"}
    env["ANIMSTUDY_VAR_DIR"] = str(tmp_path / "var")
    # `python -m` puts the copy first on sys.path, ahead of the editable install of this checkout.
    proc = subprocess.run(
        [sys.executable, "-c",
         "import server.cli, anim_core, sys; print(anim_core.__file__); sys.exit(server.cli.main(sys.argv[1:]))",
         "clips", "build", "--out", str(tmp_path / "clips")],
        cwd=checkout, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.splitlines()[0].startswith(str(checkout)), "the copy's own code must run"
    manifest = json.loads((tmp_path / "clips" / "manifest.json").read_text())
    assert len(manifest["clips"]) == 16
    assert {c["animation"] for c in manifest["clips"]} == {"walk", "run", "crouch", "idle"}
