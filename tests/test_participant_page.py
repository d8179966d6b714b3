"""The participant page in a real browser (Debian's Chromium driven by Playwright) against a live server with
really rendered videos.  Screenshots of every page go to var/test-artifacts/browser/."""

import json
import time
from pathlib import Path

import pytest
from playwright.sync_api import sync_playwright
from sqlalchemy import func, select

from anim_core.clipset import build_clip_set, write_clip_set
from server.app import create_app
from server.config import Settings
from server.db import migrate, session_factory
from server.media.build import render_media
from server.media.scene import RenderSettings
from server.participants.models import ParticipantSession, Vote
from server.studies.models import StudyState
from server.studies.service import clip_set_index, create_study, required_pairs, set_state
from server.studies.studyfile import thesis_study
from tests.conftest import _fresh_engine
from tests.server_fixtures import live_server

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]
ARTIFACTS = Path(__file__).resolve().parents[1] / "var" / "test-artifacts" / "browser"
VIDEO = RenderSettings(width=320, height=240)  # real renders, smaller than the default to keep the suite quick
LEAKS = ("hybrid", "keyframe", "increment", "mocap")


@pytest.fixture(scope="module")
def site(data, tmp_path_factory):
    """A live server on SQLite with the default study over really rendered videos."""
    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing: `make test` installs Debian's chromium")
    var = tmp_path_factory.mktemp("var")
    settings = Settings(var_dir=var, data_dir=data, secret_key="browser-test-secret-0123456789abcdef")
    write_clip_set(build_clip_set(data), settings.clips_dir)
    study_file = thesis_study()
    manifest = render_media(data, settings.clips_dir, settings.media_dir, settings.secret, VIDEO,
                            pairs=required_pairs(study_file.design, clip_set_index(settings.clips_dir)))
    engine = _fresh_engine("sqlite", tmp_path_factory)
    migrate(engine)
    factory = session_factory(engine)
    with factory() as db:
        set_state(db, create_study(db, json.loads(manifest.read_text()), study_file), StudyState.open)
    app = create_app(settings, engine, run_migrations=False)
    with live_server(app) as base:
        yield base, factory
    engine.dispose()


@pytest.fixture(scope="module")
def browser():
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        yield b
        b.close()


@pytest.fixture
def page(browser, tmp_path):
    context = browser.new_context(viewport={"width": 1280, "height": 720})
    pg = context.new_page()
    errors = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    yield pg
    context.close()
    assert not errors, errors


def shot(pg, name):
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    pg.screenshot(path=str(ARTIFACTS / f"{name}.png"))


def visible(pg, page_id):
    pg.wait_for_selector(f"#page-{page_id}:not([hidden])")


def press_on(pg, selector, key="Enter"):
    pg.focus(selector)
    pg.keyboard.press(key)


def begin(pg, base, screenshots=False, query="?PROLIFIC_PID=pp1&STUDY_ID=st&SESSION_ID=se"):
    """Information, consent, demographics and instructions, by keyboard only."""
    pg.goto(f"{base}/study/thesis{query}")
    visible(pg, "info")
    if screenshots:
        shot(pg, "1-information")
    press_on(pg, "#info-next")
    visible(pg, "consent")
    press_on(pg, "#consent-box", "Space")
    if screenshots:
        shot(pg, "2-consent")
    press_on(pg, "#consent-next")
    visible(pg, "demographics")
    press_on(pg, "input[name=gamer][value=yes]", "Space")
    press_on(pg, "input[name=tech_savvy][value=dont_know]", "Space")
    if screenshots:
        shot(pg, "3-demographics")
    press_on(pg, "#demographics-form button")
    visible(pg, "instructions")
    if screenshots:
        shot(pg, "4-instructions")
    press_on(pg, "#instructions-next")


def credentials(pg):
    return pg.evaluate("JSON.parse(localStorage.getItem('animstudy:thesis'))")


def wait_until(pg, expression: str, timeout_s: float = 30.0) -> None:
    """Poll a JavaScript expression until it is truthy.  Not ``page.wait_for_function``: that evals its string in
    the page, which the page's Content-Security-Policy (no 'unsafe-eval') rightly forbids."""
    deadline = time.monotonic() + timeout_s
    while not pg.evaluate(expression):
        if time.monotonic() > deadline:
            raise TimeoutError(f"still false after {timeout_s} s: {expression}")
        pg.wait_for_timeout(50)


def wait_trial(pg, number):
    """Wait until trial ``number`` (1-based) is on screen with its video loaded and playing."""
    wait_until(pg, f"document.getElementById('trial-progress').textContent.startsWith('Trial {number} of')")
    pg.wait_for_selector("#loading", state="hidden")
    wait_until(pg, "document.getElementById('video').currentTime > 0.05")


def playing_check(pg):
    """Frames advance: presented frames and the media clock both move over 0.4 s."""
    before = pg.evaluate("[document.getElementById('video').getVideoPlaybackQuality().totalVideoFrames,"
                         " document.getElementById('video').currentTime]")
    pg.wait_for_timeout(400)
    after = pg.evaluate("[document.getElementById('video').getVideoPlaybackQuality().totalVideoFrames,"
                        " document.getElementById('video').currentTime]")
    assert after[0] > before[0] and after[1] != before[1], (before, after)


