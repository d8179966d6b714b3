"""Study archives: a study exported with its pinned stimulus set and videos is recreated on a second, empty
database and var directory with the same comparisons and the same video hashes, and takes votes there; a
truncated, altered or newer archive is refused with nothing imported; a second import is a conflict."""

from __future__ import annotations

import hashlib
import io
import json
import zipfile

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from server import cli
from server.app import create_app
from server.config import Settings
from server.research.export import export_rows
from server.studies import service
from server.studies.archive import ArchiveError, export_archive, import_archive
from server.studies.models import Study
from tests.conftest import DATABASES
from tests.server_fixtures import answer_all, start, study_file, write_fake_media


def shown(study: Study, media_dir) -> list[tuple]:
    """What each comparison shows, by content: kind, animation, conditions, and the sha256 of both side orders."""
    def sha(name: str) -> str:
        return hashlib.sha256((media_dir / name).read_bytes()).hexdigest()

    return [(c.kind, c.reference.animation, c.reference.condition, c.test.condition, sha(c.video_reference_left),
             sha(c.video_reference_right)) for c in study.comparisons]


@pytest.fixture
def archived(db, tmp_path):
    """An open study with votes on server 1 (the test database), and its archive."""
    media = tmp_path / "server1" / "media"
    write_fake_media(media)
    study = service.create_study(db, service.RenderManifest.model_validate_json(
        (media / "manifest.json").read_text()), study_file(slug="rerun"), media_dir=media)
    service.open_study(db, study, media)
    path = export_archive(study, media, tmp_path / "rerun.animstudy.zip")
    return study, media, path


@pytest.fixture(params=DATABASES)
def second(request, tmp_path, migrated_copy):
    """Server 2: an empty database and var directory."""
    engine = migrated_copy(request.param, "test_animstudy_archive")
    settings = Settings(var_dir=tmp_path / "server2", secret_key="archive-test-secret-0123456789abcdef")
    yield engine, settings
    engine.dispose()


def test_round_trip_onto_an_empty_server(archived, second):
    study, media, path = archived
    engine, settings = second
    with Session(engine, expire_on_commit=False) as db:
        imported = import_archive(db, path, settings.media_dir)
        assert imported.stimulus_set.digest == study.stimulus_set.digest
        assert imported.stimulus_set.content == study.stimulus_set.content
        assert shown(imported, settings.media_dir) == shown(study, media)
        assert service.definition(imported) == service.definition(study)
        service.open_study(db, imported, settings.media_dir)
    with TestClient(create_app(settings, engine, run_migrations=False)) as client:
        sid, headers = start(client, "rerun")
        trials = answer_all(client, sid, headers)
        for t in trials:
            assert client.get(t["video_url"]).status_code == 200
    with Session(engine) as db:
        rows = list(export_rows(db, service.get_study(db, "rerun")))
    assert len(rows) == len(trials) == 16
    assert {r["stimulus_set"] for r in rows} == {study.stimulus_set.digest}
    hashes = {sha for c in shown(study, media) for sha in c[4:]}
    assert {r["pair_video"] for r in rows} <= hashes


def test_the_command_line_round_trip(archived, tmp_path, monkeypatch, capsys):
    _, _, path = archived
    monkeypatch.setenv("ANIMSTUDY_VAR_DIR", str(tmp_path / "cli"))
    monkeypatch.setenv("ANIMSTUDY_SECRET_KEY", "archive-cli-secret-0123456789abcdef0")
    monkeypatch.delenv("ANIMSTUDY_DATABASE_URL", raising=False)
    monkeypatch.delenv("DATABASE_URL", raising=False)
    assert cli.main(["study", "import-archive", str(path), "--open"]) == 0
    assert "imported study 'rerun' (open)" in capsys.readouterr().out
    again = tmp_path / "again.zip"
    assert cli.main(["study", "export-archive", "rerun", "--out", str(again)]) == 0
    assert cli.main(["study", "import-archive", str(again)]) == 2  # a second import: a conflict
    assert "exists already" in capsys.readouterr().err


