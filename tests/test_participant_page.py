"""The participant page in a real browser (Debian's Chromium driven by Playwright) against a live server with
really rendered videos.  Screenshots of every page go to var/test-artifacts/browser/."""

import hashlib
import json
import shutil
import time
from pathlib import Path

import pytest
from sqlalchemy import func, select

from server.app import create_app
from server.clipset.manifest import write_clip_set
from server.config import Settings
from server.db import migrate, session_factory
from server.media.build import render_media
from server.media.manifest import read_render_manifest
from server.media.scene import RenderSettings
from server.participants.models import ParticipantSession, PlaybackEvent, Vote
from server.research.export import export_rows
from server.studies.models import StudyState
from server.studies.page import Chrome
from server.studies.service import clip_set_index, create_study, required_pairs, set_state
from server.studies.studyfile import load_study_file, thesis_study
from tests.conftest import CHROMIUM, CHROMIUM_ARGS, _fresh_engine, once_per_run
from tests.server_fixtures import live_server

REPO_STUDIES = Path(__file__).resolve().parents[1] / "studies"

ARGS = CHROMIUM_ARGS  # the name the other browser test files import
ARTIFACTS = Path(__file__).resolve().parents[1] / "var" / "test-artifacts" / "browser"
VIDEO = RenderSettings(width=320, height=240, shadows=False)  # real renders, cheaper than the default: a quick suite
LEAKS = ("hybrid", "keyframe", "increment", "mocap")
SWEDISH = REPO_STUDIES / "thesis-sv.toml"


@pytest.fixture(scope="module")
def site(data, built_clip_set, run_directory, tmp_path_factory):
    """A live server on SQLite with the default study over really rendered videos."""
    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing: `make test` installs Debian's chromium")
    var = tmp_path_factory.mktemp("var")
    settings = Settings(var_dir=var, data_dir=data, secret_key="browser-test-secret-0123456789abcdef")
    write_clip_set(built_clip_set(), settings.clips_dir)
    study_file = thesis_study()
    pairs = required_pairs(study_file.design, clip_set_index(settings.clips_dir))

    # Rendered once per run (the serial step's test reuses the parallel step's videos: tests/conftest.py), in this
    # process (workers=1), as the end-to-end tests render: beside the other test worker, a local Dask cluster's
    # start costs more CPU than its second process saves (the cluster: test_cluster.py, test_media.py).
    def render(out: Path) -> None:
        render_media(data, settings.clips_dir, out, settings.secret, VIDEO, pairs=pairs, workers=1)

    key = hashlib.sha256(repr((str(data), settings.secret, VIDEO, sorted(pairs))).encode()).hexdigest()[:16]
    shutil.copytree(once_per_run(run_directory, f"participant-page-media-{key}", render), settings.media_dir)
    engine = _fresh_engine("sqlite", tmp_path_factory)
    migrate(engine)
    factory = session_factory(engine)
    with factory() as db:
        set_state(db, create_study(db, read_render_manifest(settings.media_dir), study_file), StudyState.open)
        set_state(db, create_study(db, read_render_manifest(settings.media_dir), load_study_file(SWEDISH)),
                  StudyState.open)
    app = create_app(settings, engine, run_migrations=False)
    with live_server(app) as base:
        yield base, factory
    engine.dispose()


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


def run_trials(pg, base, trials, screenshots=False):
    """A participant from the information page through ``trials`` trials by keyboard: the pages' HTML of each
    trial, and the session id."""
    begin(pg, base, screenshots=screenshots)
    html_seen = []
    for number in range(1, trials + 1):
        wait_trial(pg, number)
        playing_check(pg)
        if number == 1 and screenshots:
            shot(pg, "5-trial")
        html_seen.append(pg.content())
        vote_by_keyboard(pg, str((number % 5) + 1))
    return html_seen, credentials(pg)["session_id"]


