"""Short forms of the fault scenarios (the full load test is `animstudy loadtest`, see docs/reference/load-test.md):
a server killed with SIGKILL mid-load, PostgreSQL stopped mid-load, schema-driven fuzzing, and a targeted fuzz
with what schemas cannot describe (NaN, Infinity, lone surrogates, bytes that are not UTF-8)."""

import json
import os

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from sqlalchemy import make_url

from server import loadtest
from server.app import create_app
from server.config import Settings, normalize_database_url
from server.db import make_engine, migrate, session_factory
from tests.conftest import own_database
from tests.server_fixtures import make_study


def assert_exactly_once(report):
    check = report["check"]
    assert check["acknowledged"] == report["participants"] * 16, report
    assert (check["lost"], check["duplicated"], check["stored_without_acknowledgement"]) == (0, 0, 0), check


def test_sigkill_in_the_middle_loses_and_doubles_nothing():
    report = loadtest.run("sqlite", participants=8, workers=2, concurrency=8, crash_at=0.4, time_limit=120,
                          progress=lambda _m: None)
    print(loadtest.format_report(report))
    assert report["events"][:1] and report["events"][0].startswith("SIGKILL") and "restarted" in report["events"][1]
    assert_exactly_once(report)


if os.environ.get("TEST_DATABASE_URL"):  # a PostgreSQL scenario: defined only where PostgreSQL is configured

    # Serial: it stops the whole PostgreSQL server (pg_ctlcluster), which would fail every other worker's database
    # tests of a parallel run; `make test` runs it alone after the parallel step.
    @pytest.mark.serial
    def test_postgresql_outage_answers_503_and_loses_nothing():
        url = make_url(normalize_database_url(os.environ["TEST_DATABASE_URL"]))
        url = url.set(database=own_database(url, "test_animstudy_load"))
        report = loadtest.run("postgresql", participants=8, workers=2, concurrency=8, outage_at=0.3, outage_s=3,
                              time_limit=120, pg_url=url.render_as_string(hide_password=False),
                              progress=lambda _m: None)
        print(loadtest.format_report(report))
        assert any(e.startswith("PostgreSQL stopped") for e in report["events"])
        assert any(k.endswith(" 503") for k in report["statuses"]), report["statuses"]  # not 500, not a hang
        assert not any(k.endswith(" 500") for k in report["statuses"]), report["statuses"]
        assert_exactly_once(report)


def test_fuzzed_requests_never_get_a_server_error(tmp_path):
    """Schema-driven fuzzing (schemathesis + hypothesis) of every operation of the served OpenAPI schema."""
    engine = make_engine(f"sqlite:///{tmp_path / 'fuzz.db'}")
    migrate(engine)
    with session_factory(engine)() as db:
        make_study(db)
    app = create_app(Settings(var_dir=tmp_path, secret_key="fuzz-secret-0123456789abcdef0123456789",
                              api_docs=True), engine, run_migrations=False)
    schema = schemathesis.openapi.from_asgi("/openapi.json", app)
    operations = [result.ok() for result in schema.get_all_operations()]
    assert len(operations) >= 12
    seen = []
    for operation in operations:

        @given(case=operation.as_strategy())
        @settings(max_examples=25, deadline=None, suppress_health_check=list(HealthCheck), database=None)
        def call(case):
            response = case.call()
            seen.append(response.status_code)
            assert response.status_code < 500, (case.method, case.formatted_path, response.status_code,
                                                response.text)

        call()
    print(f"{len(seen)} fuzzed requests over {len(operations)} operations")
    assert len(seen) > 100


# Values no JSON schema describes but Python's json module accepts: non-finite numbers, lone surrogates.
_SURROGATE = st.integers(0xD800, 0xDFFF).map(chr)
_TEXT = st.lists(st.one_of(st.characters(), _SURROGATE), max_size=12).map("".join)
_SCALAR = st.one_of(st.sampled_from([float("nan"), float("inf"), float("-inf")]), st.floats(), st.integers(),
                    st.booleans(), st.none(), _TEXT, st.sampled_from(["equal", "yes", "error", "true"]))
