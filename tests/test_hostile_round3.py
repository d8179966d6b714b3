"""Hostile input, round three (issue 36, findings 5, 6, 7, 8, 11, 13, 15, 16 and the command line's inspect bomb):
huge numbers, archive bombs and malformed archives, names with a trailing newline, the login throttle under real
concurrency, the local Dask cluster's TLS, invisible characters before a formula, passwords on the command line,
HSTS and the API documentation, and a BVH bomb given to ``animstudy clips inspect``."""

from __future__ import annotations

import csv
import hashlib
import io
import json
import zipfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from server import cli
from server.stimuli.service import content_digest
from server.studies.archive import ArchiveError, import_archive
from server.studies.models import Study
from tests import test_study_archive
from tests.conftest import DATABASES
from tests.server_fixtures import make_study, start

# The archive fixtures: an archived study with votes, and a second, empty server.
archived = test_study_archive.archived
second = test_study_archive.second

# --- 5: a number answer of 309 digits -------------------------------------------------------------------------

NUMBER = [{"id": "age", "text": "Your age?", "type": "number"}]


@pytest.mark.parametrize("value", [10**309, -(10**309), 2**53, 10**20])
def test_a_huge_whole_number_answer_is_a_422_not_a_500(client, db, value):
    make_study(db, questions=NUMBER)
    sid, headers = start(client)
    r = client.put(f"/api/v1/sessions/{sid}/demographics", json={"age": value}, headers=headers)
    assert r.status_code == 422, r.text[:300]
    assert r.json()["detail"][0]["loc"][-1] == "age" and "Input should be a number between" in r.text
    assert client.put(f"/api/v1/sessions/{sid}/demographics", json={"age": 2**53 - 1},
                      headers=headers).status_code == 200


# --- 6 and 7: archives ----------------------------------------------------------------------------------------

def forge(path: Path, out: Path, index_change=None, extra: dict[str, bytes] | None = None,
          compression: int = zipfile.ZIP_STORED, replace: dict[str, bytes] | None = None) -> Path:
    """A copy of the archive ``path`` whose index went through ``index_change(index)`` (the set's digest made
    right again, so only the limits and checks under test refuse it), with members added or replaced."""
    with zipfile.ZipFile(path) as z:
        members = {name: z.read(name) for name in z.namelist()}
    if index_change is not None:
        index = json.loads(members["archive.json"])
        index_change(index)
        content = index["stimulus_set"].get("content") if isinstance(index["stimulus_set"], dict) else None
        if isinstance(content, dict):
            index["stimulus_set"]["digest"] = content_digest(content)
        members["archive.json"] = json.dumps(index).encode()
    members.update(replace or {})
    with zipfile.ZipFile(out, "w", compression=compression) as w:
        for name, data in {**members, **(extra or {})}.items():
            w.writestr(name, data)
    return out


def nothing_imported(engine, settings) -> None:
    with Session(engine) as db:
        assert db.scalar(select(func.count(Study.id))) == 0
    media = settings.media_dir
    assert not media.exists() or not any(media.iterdir()), sorted(p.name for p in media.iterdir())


def swap_first_video(index: dict, data: bytes) -> str:
    """Make the set's first clip video the file ``data`` (its sha256 recorded): returns its member name."""
    clip = index["stimulus_set"]["content"]["clips"][0]
    clip["video_sha256"] = hashlib.sha256(data).hexdigest()
    return f"media/{clip['video']}"


def test_a_compressed_bomb_member_is_refused_before_it_is_read(archived, second, tmp_path):
    """A member that inflates 1000-fold (issue: 1.66 MB took 2,232 MiB and wrote 1 GiB into media): refused from
    the ZIP directory, before reading it, whatever the sha256 the set records."""
    _, _, path = archived
    engine, settings = second
    bomb = b"\0" * (64 * 2**20)
    names = {}

    def change(index):
        names["member"] = swap_first_video(index, bomb)

    forged = forge(path, tmp_path / "x.zip", change)
    forged = forge(forged, tmp_path / "bomb.zip", compression=zipfile.ZIP_DEFLATED,
                   replace={names["member"]: bomb})
    assert forged.stat().st_size < 2**20
    with Session(engine) as db, pytest.raises(ArchiveError, match="compress"):
        import_archive(db, forged, settings.media_dir)
    nothing_imported(engine, settings)


