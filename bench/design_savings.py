"""Trials saved by the incomplete and adaptive designs against all-pairs, at equal precision (issue 27).

For N = 4, 6, 8 conditions spanning the same quality range (true scale values evenly spaced over 0..SPAN logit
units, one animation), simulated observers (server.analysis.simulate: ordinal Bradley-Terry answers with
per-observer taste, side bias and noise) run through the real design code.

Precision is the same number for every design: the root mean square error of the fitted scale values (maximum
likelihood, the reference at 0, as the results report them) against the truth, pooled over the conditions and the
SEEDS simulated studies of a point (the square root of the mean squared error; one study's error varies by about
half its size from study to study, so the mean over many studies is what can be compared).  Simulated study s
has the same people for every design and participant count (common random numbers), so the designs are compared
on the same observers.

Equal precision: all-pairs with BASE participants sets the target; every other design is run at a grid of
participant counts (about 0.4 to 1.3 times all-pairs' trials) and the trials at which it reaches the target are
interpolated on the line log(MSE) = a - b log(trials) fitted (least squares) to the three grid points nearest
the target (the mean squared error of a fixed design falls about as 1/trials).  The 90 % interval of the saving
is the bootstrap over the simulated studies (the same resample for every design of a row).  A second precision,
the "centred" error (the errors after removing their mean per study: how well the scale's shape is found,
whichever condition is the anchor), is reported beside it, and so is the saving for the mean over studies of each
study's RMSE (the first version's aggregation: it weighs a rare bad study less than the pooled error does); the
goal is read on the first.

    PYTHONPATH=. .venv/bin/python bench/design_savings.py [--seeds 60] [--base 10] [--sizes 4 6 8] [--span 2.5]
        [--aim reference|order] [--modes incomplete adaptive] [--json out.json]

Prints the measured points and the table for docs/designs.md; every number is measured in the run.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from functools import partial

import numpy as np
from scipy import optimize

from server.analysis import adaptive
from server.analysis.adaptive import Belief
from server.analysis.simulate import CUTS, Observers, simulate
from server.studies.design import Design

SPAN = 2.5
GRID = (0.4, 0.6, 0.8, 1.0, 1.3)  # the other designs' trials, as shares of all-pairs' trials
BOOT = 1000
NEAR = 3
TRUE_CUTS = np.array([-CUTS[1], -CUTS[0], CUTS[0], CUTS[1]])  # the simulated observers' cut points


def squared_errors(design: Design, truth: dict[str, float], participants: int, seeds: int,
                   observers: Observers,
                   belief: Belief = adaptive.posterior) -> tuple[np.ndarray, np.ndarray, int, int]:
    """(seeds, N-1) errors squared, anchored and centred; the trials per study; conditions without a finite
    value over all studies (left out of the errors).  ``belief``: what an adaptive design plans on."""
    anchored, centred, failed, trials = [], [], 0, 0
    conditions = design.all_conditions()[1:]
    for s in range(seeds):
        run = simulate(design, truth, participants, seed=s, observers=observers, belief=belief)
        trials = run.trials
        values = run.estimate[design.animations[0]]
        error = np.array([math.nan if values[c] is None else values[c] - (truth[c] - truth[design.reference])
                          for c in conditions])
        failed += int(np.isnan(error).sum())
        anchored.append(error**2)
        # The anchor's error is 0 by construction; the centred error removes the mean over all N conditions.
        full = np.concatenate([[0.0], error])
        centred.append((full - np.nanmean(full))[1:] ** 2)
    return np.array(anchored), np.array(centred), trials, failed


def pooled(errors: np.ndarray, rows: np.ndarray | slice = slice(None)) -> float:
    return float(np.nanmean(errors[rows]))


def mean_rmse(errors: np.ndarray) -> float:
    """The mean over studies of each study's RMSE (how the first version of this bench aggregated)."""
    return float(np.mean(np.sqrt(np.nanmean(errors, axis=1))))


def trials_at(target: float, trials: np.ndarray, mse: np.ndarray) -> tuple[float, float]:
    """The trials at which the line log(mse) = a - b log(trials), fitted to the NEAR grid points closest to
    ``target``, reaches it; and b.  Only the near points: with few participants a study can be nearly separated
    and its maximum likelihood values huge, a point far off the line that must not bend it at the target."""
    near = np.argsort(np.abs(np.log(mse) - np.log(target)))[:NEAR]
    slope, intercept = np.polyfit(np.log(trials[near]), np.log(mse[near]), 1)
    return float(np.exp((np.log(target) - intercept) / slope)), float(-slope)


