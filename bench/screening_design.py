"""The screening of issue 36's panel over many seeds: fixed (the standards') against design-calibrated thresholds.

    PYTHONPATH=. .venv/bin/python bench/screening_design.py [--panels 100] [--good 36]

Each panel is the thesis design (8 comparisons x 2 showings = 16 trials, no catch trials) with ``--good`` good
observers and one random, straight-lining, inverted and fast one (tests/screening_sim.py, ``design_panel``), seeds
0 .. panels-1, screened with ``rules = "all"``.  Prints per mode: the panels with at most one good observer
flagged, the good observers flagged per rule, each bad kind caught (by any rule) and by which rules, the rules
that said "too little data", and the time of one calibration (cold, without the fit's cache, and cached).
"""

from __future__ import annotations

import argparse
import time
from collections import Counter

import numpy as np

from server.analysis import screening_design
from server.analysis.screening import calibration, screen
from server.studies.screening import RULES, Screening
from tests.screening_sim import THESIS_PLAYBACK, design_panel

MODES = {
    "fixed": Screening(rules=[r for r in RULES if r != "disagreement"], thresholds="fixed"),  # before issue 36
    "design": Screening(rules="all"),
}


def run(name: str, rules: Screening, panels: int, good: int) -> None:
    at_most_one, good_by_rule, caught, by_rule, too_little = 0, Counter(), Counter(), Counter(), Counter()
    flagged_per_panel = Counter()
    for seed in range(panels):
        rows, kinds = design_panel(seed, good=good)
        got = screen(rows, rules, 0, THESIS_PLAYBACK)
        flagged = [s for s, k in kinds.items() if k == "good" and got[s].screened_out]
        at_most_one += len(flagged) <= 1
        flagged_per_panel[len(flagged)] += 1
        good_by_rule.update(r for s in flagged for r in got[s].flagged_by)
        for sid, kind in kinds.items():
            if kind != "good":
                caught[kind] += got[sid].screened_out
                by_rule.update(f"{kind}:{r}" for r in got[sid].flagged_by)
        too_little.update(r for r, v in got["good00"].results.items() if not v.judged)
    print(f"[{name}] {panels} panels of {good} good + 4 bad: at most one good observer flagged in {at_most_one}; "
          f"good flagged per panel {dict(sorted(flagged_per_panel.items()))}")
    print(f"[{name}] good observers flagged, by rule (of {panels * good}): {dict(good_by_rule)}")
    print(f"[{name}] bad caught by any rule (of {panels} each): {dict(caught)}")
    print(f"[{name}] bad caught, by kind and rule: {dict(sorted(by_rule.items()))}")
    print(f"[{name}] panels in which a rule said too little data: {dict(too_little)}")


def timing(good: int) -> None:
    rows, _ = design_panel(0, good=good)
    cold = []
    for _ in range(3):
        screening_design._calibrate.cache_clear()
        screening_design._fitted.cache_clear()
        start = time.perf_counter()
        c = calibration(rows, MODES["design"], THESIS_PLAYBACK)
        cold.append(time.perf_counter() - start)
    start = time.perf_counter()
    calibration(rows, MODES["design"], THESIS_PLAYBACK)
    warm = time.perf_counter() - start
    assert c is not None
    print(f"calibration of {good + 4} participants: cold {np.median(cold):.3f} s (median of 3, fit included; "
          f"the simulation alone {c.seconds:.3f} s, {c.panels} panels), cached {1000 * warm:.2f} ms")
    for rule, r in c.rules.items():
        print(f"  {rule:16} threshold {r.threshold if r.threshold is None else round(r.threshold, 4)} "
              f"({'below' if r.tail == 'lower' else 'above'}), good flagged {r.false_flag:.4f}, power "
              f"{ {k: round(v, 2) for k, v in r.power.items()} }, {'judges' if r.judged else r.reason}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--panels", type=int, default=100)
    parser.add_argument("--good", type=int, default=36)
    args = parser.parse_args()
    timing(args.good)
    for name, rules in MODES.items():
        run(name, rules, args.panels, args.good)


if __name__ == "__main__":
    main()
