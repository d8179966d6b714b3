"""Issue 27's "done when": a six-condition study (issue 16's conditions of the walk, studies/adaptive-walk.toml)
runs adaptively in the browser with simulated and real votes, and the dashboard shows the scale with intervals.

The clips of the study (the walk in the six conditions, cut out of server/clipset/conditions16.toml) are built
and its videos rendered small (160 x 120, no shadows) with the real commands; simulated participants vote through
the service layer (the same code the API calls), then a participant in Chromium gets the batch the adaptive
design chooses from those votes, watches every video and votes; the dashboard then shows the scale of the six
conditions with intervals.  Screenshots go to var/test-artifacts/browser/.
"""

from __future__ import annotations

import random
import re
import tomllib
from pathlib import Path

import pytest
from sqlalchemy import select

from server.app import create_app
from server.config import Settings
from server.db import make_engine, session_factory
from server.participants import service
from server.participants.assign import session_batches
from server.participants.models import ParticipantSession
from server.researchers.service import create_researcher
from server.studies.models import Study
from server.studies.scale import CHOICES
from tests.conftest import own_contexts
from tests.server_fixtures import live_server, seeded_sessions
from tests.test_participant_page import ARTIFACTS, CHROMIUM, wait_until
from tests.test_studies16_browser import CLIP_SET, RESEARCHER, cli_environment, run, walk_through

REPO = Path(__file__).resolve().parents[1]
STUDY = REPO / "studies" / "adaptive-walk.toml"
SIMULATED = 6


def study_clip_set(folder: Path) -> Path:
    """conditions16.toml cut down to the study's animation and conditions (the whole set, 4 animations x 14
    conditions, took most of the test's time to build), written into ``folder``."""
    design = tomllib.loads(STUDY.read_text(encoding="utf-8"))["design"]
    wanted = {design["reference"], *design["conditions"]}
    sections = re.split(r"(?m)^(?=\[)", CLIP_SET.read_text(encoding="utf-8"))
    kept = [sections[0]]  # fps
    for section in sections[1:]:
        header = section.split("\n", 1)[0].strip()
        if header.startswith("[animations.") and header.removeprefix("[animations.").rstrip("]") not in \
                design["animations"]:
            continue
        if header == "[[conditions]]" and tomllib.loads(section.removeprefix(header))["id"] not in wanted:
            continue
        kept.append(section)
    path = folder / "adaptive-walk-clips.toml"
    path.write_text("".join(kept), encoding="utf-8")
    config = tomllib.loads(path.read_text(encoding="utf-8"))
    assert set(config["animations"]) == set(design["animations"])
    assert {c["id"] for c in config["conditions"]} == wanted
    return path


@pytest.fixture(scope="module")
def site(data, tmp_path_factory):
    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing: `make test` installs Debian's chromium")
    var = tmp_path_factory.mktemp("var")
    with cli_environment(data, var, "adaptive-test-secret-0123456789abcdef"):
        run("clips", "build", "--config", str(study_clip_set(var)))
        run("render", "--width", "160", "--height", "120", "--no-shadows", "--workers", "1", "--study", str(STUDY))
        run("study", "create", str(STUDY), "--open")
        settings = Settings()
    engine = make_engine(settings.sqlalchemy_url)
    factory = session_factory(engine)
    rng = random.Random(27)
    design = tomllib.loads(STUDY.read_text(encoding="utf-8"))["design"]
    # Simulated participants: the keyframe best, the others worse in the order listed, with noise.
    quality = {c: -0.6 * i for i, c in enumerate([design["reference"], *design["conditions"]])}
    # Each session's pairs and sides come from its seed (`secrets.randbits` in the service): seeded with the votes, so
    # that which conditions the simulated rounds leave with an interval is the same every run.
    with factory() as db, seeded_sessions(random.Random(28)):
        create_researcher(db, *RESEARCHER, admin=True)
        study = db.scalar(select(Study).where(Study.slug == "adaptive-walk"))
        for _ in range(SIMULATED):
            ps = service.start_session(db, study, None).session
            service.set_answers(db, ps, {"gamer": "no", "tech_savvy": "yes"})
            for trial in ps.trials:
                c = trial.comparison
                delta = quality[c.test.condition] - quality[c.reference.condition] + rng.gauss(0, 0.7)
                score = 0 if c.test_id == c.reference_id else max(-2, min(2, round(delta)))
                raw = score if trial.reference_side == "right" else -score  # left = +2
                service.cast_vote(db, ps, trial, CHOICES[2 - raw], 1200, f"k{trial.id}", {})
    with live_server(create_app(settings, engine, run_migrations=False)) as base:
        yield base, factory
    engine.dispose()


@pytest.mark.slow  # tens of seconds (the serial run's slowest; still run by `make test`)
def test_six_conditions_run_adaptively_in_the_browser(browser, site):
    base, factory = site
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    with own_contexts(browser):
        context = browser.new_context(viewport={"width": 1280, "height": 720})
        page = context.new_page()
        errors = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        assert walk_through(page, base, "adaptive-walk") == 5 * 2 + 1  # a spanning tree of 6, both sides, 1 catch
        with factory() as db:
            study = db.scalar(select(Study).where(Study.slug == "adaptive-walk"))
            rounds = session_batches(db, study)
            assert len(rounds) == SIMULATED + 1 and rounds[-1].votes_before == SIMULATED * 10
            real = db.scalar(select(ParticipantSession).where(ParticipantSession.id == rounds[-1].session_id))
            assert real.state == "completed"
            shown = {(t.comparison.reference.condition, t.comparison.test.condition) for t in real.trials
                     if t.comparison.reference_id != t.comparison.test_id}
            assert shown == set(rounds[-1].pairs["walk"])  # the batch the votes before chose, replayed from the log
        page.goto(f"{base}/dashboard?study=adaptive-walk")
        page.fill("#email", RESEARCHER[0])
        page.fill("#password", RESEARCHER[1])
        page.click("#login-form button")
        page.wait_for_selector("#dashboard:not([hidden])")
        wait_until(page, "document.querySelectorAll('#chart-scale svg circle').length === 6")
        cells = page.eval_on_selector_all("#table-scale tbody tr", "rs => rs.map(r => [...r.cells].map(c => "
                                          "c.textContent))")
        assert len(cells) == 6 and all("…" in r[3] for r in cells), cells  # every condition with an interval
        assert page.eval_on_selector_all("#table-rounds tbody tr", "rs => rs.length") == SIMULATED + 1
        page.locator("#scale-panel").screenshot(path=str(ARTIFACTS / "adaptive-walk-scale.png"))
        page.locator("#adaptive-panel").screenshot(path=str(ARTIFACTS / "adaptive-walk-rounds.png"))
        context.close()
        assert not errors, errors