_VALUE = st.recursive(_SCALAR, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                       st.dictionaries(_TEXT, inner, max_size=4)), max_leaves=12)
_FIELDS = ["consent", "external", "gamer", "tech_savvy", "choice", "rt_ms", "idempotency_key", "kind", "trial_id",
           "detail"]


def test_fuzzed_non_finite_numbers_and_invalid_unicode_get_422_not_500(tmp_path):
    """A targeted fuzz of every participant body: objects whose values (at any depth) and names may be NaN,
    ±Infinity, lone surrogates or anything else, and bodies of arbitrary bytes.  Nothing is a 5xx, every answer
    has the security headers, and a body with a non-finite number or a lone surrogate is a 422 naming a field."""
    from fastapi.testclient import TestClient

    engine = make_engine(f"sqlite:///{tmp_path / 'fuzz.db'}")
    migrate(engine)
    with session_factory(engine)() as db:
        make_study(db)
    app = create_app(Settings(var_dir=tmp_path, secret_key="fuzz-secret-0123456789abcdef0123456789",
                              sessions_per_minute=0), engine, run_migrations=False)
    client = TestClient(app)
    created = client.post("/api/v1/studies/thesis/sessions", json={"consent": True}).json()
    sid, auth = created["session_id"], {"Authorization": f"Bearer {created['token']}"}
    trial = client.get(f"/api/v1/sessions/{sid}/next", headers=auth).json()["trial_id"]
    # (method, path, a valid body): the fuzz replaces or adds one field of it, or sends anything at all.
    targets = [("POST", "/api/v1/studies/thesis/sessions", {"consent": True, "external": {"PROLIFIC_PID": "p"}}),
               ("PUT", f"/api/v1/sessions/{sid}/demographics", {"gamer": "no", "tech_savvy": "yes"}),
               ("POST", f"/api/v1/sessions/{sid}/trials/{trial}/vote",
                {"choice": "equal", "rt_ms": 900, "idempotency_key": "k"}),
               ("POST", f"/api/v1/sessions/{sid}/events", {"kind": "error", "trial_id": trial, "detail": {}})]
    statuses: dict[int, int] = {}

    def hostile(value) -> bool:
        """What the server receives cannot be written as strict JSON in UTF-8."""
        try:
            json.dumps(json.loads(json.dumps(value)), ensure_ascii=False, allow_nan=False).encode()
        except ValueError:  # a non-finite number, or a lone surrogate (UnicodeEncodeError)
            return True
        return False

    @given(data=st.data())
    @settings(max_examples=600, deadline=None, suppress_health_check=list(HealthCheck), database=None)
    def call(data):
        method, path, valid = data.draw(st.sampled_from(targets))
        body = data.draw(st.one_of(
            st.builds(lambda k, v: {**valid, k: v}, st.sampled_from([*valid, "extra"]), _VALUE),
            st.dictionaries(st.one_of(st.sampled_from(_FIELDS), _TEXT), _VALUE, max_size=6),
            st.binary(max_size=64)))
        content = body if isinstance(body, bytes) else json.dumps(body).encode()
        r = client.request(method, path, content=content, headers={**auth, "content-type": "application/json"})
        statuses[r.status_code] = statuses.get(r.status_code, 0) + 1
        assert r.status_code < 500, (method, path, content, r.status_code, r.text)
        assert r.headers["x-frame-options"] == "DENY" and "content-security-policy" in r.headers
        if isinstance(body, dict) and hostile(body):
            assert r.status_code == 422 and r.json()["detail"][0]["loc"][0] == "body", (content, r.text)

    call()
    print("statuses:", dict(sorted(statuses.items())))
    assert statuses.get(422, 0) > 100 and sum(n for code, n in statuses.items() if code < 300) > 10
