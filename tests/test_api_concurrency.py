"""Exactly-once votes under real concurrency: a live server on loopback, many simultaneous requests."""

import threading
from concurrent.futures import ThreadPoolExecutor

import httpx
import pytest
from sqlalchemy import func, select

from server.app import create_app
from server.config import Settings
from server.db import migrate, session_factory
from server.participants import service
from server.participants.models import ParticipantSession, Vote
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
    with httpx.Client(base_url=base, timeout=30, verify=False) as client:  # plain HTTP: no CA bundle to load
        s = client.post("/api/v1/studies/thesis/sessions", json={"consent": True}).json()
        headers = {"Authorization": f"Bearer {s['token']}"}
        url = f"/api/v1/sessions/{s['session_id']}"
        trial = client.get(f"{url}/next", headers=headers).json()["trial_id"]
        body = {"choice": "left_much", "rt_ms": 900, "idempotency_key": "same"}

        def post(b: dict) -> int:
            with httpx.Client(base_url=base, timeout=30, verify=False) as c:
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


@pytest.mark.parametrize("kind", DATABASES)
def test_a_withdrawal_waits_for_a_vote_in_flight_and_deletes_it_too(kind, tmp_path_factory):
    """A vote request has begun (session authorized) when the same participant withdraws from another tab: the
    withdrawal must wait for the vote and then delete it — never leave an answer of a withdrawn participant."""
    engine = _fresh_engine(kind, tmp_path_factory, database="test_animstudy_race")
    migrate(engine)
    factory = session_factory(engine)
    with factory() as db:
        new = service.start_session(db, make_study(db), None)
        sid, token = new.session.id, new.token
        first = service.upcoming(db, new.session)[0].id
    voter = factory()
    ps, trial = service.authorize_answer(voter, sid, token, first)  # as the vote request does
    done, errors = threading.Event(), []

    def withdraw() -> None:
        try:
            with factory() as db:
                service.withdraw(db, service.authorize(db, sid, token, lock="update"))
        except Exception as e:  # handed to the test
            errors.append(e)
        done.set()

    thread = threading.Thread(target=withdraw)
    thread.start()
    assert not done.wait(0.5), "the withdrawal did not wait for the vote in flight"
    assert service.cast_vote(voter, ps, trial, "equal", 900, "k", {}).created
    voter.close()
    assert done.wait(10)
    thread.join()
    assert errors == []
    with factory() as db:
        assert db.scalar(select(func.count(Vote.id)).where(Vote.session_id == sid)) == 0
        assert db.get(ParticipantSession, sid).state == "withdrawn"
    engine.dispose()
