"""Issue 38 in Debian's Chromium: the update-rate study (studies/update-rate.toml: 2AFC, QUEST+ staircases over the
`pps` ladder on walk and run) with simulated participants voting through the HTTP API and one real participant by
keyboard on the page.  Its trial budget is cut to 6 per staircase to keep the test short.

The clip set is the real `pps` ladder of server/clipset/update-rate.toml on walk and run, built here (its manifest
gives every level and its measured run-time cost); only the videos stand in for its renders: every video is one
small real H.264 file (a bar crossing the frame), under the opaque names of a render manifest of the study's pairs,
so the page loads, plays and loops real video and the server does everything it does for a rendered set.
"""

from __future__ import annotations

import random
from pathlib import Path

import av
import httpx
import numpy as np
import pytest
from sqlalchemy import select

from server.app import create_app
from server.clipset.build import build_clip_set
from server.clipset.config import load_config
from server.clipset.manifest import read_clip_manifest, write_clip_set
from server.config import Settings
from server.db import migrate, session_factory
from server.participants import staircase
from server.participants.models import ParticipantSession, Trial, Vote
from server.research.export import export_rows
from server.studies.design import Design
from server.studies.models import Study, StudyState
from server.studies.service import create_study, set_state
from server.studies.studyfile import StudyFile, load_study_file
from tests.conftest import _fresh_engine, own_contexts
from tests.server_fixtures import live_server
from tests.test_answer_formats import UPDATE_RATE, ladder_media, observer, run_session
from tests.test_participant_page import ARTIFACTS, CHROMIUM, wait_until
from tests.test_update_rate_study import pps_clip_set

TRIALS = 6  # per staircase (the file's 30, cut for time)
SIMULATED = 3
LEAKS = ("pps", "keyframe", "level", "ladder", "update_rate")


def tiny_video(path: Path, width: int = 324, height: int = 120, frames: int = 20) -> bytes:
    """A real H.264 video: a bar crossing the frame, 2/3 s at 30 fps."""
    container = av.open(str(path), "w")
    stream = container.add_stream("libx264", rate=30)
    stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
    for i in range(frames):
        image = np.full((height, width, 3), 40, np.uint8)
        x = i * width // frames
        image[:, x:x + 12] = 230
        for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")):
            container.mux(packet)
    for packet in stream.encode():
        container.mux(packet)
    container.close()
    return path.read_bytes()


def study_file(**changes: object) -> StudyFile:
    raw = load_study_file(UPDATE_RATE).model_dump()
    raw["design"]["trials"] = TRIALS
    return StudyFile.model_validate({**raw, **changes})


@pytest.fixture(scope="module")
def site(tmp_path_factory, data):
    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing: `make test` installs Debian's chromium")
    var = tmp_path_factory.mktemp("var")
    settings = Settings(var_dir=var, secret_key="staircase-test-secret-0123456789abcdef")
    # the pps ladder of the clip-set file, built (about 15 s): levels and costs as a server has them
    clip_set = load_config(pps_clip_set(tmp_path_factory.mktemp("clipset")))
    write_clip_set(build_clip_set(data, clip_set), settings.clips_dir)
    media = ladder_media()
    settings.media_dir.mkdir(parents=True, exist_ok=True)
    video = tiny_video(var / "pair.mp4")
    for v in [*media.clips.values(), *media.pairs]:
        (settings.media_dir / v.video).write_bytes(video)
        (settings.media_dir / v.poster).write_bytes(b"poster")
    (settings.media_dir / "manifest.json").write_text(media.model_dump_json())
    engine = _fresh_engine("sqlite", tmp_path_factory)
    migrate(engine)
    factory = session_factory(engine)
    with factory() as db:
        set_state(db, create_study(db, media, study_file(), media_dir=settings.media_dir,
                                   clips_dir=settings.clips_dir), StudyState.open)
        phone = study_file(slug="update-rate-phone", page={"device_gate": {"min_scale": 0.25}})  # a phone's width
        set_state(db, create_study(db, media, phone, media_dir=settings.media_dir, clips_dir=settings.clips_dir),
                  StudyState.open)
        # constant stimuli over the whole ladder (conditions = ["pps"]), for the thresholds panel
        constant = study_file(slug="update-rate-cs", design={
            **load_study_file(UPDATE_RATE).design.model_dump(), "mode": "constant-stimuli", "conditions": ["pps"],
            "trials": None, "repeats": 5, "catch_trials": 1})
        set_state(db, create_study(db, media, constant, media_dir=settings.media_dir, clips_dir=settings.clips_dir),
                  StudyState.open)
    with live_server(create_app(settings, engine, run_migrations=False)) as base:
        yield base, factory, settings.clips_dir
    engine.dispose()