def test_full_run_by_keyboard_with_real_videos(site, page):
    base, factory = site
    html_seen, sid = run_trials(page, base, 16, screenshots=True)
    visible(page, "thanks")
    shot(page, "6-thanks")
    with factory() as db:
        votes = db.scalars(select(Vote).where(Vote.session_id == sid)).all()
        ps = db.get(ParticipantSession, sid)
        assert len(votes) == 16 and ps.state == "completed"
        assert ps.external == {"PROLIFIC_PID": "pp1", "STUDY_ID": "st", "SESSION_ID": "se"}
        assert ps.answers == {"gamer": "yes", "tech_savvy": "dont_know"}
        reports = [v.extra["playback"] for v in votes]
    # Every trial really played (at the shared browser's FAST_PLAYBACK, tests/conftest.py): frames were presented
    # and it looped at least once before the vote was taken.
    for r in reports:
        assert r["frames_presented"] > 0 and r["loops"] >= 1, r
    # Nothing in the page says which side is which.
    for html in html_seen:
        assert not any(word in html.lower() for word in LEAKS)


@pytest.mark.serial  # it counts video stalls: with every core busy with another worker, playback stalls (seen once)
@pytest.mark.real_speed
def test_videos_play_at_their_own_speed_without_stalls(site, page):
    # Three trials at real speed (the full run above plays at FAST_PLAYBACK): each video loops, presents its frames
    # and never waits for data.
    base, factory = site
    _, sid = run_trials(page, base, 3)
    wait_until(page, "document.getElementById('trial-progress').textContent.startsWith('Trial 4 of')")
    with factory() as db:
        reports = [v.extra["playback"] for v in db.scalars(select(Vote).where(Vote.session_id == sid)).all()]
    assert len(reports) == 3
    for r in reports:
        assert r["frames_presented"] > 0 and r["loops"] >= 1 and r["stalls"] == 0, r
    summary = {k: [r[k] for r in reports] for k in ("frames_presented", "hitches", "max_gap_ms", "dropped_frames")}
    print("playback per trial:", json.dumps(summary))


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


# --- issue 17: narrow screens, the device gate, accessibility, autoplay refusal ---------------------------------
AXE = Path(__file__).resolve().parents[1] / "var" / "node" / "node_modules" / "axe-core" / "axe.min.js"
WCAG = ["wcag2a", "wcag2aa", "wcag21a", "wcag21aa"]
# Viewport -> whether the thesis study's gate (each character at >= 80 % of its 642 px render, the pair video
# 1284x480) must stop a participant: only the 1920-wide window leaves room for 1284 px minus the page's margins.
LAYOUTS = {(320, 640): True, (390, 844): True, (768, 1024): True, (1920, 1080): False}
SMALL_SCREEN_STUDY = {"min_scale": 0.2}  # a study that accepts phones (the gate's per-study setting)


@pytest.fixture(scope="module")
def axe_source():
    if not AXE.exists():
        pytest.fail(f"{AXE} is missing: `make test` installs axe-core 4 from the npm registry")
    return AXE.read_text()


def check_page(pg, axe_source, name):
    """No sideways scrolling, zero axe-core WCAG 2.1 A/AA violations, and a screenshot."""
    overflow = pg.evaluate("[document.documentElement.scrollWidth, document.documentElement.clientWidth]")
    assert overflow[0] <= overflow[1], f"{name}: page is {overflow[0]} px wide in a {overflow[1]} px window"
    if not pg.evaluate("typeof window.axe === 'object'"):
        pg.add_script_tag(content=axe_source)  # the context bypasses the page's CSP for this inline script
    result = pg.evaluate("tags => axe.run(document, {runOnly: {type: 'tag', values: tags}})", WCAG)
    violations = [(v["id"], v["impact"], [n["target"] for n in v["nodes"]][:3]) for v in result["violations"]]
    assert not violations, f"{name}: {violations}"
    print(f"axe-core {result['testEngine']['version']} {name}: 0 violations, {len(result['passes'])} rules passed,"
          f" {len(result['incomplete'])} to review by hand {[v['id'] for v in result['incomplete']]}")
    shot(pg, f"layout-{name}")


