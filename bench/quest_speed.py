"""QUEST+ staircases: ``server/analysis/quest.py`` against the ``questplus`` package (a test dependency), timed in
one run, interleaved, on the same ladder, answers and grid (the 2AFC grid of the staircase designs).

    PYTHONPATH=. .venv/bin/python bench/quest_speed.py [--staircases 20] [--trials 60]

Prints per implementation the median time of one staircase of ``--trials`` trials (next level, answer, update)
and of one staircase vote after ``--trials`` answers (the server replays the history: posterior, then the next
level), the ratio, and whether both chose the same levels.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import questplus

from server.analysis import quest
from server.analysis.thresholds import PPS_LEVELS, Observer


def staircase_numpy(detection: np.ndarray, observer: Observer, trials: int, seed: int) -> list[int]:
    rng = np.random.default_rng(seed)
    post, shown = quest.posterior(detection, []), []
    for _ in range(trials):
        i = quest.next_index(detection, post)
        post = quest.update(post, detection, i, bool(rng.random() < observer.p(np.array([PPS_LEVELS[i]]))[0]))
        shown.append(i)
    return shown


def staircase_questplus(grid: quest.Grid, observer: Observer, trials: int, seed: int) -> list[int]:
    rng = np.random.default_rng(seed)
    q = questplus.QuestPlus(stim_domain={"intensity": list(grid.xs)}, param_domain=grid.domain(),
                            outcome_domain={"response": ["Yes", "No"]}, func="norm_cdf", stim_scale="linear",
                            stim_selection_method="min_entropy")
    shown = []
    for _ in range(trials):
        i = grid.xs.index(q.next_stim["intensity"])
        seen = bool(rng.random() < observer.p(np.array([PPS_LEVELS[i]]))[0])
        q.update(stim={"intensity": grid.xs[i]}, outcome={"response": "Yes" if seen else "No"})
        shown.append(i)
    return shown


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--staircases", type=int, default=20)
    parser.add_argument("--trials", type=int, default=60)
    args = parser.parse_args()
    observer = Observer(threshold=10.0, width=0.5, lapse=0.02)
    grid = quest.Grid(tuple(-np.log10(PPS_LEVELS)), (0.5,))
    detection = grid.detection()
    staircase_questplus(grid, observer, 2, 0)  # imports and first calls outside the timing
    times: dict[str, list[float]] = {"questplus": [], "numpy": []}
    same = True
    for seed in range(args.staircases):
        for name in ("questplus", "numpy") if seed % 2 else ("numpy", "questplus"):
            started = time.perf_counter()
            shown = (staircase_questplus(grid, observer, args.trials, seed) if name == "questplus"
                     else staircase_numpy(detection, observer, args.trials, seed))
            times[name].append(time.perf_counter() - started)
            if name == "numpy":
                ours = shown
            else:
                theirs = shown
        same &= ours == theirs
    history = [(i % len(PPS_LEVELS), i % 3 == 0) for i in range(args.trials)]
    vote = []
    for _ in range(50):
        started = time.perf_counter()
        quest.next_index(detection, quest.posterior(detection, history))
        vote.append(time.perf_counter() - started)
    med = {k: statistics.median(v) for k, v in times.items()}
    print(f"{args.staircases} staircases of {args.trials} trials, median per staircase: questplus "
          f"{med['questplus'] * 1000:.1f} ms, numpy {med['numpy'] * 1000:.2f} ms, ratio "
          f"{med['questplus'] / med['numpy']:.0f}; same levels chosen: {same}")
    print(f"a vote after {args.trials} answers (replayed history, numpy): {statistics.median(vote) * 1000:.3f} ms")


if __name__ == "__main__":
    main()