def test_members_over_the_size_limits_are_refused(archived, second, tmp_path):
    from server.studies.archive import ArchiveLimits

    _, _, path = archived
    engine, settings = second
    with Session(engine) as db:
        with pytest.raises(ArchiveError, match="larger than the 1000 bytes"):
            import_archive(db, path, settings.media_dir, limits=ArchiveLimits(member_bytes=1000))
        with pytest.raises(ArchiveError, match="in all"):
            import_archive(db, path, settings.media_dir, limits=ArchiveLimits(total_bytes=5000))
        with pytest.raises(ArchiveError, match=r"archive\.json of"):
            import_archive(db, path, settings.media_dir, limits=ArchiveLimits(index_bytes=100))
    nothing_imported(engine, settings)


def test_a_huge_index_is_refused_unread(archived, second, tmp_path):
    _, _, path = archived
    engine, settings = second
    forged = forge(path, tmp_path / "big.zip", lambda index: index.update(padding="x" * (40 * 2**20)))
    with Session(engine) as db, pytest.raises(ArchiveError, match=r"archive\.json of"):
        import_archive(db, forged, settings.media_dir)
    nothing_imported(engine, settings)


def test_junk_members_are_refused(archived, second, tmp_path):
    _, _, path = archived
    engine, settings = second
    many = forge(path, tmp_path / "many.zip", extra={f"junk/{i}": b"" for i in range(20_001)})
    one = forge(path, tmp_path / "one.zip", extra={"media/../../evil": b"x"})
    with Session(engine) as db:
        with pytest.raises(ArchiveError, match="members"):
            import_archive(db, many, settings.media_dir)
        with pytest.raises(ArchiveError, match="not part of a study archive"):
            import_archive(db, one, settings.media_dir)
    nothing_imported(engine, settings)


def set_as_list(index):
    index["stimulus_set"] = [index["stimulus_set"]]


def unknown_pair_clip(index):
    index["stimulus_set"]["content"]["pairs"][0]["left"] = "nobody-hybrid9"


def no_clips(index):
    index["stimulus_set"]["content"]["clips"] = []


@pytest.mark.parametrize(("fault", "message"), [
    ("deep", "nested too deeply"),
    ("set as a list", "stimulus_set"),
    ("unknown pair clip", "nobody-hybrid9"),
    ("no clips", "no clips"),
    ("method 99", "compression method 99"),
])
def test_malformed_archives_are_one_clear_error_from_the_command_line(archived, tmp_path, monkeypatch, capsys,
                                                                      fault, message):
    _, _, path = archived
    bad = tmp_path / "bad.zip"
    if fault == "deep":
        forge(path, bad, replace={"archive.json": b"[" * 100_000 + b"]" * 100_000})
    elif fault == "method 99":
        forge(path, bad)
        raw = bytearray(bad.read_bytes())
        with zipfile.ZipFile(bad) as z:
            info = z.getinfo("archive.json")
        # the method field of the local header (offset 8) and of the central directory entry (offset 10)
        raw[info.header_offset + 8: info.header_offset + 10] = (99).to_bytes(2, "little")
        central = raw.rindex(b"PK\x01\x02" + raw[raw.rindex(b"PK\x01\x02") + 4: raw.rindex(b"PK\x01\x02") + 8])
        at = raw.find(b"archive.json", raw.index(b"PK\x01\x02")) - 46
        assert raw[at:at + 4] == b"PK\x01\x02", central
        raw[at + 10: at + 12] = (99).to_bytes(2, "little")
        bad.write_bytes(bytes(raw))
    else:
        forge(path, bad, {"set as a list": set_as_list, "unknown pair clip": unknown_pair_clip,
                          "no clips": no_clips}[fault])
    var = tmp_path / "cli"
    monkeypatch.setenv("ANIMSTUDY_VAR_DIR", str(var))
    monkeypatch.setenv("ANIMSTUDY_SECRET_KEY", "archive-cli-secret-0123456789abcdef0")
    monkeypatch.delenv("ANIMSTUDY_DATABASE_URL", raising=False)
    monkeypatch.delenv("DATABASE_URL", raising=False)
    code = cli.main(["study", "import-archive", str(bad)])
    err = capsys.readouterr().err
    assert code != 0 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err[-2000:]
    assert message in err, err
    media = var / "media"
    assert not media.exists() or not any(media.iterdir())