def api_call(base, method, path, body=None, token=None):
    import urllib.request
    headers = {"Content-Type": "application/json"} | ({"Authorization": f"Bearer {token}"} if token else {})
    data = None if body is None else json.dumps(body).encode()
    with urllib.request.urlopen(urllib.request.Request(f"{base}/api/v1{path}", data=data, headers=headers,
                                                       method=method)) as r:
        return r.status, (json.loads(r.read() or b"null"))


def api_session(base):
    """A participant who consented and answered the questions, through the API."""
    _, created = api_call(base, "POST", "/studies/thesis/sessions", {"consent": True})
    api_call(base, "PUT", f"/sessions/{created['session_id']}/demographics", {"gamer": "no", "tech_savvy": "no"},
             created["token"])
    return created


def api_vote_rest(base, creds):
    """Answer the remaining trials through the API (the page's own voting is tested above)."""
    sid, token = creds["session_id"], creds["token"]
    while True:
        status, trial = api_call(base, "GET", f"/sessions/{sid}/next", token=token)
        if status == 204:
            return
        api_call(base, "POST", f"/sessions/{sid}/trials/{trial['trial_id']}/vote",
                 {"choice": "equal", "rt_ms": 3000, "idempotency_key": f"k{trial['trial_id']}"}, token)


def study_with_gate(pg, base, gate):
    """The study as the API gives it, with a device-gate setting of the study added."""
    def patch(route):
        response = route.fetch()
        study = response.json()
        route.fulfill(response=response, json={**study, "page": {**study["page"], "device_gate": gate}})
    pg.route(f"{base}/api/v1/studies/thesis", patch)


@pytest.fixture
def sized(browser, request):
    width, height = request.param
    context = browser.new_context(viewport={"width": width, "height": height}, bypass_csp=True)
    pg = context.new_page()
    errors = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    yield pg, f"{width}x{height}"
    context.close()
    assert not errors, errors


