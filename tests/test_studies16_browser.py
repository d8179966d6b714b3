"""Issue 16's two example studies end to end, as a user runs them (docs/motion/conditions.md): the clip set of
server/clipset/conditions16.toml built, the videos of both studies rendered (small, no shadows: the pipeline is
the one of the full size, only cheaper), both studies created and opened with `animstudy study create`, one
participant walked through each in Chromium (every trial's video plays, every vote is stored), and the dashboard
showing each study's clips with finite metrics, the votes, and chart legends that do not overlap.

Expected values come from the study files and the clip-set file, never from the code under test.  Screenshots go
to var/test-artifacts/browser/.
"""

import contextlib
import io
import json
import math
import tomllib
from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy import select

from server import cli
from server.app import create_app
from server.config import Settings
from server.db import make_engine, session_factory
from server.media.manifest import read_render_manifest
from server.participants.models import ParticipantSession, Vote
from server.researchers.service import create_researcher
from server.studies.models import Study
from tests.server_fixtures import live_server
from tests.test_participant_page import ARTIFACTS, CHROMIUM, wait_until

REPO = Path(__file__).resolve().parents[1]
CLIP_SET = REPO / "server" / "clipset" / "conditions16.toml"
STUDIES = {slug: REPO / "studies" / f"{slug}.toml" for slug in ("future-work", "compression")}
RESEARCHER = ("lead@example.org", "correct horse battery")
# Every metric the issue names, as the dashboard's metrics table heads it; "–" is allowed only where a metric
# compares a clip with its reference and the clip is the reference.
METRICS = ("foot skate", "slide mm", "penetration mm", "MPJPE mm", "max rotation error °",
           "key velocity jump rad/s", "key acceleration jump rad/s²", "jerk m/s³", "bytes")
AGAINST_REFERENCE = {"MPJPE mm", "max rotation error °"}


def designs() -> dict[str, dict]:
    return {slug: tomllib.loads(path.read_text(encoding="utf-8")) for slug, path in STUDIES.items()}


@contextlib.contextmanager
def cli_environment(data: Path, var: Path, secret: str) -> Iterator[None]:
    """The environment `run` works in for a test's own site: var dir ``var``, the sample data, a fixed secret,
    SQLite under the var dir (no DATABASE_URL); restored after."""
    with pytest.MonkeyPatch.context() as mp:
        for key, value in {"ANIMSTUDY_VAR_DIR": str(var), "ANIMSTUDY_DATA_DIR": str(data),
                           "ANIMSTUDY_SECRET_KEY": secret}.items():
            mp.setenv(key, value)
        mp.delenv("DATABASE_URL", raising=False)
        yield