# --- 8: names with a trailing newline -------------------------------------------------------------------------

def test_a_media_name_with_a_trailing_newline_is_refused_by_the_import(archived, second, tmp_path):
    _, _, path = archived
    engine, settings = second
    renamed = {}

    def change(index):
        clip = index["stimulus_set"]["content"]["clips"][0]
        renamed["old"], renamed["new"] = clip["video"], clip["video"] + "\n"
        clip["video"] = renamed["new"]

    forged = forge(path, tmp_path / "x.zip", change)
    with zipfile.ZipFile(forged) as z:
        data = z.read(f"media/{renamed['old']}")
    forged = forge(forged, tmp_path / "nl.zip", extra={f"media/{renamed['new']}": data})
    with Session(engine) as db, pytest.raises(ArchiveError, match="not a video or poster name"):
        import_archive(db, forged, settings.media_dir)
    nothing_imported(engine, settings)


def test_every_validating_pattern_refuses_a_trailing_newline(client):
    from server.clipset.config import ConfigError, _animation
    from server.errors import Unprocessable
    from server.media.plan import MEDIA_NAME
    from server.participants.schemas import _trial_key
    from server.uploads.service import animation_name, check_filename

    assert MEDIA_NAME.fullmatch("0" * 24 + ".mp4") and not MEDIA_NAME.fullmatch("0" * 24 + ".mp4\n")
    assert client.get("/media/" + "0" * 24 + ".mp4%0A").status_code == 404
    with pytest.raises(Unprocessable):
        check_filename("walk.bvh\n")
    with pytest.raises(Unprocessable):
        animation_name("walk.bvh", "walk\n")
    with pytest.raises(ConfigError):
        _animation("walk\n", {}, "animations")
    with pytest.raises(ValueError):
        _trial_key("1\n")


# --- 15: invisible characters before a formula ----------------------------------------------------------------

@pytest.mark.parametrize("invisible", ["\u200b", "\u200e", "\u200f", "\u2066", "\ufeff", "\u00a0", "\u3000",
                                       "\u200b\u200c\u200d"])
def test_invisible_characters_before_a_formula_do_not_hide_it_from_the_csv_guard(client, db, researcher_headers,
                                                                                 invisible):
    from server.research.export import csv_cell

    text = [{"id": "remarks", "text": "Anything to add?", "type": "text", "max_length": 100}]
    make_study(db, questions=text)
    payload = f"{invisible}=1+1"
    sid, headers = start(client)
    assert client.put(f"/api/v1/sessions/{sid}/demographics", json={"remarks": payload},
                      headers=headers).status_code == 200
    trial = client.get(f"/api/v1/sessions/{sid}/next", headers=headers).json()["trial_id"]
    assert client.post(f"/api/v1/sessions/{sid}/trials/{trial}/vote", headers=headers,
                       json={"choice": "equal", "rt_ms": 900, "idempotency_key": "k"}).status_code == 201
    body = client.get("/api/v1/studies/thesis/export.csv", headers=researcher_headers).text
    row = next(csv.DictReader(io.StringIO(body, newline="")))
    assert row["remarks"] == "'" + payload
    assert csv_cell(f"{invisible}+SUM(A1)") == f"'{invisible}+SUM(A1)"
    assert csv_cell(f"{invisible}plain") == f"{invisible}plain"  # only formulas are prefixed


