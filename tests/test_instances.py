"""Two real ``animstudy serve`` processes (uvicorn) on one database behave as one: the session limit and the login
throttle are counted once across both, and votes sent to both at once are stored exactly once.

PostgreSQL when TEST_DATABASE_URL is set (the deployment), and one SQLite file (several workers on one machine).
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import pytest
from sqlalchemy import func, make_url, select

from server.db import migrate, session_factory
from server.participants.models import Trial, Vote
from server.researchers.service import create_researcher
from tests.conftest import DATABASES, _fresh_engine
from tests.server_fixtures import RESEARCHER, make_study, write_fake_media

ANIMSTUDY = Path(sys.executable).with_name("animstudy")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _serve(env: dict[str, str], log: Path) -> tuple[subprocess.Popen, str]:
    port = _free_port()
    proc = subprocess.Popen([str(ANIMSTUDY), "serve", "--host", "127.0.0.1", "--port", str(port)], env=env,
                            stdout=log.open("wb"), stderr=subprocess.STDOUT)
    return proc, f"http://127.0.0.1:{port}"


def _wait(proc: subprocess.Popen, base: str, log: Path) -> None:
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            pytest.fail(f"animstudy serve exited with {proc.returncode}: {log.read_text()[-2000:]}")
        try:
            if httpx.get(f"{base}/healthz", timeout=1, verify=False).status_code == 200:  # plain HTTP: no CA bundle
                return
        except httpx.HTTPError:
            time.sleep(0.2)
    proc.kill()
    pytest.fail(f"animstudy serve did not answer within 60 s: {log.read_text()[-2000:]}")


@pytest.fixture(params=DATABASES)
def two_instances(request, tmp_path_factory, tmp_path) -> Iterator[tuple[list[str], object]]:
    """Two ``animstudy serve`` instances (separate processes, separate var directories as on two machines; one
    database and one secret key) over the open thesis study."""
    database = None
    if request.param == "postgresql":  # a database of its own beside TEST_DATABASE_URL's
        database = f"{make_url(os.environ['TEST_DATABASE_URL']).database}_instances"
    engine = _fresh_engine(request.param, tmp_path_factory, database=database)
    migrate(engine)
    factory = session_factory(engine)
    media_dirs = [tmp_path / f"var{i}" / "media" for i in (1, 2)]
    for media_dir in media_dirs:  # the same stimulus store on both (here: a copy of the same files)
        write_fake_media(media_dir)
    with factory() as db:
        make_study(db, media_dir=media_dirs[0])
        create_researcher(db, *RESEARCHER)
        db.commit()
    url = engine.url.render_as_string(hide_password=False)
    procs, bases = [], []
    try:
        for i in (1, 2):
            # PYTHONPATH: the instances run this checkout's code (the one that migrated the database above).
            env = {**os.environ, "DATABASE_URL": url, "ANIMSTUDY_VAR_DIR": str(tmp_path / f"var{i}"),
                   "ANIMSTUDY_SECRET_KEY": "two-instances-secret-0123456789abcdef01",
                   "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
            env.pop("ANIMSTUDY_SESSIONS_PER_MINUTE", None)
            proc, base = _serve(env, tmp_path / f"serve{i}.log")  # both start at once (the schema is current)
            procs.append(proc)
            bases.append(base)
        for i, (proc, base) in enumerate(zip(procs, bases, strict=True), 1):
            _wait(proc, base, tmp_path / f"serve{i}.log")
        yield bases, factory
    finally:
        for proc in procs:
            proc.terminate()
        for proc in procs:
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
        engine.dispose()


@pytest.mark.slow  # tens of seconds (the parallel run's slowest; still run by `make test`)
def test_two_instances_count_limits_once_and_store_votes_once(two_instances):
    bases, factory = two_instances
    clients = [httpx.Client(base_url=b, timeout=30, verify=False) for b in bases]

    def new_session(i: int) -> httpx.Response:
        return clients[i % 2].post("/api/v1/studies/thesis/sessions", json={"consent": True})

    # Mixed load: six participants, each trial's vote sent to both instances at once (same idempotency key,
    # twice each) together with a conflicting answer under another key, while the others do the same.
    participants = []
    for i in range(6):
        r = new_session(i)
        assert r.status_code == 201, r.text
        participants.append((r.json()["session_id"], {"Authorization": f"Bearer {r.json()['token']}"}))

    def answer(i: int) -> list[int]:
        sid, headers = participants[i]
        codes = []
        with httpx.Client(timeout=30, verify=False) as c:
            for step in range(4):
                trial = c.get(f"{bases[step % 2]}/api/v1/sessions/{sid}/next", headers=headers).json()["trial_id"]
                path = f"/api/v1/sessions/{sid}/trials/{trial}/vote"
                same = {"choice": "left_much", "rt_ms": 800, "idempotency_key": f"k{trial}"}
                other = {"choice": "right_much", "rt_ms": 800, "idempotency_key": f"x{trial}"}
                sends = [(bases[i], path, body) for i, body in ((0, same), (1, same), (0, same), (1, same),
                                                               (step % 2, other))]
                with ThreadPoolExecutor(5) as pool:
                    codes += pool.map(lambda s: c.post(s[0] + s[1], json=s[2], headers=headers).status_code, sends)
        return codes

    with ThreadPoolExecutor(6) as pool:
        codes = [c for cs in pool.map(answer, range(6)) for c in cs]
    assert set(codes) <= {200, 201, 409}, codes
    assert codes.count(201) == 6 * 4, codes  # one stored vote per trial, whichever answer came first
    with factory() as db:
        sids = [sid for sid, _ in participants]
        votes = db.scalar(select(func.count(Vote.id)).join(Trial, Vote.trial_id == Trial.id)
                          .where(Trial.session_id.in_(sids)))
        voted_trials = db.scalar(select(func.count(func.distinct(Vote.trial_id))).join(
            Trial, Vote.trial_id == Trial.id).where(Trial.session_id.in_(sids)))
    assert votes == voted_trials == 6 * 4

    # The session limit (60 a minute per address) across both instances: 54 more are let in, the 61st is not,
    # whichever instance it reaches.
    more = [new_session(i).status_code for i in range(54)]
    assert more == [201] * 54
    for i in (0, 1):
        refused = new_session(i)
        assert refused.status_code == 429, refused.text
        assert 1 <= int(refused.headers["retry-after"]) <= 60

    # The login throttle (10 failures per address and account) across both instances.
    codes = [clients[i % 2].post("/api/v1/auth/token", data={"username": RESEARCHER[0], "password": f"guess {i}"})
             .status_code for i in range(12)]
    assert codes == [401] * 10 + [429, 429]
    for c in clients:
        c.close()