def rewrite(path, out, change):
    """A copy of the archive ``path`` with ``change(name, data) -> data`` applied to each member."""
    with zipfile.ZipFile(path) as z, zipfile.ZipFile(out, "w") as w:
        for name in z.namelist():
            w.writestr(name, change(name, z.read(name)))
    return out


def altered_member(name: str, data: bytes) -> bytes:
    """One byte more in every video: a well-formed ZIP whose files are not the set's."""
    return data + b"!" if name.endswith(".mp4") else data


def newer(name: str, data: bytes) -> bytes:
    if name != "archive.json":
        return data
    index = json.loads(data)
    index["version"] += 1
    return json.dumps(index).encode()


def other_set(name: str, data: bytes) -> bytes:
    if name != "archive.json":
        return data
    index = json.loads(data)
    index["stimulus_set"]["content"]["clips"][0]["metrics"] = {"foot_skate_ratio": 0.0}
    return json.dumps(index).encode()


@pytest.mark.parametrize(("fault", "message"), [
    ("truncated", "truncated or not a ZIP"),
    ("flipped", "damaged"),
    ("altered file", "other bytes than its stimulus set records"),
    ("altered set", "does not match its digest"),
    ("newer", "made by a newer animstudy"),
])
def test_a_bad_archive_is_refused_and_nothing_is_imported(archived, second, tmp_path, fault, message):
    _, _, path = archived
    engine, settings = second
    raw = path.read_bytes()
    bad = tmp_path / "bad.zip"
    if fault == "truncated":
        bad.write_bytes(raw[: len(raw) * 2 // 3])
    elif fault == "flipped":  # one byte of a stored video changed in place: its CRC no longer matches
        at = raw.index(b"stand-in for") + 3
        bad.write_bytes(raw[:at] + bytes([raw[at] ^ 1]) + raw[at + 1:])
    elif fault == "altered file":
        rewrite(path, bad, altered_member)
    elif fault == "altered set":
        rewrite(path, bad, other_set)
    else:
        rewrite(path, bad, newer)
    with Session(engine) as db:
        with pytest.raises(ArchiveError, match=message):
            import_archive(db, bad, settings.media_dir)
        assert db.scalar(select(func.count(Study.id))) == 0
    assert not settings.media_dir.exists() or not any(settings.media_dir.iterdir())


def test_a_second_import_is_a_conflict(archived, second):
    _, _, path = archived
    engine, settings = second
    with Session(engine) as db:
        import_archive(db, path, settings.media_dir)
        files = sorted(p.name for p in settings.media_dir.iterdir())
        with pytest.raises(service.Conflict, match="exists already"):
            import_archive(db, path, settings.media_dir)
        assert db.scalar(select(func.count(Study.id))) == 1
    assert sorted(p.name for p in settings.media_dir.iterdir()) == files


def test_an_incomplete_set_is_not_archived(db, tmp_path):
    media = tmp_path / "media"
    write_fake_media(media)
    manifest = service.RenderManifest.model_validate_json((media / "manifest.json").read_text())
    study = service.create_study(db, manifest, study_file(slug="holes"), media_dir=media)
    (media / study.comparisons[0].video_reference_left).unlink()
    with pytest.raises(service.Conflict, match="incomplete"):
        export_archive(study, media, tmp_path / "holes.zip")
    assert not (tmp_path / "holes.zip").exists()


def test_archive_is_one_zip_with_the_index_and_every_file(archived):
    study, _, path = archived
    with zipfile.ZipFile(io.BytesIO(path.read_bytes())) as z:
        names = set(z.namelist())
        index = json.loads(z.read("archive.json"))
    assert index["format"] == "animstudy-study-archive" and index["version"] == 1
    assert names == {"archive.json", *(f"media/{n}" for n in
                                       service.stimulus_sets.content_of(study.stimulus_set).hashes())}
