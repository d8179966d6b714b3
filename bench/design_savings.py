"""Trials saved by the incomplete and adaptive designs against all-pairs, at equal precision (issue 27).

For N = 4, 6, 8 conditions spanning the same quality range (true scale values evenly spaced over 0..SPAN logit
units, one animation), simulated observers (server.studies.simulate: ordinal Bradley-Terry answers with
per-observer taste, side bias and noise) run through the real design code.  Precision is the root mean square
error of the fitted scale values against the truth, averaged over SEEDS simulated studies.  The target is the
precision of all-pairs with BASE participants; for each other design the participants needed to reach it are
found by bisection on the mean error, and the trials (participants x trials per participant) compared.

    .venv/bin/python bench/design_savings.py [--seeds 20] [--base 10] [--json out.json]

Prints one line per design and N and the table for docs/designs.md; every number is measured in the run.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from server.studies.design import Design
from server.studies.simulate import Observers, simulate

SPAN = 2.5


OBSERVERS = Observers()


def error(design: Design, truth: dict[str, float], participants: int, seeds: int) -> float:
    return float(np.mean([simulate(design, truth, participants, seed=s, observers=OBSERVERS).rmse
                          for s in range(seeds)]))


def needed(design: Design, truth: dict[str, float], target: float, seeds: int, start: int) -> tuple[int, float]:
    """The fewest participants whose mean error is at most ``target`` (bisection between a failing and a passing
    count; the mean error over fixed seeds falls with participants, up to simulation noise)."""
    low, high = 1, start
    high_error = error(design, truth, high, seeds)
    while high_error > target:
        low, high = high, high * 2
        high_error = error(design, truth, high, seeds)
    while high - low > 1:
        mid = (low + high) // 2
        mid_error = error(design, truth, mid, seeds)
        if mid_error <= target:
            high, high_error = mid, mid_error
        else:
            low = mid
    return high, high_error


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--base", type=int, default=10, help="participants of the all-pairs design")
    parser.add_argument("--sizes", type=int, nargs="+", default=[4, 6, 8])
    parser.add_argument("--span", type=float, default=SPAN, help="logit units from the worst to the best condition")
    parser.add_argument("--taste-sd", type=float, default=Observers.taste_sd,
                        help="sd of each observer's own offset per condition (0: all observers alike)")
    parser.add_argument("--json", type=str, default=None)
    args = parser.parse_args(argv)
    global OBSERVERS
    OBSERVERS = Observers(taste_sd=args.taste_sd)
    rows = []
    for n in args.sizes:
        names = [f"c{i}" for i in range(n)]
        truth = {c: args.span * i / (n - 1) for i, c in enumerate(names)}
        designs = {mode: Design(mode=mode, reference="c0", conditions=names[1:], animations=["walk"])
                   for mode in ("all-pairs", "incomplete", "adaptive")}
        started = time.perf_counter()
        target = error(designs["all-pairs"], truth, args.base, args.seeds)
        base_trials = args.base * designs["all-pairs"].trials_total()
        rows.append({"conditions": n, "design": "all-pairs", "participants": args.base, "trials": base_trials,
                     "rmse": target, "saved": 0.0})
        print(f"N={n} all-pairs: {args.base} participants, {base_trials} trials, RMSE {target:.3f}", flush=True)
        for mode in ("incomplete", "adaptive"):
            per = designs[mode].trials_total()
            start = max(2, base_trials // per // 2)
            participants, rmse = needed(designs[mode], truth, target, args.seeds, start)
            trials = participants * per
            rows.append({"conditions": n, "design": mode, "participants": participants, "trials": trials,
                         "rmse": rmse, "saved": 1 - trials / base_trials})
            print(f"N={n} {mode}: {participants} participants, {trials} trials, RMSE {rmse:.3f}, "
                  f"{100 * (1 - trials / base_trials):.0f} % fewer trials than all-pairs", flush=True)
        print(f"  ({time.perf_counter() - started:.0f} s)", flush=True)
    print(f"\nspan {args.span:g} logit units, observers {OBSERVERS}, {args.seeds} seeds, all-pairs with "
          f"{args.base} participants")
    print("\n| conditions | design | participants | trials | RMSE (logit) | trials saved vs all-pairs |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['conditions']} | {r['design']} | {r['participants']} | {r['trials']} | {r['rmse']:.3f} | "
              f"{100 * r['saved']:.0f} % |")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump({"seeds": args.seeds, "base": args.base, "span": args.span, "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
