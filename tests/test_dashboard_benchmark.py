"""The dashboard's performance panel in Chromium, drawn from a results file written by a short benchmark run."""

import dataclasses
import json
from pathlib import Path

import pytest

from anim_core.bench import suite as benchmark
from server.app import create_app
from server.clipset.build import build_clip_set
from server.clipset.config import load_config
from server.config import Settings
from server.db import migrate, session_factory
from server.researchers.service import create_researcher
from tests.conftest import _fresh_engine, own_contexts
from tests.server_fixtures import live_server, make_study
from tests.test_participant_page import ARTIFACTS

CONDITIONS16 = Path(__file__).resolve().parents[1] / "server" / "clipset" / "conditions16.toml"


@pytest.fixture(scope="module")
def site(data, built_clip_set, tmp_path_factory):
    settings = Settings(var_dir=tmp_path_factory.mktemp("var"), data_dir=data,
                        secret_key="dashboard-test-secret-0123456789abcdef")
    # The thesis's conditions and those of issue 16 on the walk (14 clips), the thesis's on the idle (4).
    walk = dataclasses.replace(config := load_config(CONDITIONS16), animations={"walk": config.animations["walk"]})
    clips = build_clip_set(data, walk) + [c for c in built_clip_set() if c.animation == "idle"]
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


def test_performance_panel_shows_the_keys_figures_and_the_memory_chart(browser, site):
    base, doc = site
    with own_contexts(browser):
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
        for method in ("hybrid_ik", "hybrid_c2", "reduced", "quantized"):
            assert f"{method}, from its keys" in legend
        bars = page.eval_on_selector("#chart-memory", "e => e.querySelectorAll('svg rect').length")
        assert bars >= 18 * 4  # 18 clips x (stored, keys, baked, reference)
        rows = page.eval_on_selector_all("#table-benchmark tbody tr",
                                         "rs => rs.map(r => [...r.cells].map(c => c.textContent))")
        assert [r[0] for r in rows] == [m["clip"] for m in doc["memory"] if m["variant"] == "keys"]
        assert {"walk-hybrid_ik0", "walk-hybrid_c2_0", "walk-reduced5", "walk-quantized8"} <= {r[0] for r in rows}
        keys_bytes = {m["clip"]: m["runtime_bytes"] for m in doc["memory"] if m["variant"] == "keys"}
        assert all(int(r[3]) == keys_bytes[r[0]] for r in rows)
        # Every condition's cost per frame at the largest crowd (10) and its ratio to the keyframe clip, as timed.
        timed = {f"{r['animation']}-{r['condition']}": r["median_ms"] for r in doc["results"]
                 if r["variant"] == "keys" and r["threads"] == 1 and r["characters"] == 10}
        ratio = {f"{r['animation']}-{r['condition']}": r["ratio"] for r in doc["summary"]["ratios"]
                 if r["characters"] == 10}
        assert len(rows) == len(timed) == 18 and len(ratio) == 16
        for r in rows:
            assert float(r[1]) == pytest.approx(timed[r[0]], abs=6e-4), r
            if r[0].endswith("-keyframe"):
                assert r[2] == "1 (base)"
            else:
                assert float(r[2]) == pytest.approx(ratio[r[0]], abs=6e-3), r  # 10 is the only crowd >= 10
        assert "keys runtime: worst hybrid / keyframe" in page.inner_text("#summary-benchmark")
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        page.locator("#chart-benchmark").locator("xpath=..").screenshot(path=str(ARTIFACTS / "performance.png"))
        assert not errors, errors