# --- 11: the login throttle under real concurrency, two instances on one database -----------------------------

@pytest.fixture(params=DATABASES)
def two_instances(request, migrated_copy, tmp_path, production_password_hashes):
    """Two ``serve`` instances (own engines, own apps, live on loopback) on one database, with a researcher; the
    password check at its real cost, which the concurrency tests race against."""
    from server.app import create_app
    from server.config import Settings
    from server.db import make_engine, session_factory
    from server.researchers.service import create_researcher
    from tests.server_fixtures import live_server

    first = migrated_copy(request.param, "test_animstudy_throttle")
    other = make_engine(first.url.render_as_string(hide_password=False))
    with session_factory(first)() as db:
        create_researcher(db, "owner@example.org", "the right password 123")
    settings = Settings(var_dir=tmp_path / "var", secret_key="throttle-test-secret-0123456789abcdef")
    apps = [create_app(settings, engine, run_migrations=False) for engine in (first, other)]
    with live_server(apps[0]) as one, live_server(apps[1]) as two:
        yield apps, [one, two]
    for engine in (first, other):
        engine.dispose()


def guesses(urls: list[str], accounts: list[str]) -> list[int]:
    """One wrong password per account in ``accounts``, all at once (8 in flight), alternating the instances."""
    import httpx

    def post(i: int) -> int:
        with httpx.Client(base_url=urls[i % 2], timeout=60, verify=False) as c:  # plain HTTP: no CA bundle (50 ms)
            return c.post("/api/v1/auth/token", data={"username": accounts[i], "password": f"guess {i}"}).status_code

    with ThreadPoolExecutor(8) as pool:
        return list(pool.map(post, range(len(accounts))))


def test_concurrent_wrong_passwords_are_counted_before_they_are_checked(two_instances):
    from server.security import LoginLimiter

    apps, urls = two_instances
    for app in apps:
        app.state.login_limiter = LoginLimiter(per_pair=3, per_address=1000, account_free=1000)
    codes = guesses(urls, ["owner@example.org"] * 16)
    assert sorted(codes) == [401] * 3 + [429] * 13, f"{codes.count(401)} of 16 guesses checked, limit 3: {codes}"


def test_concurrent_guesses_across_accounts_keep_the_per_address_limit(two_instances):
    from server.security import LoginLimiter

    apps, urls = two_instances
    for app in apps:
        app.state.login_limiter = LoginLimiter(per_pair=1000, per_address=4, account_free=1000)
    codes = guesses(urls, [f"user{i}@example.org" for i in range(16)])
    assert sorted(codes) == [401] * 4 + [429] * 12, f"{codes.count(401)} of 16 guesses checked, limit 4: {codes}"


def test_the_right_password_is_not_counted_as_a_failure(two_instances):
    import httpx

    from server.security import LoginLimiter

    apps, urls = two_instances
    for app in apps:
        app.state.login_limiter = LoginLimiter(per_pair=2, per_address=1000, account_free=1000)
    for i in range(3):  # three right ones in a row: none of them counts against the limit of 2
        r = httpx.post(f"{urls[i % 2]}/api/v1/auth/token",
                       data={"username": "owner@example.org", "password": "the right password 123"})
        assert r.status_code == 200, r.text
    assert sorted(guesses(urls, ["owner@example.org"] * 4)) == [401, 401, 429, 429]


# --- the command line's inspect bomb ---------------------------------------------------------------------------

