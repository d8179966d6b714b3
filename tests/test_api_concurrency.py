"""Exactly-once votes under real concurrency: a live server on loopback, many simultaneous requests."""

from concurrent.futures import ThreadPoolExecutor

import httpx
import pytest
from sqlalchemy import func, select

from server.app import create_app
from server.config import Settings
from server.db import migrate, session_factory
from server.participants.models import Vote
from tests.conftest import DATABASES, _fresh_engine
from tests.server_fixtures import live_server, make_study


@pytest.fixture(params=DATABASES)
def live(request, tmp_path_factory, tmp_path):
    engine = _fresh_engine(request.param, tmp_path_factory, database="test_animstudy_live")
    migrate(engine)
    factory = session_factory(engine)
    with factory() as db:
        make_study(db)
    app = create_app(Settings(var_dir=tmp_path / "var", secret_key="live-test-secret-0123456789abcdef012"), engine,
                     run_migrations=False)
    with live_server(app) as base:
        yield base, factory
    engine.dispose()


def test_simultaneous_identical_and_conflicting_votes(live):
    base, factory = live
    with httpx.Client(base_url=base, timeout=30) as client:
        s = client.post("/api/v1/studies/thesis/sessions", json={"consent": True}).json()
        headers = {"Authorization": f"Bearer {s['token']}"}
        url = f"/api/v1/sessions/{s['session_id']}"
        trial = client.get(f"{url}/next", headers=headers).json()["trial_id"]
        body = {"choice": "left_much", "rt_ms": 900, "idempotency_key": "same"}

        def post(b: dict) -> int:
            with httpx.Client(base_url=base, timeout=30) as c:
                return c.post(f"{url}/trials/{trial}/vote", json=b, headers=headers).status_code

        with ThreadPoolExecutor(8) as pool:
            codes = list(pool.map(post, [body] * 16))
        assert sorted(codes) == [200] * 15 + [201], codes
        # The next trial: sixteen different answers at once; exactly one wins.
        trial = client.get(f"{url}/next", headers=headers).json()["trial_id"]
        choices = ["left_much", "left_slightly", "equal", "right_slightly", "right_much"]
        bodies = [{"choice": choices[i % 5], "rt_ms": i, "idempotency_key": f"k{i}"} for i in range(16)]
        with ThreadPoolExecutor(8) as pool:
            codes = list(pool.map(post, bodies))
        assert codes.count(201) == 1 and set(codes) <= {201, 409}, codes
    with factory() as db:
        assert db.scalar(select(func.count(Vote.id)).where(Vote.session_id == s["session_id"])) == 2