def allocation_bound(n: int, span: float) -> tuple[float, float]:
    """The most trials any fixed allocation of the pairs can save against all-pairs (equal shares of every pair),
    for the variances against the anchor and of the centred values: the A-optimal design under the Fisher
    information of one five-point answer at the true differences (the simulated observers' cut points; no taste,
    side bias or noise differences between observers, so the participant-count effect is not in it).  The
    variance of a fixed design falls as 1/trials, so the saving at equal precision is 1 - optimal/all-pairs."""
    truth = np.linspace(0.0, span, n)
    first, second = np.triu_indices(n, 1)
    info = adaptive.answer_information(truth[second] - truth[first], TRUE_CUTS)
    x = np.zeros((first.size, n))
    x[np.arange(first.size), second], x[np.arange(first.size), first] = 1.0, -1.0

    def variance(share: np.ndarray, anchored: bool) -> float:
        fisher = x.T @ ((share * info)[:, None] * x)
        # Against the anchor: the anchor's row and column out; centred: the pseudo-inverse (the zero eigenvalue of
        # the all-ones direction out).  A disconnected allocation has another zero eigenvalue: infinite variance.
        eig = np.linalg.eigvalsh(fisher[1:, 1:]) if anchored else np.linalg.eigvalsh(fisher)[1:]
        return float(np.sum(1 / np.maximum(eig, 1e-12)))

    savings = []
    for anchored in (True, False):
        equal = variance(np.full(first.size, 1 / first.size), anchored)
        best = optimize.minimize(lambda z, a=anchored: variance(np.exp(z) / np.exp(z).sum(), a),
                                 np.zeros(first.size), method="BFGS")
        savings.append(1 - min(best.fun, equal) / equal)
    return savings[0], savings[1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=60)
    parser.add_argument("--base", type=int, default=10, help="participants of the all-pairs design")
    parser.add_argument("--sizes", type=int, nargs="+", default=[4, 6, 8])
    parser.add_argument("--span", type=float, default=SPAN, help="logit units from the worst to the best condition")
    parser.add_argument("--taste-sd", type=float, default=Observers.taste_sd,
                        help="sd of each observer's own offset per condition (0: all observers alike)")
    parser.add_argument("--aim", choices=("reference", "order"), default="reference",
                        help="the adaptive design's aim: reference (the tree for the values against the anchor, the "
                        "default) or order (ASAP's information-gain tree)")
    parser.add_argument("--modes", nargs="+", default=["incomplete", "adaptive"],
                        choices=("incomplete", "adaptive", "oracle"),
                        help="oracle: the adaptive design planning on the true values and cut points instead of "
                        "the posterior (what knowing the truth would save; not a design a study can use)")
    parser.add_argument("--json", type=str, default=None)
    args = parser.parse_args(argv)
    observers = Observers(taste_sd=args.taste_sd)
    rng = np.random.default_rng(0)
    boot = rng.integers(0, args.seeds, (BOOT, args.seeds))
    rows = []
    for n in args.sizes:
        names = [f"c{i}" for i in range(n)]
        truth = {c: args.span * i / (n - 1) for i, c in enumerate(names)}
        designs = {mode: Design(mode="adaptive" if mode == "oracle" else mode, reference="c0",
                                conditions=names[1:], animations=["walk"],
                                aim=args.aim if mode in ("adaptive", "oracle") else None)
                   for mode in ("all-pairs", *args.modes)}
        beliefs = {mode: adaptive.posterior for mode in designs}
        beliefs["oracle"] = partial(adaptive.known_posterior, values=truth, cuts=TRUE_CUTS)
        started, cpu = time.perf_counter(), time.process_time()
        base_a, base_c, base_trials, base_failed = squared_errors(designs["all-pairs"], truth, args.base,
                                                                  args.seeds, observers)
        row = {"conditions": n, "design": "all-pairs", "participants": [args.base], "trials": [base_trials],
               "rmse": [math.sqrt(pooled(base_a))], "rmse_centred": [math.sqrt(pooled(base_c))],
               "failed": base_failed, "per_study_mse": [np.nanmean(base_a, axis=1).tolist()]}
        rows.append(row)
        bound = allocation_bound(n, args.span)
        row["bound"] = list(bound)
        print(f"N={n} best fixed allocation of the pairs (Fisher information at the true values, observers "
              f"alike): {100 * bound[0]:.0f} % fewer trials against the anchor, {100 * bound[1]:.0f} % centred",
              flush=True)
        print(f"N={n} all-pairs: {args.base} participants, {base_trials} trials, RMSE {row['rmse'][0]:.3f} "
              f"(centred {row['rmse_centred'][0]:.3f}), {base_failed} conditions without a value", flush=True)
        for mode in args.modes:
            per = designs[mode].trials_total()
            counts = sorted({max(2, round(f * base_trials / per)) for f in GRID})
            grid = [squared_errors(designs[mode], truth, p, args.seeds, observers, beliefs[mode]) for p in counts]
            trials = np.array([g[2] for g in grid], dtype=float)
            out = {"conditions": n, "design": mode, "participants": counts, "trials": trials.tolist(),
                   "rmse": [math.sqrt(pooled(g[0])) for g in grid],
                   "rmse_centred": [math.sqrt(pooled(g[1])) for g in grid],
                   "failed": sum(g[3] for g in grid),
                   "per_study_mse": [np.nanmean(g[0], axis=1).tolist() for g in grid]}
            for key, k, base in (("", 0, base_a), ("_centred", 1, base_c)):
                needed, slope = trials_at(pooled(base), trials, np.array([pooled(g[k]) for g in grid]))
                saved = []
                for draw in boot:
                    t, _ = trials_at(pooled(base, draw), trials, np.array([pooled(g[k], draw) for g in grid]))
                    saved.append(1 - t / base_trials)
                out["trials_needed" + key] = needed
                out["slope" + key] = slope
                out["saved" + key] = 1 - needed / base_trials
                out["saved_90" + key] = [float(np.percentile(saved, 5)), float(np.percentile(saved, 95))]
            # The first version's aggregation, the mean over studies of each study's RMSE, beside it.
            out["saved_mean_rmse"] = 1 - trials_at(mean_rmse(base_a) ** 2, trials,
                                                   np.array([mean_rmse(g[0]) ** 2 for g in grid]))[0] / base_trials
            rows.append(out)
            points = ", ".join(f"{p}: {r:.3f}" for p, r in zip(counts, out["rmse"], strict=True))
            print(f"N={n} {mode}: RMSE by participants {{{points}}}; all-pairs' precision at "
                  f"{out['trials_needed']:.0f} trials: {100 * out['saved']:.0f} % fewer "
                  f"(90 % {100 * out['saved_90'][0]:.0f}..{100 * out['saved_90'][1]:.0f}); centred: "
                  f"{100 * out['saved_centred']:.0f} % ({100 * out['saved_90_centred'][0]:.0f}.."
                  f"{100 * out['saved_90_centred'][1]:.0f}); mean of the studies' RMSE: "
                  f"{100 * out['saved_mean_rmse']:.0f} %; "
                  f"{out['failed']} conditions without a value",
                  flush=True)
        print(f"  ({time.perf_counter() - started:.0f} s wall, {time.process_time() - cpu:.0f} s CPU)",
              flush=True)
    print(f"\nspan {args.span:g} logit units, observers {observers}, {args.seeds} simulated studies per point, "
          f"all-pairs with {args.base} participants, adaptive aim {args.aim}")
    print("\n| conditions | all-pairs: trials, RMSE | design | trials for the same RMSE | trials saved (90 % interval) "
          "| saved, centred RMSE | saved, mean of the studies' RMSE |")
    print("|---|---|---|---|---|---|---|")
    base = {}
    for r in rows:
        if r["design"] == "all-pairs":
            base = r
            continue
        print(f"| {r['conditions']} | {base['trials'][0]}, {base['rmse'][0]:.3f} | {r['design']} | "
              f"{r['trials_needed']:.0f} | {100 * r['saved']:.0f} % ({100 * r['saved_90'][0]:.0f} to "
              f"{100 * r['saved_90'][1]:.0f} %) | {100 * r['saved_centred']:.0f} % | "
              f"{100 * r['saved_mean_rmse']:.0f} % |")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump({"seeds": args.seeds, "base": args.base, "span": args.span, "aim": args.aim,
                       "taste_sd": args.taste_sd, "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
