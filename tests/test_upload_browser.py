"""The dashboard's upload flow in Chromium: a draft study's motion files (a bad file refused with its reason, a
good one listed with what inspecting it found), the build started with a button and its progress shown to the end,
the study's trial count updated; keyboard only for the upload."""

from __future__ import annotations

from pathlib import Path

import pytest

from server.app import create_app
from server.clipset.config import NAME_PATTERN
from server.config import Settings
from server.db import migrate
from tests.conftest import _fresh_engine, own_contexts
from tests.server_fixtures import RESEARCHER, live_server
from tests.test_participant_page import ARTIFACTS, AXE, CHROMIUM, check_page, wait_until
from tests.test_upload_job import small_site
from tests.test_uploads import SECRET, excerpt


@pytest.fixture
def site(tmp_path, tmp_path_factory, data):
    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing: `make test` installs Debian's chromium")
    settings = Settings(var_dir=tmp_path / "var", data_dir=data, secret_key=SECRET)
    engine = _fresh_engine("sqlite", tmp_path_factory)
    migrate(engine)
    small_site(settings, engine, tmp_path)
    with live_server(create_app(settings, engine, run_migrations=False)) as base:
        yield base
    engine.dispose()


def test_upload_inspect_and_build_from_the_studies_page(browser, site, tmp_path, data):
    base = site
    good = tmp_path / "Sway 45.bvh"
    good.write_bytes(excerpt(data, frames=45))
    bad = tmp_path / "broken.bvh"
    bad.write_bytes(excerpt(data, frames=45)[:300])
    with own_contexts(browser):
        # the context bypasses the page's CSP only so that the test can inject axe-core
        page = browser.new_context(viewport={"width": 1280, "height": 900}, bypass_csp=True).new_page()
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(f"{base}/dashboard/studies")
        page.wait_for_selector("#login:not([hidden])")
        page.fill("#email", RESEARCHER[0])
        page.fill("#password", RESEARCHER[1])
        page.click("#login-form button")
        page.wait_for_selector("#table-studies tr[data-slug=own]")
        assert page.inner_text("#table-studies tr[data-slug=own] td:nth-child(7)") == "3"  # trials
        page.click("#table-studies tr[data-slug=own] >> text=Motion files")
        page.wait_for_selector("#assets-panel:not([hidden])")
        wait_until(page, "document.activeElement.id === 'assets-title'")  # focus moves once the list is loaded
        assert "No motion files yet." in page.inner_text("#table-assets")
        assert page.is_disabled("#build-button")
        # the name rule comes from the server (issue 37: defined once), not from the page
        assert page.get_attribute("#asset-name", "pattern") == NAME_PATTERN[1:-1]

        # a broken file: refused with the reader's message, nothing listed
        page.set_input_files("#asset-file", str(bad))
        page.focus("#asset-name")
        page.keyboard.press("Tab")  # to the Upload button, by keyboard
        assert page.evaluate("document.activeElement.textContent") == "Upload"
        page.keyboard.press("Enter")
        wait_until(page, "document.getElementById('asset-errors').textContent.includes('broken.bvh')")
        assert "No motion files yet." in page.inner_text("#table-assets")

        # a good one: listed with what inspecting it found
        page.set_input_files("#asset-file", str(good))
        page.click("#asset-form button")
        page.wait_for_selector("#table-assets tr[data-asset=sway_45]")
        row = page.inner_text("#table-assets tr[data-asset=sway_45]")
        for text in ("Sway 45.bvh", "31", "CMU", "cmu, Y up", "45", "idle, frames 0..44"):
            assert text in row, (text, row)
        assert page.inner_text("#asset-errors") == ""

        # built from other frames: the form takes the focus, a bad range is refused with the reason
        page.click("#table-assets tr[data-asset=sway_45] >> text=Change")
        assert page.evaluate("document.activeElement.id") == "asset-kind"
        assert page.eval_on_selector_all("#asset-kind option", "os => os.map(o => o.value)")[:3] == \
            ["gait", "crouch", "idle"]
        check_page(page, AXE.read_text(), "studies-motion-files")  # zero axe-core WCAG 2.1 A/AA violations
        page.fill("#asset-first", "44")  # not before the last frame: the server says why
        page.click("#asset-edit button[type=submit]")
        wait_until(page, "document.getElementById('asset-errors').textContent.includes('frames')")
        page.fill("#asset-first", "2")
        page.click("#asset-edit button[type=submit]")
        wait_until(page, "document.querySelector('#table-assets tr[data-asset=sway_45]').textContent"
                         ".includes('idle, 2..44')")

        # the build, with its progress to the end; the study now has the new animation's trials
        page.click("#build-button")
        page.wait_for_selector("#build:not([hidden])")
        wait_until(page, "['done', 'failed'].includes(document.getElementById('build').dataset.state)",
                   timeout_s=600)
        assert page.get_attribute("#build", "data-state") == "done", page.inner_text("#build")
        assert page.inner_text("#build-error") == ""
        assert page.evaluate("document.getElementById('build-progress').value") == \
            page.evaluate("document.getElementById('build-progress').max")
        assert page.inner_text("#build-stage").startswith("Done")
        wait_until(page, "document.querySelector('#table-studies tr[data-slug=own] td:nth-child(7)')"
                         ".textContent === '5'")
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(ARTIFACTS / "studies-upload.png"), full_page=True)
        assert not errors, errors
