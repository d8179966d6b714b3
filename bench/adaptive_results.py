"""Time of one results request of an adaptive study at about 1,000, 5,000 and 10,000 votes (issue 36, finding 4).

    PYTHONPATH=. .venv/bin/python bench/adaptive_results.py [--votes 1000 5000 10000] [--before REV] [--repeats 3]

The study is issue 36's: four conditions (the reference and three), two animations, adaptive, one catch trial:
13 votes per participant, so 80, 380 and 780 simulated participants (ordinal Bradley-Terry observers, the reference
best) give 1,040, 4,940 and 10,140 votes.  The study is built once, through the service layer, into SQLite files
(one per size); then each source tree measures ``research.results.study_results`` (what
``GET /api/v1/studies/{slug}/results`` returns) on copies of those files in a process of its own:

- *cold*: the first request of a new server process (no cache);
- *next vote*: a new participant starts, answers one trial, and the dashboard asks again (what every vote costs
  while a dashboard polls), median of ``--repeats``.

``--before REV`` also measures the code of commit REV (``git archive`` into a temporary directory) on the same
files, in the same run, alternating with this tree.  Times are wall-clock seconds on whatever else the machine
is doing; CPU seconds of the measuring process beside them.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SLUG = "adaptive"
CONDITIONS = ["hybrid0", "hybrid1", "hybrid2"]
QUALITY = {"keyframe": 0.0, "hybrid0": -0.7, "hybrid1": -1.4, "hybrid2": -2.1}  # logit units, the reference best
VOTES_PER_PARTICIPANT = 13


def _answer(rng: random.Random, trial: object) -> str:
    """A simulated observer's answer (ordinal Bradley-Terry with cut points 0.5 and 2, logistic noise)."""
    from server.studies.scale import CHOICES

    c = trial.comparison  # type: ignore[attr-defined]
    if c.test_id == c.reference_id:
        return "equal"
    u = min(max(rng.random(), 1e-12), 1 - 1e-12)
    delta = QUALITY[c.test.condition] - QUALITY[c.reference.condition] + math.log(u / (1 - u))
    score = -2 if delta < -2 else -1 if delta < -0.5 else 0 if delta <= 0.5 else 1 if delta <= 2 else 2
    raw = score if trial.reference_side == "right" else -score  # type: ignore[attr-defined]  # left = +2
    return CHOICES[2 - raw]


def participate(db: object, study: object, rng: random.Random, trials: int | None = None) -> None:
    """One simulated participant: starts, answers ``trials`` trials (all by default)."""
    from server.participants import service

    ps = service.start_session(db, study, None).session  # type: ignore[arg-type]
    for trial in ps.trials[:trials]:
        service.cast_vote(db, ps, trial, _answer(rng, trial), 4000, f"k{trial.id}", {})  # type: ignore[arg-type]


def _copy(source: Path, target: Path) -> None:
    """A consistent copy of a SQLite database (its write-ahead log included)."""
    with sqlite3.connect(source) as src, sqlite3.connect(target) as dst:
        src.backup(dst)


def build(folder: Path, sizes: list[int]) -> list[Path]:
    """SQLite files of the study at each size (votes), built by one study growing."""
    from sqlalchemy import select

    from server.db import make_engine, migrate, session_factory
    from server.participants.models import Vote
    from server.studies.design import Design
    from tests.server_fixtures import make_study

    path = folder / "study.db"
    engine = make_engine(f"sqlite:///{path}")
    migrate(engine)
    rng = random.Random(36)
    out = []
    with session_factory(engine)() as db:
        study = make_study(db, Design(mode="adaptive", conditions=CONDITIONS, animations=["walk", "run"],
                                      catch_trials=1), slug=SLUG)
        for size in sorted(sizes):
            while len(db.scalars(select(Vote.id)).all()) < size:
                participate(db, study, rng)
            out.append(folder / f"study-{size}.db")
            _copy(path, out[-1])
            print(f"built {out[-1].name}: {len(db.scalars(select(Vote.id)).all())} votes", file=sys.stderr)
    engine.dispose()
    return out


def measure(db_path: Path, repeats: int) -> dict[str, object]:
    """(in the tree to measure) The cold request and the request after each of ``repeats`` new votes."""
    from sqlalchemy import func, select

    from server.config import Settings
    from server.db import make_engine, session_factory
    from server.participants.models import Vote
    from server.research.results import study_results
    from server.studies.models import Study

    engine = make_engine(f"sqlite:///{db_path}")
    rng = random.Random(7)
    benchmark = Settings().benchmark_path

    def request(db: object) -> tuple[float, float]:
        study = db.scalar(select(Study).where(Study.slug == SLUG))  # type: ignore[attr-defined]
        wall, cpu = time.perf_counter(), time.process_time()
        study_results(db, study, benchmark)  # type: ignore[arg-type]
        return time.perf_counter() - wall, time.process_time() - cpu

    with session_factory(engine)() as db:
        votes = db.scalar(select(func.count()).select_from(Vote))
        cold = request(db)
        after = []
        for _ in range(repeats):
            participate(db, db.scalar(select(Study).where(Study.slug == SLUG)), rng, trials=1)
            db.expire_all()
            after.append(request(db))
    engine.dispose()
    return {"votes": votes, "cold": cold, "next_vote": [statistics.median(t[0] for t in after),
                                                        statistics.median(t[1] for t in after)]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--votes", type=int, nargs="+", default=[1000, 5000, 10000])
    parser.add_argument("--before", help="also measure this commit's code (git archive)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--measure", type=Path, help=argparse.SUPPRESS)  # internal: one tree, one file
    args = parser.parse_args()
    if args.measure:
        print(json.dumps(measure(args.measure, args.repeats)))
        return
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        files = build(folder, args.votes)
        trees = {"after": REPO}
        if args.before:
            before = folder / "before"
            before.mkdir()
            archive = subprocess.run(["git", "-C", str(REPO), "archive", args.before], check=True,
                                     capture_output=True).stdout
            subprocess.run(["tar", "-x", "-C", str(before)], input=archive, check=True)
            trees = {"before": before, "after": REPO}
        print("| tree | votes | cold request: wall s | CPU s | after one more vote: wall s | CPU s |")
        print("|---|---|---|---|---|---|")
        for file in files:
            for name, tree in trees.items():
                copy = folder / f"{name}-{file.name}"
                _copy(file, copy)
                out = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--measure", str(copy),
                                      "--repeats", str(args.repeats)], cwd=tree, env={**os.environ,
                                      "PYTHONPATH": str(tree)}, check=True, capture_output=True, text=True)
                r = json.loads(out.stdout.strip().splitlines()[-1])
                print(f"| {name} | {r['votes']} | {r['cold'][0]:.2f} | {r['cold'][1]:.2f} | "
                      f"{r['next_vote'][0]:.2f} | {r['next_vote'][1]:.2f} |", flush=True)


if __name__ == "__main__":
    main()