def test_clips_inspect_refuses_a_bvh_bomb_before_reading_its_frames(data, tmp_path, capsys):
    """969 joints without channels and 10,000 frames in 115 KB: took 2.6 GiB and 16.5 s and exited 0."""
    import time

    from tests.hostile_files import bvh_bomb

    bomb = tmp_path / "bomb.bvh"
    bomb.write_bytes(bvh_bomb(data))
    started = time.perf_counter()
    assert cli.main(["clips", "inspect", str(bomb)]) == 2
    assert time.perf_counter() - started < 5
    err = capsys.readouterr().err
    assert "frame-joints" in err and "--max-frame-joints" in err and len(err.strip().splitlines()) == 1, err
    assert cli.main(["clips", "convert", str(bomb), str(tmp_path / "out.glb")]) == 2
    assert "frame-joints" in capsys.readouterr().err and not (tmp_path / "out.glb").exists()
    # The flag lowers (or raises) the bound; a real recording is read under the default.
    small = tmp_path / "small.bvh"
    small.write_bytes(bvh_bomb(data, extra_joints=0, frames=100))
    assert cli.main(["clips", "inspect", str(small), "--max-frame-joints", "50"]) == 2
    assert "--max-frame-joints" in capsys.readouterr().err
    assert cli.main(["clips", "inspect", str(data / "mocap" / "cmu" / "113_21_idle_30fps.bvh.gz")]) == 0


# --- 16: passwords on the command line, the API's documentation, HSTS -----------------------------------------

def cli_env(monkeypatch, tmp_path) -> None:
    monkeypatch.setenv("ANIMSTUDY_VAR_DIR", str(tmp_path / "cli"))
    monkeypatch.setenv("ANIMSTUDY_SECRET_KEY", "password-cli-secret-0123456789abcdef0")
    monkeypatch.delenv("ANIMSTUDY_DATABASE_URL", raising=False)
    monkeypatch.delenv("DATABASE_URL", raising=False)


def can_log_in(tmp_path, email: str, password: str) -> bool:
    from server.db import make_engine
    from server.errors import Unauthorized
    from server.researchers.service import authenticate

    engine = make_engine(f"sqlite:///{tmp_path / 'cli' / 'animstudy.db'}")
    try:
        with Session(engine) as db:
            authenticate(db, email, password)
        return True
    except Unauthorized:
        return False
    finally:
        engine.dispose()


def test_researcher_create_reads_the_password_from_stdin_and_warns_about_the_argument(monkeypatch, tmp_path, capsys):
    cli_env(monkeypatch, tmp_path)
    monkeypatch.setattr("sys.stdin", io.StringIO("a long secret from stdin\nignored\n"))
    assert cli.main(["researcher", "create", "--email", "a@example.org", "--password-stdin"]) == 0
    assert "warning" not in capsys.readouterr().err
    assert can_log_in(tmp_path, "a@example.org", "a long secret from stdin")
    assert cli.main(["researcher", "create", "--email", "b@example.org", "--password", "visible secret 12"]) == 0
    assert "warning: --password shows the password" in capsys.readouterr().err
    assert can_log_in(tmp_path, "b@example.org", "visible secret 12")
    monkeypatch.setattr("sys.stdin", io.StringIO(""))  # no terminal to prompt on, nothing given
    assert cli.main(["researcher", "create", "--email", "c@example.org"]) == 2
    assert "no password" in capsys.readouterr().err


def test_researcher_create_prompts_without_echo(monkeypatch, tmp_path, capsys):
    cli_env(monkeypatch, tmp_path)
    typed = iter(["typed at the prompt 1", "typed at the prompt 1"])
    monkeypatch.setattr("getpass.getpass", lambda prompt="": next(typed))
    monkeypatch.setattr("sys.stdin.isatty", lambda: True, raising=False)
    assert cli.main(["researcher", "create", "--email", "d@example.org"]) == 0
    assert can_log_in(tmp_path, "d@example.org", "typed at the prompt 1")


