"""The results' Wilcoxon p: ``server/analysis/statistics.wilcoxon_p`` (the exact sign-flip distribution counted)
against ``scipy.stats.wilcoxon(..., zero_method="pratt")`` (the same distribution enumerated by a permutation test),
timed in one run, interleaved, on the same participant means (halves from -2 to 2: ties and zeros).

    PYTHONPATH=. .venv/bin/python bench/wilcoxon_exact.py [--repeats 3]

Prints per number of participants the median time of one p of each, the ratio, and the largest difference of
the p-values.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
from scipy import stats

from server.analysis.statistics import WILCOXON_EXACT_MAX_N, wilcoxon_p


def timed(f, x: np.ndarray) -> tuple[float, float]:
    start = time.perf_counter()
    p = f(x)
    return time.perf_counter() - start, p


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    print(f"{'n':>3} {'scipy ms':>10} {'counted ms':>11} {'ratio':>9} {'max |dp|':>9}")
    for n in range(4, WILCOXON_EXACT_MAX_N + 1):
        scipy_s, ours_s, diff = [], [], 0.0
        for _ in range(args.repeats):
            x = rng.integers(-4, 5, n) / 2
            if not np.any(x != 0):
                x[0] = 0.5
            ts, ps = timed(lambda v: stats.wilcoxon(v, zero_method="pratt").pvalue, x)
            to, po = timed(wilcoxon_p, x)
            scipy_s.append(ts)
            ours_s.append(to)
            diff = max(diff, abs(ps - po))
        s, o = statistics.median(scipy_s), statistics.median(ours_s)
        print(f"{n:>3} {s * 1e3:>10.2f} {o * 1e3:>11.3f} {s / o:>9.0f} {diff:>9.1e}", flush=True)


if __name__ == "__main__":
    main()