@pytest.mark.parametrize("sized", list(LAYOUTS), indirect=True, ids=lambda s: f"{s[0]}x{s[1]}")
def test_every_layout_fits_gates_and_has_no_axe_violations(site, sized, axe_source):
    base, factory = site
    pg, size = sized
    width = int(size.split("x")[0])
    pg.goto(f"{base}/study/thesis")
    wait_until(pg, "!document.getElementById('gate').hidden || !document.getElementById('page-info').hidden")
    gated = pg.is_visible("#gate")
    assert gated == LAYOUTS[(width, int(size.split("x")[1]))], size
    if gated:
        assert not pg.is_visible("#info-next") and not pg.is_visible("#consent-next")  # cannot start
        check_page(pg, axe_source, f"{size}-gate")
        # A study that accepts small screens: the whole flow at this size.
        study_with_gate(pg, base, SMALL_SCREEN_STUDY)
        pg.reload()
    visible(pg, "info")
    assert not pg.is_visible("#gate")
    check_page(pg, axe_source, f"{size}-1-information")
    press_on(pg, "#info-next")
    visible(pg, "consent")
    press_on(pg, "#consent-box", "Space")
    check_page(pg, axe_source, f"{size}-2-consent")
    press_on(pg, "#consent-next")
    visible(pg, "demographics")
    press_on(pg, "input[name=gamer][value=no]", "Space")
    press_on(pg, "input[name=tech_savvy][value=yes]", "Space")
    check_page(pg, axe_source, f"{size}-3-demographics")
    press_on(pg, "#demographics-form button")
    visible(pg, "instructions")
    check_page(pg, axe_source, f"{size}-4-instructions")
    press_on(pg, "#instructions-next")
    wait_trial(pg, 1)
    pg.keyboard.press("4")
    check_page(pg, axe_source, f"{size}-5-trial")
    labels = pg.eval_on_selector_all("#vote-form label", "ls => ls.map(l => l.getBoundingClientRect().toJSON())")
    video = pg.eval_on_selector("#video", "v => v.getBoundingClientRect().toJSON()")
    assert all(r["right"] <= width for r in labels) and video["right"] <= width
    in_one_row = len({round(r["top"]) for r in labels}) == 1
    assert in_one_row == (width >= 1024), labels  # five in a row on wide screens, stacked on narrow ones
    if not in_one_row:
        assert [r["top"] for r in labels] == sorted(r["top"] for r in labels)  # in the scale's order
    pg.wait_for_selector("#vote-submit:not([disabled])", timeout=15000)
    # Every text the status line shows, recorded as it changes: the next trial's first loop clears it, which at the
    # tests' fast playback can come before a look after the fact.
    pg.evaluate("""() => { const s = document.getElementById('status'); window.statusSaid = [];
        new MutationObserver(() => window.statusSaid.push(s.textContent))
            .observe(s, {childList: true, characterData: true, subtree: true}); }""")
    pg.keyboard.press("Enter")
    wait_trial(pg, 2)
    assert any("Vote saved" in said for said in pg.evaluate("window.statusSaid"))  # announced (role=status)
    creds = credentials(pg)
    with factory() as db:
        vote = db.scalars(select(Vote).where(Vote.session_id == creds["session_id"])).one()
        device = vote.extra["device"]
    assert (device["viewport_width"], device["device_pixel_ratio"]) == (width, 1)
    assert device["scaled"] == (width < 660) and device["passed"] is True  # the test renders are 644 px wide
    with factory() as db:  # the device at the start is the session's, and exported
        ps = db.get(ParticipantSession, creds["session_id"])
        assert (ps.device["viewport_width"], ps.device["viewport_height"]) == (width, int(size.split("x")[1]))
        row = next(r for r in export_rows(db, ps.study) if r["session_id"] == ps.id)
        assert (row["viewport_width"], row["device_pixel_ratio"]) == (width, 1)
        assert row["video_scaled"] == ps.device["scaled"] and row["video_scale"] == ps.device["scale"]
    api_vote_rest(base, creds)
    pg.reload()
    visible(pg, "thanks")
    check_page(pg, axe_source, f"{size}-6-thanks")
    pg.evaluate("localStorage.clear()")
    begin(pg, base, query="")
    wait_trial(pg, 1)
    pg.once("dialog", lambda d: d.accept())
    pg.click("#withdraw")
    visible(pg, "withdrawn")
    check_page(pg, axe_source, f"{size}-7-withdrawn")
    pg.goto(f"{base}/study/no-such-study")
    visible(pg, "message")
    check_page(pg, axe_source, f"{size}-8-message")


@pytest.mark.parametrize("sized", list(LAYOUTS), indirect=True, ids=lambda s: f"{s[0]}x{s[1]}")
def test_dashboard_has_no_axe_violations(site, sized, axe_source):
    from server.researchers.service import create_researcher
    base, factory = site
    pg, size = sized
    api_vote_rest(base, api_session(base))  # a completed participant, so the charts have data
    with factory() as db:
        try:
            create_researcher(db, "axe@example.org", "correct horse battery", admin=True)  # sees the ownerless studies
        except Exception:  # already made for an earlier layout
            db.rollback()
    pg.goto(f"{base}/dashboard")
    pg.wait_for_selector("#login:not([hidden])")
    check_page(pg, axe_source, f"{size}-dashboard-login")
    pg.fill("#email", "axe@example.org")
    pg.fill("#password", "correct horse battery")
    pg.click("#login-form button")
    pg.wait_for_selector("#dashboard:not([hidden])")
    pg.wait_for_timeout(500)  # charts drawn
    check_page(pg, axe_source, f"{size}-dashboard")


def test_gate_comes_back_on_resize_and_pauses_the_trial(site, browser):
    base, _ = site
    context = browser.new_context(viewport={"width": 1920, "height": 1080})
    pg = context.new_page()
    begin(pg, base, query="")
    wait_trial(pg, 1)
    pg.set_viewport_size({"width": 390, "height": 844})  # e.g. the window made narrow, or a tablet turned
    pg.wait_for_selector("#gate:not([hidden])")
    assert pg.is_hidden("#page-trial") and pg.evaluate("document.getElementById('video').paused")
    pg.keyboard.press("3")  # no answer while the gate is up
    assert pg.evaluate("!document.querySelector('input[name=choice]:checked')")
    pg.set_viewport_size({"width": 1920, "height": 1080})
    pg.wait_for_selector("#gate", state="hidden")
    assert pg.is_visible("#page-trial")
    wait_until(pg, "!document.getElementById('video').paused")
    playing_check(pg)
    context.close()