@pytest.mark.parametrize("path", ["/docs", "/redoc", "/openapi.json"])
def test_the_api_documentation_is_not_public_unless_configured(db, engine, tmp_path, path):
    from fastapi.testclient import TestClient

    from server.app import create_app
    from server.config import Settings

    def get(**options):
        settings = Settings(var_dir=tmp_path / "var", secret_key="docs-test-secret-0123456789abcdef01", **options)
        with TestClient(create_app(settings, engine, run_migrations=False)) as c:
            return c.get(path)

    assert get().status_code == 404
    assert get(api_docs=True).status_code == 200


def test_hsts_is_sent_over_https_only(db, engine, tmp_path, study):
    from fastapi.testclient import TestClient

    from server.app import create_app
    from server.config import Settings
    from server.deps import get_session

    def app(**options):
        made = create_app(Settings(var_dir=tmp_path / "var", secret_key="hsts-test-secret-0123456789abcdef01",
                                   **options), engine, run_migrations=False)
        made.dependency_overrides[get_session] = lambda: db
        return made

    plain = app()
    with TestClient(plain, base_url="https://testserver") as c:
        responses = (c.get("/api/v1/studies/thesis"), c.get("/nothing-here"),
                     c.post("/api/v1/studies/thesis/sessions", content=b"x" * 70_000))
        assert [r.status_code for r in responses] == [200, 404, 413]
        for r in responses:
            assert r.headers["strict-transport-security"] == "max-age=31536000", (r.status_code, r.headers)
    with TestClient(plain, base_url="http://testserver") as c:
        r = c.get("/api/v1/studies/thesis", headers={"X-Forwarded-Proto": "https"})  # from anyone: ignored
        assert r.status_code == 200 and "strict-transport-security" not in r.headers
    proxied = app(trusted_proxies=["10.0.0.0/8"])
    with TestClient(proxied, base_url="http://testserver", client=("10.0.0.5", 50000)) as c:
        assert c.get("/api/v1/studies/thesis", headers={"X-Forwarded-Proto": "https"}
                     ).headers["strict-transport-security"] == "max-age=31536000"
        assert "strict-transport-security" not in c.get("/api/v1/studies/thesis").headers
    with TestClient(proxied, base_url="http://testserver", client=("203.0.113.5", 50000)) as c:
        assert "strict-transport-security" not in c.get("/api/v1/studies/thesis",
                                                        headers={"X-Forwarded-Proto": "https"}).headers


# --- 13: the local Dask cluster speaks TLS with its own temporary certificate ----------------------------------

INTRUDER = """
import sys
from distributed import Client
from distributed.security import Security
options = {"security": Security.temporary()} if sys.argv[2] == "own-certificate" else {}
client = Client(sys.argv[1], timeout=3, set_as_default=False, **options)
print("RAN", client.run(lambda: 1))
"""


def test_the_local_dask_cluster_admits_only_its_own_clients():
    """Another user of the machine reached the scheduler on 127.0.0.1 and ran code in a worker.  Now the cluster
    speaks TLS and requires the certificate made for it: another process connecting without it, plainly or with a
    certificate of its own (another temporary one), runs nothing; the job's client runs tasks."""
    import subprocess
    import sys

    from server.cluster import dask_client

    with dask_client(None, workers=1) as client:
        address = client.scheduler.address
        assert client.submit(sum, [1, 2, 3]).result(timeout=60) == 6
        attempts = [(address.replace("tls://", "tcp://"), "plain"), (address, "plain"),
                    (address, "own-certificate")]
        intruders = [subprocess.Popen([sys.executable, "-c", INTRUDER, a, how], stdout=subprocess.PIPE,
                                      stderr=subprocess.PIPE, text=True) for a, how in attempts]
        outputs = []
        for intruder in intruders:
            try:
                outputs.append(intruder.communicate(timeout=30)[0])
            except subprocess.TimeoutExpired:  # still waiting for a handshake that never comes: not admitted
                intruder.kill()
                outputs.append(intruder.communicate()[0])
    assert not any("RAN" in out for out in outputs), list(zip(attempts, outputs, strict=True))
    assert address.startswith("tls://127.0.0.1:"), address
