"""Studies in Chromium: each study's participant page shows its own texts, labels and questions; the dashboard's
studies page lists studies with their counts, creates one from an uploaded study file, edits texts, opens it."""

from __future__ import annotations

from pathlib import Path

import pytest

from server.app import create_app
from server.config import Settings
from server.db import migrate, session_factory
from server.participants.models import ParticipantSession
from server.researchers.service import create_researcher
from server.studies.models import Study
from tests.conftest import _fresh_engine, own_contexts
from tests.server_fixtures import live_server, make_study, write_fake_media
from tests.test_participant_page import ARTIFACTS, CHROMIUM, wait_until

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """A live server (SQLite) with the thesis study open, over a fake render manifest (these tests read texts and
    lists, they play no video)."""
    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing: `make test` installs Debian's chromium")
    settings = Settings(var_dir=tmp_path_factory.mktemp("var"), secret_key="studies-browser-secret-0123456789abcd")
    write_fake_media(settings.media_dir)
    engine = _fresh_engine("sqlite", tmp_path_factory)
    migrate(engine)
    factory = session_factory(engine)
    with factory() as db:
        make_study(db)
        create_researcher(db, "lead@example.org", "correct horse battery", admin=True)
    with live_server(create_app(settings, engine, run_migrations=False)) as base:
        yield base, factory
    engine.dispose()


@pytest.fixture
def page(browser):
    with own_contexts(browser):
        pg = browser.new_page(viewport={"width": 1280, "height": 800})
        errors: list[str] = []
        pg.on("pageerror", lambda e: errors.append(str(e)))
        yield pg
        assert not errors, errors


def test_studies_page_and_a_second_studys_own_participant_page(site, page, tmp_path):
    base, factory = site
    page.goto(f"{base}/dashboard/studies")
    page.wait_for_selector("#login:not([hidden])")
    page.fill("#email", "lead@example.org")
    page.fill("#password", "correct horse battery")
    page.click("#login-form button")
    page.wait_for_selector("#studies:not([hidden])")
    assert page.eval_on_selector_all("#table-studies tbody tr", "rows => rows.map(r => r.dataset.slug)") == ["thesis"]

    # Create from an uploaded study file: first one with an error (shown with its field and line), then the good one.
    study_file = tmp_path / "gait.toml"
    text = (REPO / "studies" / "example.toml").read_text().replace('slug = "gait-example"', 'slug = "gait"')
    study_file.write_text(text.replace("repeats = 1", "repeats = 7"))
    page.set_input_files("#create-file", str(study_file))
    page.click("#create-form button")
    wait_until(page, "document.getElementById('create-errors').textContent.includes('design.repeats (line')")
    study_file.write_text(text)
    page.set_input_files("#create-file", str(study_file))
    page.click("#create-form button")
    page.wait_for_selector("#table-studies tr[data-slug=gait]")
    row = page.inner_text("#table-studies tr[data-slug=gait]")
    assert "draft" in row and "Which walk looks more natural?" in row

    # Edit a text while the study is a draft, then open it.
    page.click("#table-studies tr[data-slug=gait] >> text=Edit texts")
    page.wait_for_selector("#edit-panel:not([hidden])")
    page.fill("#text-thanks", "Thanks from the gait team.")
    page.click("#edit-form button")
    page.wait_for_selector("#edit-panel[hidden]", state="attached")
    page.click("#table-studies tr[data-slug=gait] >> text=Open")
    wait_until(page, "document.querySelector('#table-studies tr[data-slug=gait] .badge').textContent === 'open'")
    assert page.query_selector("#table-studies tr[data-slug=gait] >> text=Edit texts") is None
    assert page.get_attribute("#table-studies tr[data-slug=gait] >> text=participant page", "href") == "/s/gait"
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / "studies.png"), full_page=True)

    # Its participant page: its texts, its question, its answer labels.
    page.goto(f"{base}/s/gait?PROLIFIC_PID=pp9&workerId=not-accepted")
    page.wait_for_selector("#page-info:not([hidden])")
    assert page.inner_text("#study-title") == "Which walk looks more natural?"
    assert "walking and a running character" in page.inner_text("#info-text")
    assert page.inner_text("#contact-text") == "Gait study team, gait-study@example.org"
    page.click("#info-next")
    page.check("#consent-box")
    page.click("#consent-next")
    page.wait_for_selector("#page-demographics:not([hidden])")
    assert page.inner_text("#questions-title") == "Questions about you"  # the default wording
    assert "Have you ever animated characters" in page.inner_text("#demographics-form")
    assert page.query_selector("input[name=gamer]") is None
    page.check("input[name=animator][value=hobby]")
    page.click("#demographics-form button")
    page.wait_for_selector("#page-instructions:not([hidden])")
    labels = page.eval_on_selector_all("#vote-form .choice-label", "els => els.map(e => e.textContent)")
    assert labels == ["Left is much more natural", "Left is a bit more natural", "No difference",
                      "Right is a bit more natural", "Right is much more natural"]
    with factory() as db:
        study = db.query(Study).filter_by(slug="gait").one()
        ps = db.query(ParticipantSession).filter_by(study_id=study.id).one()
        assert ps.answers == {"animator": "hobby"} and ps.external == {"PROLIFIC_PID": "pp9"}
        assert study.texts["thanks"] == "Thanks from the gait team."

    # The thesis page keeps its own texts, questions and labels.
    page.goto(f"{base}/")
    page.wait_for_selector("#page-info:not([hidden])")
    assert page.url.endswith("/s/thesis")
    assert page.inner_text("#study-title") == "How good does this character animation look?"
    page.click("#info-next")
    page.check("#consent-box")
    page.click("#consent-next")
    page.wait_for_selector("#page-demographics:not([hidden])")
    assert page.inner_text("#questions-title") == "Two questions about you"
    assert page.query_selector("input[name=gamer][value=dont_know]") is not None
    assert page.eval_on_selector_all("#vote-form .choice-label", "els => els.map(e => e.textContent)")[2] == \
        "They look equal in visual quality"