def test_reduced_motion_keeps_the_stimulus_playing(site, browser):
    base, _ = site
    context = browser.new_context(viewport={"width": 1920, "height": 1080}, reduced_motion="reduce")
    pg = context.new_page()
    begin(pg, base, query="")
    wait_trial(pg, 1)
    playing_check(pg)  # the stimulus is the task: it plays
    durations = pg.evaluate("Array.from(document.querySelectorAll('*'), e => getComputedStyle(e))"
                            ".flatMap(s => [s.transitionDuration, s.animationDuration])")
    assert set(durations) <= {"0s"}, set(durations)
    context.close()


# Chromium lets a muted video autoplay under every --autoplay-policy (tried: document-user-activation-required and
# user-gesture-required both play it), while Safari in Low Power Mode and some embedded browsers refuse it.  So the
# refusal is that of such a browser: play() outside the handler of a real click or key press is refused with the
# NotAllowedError a browser raises; inside one (the participant's click on Play) it is Chromium's own play().
REFUSE_WITHOUT_GESTURE = """
const play = HTMLMediaElement.prototype.play;
HTMLMediaElement.prototype.play = function () {
  const e = window.event;
  if (!(e && e.isTrusted && ["click", "keydown", "keyup"].includes(e.type)))
    return Promise.reject(new DOMException("play() needs a user gesture", "NotAllowedError"));
  return play.call(this);
};
"""


def test_autoplay_refusal_shows_play_and_is_recorded(site, playwright):
    base, factory = site
    b = playwright.chromium.launch(executable_path=CHROMIUM,
                                   args=[*ARGS, "--autoplay-policy=document-user-activation-required"])
    pg = b.new_page(viewport={"width": 1920, "height": 1080})
    pg.add_init_script(REFUSE_WITHOUT_GESTURE)
    begin(pg, base, query="")
    pg.wait_for_selector("#play:not([hidden])")
    assert pg.evaluate("document.getElementById('video').paused")
    assert pg.evaluate("document.activeElement.id") == "play"  # the keyboard reaches it first
    shot(pg, "autoplay-refused")
    pg.keyboard.press("Enter")
    pg.wait_for_selector("#play", state="hidden")
    playing_check(pg)
    vote_by_keyboard(pg, "2")
    wait_until(pg, "document.getElementById('trial-progress').textContent.startsWith('Trial 2 of')")
    pg.wait_for_selector("#play:not([hidden])")  # refused again: the next trial asks again
    sid = credentials(pg)["session_id"]
    b.close()
    with factory() as db:
        playback = db.scalars(select(Vote).where(Vote.session_id == sid)).one().extra["playback"]
    assert playback["autoplay_refused"] is True and playback["play_wait_ms"] > 0 and playback["loops"] >= 1


def test_fullscreen_is_asked_for_at_the_first_trial_and_leaving_it_is_recorded(site, browser):
    """A study with ``[page] fullscreen = true`` (the API answer rewritten, as for the gate): the start of the
    first trial asks for full screen; leaving it stores a ``fullscreen_exit`` event; each vote says whether it was
    cast in full screen."""
    base, factory = site
    pg = browser.new_page(viewport={"width": 1920, "height": 1080})

    def patch(route):
        response = route.fetch()
        study = response.json()
        route.fulfill(response=response, json={**study, "page": {**study["page"], "fullscreen": True}})
    pg.route(f"{base}/api/v1/studies/thesis", patch)
    begin(pg, base, query="")
    wait_until(pg, "document.fullscreenElement !== null")
    wait_trial(pg, 1)
    vote_by_keyboard(pg, "3")
    wait_trial(pg, 2)
    pg.evaluate("document.exitFullscreen()")
    wait_until(pg, "document.fullscreenElement === null")
    vote_by_keyboard(pg, "3")
    wait_until(pg, "document.getElementById('trial-progress').textContent.startsWith('Trial 3 of')")
    sid = credentials(pg)["session_id"]
    pg.close()
    with factory() as db:
        votes = db.scalars(select(Vote).where(Vote.session_id == sid).order_by(Vote.id)).all()
        events = db.scalars(select(PlaybackEvent).where(PlaybackEvent.session_id == sid)).all()
    assert [v.extra["playback"]["fullscreen"] for v in votes] == [True, False]
    assert [e.kind for e in events] == ["fullscreen_exit"] and events[0].trial_id == votes[1].trial_id