def run(*argv: str) -> str:
    """`animstudy ARGV`; its standard output (it must succeed)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = cli.main(list(argv))
    assert status == 0, f"animstudy {' '.join(argv)} exited {status}: {err.getvalue()}{out.getvalue()[-2000:]}"
    return out.getvalue()


@pytest.fixture(scope="module")
def site(data, tmp_path_factory):
    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing: `make test` installs Debian's chromium")
    var = tmp_path_factory.mktemp("var")
    with cli_environment(data, var, "studies16-test-secret-0123456789abcdef"):
        logs = {"build": run("clips", "build", "--config", str(CLIP_SET))}
        logs["render"] = run("render", "--width", "160", "--height", "120", "--no-shadows", "--workers", "1",
                             *[arg for path in STUDIES.values() for arg in ("--study", str(path))])
        for slug, path in STUDIES.items():
            logs[slug] = run("study", "create", str(path), "--open")
        settings = Settings()
    engine = make_engine(settings.sqlalchemy_url)
    factory = session_factory(engine)
    with factory() as db:
        create_researcher(db, *RESEARCHER, admin=True)
    with live_server(create_app(settings, engine, run_migrations=False)) as base:
        yield base, factory, settings, logs
    engine.dispose()


@pytest.mark.slow  # tens of seconds (the parallel run's slowest; still run by `make test`)
def test_only_what_the_studies_show_is_rendered_and_the_counts_agree(site):
    _, _, settings, logs = site
    clip_set = tomllib.loads(CLIP_SET.read_text(encoding="utf-8"))
    assert "\n56 clips in" in logs["build"], logs["build"][-500:]
    planned = next(line for line in logs["render"].splitlines() if " to render " in line)
    done = next(line for line in logs["render"].splitlines() if line.startswith("rendered "))
    todo = int(planned.split(" to render")[0].rsplit(", ", 1)[1])
    assert done.startswith(f"rendered {todo} videos"), (planned, done)
    # compression uses the server's clip set: its videos are there at the size they were made, creating renders
    # nothing.  future-work names its own clip set ([clips] set = conditions16.toml): `study create` builds the 8
    # clips it needs and renders them (its camera frames those clips only, so the videos are its own).
    assert ", 0 to render" in logs["compression"] and "rendered " not in logs["compression"], logs["compression"]
    assert "clips: 8 built into the clip set" in logs["future-work"], logs["future-work"]
    assert "created study 'future-work' (open" in logs["future-work"], logs["future-work"]
    manifest = read_render_manifest(settings.media_dir)
    assert (manifest.settings["width"], manifest.settings["height"]) == (160, 120)
    shown = {f"{a}-{c}" for d in designs().values() for a in d["design"]["animations"]
             for c in [d["design"]["reference"], *d["design"]["conditions"]]}
    every = {f"{a}-{c['id']}" for a in clip_set["animations"] for c in clip_set["conditions"]}
    assert len(every) == 56 and shown < every
    # No video of a clip no study shows (idle, hybrid1, ...), except the one of a clip identical to a shown one
    # (run-quantized12_reduced2 kept every key of run-quantized12), which is that clip's file.
    assert set(manifest.clips) >= shown
    videos = {manifest.clips[i].video for i in shown}
    assert all(manifest.clips[i].video in videos for i in set(manifest.clips) - shown)
    assert not any(i.startswith("idle-") or i.endswith("-hybrid1") for i in manifest.clips)
    assert {(p.left, p.right) for p in manifest.pairs} >= {
        (f"{a}-{d['design']['reference']}", f"{a}-{c}") for d in designs().values()
        for a in d["design"]["animations"] for c in d["design"]["conditions"]}


def walk_through(pg, base: str, slug: str) -> int:
    """Information, consent, the two questions, instructions, every trial (video playing, one vote each), thanks;
    returns the number of trials."""
    pg.goto(f"{base}/s/{slug}?PROLIFIC_PID=p-{slug}&STUDY_ID=s&SESSION_ID=x")
    pg.wait_for_selector("#page-info:not([hidden])")
    pg.click("#info-next")
    pg.wait_for_selector("#page-consent:not([hidden])")
    pg.check("#consent-box")
    pg.click("#consent-next")
    pg.wait_for_selector("#page-demographics:not([hidden])")
    pg.check("input[name=gamer][value=yes]")
    pg.check("input[name=tech_savvy][value=no]")
    pg.click("#demographics-form button")
    pg.wait_for_selector("#page-instructions:not([hidden])")
    pg.click("#instructions-next")
    wait_until(pg, "document.getElementById('trial-progress').textContent.startsWith('Trial 1 of')")
    total = int(pg.inner_text("#trial-progress").split(" of ")[1].split()[0])
    for number in range(1, total + 1):
        wait_until(pg, f"document.getElementById('trial-progress').textContent.startsWith('Trial {number} of')")
        pg.wait_for_selector("#loading", state="hidden")
        wait_until(pg, "document.getElementById('video').currentTime > 0.05")
        assert pg.evaluate("document.getElementById('video').videoWidth") == 2 * 160 + 4
        if number == 1:
            pg.screenshot(path=str(ARTIFACTS / f"studies16-{slug}-trial.png"))
        pg.keyboard.press(str(number % 3 + 2))  # never "significantly": a catch trial would screen them out
        pg.wait_for_selector("#vote-submit:not([disabled])", timeout=15000)  # after one full loop
        pg.keyboard.press("Enter")
    pg.wait_for_selector("#page-thanks:not([hidden])")
    return total


@pytest.fixture(scope="module")
def walked(site, browser) -> dict[str, int]:
    """One participant through each study (slug -> trials seen); the dashboard test reads their votes."""
    base = site[0]
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    context = browser.new_context(viewport={"width": 1280, "height": 720})
    pg = context.new_page()
    errors = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    seen = {slug: walk_through(pg, base, slug) for slug in STUDIES}
    context.close()
    assert not errors, errors
    return seen


@pytest.mark.slow  # tens of seconds (the serial run's slowest; still run by `make test`)
def test_a_participant_completes_each_study(site, walked):
    _, factory, _, _ = site
    for slug, d in designs().items():
        design = d["design"]
        expected = 2 * len(design["animations"]) * len(design["conditions"]) + design["catch_trials"]
        assert walked[slug] == expected
        with factory() as db:
            ps = db.scalar(select(ParticipantSession).join(Study).where(Study.slug == slug))
            assert ps.state == "completed" and ps.answers == {"gamer": "yes", "tech_savvy": "no"}
            votes = db.scalars(select(Vote).where(Vote.session_id == ps.id)).all()
            assert len(votes) == expected
            for v in votes:  # every trial really played, at least one loop
                assert v.extra["playback"]["frames_presented"] > 0 and v.extra["playback"]["loops"] >= 1


def rows(pg, selector: str) -> list[dict[str, str]]:
    head = pg.eval_on_selector_all(f"{selector} thead th", "hs => hs.map(h => h.textContent)")
    body = pg.eval_on_selector_all(f"{selector} tbody tr", "rs => rs.map(r => [...r.cells].map(c => c.textContent))")
    return [dict(zip(head, r, strict=True)) for r in body]


# Every pair of legend labels (SVG text in the legend row(s), above the plot) of one chart whose boxes intersect.
OVERLAPS = """(chart) => {
  const svg = chart.querySelector("svg");
  if (!svg) return [];
  const swatches = [...svg.querySelectorAll("rect[rx='2']")];
  const labels = swatches.map((r) => r.nextElementSibling).filter((t) => t && t.tagName === "text");
  const boxes = labels.map((t) => [t.textContent, t.getBBox()]);
  const out = [];
  boxes.forEach(([a, p], i) => boxes.slice(i + 1).forEach(([b, q]) => {
    if (p.x < q.x + q.width && q.x < p.x + p.width && p.y < q.y + q.height && q.y < p.y + p.height) out.push([a, b]);
  }));
  const right = svg.viewBox.baseVal.width;
  boxes.forEach(([a, p]) => { if (p.x + p.width > right) out.push([a, "right edge"]); });
  return out;
}"""


def test_the_dashboard_shows_each_studys_clips_metrics_and_votes(site, walked, page):
    base, _, settings, _ = site
    # A benchmark with long series names, to check the line chart's legend too (the benchmark itself is
    # tests/test_dashboard_benchmark.py's subject).
    names = ["keyframe", "hybrid, from its keys", "hybrid, baked table", "keyframe, numpy reference",
             "hybrid, numpy reference", "hybrid, naive SQUAD"]  # anim_core.bench.suite.series's
    names += [f"{a} {m}, from its keys" for a in ("walk", "run", "crouch", "idle") for m in ("keyframe", "hybrid")]
    settings.benchmark_path.parent.mkdir(parents=True, exist_ok=True)
    settings.benchmark_path.write_text(json.dumps({"series": [
        {"name": n, "points": [[10, 0.1 * (i + 1)], [200, 1.0 * (i + 1)]]} for i, n in enumerate(names)]}))
    page.goto(f"{base}/dashboard")
    page.wait_for_selector("#login:not([hidden])")
    page.fill("#email", RESEARCHER[0])
    page.fill("#password", RESEARCHER[1])
    page.click("#login-form button")
    page.wait_for_selector("#dashboard:not([hidden])")
    for slug, d in designs().items():
        design = d["design"]
        page.goto(f"{base}/dashboard?study={slug}")
        page.wait_for_selector("#table-metrics tbody tr")
        wait_until(page, f"document.getElementById('title').textContent.endsWith('{slug}')")
        page.screenshot(path=str(ARTIFACTS / f"studies16-dashboard-{slug}.png"), full_page=True)
        cards = page.inner_text("#overview").split("\n")
        assert cards[cards.index("votes") - 1] == str(2 * len(design["animations"]) * len(design["conditions"])
                                                      + design["catch_trials"]), cards
        # The study's clips, and only they, are marked as its own, each with every metric a finite number.
        metrics = rows(page, "#table-metrics")
        mine = {r["clip"]: r for r in metrics if r["in this study"] == "yes"}
        expected = {f"{a} {c}" for a in design["animations"] for c in [design["reference"], *design["conditions"]]}
        assert set(mine) == expected
        assert len(metrics) == len(expected)  # the study's stimulus set, not the server's 56 clips
        for clip, r in mine.items():
            for name in METRICS:
                if name in AGAINST_REFERENCE and clip.endswith(f" {design['reference']}"):
                    assert r[name] == "–", (clip, name, r[name])
                else:
                    assert math.isfinite(float(r[name])), (clip, name, r[name])
        chart = page.inner_text("#chart-metrics")
        assert all(c in chart for c in design["conditions"])
        # The votes: one row per comparison with this participant in it.
        stats = rows(page, "#table-stats")
        assert sorted(r["comparison"] for r in stats) == sorted(
            f"{a}, {c}" for a in design["animations"] for c in design["conditions"])
        assert {r["n"] for r in stats} == {"1"}
        for chart_id in page.eval_on_selector_all(".chart", "cs => cs.map(c => c.id)"):
            overlaps = page.eval_on_selector(f"#{chart_id}", OVERLAPS)
            assert not overlaps, (slug, chart_id, overlaps)
    assert page.eval_on_selector("#chart-benchmark", "c => c.querySelectorAll('svg path').length") == len(names)