def simulate(base: str, factory, rng: random.Random, threshold: float) -> str:
    """A planted observer through the HTTP API (the truth of each trial read from the database, as the page
    never has it); returns the session id."""
    with httpx.Client(base_url=base, verify=False) as http:  # plain HTTP: no CA bundle to load
        r = http.post("/api/v1/studies/update-rate/sessions", json={"consent": True})
        assert r.status_code == 201, r.text
        sid, headers = r.json()["session_id"], {"Authorization": f"Bearer {r.json()['token']}"}
        answer = observer(threshold, rng)
        assert http.put(f"/api/v1/sessions/{sid}/demographics", json={"gamer": "no", "tech_savvy": "yes"},
                        headers=headers).status_code == 200
        trial = http.get(f"/api/v1/sessions/{sid}/next", headers=headers).json()
        while trial is not None:
            with factory() as db:
                stored = db.scalar(select(Trial).where(Trial.public_id == trial["trial_id"]))
                choice = answer(stored)
            r = http.post(f"/api/v1/sessions/{sid}/trials/{trial['trial_id']}/vote", headers=headers,
                          json={"choice": choice, "rt_ms": 800, "idempotency_key": trial["trial_id"]})
            assert r.status_code == 201, r.text
            trial = r.json()["next"]
    return sid


def stored_and_replayed(db, sid: str) -> tuple[list, list]:
    ps = db.get(ParticipantSession, sid)
    design = Design.model_validate(ps.study.design)
    rows, stored = [], []
    for t in sorted(ps.trials, key=lambda t: t.index):
        v = db.scalar(select(Vote).where(Vote.trial_id == t.id))
        decided = staircase.undecided(ps, t)
        rows.append((t.comparison.reference.animation if decided else None, t.comparison.test.condition,
                     v.choice if v else None, t.reference_side))
        stored.append(t.comparison.test.condition if decided else None)
    return stored, staircase.replay(design, "2afc", rows)


