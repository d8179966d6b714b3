"""The dashboard's performance panel in Chromium, drawn from a results file written by a short benchmark run."""

import json

import pytest
from playwright.sync_api import sync_playwright

from anim_core import benchmark
from server.app import create_app
from server.clipset.build import build_clip_set
from server.config import Settings
from server.db import migrate, session_factory
from server.researchers.service import create_researcher
from tests.conftest import _fresh_engine
from tests.server_fixtures import live_server, make_study
from tests.test_participant_page import ARGS, ARTIFACTS, CHROMIUM


@pytest.fixture(scope="module")
def site(data, tmp_path_factory):
    settings = Settings(var_dir=tmp_path_factory.mktemp("var"), data_dir=data,
                        secret_key="dashboard-test-secret-0123456789abcdef")
    clips = [c for c in build_clip_set(data) if c.animation in ("walk", "idle")]
    doc = benchmark.run(clips, characters=(1, 10), stages=("pose",), frames=2, warmup=1)
    doc["series"] = benchmark.series(doc["results"])
    settings.benchmark_path.parent.mkdir(parents=True)
    settings.benchmark_path.write_text(json.dumps(doc), encoding="utf-8")
    engine = _fresh_engine("sqlite", tmp_path_factory)
    migrate(engine)
    with session_factory(engine)() as db:
        make_study(db)
        create_researcher(db, "lead@example.org", "correct horse battery", admin=True)
    with live_server(create_app(settings, engine, run_migrations=False)) as base:
        yield base, doc
    engine.dispose()


def test_performance_panel_shows_the_keys_figures_and_the_memory_chart(site):
    base, doc = site
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        page = browser.new_page(viewport={"width": 1280, "height": 720})
        errors = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(f"{base}/dashboard")
        page.wait_for_selector("#login:not([hidden])")
        page.fill("#email", "lead@example.org")
        page.fill("#password", "correct horse battery")
        page.click("#login-form button")
        page.wait_for_selector("#dashboard:not([hidden])")
        page.wait_for_selector("#chart-memory svg")
        legend = page.inner_text("#chart-benchmark")
        assert "hybrid, from its keys" in legend and "animstudy bench" in page.inner_text("#dashboard")
        bars = page.eval_on_selector("#chart-memory", "e => e.querySelectorAll('svg rect').length")
        assert bars >= 8 * 4  # 8 clips x (stored, keys, baked, reference)
        rows = page.eval_on_selector_all("#table-benchmark tbody tr",
                                         "rs => rs.map(r => [...r.cells].map(c => c.textContent))")
        assert [r[0] for r in rows] == [m["clip"] for m in doc["memory"] if m["variant"] == "keys"]
        keys_bytes = {m["clip"]: m["runtime_bytes"] for m in doc["memory"] if m["variant"] == "keys"}
        assert all(int(r[2]) == keys_bytes[r[0]] for r in rows)
        assert "keys runtime: worst hybrid / keyframe" in page.inner_text("#summary-benchmark")
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        page.locator("#chart-benchmark").locator("xpath=..").screenshot(path=str(ARTIFACTS / "performance.png"))
        browser.close()
        assert not errors, errors