def test_focus_order_and_visible_focus_on_the_trial_page(site, page):
    """Tab from the top reaches the withdrawal button, the answer group and Submit, in that order, each with a
    visible focus outline."""
    base, _ = site
    begin(page, base, query="")
    wait_trial(page, 1)
    page.keyboard.press("3")
    page.wait_for_selector("#vote-submit:not([disabled])", timeout=15000)
    order = []
    for _ in range(8):  # twice round the page (the browser's own UI takes one stop: nothing focused there)
        page.keyboard.press("Tab")
        order.append(page.evaluate("(() => { const e = document.activeElement, s = getComputedStyle(e);"
                                   " return e === document.body ? null :"
                                   " [e.id || e.name, s.outlineStyle, parseFloat(s.outlineWidth)]; })()"))
    stops = [o for o in order if o is not None]
    names = [name for name, _, _ in stops]
    start = names.index("withdraw")
    assert names[start:start + 3] == ["withdraw", "choice", "vote-submit"], order
    assert set(names) == {"withdraw", "choice", "vote-submit"}, order
    assert all(style != "none" and width >= 2 for _, style, width in stops), order


def test_the_thesis_study_does_not_ask_for_fullscreen():
    assert thesis_study().page.fullscreen is False


def english_strings() -> set[str]:
    """The page's English defaults and every English string of the thesis study (texts, labels, questions)."""
    thesis = thesis_study()
    found = {v for v in Chrome().model_dump().values()}
    found |= {v for k, v in thesis.texts.model_dump().items() if k != "consent_version"}
    found |= {thesis.title, thesis.scale.question, *thesis.scale.labels}
    found |= {q.text for q in thesis.questions} | {c.label for q in thesis.questions for c in q.choices}
    # A template counts up to its first placeholder ("Trial {index} of {total}" -> "Trial").
    return {s.split("{")[0].strip() for s in found} - {""}


VISIBLE_TEXT = """(() => {
  const out = [document.title];
  const walk = document.createTreeWalker(document.body, NodeFilter.SHOW_TEXT);
  for (let n = walk.nextNode(); n; n = walk.nextNode()) {
    const text = n.textContent.trim();
    if (text && n.parentElement.checkVisibility({ checkVisibilityCSS: true })) out.push(text);
  }
  return out;
})()"""


def english_on_screen(pg, english):
    texts = pg.evaluate(VISIBLE_TEXT)
    assert texts, "no visible text"
    # A text node that is an English string, or holds one of four letters or more.
    return sorted({t for t in texts for e in english if t == e or (len(e) >= 4 and e in t)})