@pytest.mark.slow  # about a minute: every trial's video is watched to its end
def test_update_rate_staircase_with_simulated_and_real_participants(browser, site):
    base, factory, _ = site
    rng = random.Random(38)
    simulated = [simulate(base, factory, rng, threshold) for threshold in (6.0, 12.0, 20.0)[:SIMULATED]]
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    with own_contexts(browser):
        context = browser.new_context(viewport={"width": 1280, "height": 720})
        page = context.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(f"{base}/s/update-rate?PROLIFIC_PID=p1&STUDY_ID=s&SESSION_ID=x")
        page.wait_for_selector("#page-info:not([hidden])")
        page.focus("#info-next")
        page.keyboard.press("Enter")
        page.wait_for_selector("#page-consent:not([hidden])")
        page.focus("#consent-box")
        page.keyboard.press("Space")
        page.focus("#consent-next")
        page.keyboard.press("Enter")
        page.wait_for_selector("#page-demographics:not([hidden])")
        for selector in ("input[name=gamer][value=yes]", "input[name=tech_savvy][value=no]"):
            page.focus(selector)
            page.keyboard.press("Space")
        page.focus("#demographics-form button")
        page.keyboard.press("Enter")
        page.wait_for_selector("#page-instructions:not([hidden])")
        page.focus("#instructions-next")
        page.keyboard.press("Enter")
        wait_until(page, "document.getElementById('trial-progress').textContent.startsWith('Trial 1 of')")
        # the two answers of the format, as the API serves them, worded by the study, keys 1 and 2
        answers = page.eval_on_selector_all("#vote-form input[name=choice]", "xs => xs.map(x => x.value)")
        labels = page.eval_on_selector_all("#vote-form .choice-label", "xs => xs.map(x => x.textContent)")
        assert answers == ["left", "right"] and labels == ["The left one", "The right one"]
        total = int(page.inner_text("#trial-progress").split(" of ")[1].split()[0])
        assert total == 2 * TRIALS + 2
        pressed = []
        for number in range(1, total + 1):
            wait_until(page, f"document.getElementById('trial-progress').textContent.startsWith('Trial {number} of')")
            page.wait_for_selector("#loading", state="hidden")
            wait_until(page, "document.getElementById('video').currentTime > 0.05")
            html = page.content().lower()
            assert not any(word in html for word in LEAKS)
            if number == 1:
                page.screenshot(path=str(ARTIFACTS / "update-rate-trial.png"))
            key = "1" if number % 3 else "2"
            page.keyboard.press(key)
            pressed.append(key)
            page.wait_for_selector("#vote-submit:not([disabled])", timeout=15000)  # after one full loop
            page.keyboard.press("Enter")
        page.wait_for_selector("#page-thanks:not([hidden])")
        context.close()
        assert not errors, errors
    with factory() as db:
        study = db.scalar(select(Study).where(Study.slug == "update-rate"))
        real = db.scalars(select(ParticipantSession).where(ParticipantSession.study_id == study.id,
                                                           ParticipantSession.id.not_in(simulated))).one()
        assert real.state == "completed" and real.answers == {"gamer": "yes", "tech_savvy": "no"}
        votes = db.scalars(select(Vote).join(Trial).where(Vote.session_id == real.id).order_by(Trial.index)).all()
        assert [v.choice for v in votes] == [{"1": "left", "2": "right"}[k] for k in pressed]
        for sid in [*simulated, real.id]:
            stored, replayed = stored_and_replayed(db, sid)
            assert stored == replayed and sum(s is not None for s in stored) == 2 * TRIALS
        rows = list(export_rows(db, study))
        assert len(rows) == (SIMULATED + 1) * (2 * TRIALS + 2)
        assert {r["answer_format"] for r in rows} == {"2afc"} and {r["ladder"] for r in rows} == {"pps"}
        assert all(r["correct"] == (r["choice"] == r["reference_side"]) for r in rows)


def test_2afc_answers_stay_side_by_side_on_a_phone(browser, site):
    """On a phone-sized screen the five-point answers stack; the two 2AFC answers stay in one row, left first."""
    base, _, _ = site
    with own_contexts(browser):
        context = browser.new_context(viewport={"width": 390, "height": 844}, is_mobile=True, has_touch=True)
        page = context.new_page()
        page.goto(f"{base}/s/update-rate-phone")
        page.wait_for_selector("#page-info:not([hidden])")
        page.tap("#info-next")
        page.wait_for_selector("#page-consent:not([hidden])")
        page.tap("#consent-box")
        page.tap("#consent-next")
        page.wait_for_selector("#page-demographics:not([hidden])")
        page.tap("input[name=gamer][value=no]")
        page.tap("input[name=tech_savvy][value=no]")
        page.tap("#demographics-form button")
        page.wait_for_selector("#page-instructions:not([hidden])")
        page.tap("#instructions-next")
        wait_until(page, "document.getElementById('trial-progress').textContent.startsWith('Trial 1 of')")
        boxes = [page.locator("#vote-form label").nth(i).bounding_box() for i in range(2)]
        assert page.locator("#vote-form label").count() == 2
        assert boxes[0] and boxes[1] and abs(boxes[0]["y"] - boxes[1]["y"]) < 2 and boxes[0]["x"] < boxes[1]["x"]
        assert boxes[1]["x"] + boxes[1]["width"] <= 390
        page.screenshot(path=str(ARTIFACTS / "update-rate-phone.png"))
        context.close()


