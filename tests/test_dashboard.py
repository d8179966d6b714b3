"""The researcher dashboard in Chromium: login, every chart drawn from a study with simulated participants."""

import pytest

from server.app import create_app
from server.clipset.manifest import write_clip_set
from server.config import Settings
from server.db import migrate, session_factory
from server.researchers.service import create_researcher
from tests.conftest import _fresh_engine, own_contexts
from tests.server_fixtures import live_server, make_study
from tests.test_participant_page import ARTIFACTS, wait_until
from tests.test_results import simulate

CHARTS = ("chart-distribution", "chart-thesis", "chart-split", "chart-means", "chart-q-gamer", "chart-q-tech_savvy",
          "chart-metrics")


@pytest.fixture(scope="module")
def dashboard_site(data, built_clip_set, tmp_path_factory):
    settings = Settings(var_dir=tmp_path_factory.mktemp("var"), data_dir=data,
                        secret_key="dashboard-test-secret-0123456789abcdef")
    write_clip_set(built_clip_set(), settings.clips_dir)  # the clips' objective metrics
    engine = _fresh_engine("sqlite", tmp_path_factory)
    migrate(engine)
    with session_factory(engine)() as db:
        simulate(db, make_study(db, clips_dir=settings.clips_dir), n=20, seed=11)
        create_researcher(db, "lead@example.org", "correct horse battery", admin=True)
    with live_server(create_app(settings, engine, run_migrations=False)) as base:
        yield base
    engine.dispose()


def test_dashboard_logs_in_and_draws_every_chart(browser, dashboard_site):
    with own_contexts(browser):
        page = browser.new_page(viewport={"width": 1280, "height": 720}, accept_downloads=True)
        errors = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(f"{dashboard_site}/dashboard")
        page.wait_for_selector("#login:not([hidden])")
        page.fill("#email", "lead@example.org")
        page.fill("#password", "wrong password!")
        page.click("#login-form button")
        wait_until(page, "document.getElementById('login-error').textContent.length > 0")
        page.fill("#password", "correct horse battery")
        page.click("#login-form button")
        page.wait_for_selector("#dashboard:not([hidden])")
        assert page.inner_text("#overview").split()[:2] == ["21", "started"]
        for chart in CHARTS:
            shapes = page.eval_on_selector(f"#{chart}", "e => e.querySelectorAll('svg rect, svg circle').length")
            assert shapes >= 8, f"{chart} drew {shapes} shapes"
        assert page.eval_on_selector("#table-stats", "e => e.querySelectorAll('tbody tr').length") == 8
        # the clips of the study's stimulus set only (4 animations x keyframe, hybrid0, hybrid1), not the whole
        # clip set on the server
        assert page.eval_on_selector("#table-metrics", "e => e.querySelectorAll('tbody tr').length") == 12
        # every clip's gate figures (issue 35), a hybrid's mirrored half among them
        assert "mirrored half" in page.inner_text("#table-metrics thead")
        assert page.inner_text("#stimulus-set").startswith("The study's stimulus set ")
        assert page.eval_on_selector("#thresholds-panel", "e => e.hidden")  # a rating study: no thresholds
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(ARTIFACTS / "dashboard.png"), full_page=True)
        with page.expect_download() as download:
            page.click("#export-csv")
        assert download.value.suggested_filename == "thesis-votes.csv"
        lines = open(download.value.path()).read().splitlines()
        assert lines[0].startswith("session_id,trial_index") and len(lines) == 1 + 19 * 16 + 10
        page.click("#toggle-state")
        wait_until(page, "document.getElementById('state-badge').textContent === 'closed'")
        assert not errors, errors