def vote_by_keyboard(pg, key="3"):
    pg.keyboard.press(key)
    pg.wait_for_selector("#vote-submit:not([disabled])", timeout=15000)  # after one full loop
    pg.keyboard.press("Enter")


def test_full_run_by_keyboard_with_real_videos(site, page):
    base, factory = site
    begin(page, base, screenshots=True)
    html_seen = []
    for number in range(1, 17):
        wait_trial(page, number)
        playing_check(page)
        if number == 1:
            shot(page, "5-trial")
        html_seen.append(page.content())
        vote_by_keyboard(page, str((number % 5) + 1))
    visible(page, "thanks")
    shot(page, "6-thanks")
    sid = credentials(page)["session_id"]
    with factory() as db:
        votes = db.scalars(select(Vote).where(Vote.session_id == sid)).all()
        ps = db.get(ParticipantSession, sid)
        assert len(votes) == 16 and ps.state == "completed"
        assert ps.external == {"PROLIFIC_PID": "pp1", "STUDY_ID": "st", "SESSION_ID": "se"}
        assert ps.answers == {"gamer": "yes", "tech_savvy": "dont_know"}
        reports = [v.extra["playback"] for v in votes]
    # Every trial really played: frames were presented, it looped at least once, and it never waited for data.
    for r in reports:
        assert r["frames_presented"] > 0 and r["loops"] >= 1 and r["stalls"] == 0, r
    summary = {k: [r[k] for r in reports] for k in ("frames_presented", "hitches", "max_gap_ms", "dropped_frames")}
    print("playback per trial:", json.dumps(summary))
    # Nothing in the page says which side is which.
    for html in html_seen:
        assert not any(word in html.lower() for word in LEAKS)


def test_an_aborted_vote_is_retried_and_stored_once(site, page):
    base, factory = site
    begin(page, base, query="")
    wait_trial(page, 1)
    calls = []

    def drop_the_answer(route):
        calls.append(route.request.post_data)
        if len(calls) == 1:
            route.fetch()  # the server stores the vote ...
            route.abort()  # ... but the browser never hears back
        else:
            route.continue_()

    page.route("**/vote", drop_the_answer)
    vote_by_keyboard(page, "1")
    wait_trial(page, 2)
    assert len(calls) >= 2 and calls[0] == calls[1]  # retried with the same body and idempotency key
    sid = credentials(page)["session_id"]
    with factory() as db:
        assert db.scalar(select(func.count(Vote.id)).where(Vote.session_id == sid)) == 1


def test_reload_resumes_at_the_same_trial(site, page):
    base, factory = site
    begin(page, base, query="")
    for number in (1, 2, 3):
        wait_trial(page, number)
        vote_by_keyboard(page)
    wait_trial(page, 4)
    before = page.evaluate("document.getElementById('video').src")
    page.reload()
    wait_trial(page, 4)  # not back at the information page, not at trial 1
    assert page.evaluate("document.getElementById('video').src") != before  # a new page, a new object URL ...
    sid = credentials(page)["session_id"]
    with factory() as db:
        assert db.scalar(select(func.count(Vote.id)).where(Vote.session_id == sid)) == 3  # ... same trial
    page.go_back()  # leaving and coming back creates no vote
    page.goto(f"{base}/study/thesis")
    wait_trial(page, 4)
    with factory() as db:
        assert db.scalar(select(func.count(Vote.id)).where(Vote.session_id == sid)) == 3


def test_withdrawal_deletes_the_data(site, page):
    base, factory = site
    begin(page, base, query="?PROLIFIC_PID=leaving")
    wait_trial(page, 1)
    vote_by_keyboard(page)
    wait_trial(page, 2)
    sid = credentials(page)["session_id"]
    page.once("dialog", lambda d: d.accept())
    page.click("#withdraw")
    visible(page, "withdrawn")
    shot(page, "7-withdrawn")
    assert credentials(page) is None
    with factory() as db:
        ps = db.get(ParticipantSession, sid)
        assert ps.state == "withdrawn" and ps.external is None and ps.answers is None
        assert db.scalar(select(func.count(Vote.id)).where(Vote.session_id == sid)) == 0


def test_pages_fit_a_720p_screen(site, page):
    base, _ = site
    begin(page, base, query="")
    wait_trial(page, 1)
    # No scrolling needed at 1280x720 (and so not at 1920x1080 either).
    assert page.evaluate("document.documentElement.scrollHeight <= window.innerHeight + 1")
    box = page.evaluate("(() => { const v = document.getElementById('video'); const r = v.getBoundingClientRect();"
                        " return [r.width, r.height, v.videoWidth, v.videoHeight]; })()")
    assert box[2] == 2 * VIDEO.width + 4  # the side-by-side video, both halves in one frame
    assert box[0] > 0 and box[1] > 0
