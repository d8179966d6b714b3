"""Time to order one session's trials (issue 26 item 3: under 5 ms for any accepted design).

    .venv/bin/python bench/design_orders.py [--sessions 1000]

For each design shape (comparisons per session, repeats, catch trials) from the thesis to the largest accepted
design, orders ``--sessions`` sessions with design.trial_order and prints the median, 99th percentile and
maximum milliseconds per session (wall clock, and the CPU time of the process, which a loaded machine does not
inflate), and the share of sessions the old rejection sampler's order was kept for
(the rest were repaired).  Every number is measured in this run; on a loaded machine the tail grows.
"""

from __future__ import annotations

import argparse
import random
import sys
import time
from itertools import pairwise

import numpy as np

from server.studies.design import SHUFFLE_BUDGET, ComparisonIds, trial_order

SHAPES = [  # (name, comparisons, repeats, catch trials)
    ("thesis", 8, 1, 0), ("thesis, repeats 4", 8, 4, 0), ("thesis, repeats 5", 8, 5, 0),
    ("one comparison + catch", 1, 1, 1), ("6 conditions all-pairs, 2 animations", 30, 1, 2),
    ("8 conditions all-pairs, 4 animations, repeats 2", 112, 2, 4),
    ("largest: 16 x 16, repeats 5, 16 catch", 256, 5, 16),
]


def kept_old(ids: ComparisonIds, repeats: int, seed: int) -> bool:
    """Whether one of the first budget shuffles (as the old sampler drew them) had no repeat."""
    rng = random.Random(seed)
    items = [c for c in ids.test for _ in range(2 * repeats)] + list(ids.catch)
    for _ in range(max(1, SHUFFLE_BUDGET // len(items))):
        rng.shuffle(items)
        if all(a != b for a, b in pairwise(items)):
            return True
    return False


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sessions", type=int, default=1000)
    args = parser.parse_args(argv)
    print(f"{'design':48} {'trials':>6} {'wall: median':>12} {'p99':>7} {'max':>7} {'CPU: median':>11} {'p99':>7} "
          f"{'max':>7} {'old order kept':>14}   (ms per session)")
    for name, k, repeats, catch in SHAPES:
        ids = ComparisonIds(list(range(k)), catch=list(range(1000, 1000 + catch)), practice=999)
        times, cpu = [], []
        for seed in range(args.sessions):
            start, start_cpu = time.perf_counter(), time.process_time()
            trials = trial_order(ids, repeats, seed)
            cpu.append(1000 * (time.process_time() - start_cpu))
            times.append(1000 * (time.perf_counter() - start))
            assert all(a.comparison_id != b.comparison_id for a, b in pairwise(trials))
        kept = np.mean([kept_old(ids, repeats, s) for s in range(min(args.sessions, 200))])
        print(f"{name:48} {len(trials):6d} {np.median(times):12.3f} {np.percentile(times, 99):7.3f} "
              f"{max(times):7.3f} {np.median(cpu):11.3f} {np.percentile(cpu, 99):7.3f} {max(cpu):7.3f} "
              f"{100 * kept:13.0f}%", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
