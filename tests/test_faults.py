"""Short forms of the fault scenarios (the full load test is `animstudy loadtest`, see README.md):
a server killed with SIGKILL mid-load, PostgreSQL stopped mid-load, and schema-driven fuzzing."""

import os

import schemathesis
from hypothesis import HealthCheck, given, settings
from sqlalchemy import make_url

from server import loadtest
from server.app import create_app
from server.config import Settings, normalize_database_url
from server.db import make_engine, migrate, session_factory
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

    def test_postgresql_outage_answers_503_and_loses_nothing():
        url = make_url(normalize_database_url(os.environ["TEST_DATABASE_URL"])).set(database="test_animstudy_load")
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
    app = create_app(Settings(var_dir=tmp_path, secret_key="fuzz-secret-0123456789abcdef0123456789"), engine,
                     run_migrations=False)
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