@pytest.mark.slow  # tens of seconds (the serial run's slowest; still run by `make test`)
def test_swedish_study_end_to_end_shows_no_english(site, browser):
    base, factory = site
    english = english_strings()
    context = browser.new_context(viewport={"width": 1920, "height": 1080})
    pg = context.new_page()
    dialogs = []
    seen = []

    def check(where):
        assert pg.evaluate("[document.documentElement.lang, document.documentElement.dir]") == ["sv", "ltr"]
        left = english_on_screen(pg, english)
        assert not left, f"{where}: English on screen: {left}"
        seen.append(where)

    pg.goto(f"{base}/s/thesis-sv")
    visible(pg, "info")
    check("information")
    press_on(pg, "#info-next")
    visible(pg, "consent")
    check("consent")
    press_on(pg, "#consent-box", "Space")
    press_on(pg, "#consent-next")
    visible(pg, "demographics")
    check("demographics")
    press_on(pg, "input[name=gamer][value=no]", "Space")
    press_on(pg, "input[name=tech_savvy][value=no]", "Space")
    press_on(pg, "#demographics-form button")
    visible(pg, "instructions")
    check("instructions")
    press_on(pg, "#instructions-next")
    for number in range(1, 17):
        wait_until(pg, f"document.getElementById('trial-progress').textContent.startsWith('Försök {number} av 16')")
        if number == 1:
            check("trial loading")  # "Laddar…" (if the video is not there yet)
        pg.wait_for_selector("#loading", state="hidden")
        pg.keyboard.press("3")
        if number == 1:
            check("trial, before one full loop")  # the "watch it first" status
            shot(pg, "sv-trial")
        pg.wait_for_selector("#vote-submit:not([disabled])", timeout=15000)
        pg.keyboard.press("Enter")
    visible(pg, "thanks")
    check("thanks")
    shot(pg, "sv-thanks")
    sid = pg.evaluate("JSON.parse(localStorage.getItem('animstudy:thesis-sv'))")["session_id"]
    with factory() as db:
        ps = db.get(ParticipantSession, sid)
        assert ps.state == "completed" and len(db.scalars(select(Vote).where(Vote.session_id == sid)).all()) == 16
    # Withdrawal (with its confirmation), the gate and a study that does not exist, in Swedish too.
    pg.evaluate("localStorage.clear()")
    pg.goto(f"{base}/s/thesis-sv")
    visible(pg, "info")
    press_on(pg, "#info-next")
    visible(pg, "consent")
    press_on(pg, "#consent-box", "Space")
    press_on(pg, "#consent-next")
    visible(pg, "demographics")
    pg.once("dialog", lambda d: (dialogs.append(d.message), d.accept()))
    pg.click("#withdraw")
    visible(pg, "withdrawn")
    check("withdrawn")
    assert dialogs and not [e for e in english if e in dialogs[0]], dialogs
    pg.set_viewport_size({"width": 390, "height": 844})
    pg.goto(f"{base}/s/thesis-sv")
    pg.wait_for_selector("#gate:not([hidden])")
    check("gate")
    shot(pg, "sv-gate-390")
    context.close()
    print("Swedish study, pages checked for English:", seen, "- confirmation:", dialogs)


def test_right_to_left_study_is_laid_out_right_to_left(site, browser):
    base, _ = site
    context = browser.new_context(viewport={"width": 390, "height": 844})
    pg = context.new_page()

    def arabic(route):
        response = route.fetch()
        study = response.json()
        page = {**study["page"], "lang": "ar", "dir": "rtl", "device_gate": {"min_scale": 0.2}}
        route.fulfill(response=response, json={**study, "page": page})
    pg.route(f"{base}/api/v1/studies/thesis", arabic)
    pg.goto(f"{base}/s/thesis")
    visible(pg, "info")
    assert pg.evaluate("getComputedStyle(document.body).direction") == "rtl"
    press_on(pg, "#info-next")
    visible(pg, "consent")
    press_on(pg, "#consent-box", "Space")
    press_on(pg, "#consent-next")
    visible(pg, "demographics")
    press_on(pg, "input[name=gamer][value=no]", "Space")
    press_on(pg, "input[name=tech_savvy][value=no]", "Space")
    press_on(pg, "#demographics-form button")
    visible(pg, "instructions")
    press_on(pg, "#instructions-next")
    wait_trial(pg, 1)
    overflow = pg.evaluate("[document.documentElement.scrollWidth, document.documentElement.clientWidth]")
    assert overflow[0] <= overflow[1]
    # Right to left: a radio button sits at the right end of its answer, the title at the right of the bar.
    label = pg.eval_on_selector("#vote-form label", "l => l.getBoundingClientRect().toJSON()")
    radio = pg.eval_on_selector("#vote-form input", "i => i.getBoundingClientRect().toJSON()")
    assert radio["left"] > label["left"] + label["width"] / 2, (radio, label)
    shot(pg, "rtl-trial-390")
    context.close()
