"""studies/transitions.toml end to end (issue 39), as a user runs it (docs/methods/transitions.md): the clip set of
server/clipset/transitions.toml built, the study's pairs rendered (small, no shadows: the pipeline of the full size,
only cheaper), the study created and opened with `animstudy study create`, one participant walked through it in
Chromium (every trial's composite video loads and plays, every vote is stored), and the dashboard's metrics table
showing each transition's skate, jumps and settling.

To keep it short, each trial's video is played for a moment and then moved to its last fifth of a second, so the
page sees the loop restart without the test sitting through 8 s per trial.  Expected values come from the study
and clip-set files, never from the code under test.  Screenshots go to var/test-artifacts/browser/.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import av
import pytest
from sqlalchemy import select

from server.app import create_app
from server.config import Settings
from server.db import make_engine, session_factory
from server.media.manifest import read_render_manifest
from server.participants.models import ParticipantSession, Vote
from server.researchers.service import create_researcher
from server.studies.models import Study
from tests.server_fixtures import live_server
from tests.test_participant_page import ARTIFACTS, CHROMIUM, wait_until
from tests.test_studies16_browser import cli_environment, rows, run

REPO = Path(__file__).resolve().parents[1]
CLIP_SET = REPO / "server" / "clipset" / "transitions.toml"
STUDY = REPO / "studies" / "transitions.toml"
RESEARCHER = ("lead@example.org", "correct horse battery")
WIDTH, HEIGHT = 128, 96
TRANSITION_COLUMNS = ("transition skate", "source window skate", "transition slide mm", "switch velocity jump rad/s",
                      "switch acceleration jump rad/s²", "settle s")


def design() -> dict:
    return tomllib.loads(STUDY.read_text(encoding="utf-8"))["design"]


def sequence_seconds() -> float:
    """The loop's length: the sum of the sequence's segments in the clip-set file."""
    animations = tomllib.loads(CLIP_SET.read_text(encoding="utf-8"))["animations"]
    (sequence,) = [a["sequence"] for a in animations.values() if "sequence" in a]
    return sum(s["seconds"] for s in sequence)


@pytest.fixture(scope="module")
def site(data, tmp_path_factory):
    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing: `make test` installs Debian's chromium")
    var = tmp_path_factory.mktemp("var")
    with cli_environment(data, var, "transitions-test-secret-0123456789abcdef"):
        logs = {"build": run("clips", "build", "--config", str(CLIP_SET))}
        logs["render"] = run("render", "--width", str(WIDTH), "--height", str(HEIGHT), "--no-shadows",
                             "--workers", "1", "--study", str(STUDY))
        logs["create"] = run("study", "create", str(STUDY), "--open")
        settings = Settings()
    engine = make_engine(settings.sqlalchemy_url)
    factory = session_factory(engine)
    with factory() as db:
        create_researcher(db, *RESEARCHER, admin=True)
    with live_server(create_app(settings, engine, run_migrations=False)) as base:
        yield base, factory, settings, logs
    engine.dispose()


@pytest.mark.slow  # a minute or two: four 8 s composites rendered, 13 trials played
def test_the_sequence_is_built_and_rendered_as_a_loop(site):
    _, _, settings, logs = site
    d = design()
    (animation,) = d["animations"]
    assert "created study 'transitions' (open" in logs["create"], logs["create"]
    for condition in [d["reference"], *d["conditions"]]:
        assert f"\n{animation}-{condition} " in logs["build"]  # the transition table's rows
    manifest = read_render_manifest(settings.media_dir)
    assert (manifest.settings["width"], manifest.settings["height"]) == (WIDTH, HEIGHT)
    assert {(p.left, p.right) for p in manifest.pairs} >= {
        (f"{animation}-{d['reference']}", f"{animation}-{c}") for c in d["conditions"]}
    # Each composite's video is one loop of the whole sequence (8 s at 30 fps), side by side in the pairs.
    for condition in [d["reference"], *d["conditions"]]:
        with av.open(str(settings.media_dir / manifest.clips[f"{animation}-{condition}"].video)) as video:
            stream = video.streams.video[0]
            frames = sum(1 for _ in video.decode(stream))
        assert frames == round(sequence_seconds() * 30)


def walk_through(pg, base: str) -> int:
    """Information, consent, the question, instructions, every trial (video playing, one vote each), thanks;
    returns the number of trials."""
    pg.goto(f"{base}/s/transitions?PROLIFIC_PID=p-1&STUDY_ID=s&SESSION_ID=x")
    pg.wait_for_selector("#page-info:not([hidden])")
    pg.click("#info-next")
    pg.wait_for_selector("#page-consent:not([hidden])")
    pg.check("#consent-box")
    pg.click("#consent-next")
    pg.wait_for_selector("#page-demographics:not([hidden])")
    pg.check("input[name=animator][value=hobby]")
    pg.click("#demographics-form button")
    pg.wait_for_selector("#page-instructions:not([hidden])")
    pg.click("#instructions-next")
    wait_until(pg, "document.getElementById('trial-progress').textContent.startsWith('Trial 1 of')")
    total = int(pg.inner_text("#trial-progress").split(" of ")[1].split()[0])
    for number in range(1, total + 1):
        wait_until(pg, f"document.getElementById('trial-progress').textContent.startsWith('Trial {number} of')")
        pg.wait_for_selector("#loading", state="hidden")
        wait_until(pg, "document.getElementById('video').currentTime > 0.05")
        assert pg.evaluate("document.getElementById('video').videoWidth") == 2 * WIDTH + 4
        assert abs(pg.evaluate("document.getElementById('video').duration") - sequence_seconds()) < 0.1
        if number == 1:
            pg.screenshot(path=str(ARTIFACTS / "transitions-trial.png"))
        pg.evaluate("(() => { const v = document.getElementById('video'); v.currentTime = v.duration - 0.2; })()")
        pg.keyboard.press(str(number % 3 + 2))  # never "much more natural": a catch trial would screen them out
        pg.wait_for_selector("#vote-submit:not([disabled])", timeout=15000)  # after the loop restarts
        pg.keyboard.press("Enter")
    pg.wait_for_selector("#page-thanks:not([hidden])")
    return total


@pytest.mark.slow
def test_a_participant_completes_the_study_and_the_dashboard_shows_the_transitions(site, page):
    base, factory, _, _ = site
    d = design()
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    seen = walk_through(page, base)
    # each pair on both sides, `repeats` times, and the catch trials
    expected = 2 * d["repeats"] * len(d["animations"]) * len(d["conditions"]) + d["catch_trials"]
    assert seen == expected
    with factory() as db:
        ps = db.scalar(select(ParticipantSession).join(Study).where(Study.slug == "transitions"))
        assert ps.state == "completed" and ps.answers == {"animator": "hobby"}
        votes = db.scalars(select(Vote).where(Vote.session_id == ps.id)).all()
        assert len(votes) == expected
        for v in votes:  # every trial's video really played and looped
            assert v.extra["playback"]["frames_presented"] > 0 and v.extra["playback"]["loops"] >= 1
    page.goto(f"{base}/dashboard")
    page.wait_for_selector("#login:not([hidden])")
    page.fill("#email", RESEARCHER[0])
    page.fill("#password", RESEARCHER[1])
    page.click("#login-form button")
    page.wait_for_selector("#dashboard:not([hidden])")
    page.goto(f"{base}/dashboard?study=transitions")
    page.wait_for_selector("#table-metrics tbody tr")
    wait_until(page, "document.getElementById('title').textContent.endsWith('transitions')")
    page.screenshot(path=str(ARTIFACTS / "transitions-dashboard.png"), full_page=True)
    mine = {r["clip"]: r for r in rows(page, "#table-metrics") if r["in this study"] == "yes"}
    (animation,) = d["animations"]
    assert set(mine) == {f"{animation} {c}" for c in [d["reference"], *d["conditions"]]}
    for clip, r in mine.items():  # every shown clip is a sequence: its transition metrics are numbers
        for name in TRANSITION_COLUMNS:
            assert math.isfinite(float(r[name])), (clip, name, r[name])
    # The blends skate no more than their sources in the transitions' windows (issue 39), as the table shows it.
    for c in d["conditions"]:
        r = mine[f"{animation} {c}"]
        assert float(r["transition skate"]) <= float(r["source skate"]), (c, r["transition skate"])
        assert float(r["source window skate"]) >= float(r["source skate"]), (c, r["source window skate"])