def test_the_dashboard_shows_each_animations_threshold_panel(browser, site):
    """The researcher's dashboard of a threshold study draws the thresholds panel from the results (issue 38), with
    the costs the built clip set measured: per animation the cheapest level nobody tells from the original, with
    its cost, and the frontier plot with one point per level at its cost.  Four participants of the
    constant-stimuli study answer by a fixed rule (levels below 10 poses per second always told apart, the others
    right every second time: 50 %, 40 answers per level), so which levels are indistinguishable is known; the
    cheapest of them is found here from the manifest's costs.  A rating study's dashboard keeps the panel hidden
    (tests/test_dashboard.py's site)."""
    from server.researchers.service import create_researcher

    base, factory, clips_dir = site
    with factory() as db:
        study = db.scalar(select(Study).where(Study.slug == "update-rate-cs"))
        levels = Design.model_validate(study.design).levels
        assert levels == {f"pps{n}": n for n in (4, 6, 8, 12, 16, 24)}  # the clip set's ladder, expanded
        seen: dict[tuple[str, str], int] = {}

        def rule(trial: Trial) -> str:
            c = trial.comparison
            key = (c.reference.animation, c.test.condition)
            seen[key] = seen.get(key, 0) + 1
            right = c.test.condition == c.reference.condition or levels[c.test.condition] < 10 or seen[key] % 2
            return trial.reference_side if right else ("left" if trial.reference_side == "right" else "right")

        for _ in range(4):
            run_session(db, study, rule)
        create_researcher(db, "thresholds@example.org", "correct horse battery", admin=True)
    costs = {(c.animation, c.condition): c.metrics["cost_ms_per_1000"] for c in read_clip_manifest(clips_dir).clips}
    cheapest = {a: min(("pps12", "pps16", "pps24"), key=lambda c, a=a: costs[(a, c)]) for a in ("walk", "run")}
    with own_contexts(browser):
        page = browser.new_page(viewport={"width": 1280, "height": 720})
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(f"{base}/dashboard?study=update-rate-cs")
        page.wait_for_selector("#login:not([hidden])")
        page.fill("#email", "thresholds@example.org")
        page.fill("#password", "correct horse battery")
        page.click("#login-form button")
        page.wait_for_selector("#thresholds-panel:not([hidden])")
        summary = page.inner_text("#thresholds-summary")
        for a in ("walk", "run"):
            c = cheapest[a]
            assert f"cheapest indistinguishable: {c} ({costs[(a, c)]:.3f} cost_ms_per_1000)" in summary, summary
        assert "no cost" not in summary and "none yet" not in summary, summary
        assert page.eval_on_selector("#chart-frontier", "e => e.querySelectorAll('svg').length") == 1
        points = page.eval_on_selector_all(
            "#chart-frontier g.panel circle[data-condition]",
            "cs => cs.map(c => [c.closest('g.panel').dataset.animation, c.dataset.condition, Number(c.dataset.cost),"
            " c.dataset.cheapest === 'true', Number(c.getAttribute('cx'))])")
        assert sorted((a, c) for a, c, *_ in points) == sorted(
            (a, f"pps{n}") for a in ("walk", "run") for n in (4, 6, 8, 12, 16, 24))
        for a, c, cost, ringed, _x in points:
            assert cost == pytest.approx(costs[(a, c)], rel=1e-3), (a, c)
            assert ringed == (c == cheapest[a]), (a, c)
        for a in ("walk", "run"):  # the x axis is the cost: points left to right in the order of their costs
            mine = sorted((cost, x) for b, _c, cost, _r, x in points if b == a)
            assert [x for _, x in mine] == sorted(x for _, x in mine)
        table = page.inner_text("#table-thresholds")
        assert f"{costs[('walk', cheapest['walk'])]:.3f}" in table
    assert not errors, errors
