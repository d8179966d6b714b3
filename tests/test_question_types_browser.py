"""Question types and pilot runs in Debian's Chromium: the participant page builds each type's field, the browser
and the server both refuse bad answers (the server's message shown on the field), good ones are stored with
their types; a preview link starts a pilot session on a draft study (issue 28).  No videos are needed before the
first trial, so the study is made over fake media."""

from __future__ import annotations

from pathlib import Path

import pytest

from server.app import create_app
from server.config import Settings
from server.db import migrate, session_factory
from server.participants.models import ParticipantSession
from server.studies.models import StudyState
from server.studies.pilot import preview_link
from tests.conftest import _fresh_engine
from tests.server_fixtures import live_server, make_study
from tests.test_participant_page import CHROMIUM, press_on, visible
from tests.test_question_types import QUESTIONS

SECRET = "browser-test-secret-0123456789abcdef"


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing: `make test` installs Debian's chromium")
    settings = Settings(var_dir=tmp_path_factory.mktemp("var"), secret_key=SECRET)
    engine = _fresh_engine("sqlite", tmp_path_factory)
    migrate(engine)
    factory = session_factory(engine)
    with factory() as db:
        make_study(db, slug="typed", questions=QUESTIONS)
        draft = make_study(db, slug="draft", state=StudyState.draft)
        token = preview_link(draft, settings.secret).token
    with live_server(create_app(settings, engine, run_migrations=False)) as base:
        yield base, factory, token
    engine.dispose()


def to_demographics(pg, url):
    pg.goto(url)
    visible(pg, "info")
    press_on(pg, "#info-next")
    visible(pg, "consent")
    press_on(pg, "#consent-box", "Space")
    press_on(pg, "#consent-next")
    visible(pg, "demographics")


def stored_answers(factory, slug):
    with factory() as db:
        ps = db.query(ParticipantSession).join(ParticipantSession.study).filter_by(slug=slug).one()
        return ps.answers, ps.pilot


def test_each_question_type_in_chromium(site, page):
    base, factory, _ = site
    to_demographics(page, f"{base}/study/typed")
    age = page.locator("input[name=age]")
    assert age.get_attribute("type") == "number" and (age.get_attribute("min"), age.get_attribute("max")) == (
        "18", "99")
    assert "years" in page.locator("fieldset", has=age).inner_text()
    assert page.locator("input[name=remarks]").get_attribute("maxlength") == "40"
    assert page.locator("input[name=experience]").count() == 5
    page.check("input[name=gamer][value=yes]")
    page.check("input[name=experience][value='4']")
    page.fill("input[name=remarks]", "  smooth walks  ")
    for bad in ("17", "34.5"):  # the browser's own checks (min, step) keep the form from being sent
        page.fill("input[name=age]", bad)
        press_on(page, "#demographics-form button")
        page.wait_for_timeout(200)
        assert page.is_visible("#page-demographics") and not age.evaluate("e => e.validity.valid")
    # without the browser's check, the server refuses, and its message is shown on the field
    age.evaluate("e => e.removeAttribute('min')")
    page.fill("input[name=age]", "17")
    press_on(page, "#demographics-form button")
    page.wait_for_timeout(500)
    assert page.is_visible("#page-demographics")
    assert "from 18 to 99" in age.evaluate("e => e.validationMessage")
    assert stored_answers(factory, "typed")[0] is None
    page.fill("input[name=age]", "34")
    press_on(page, "#demographics-form button")
    visible(page, "instructions")
    answers, pilot = stored_answers(factory, "typed")
    assert answers == {"gamer": "yes", "age": 34, "remarks": "smooth walks", "experience": 4} and pilot is False


def test_a_preview_link_runs_a_draft_as_a_pilot(site, page):
    base, factory, token = site
    page.goto(f"{base}/study/draft")
    visible(page, "message")  # a draft takes no participants
    to_demographics(page, f"{base}/study/draft?preview={token}")
    page.check("input[name=gamer][value=no]")
    page.check("input[name=tech_savvy][value=no]")
    press_on(page, "#demographics-form button")
    visible(page, "instructions")
    assert stored_answers(factory, "draft") == ({"gamer": "no", "tech_savvy": "no"}, True)
