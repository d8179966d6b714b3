"""The dashboard of an adaptive study in Chromium (issue 27): the scale with intervals per animation, the P(better)
and pair-count matrices, and the information per round."""

from __future__ import annotations

import random

import pytest

from server.app import create_app
from server.config import Settings
from server.db import migrate, session_factory
from server.participants import service
from server.researchers.service import create_researcher
from server.studies.design import Design
from server.studies.scale import CHOICES
from tests.conftest import _fresh_engine, own_contexts
from tests.server_fixtures import live_server, make_study, seeded_sessions
from tests.test_participant_page import ARTIFACTS, wait_until

CONDITIONS = ["keyframe", "hybrid0", "hybrid1", "hybrid2"]
QUALITY = {"keyframe": 0.0, "hybrid0": -1.0, "hybrid1": -2.0, "hybrid2": -3.0}  # logit units, keyframe best
PARTICIPANTS = 8


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    settings = Settings(var_dir=tmp_path_factory.mktemp("var"), secret_key="designs-test-secret-0123456789abcdef")
    engine = _fresh_engine("sqlite", tmp_path_factory)
    migrate(engine)
    rng = random.Random(3)
    # Each session's trial order and adaptive choices come from its seed (`secrets.randbits` in the service): seeded
    # here, so that the votes, and with them which conditions have a finite scale value, are the same every run.
    with session_factory(engine)() as db, seeded_sessions(rng):
        study = make_study(db, Design(mode="adaptive", conditions=CONDITIONS[1:], animations=["walk", "run"]),
                           slug="adaptive")
        for _ in range(PARTICIPANTS):
            ps = service.start_session(db, study, None).session
            service.set_answers(db, ps, {"gamer": "no", "tech_savvy": "yes"})
            for trial in ps.trials:
                c = trial.comparison
                delta = QUALITY[c.test.condition] - QUALITY[c.reference.condition] + rng.gauss(0, 0.8)
                score = max(-2, min(2, round(delta)))  # from the test's point of view
                raw = score if trial.reference_side == "right" else -score  # left = +2
                service.cast_vote(db, ps, trial, CHOICES[2 - raw], 1000, f"k{trial.id}", {})
        create_researcher(db, "lead@example.org", "correct horse battery", admin=True)
    with live_server(create_app(settings, engine, run_migrations=False)) as base:
        yield base
    engine.dispose()


def test_dashboard_shows_the_scale_matrices_and_rounds(browser, site):
    with own_contexts(browser):
        page = browser.new_page(viewport={"width": 1280, "height": 720})
        errors = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(f"{site}/dashboard?study=adaptive")
        page.fill("#email", "lead@example.org")
        page.fill("#password", "correct horse battery")
        page.click("#login-form button")
        page.wait_for_selector("#dashboard:not([hidden])")
        wait_until(page, "document.querySelectorAll('#chart-scale svg circle').length > 0")
        # One dot and one interval line per condition and animation (the anchors' of length 0).
        assert page.eval_on_selector("#chart-scale", "e => e.querySelectorAll('svg circle').length") == 8
        assert page.eval_on_selector("#chart-scale", "e => e.querySelectorAll('svg line[stroke]').length") == 8
        scale = page.eval_on_selector_all("#table-scale tbody tr", "rs => rs.map(r => [...r.cells].map(c => "
                                          "c.textContent))")
        walk = {r[1]: r for r in scale if r[0] == "walk"}
        assert walk["keyframe"][2] == "0.00" and "…" in walk["hybrid2"][3]
        # The simulated keyframe is best and hybrid2 worst: the fitted scale says so too.
        assert float(walk["hybrid2"][2]) < float(walk["hybrid0"][2]) < 0
        pairs = page.eval_on_selector_all("#table-pairs tbody tr", "rs => rs.map(r => [...r.cells].map(c => "
                                          "c.textContent))")
        walk_pairs = [r for r in pairs if r[0].startswith("walk,")]
        # 8 participants x 3 pairs x 2 sides per animation, each vote counted in its row and its column.
        assert sum(int(v) for r in walk_pairs for v in r[1:] if v != "–") == 2 * PARTICIPANTS * 3 * 2
        assert page.eval_on_selector_all("#table-pbetter tbody tr", "rs => rs.length") == 8
        assert page.is_visible("#adaptive-panel")
        assert page.eval_on_selector_all("#table-rounds tbody tr", "rs => rs.length") == PARTICIPANTS
        dots = page.eval_on_selector("#chart-rounds", "e => e.querySelectorAll('svg circle').length")
        assert dots == 2 * PARTICIPANTS
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        page.locator("#scale-panel").screenshot(path=str(ARTIFACTS / "designs-scale.png"))
        page.locator("#adaptive-panel").screenshot(path=str(ARTIFACTS / "designs-rounds.png"))
        assert not errors, errors
