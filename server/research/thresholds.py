"""Threshold designs' results (issue 38): per animation, detection per level of the ladder, the psychometric fit,
the cost/quality frontier and the cheapest indistinguishable level, from a study's screened vote rows and the costs
its stimulus set's clips carry (``cost_ms_per_1000``, ms per 1,000 characters per frame, from the build).  The
statistics are :mod:`server.analysis.psychometric`'s; this module only gathers their input and shapes the output for
the results API and the dashboard."""

from __future__ import annotations

import copy
from collections import defaultdict
from dataclasses import asdict
from functools import lru_cache
from typing import Any

from server.analysis import frontier_plot, psychometric
from server.analysis.json_numbers import json_safe

THRESHOLD_MODES = ("constant-stimuli", "staircase")
COST_METRIC = "cost_ms_per_1000"
# Resamples of the threshold's bootstrap interval: a dashboard polls the results, and 200 keep a fit of a few
# hundred answers under 0.2 s; the profile-likelihood interval (the one for staircase data) needs none.
BOOTSTRAP = 200


def counts(rows: list[dict[str, Any]]) -> dict[str, list[tuple[str, float, int, int]]]:
    """Per animation, (condition, level, trials, correct) of the analysed 2AFC answers: no practice or catch
    trial, no participant screened out, a level and a right/wrong answer."""
    tally: dict[tuple[str, str, float], list[int]] = defaultdict(lambda: [0, 0])
    for r in rows:
        if (r["practice"] or r["catch"] or r.get("outcome") == "screened_out" or r.get("level") is None
                or r.get("correct") is None):
            continue
        t = tally[(r["animation"], r["test_condition"], float(r["level"]))]
        t[0] += 1
        t[1] += bool(r["correct"])
    out: dict[str, list[tuple[str, float, int, int]]] = defaultdict(list)
    for (animation, condition, level), (n, k) in sorted(tally.items()):
        out[animation].append((condition, level, n, k))
    return dict(out)


@lru_cache(maxsize=32)
def _frontiers(tallies: tuple[tuple[str, tuple[tuple[str, float, int, int], ...]], ...],
               costs: tuple[tuple[str, tuple[tuple[str, float], ...]], ...]) -> tuple[list[dict[str, Any]], str]:
    cost_of = {a: dict(c) for a, c in costs}
    fronts, out = [], []
    for animation, rows in tallies:
        try:
            f = psychometric.frontier(animation, rows, cost_of.get(animation, {}), cost_metric=COST_METRIC,
                                      bootstrap=BOOTSTRAP)
        except ValueError as exc:  # no level with answers has a cost: say so, do not fail the results
            out.append({"animation": animation, "error": str(exc)})
            continue
        fronts.append(f)
        out.append(asdict(f))
    return json_safe(out), frontier_plot.svg(fronts) if fronts else ""


def threshold_results(design: dict[str, Any], answer_format: str, rows: list[dict[str, Any]],
                      clips: list[dict[str, Any]]) -> dict[str, Any] | None:
    """The ``thresholds`` block of a study's results, or None for a design that is not a threshold design.
    ``clips``: the study's clips as the results list them (id, animation, condition, metrics)."""
    if design.get("mode") not in THRESHOLD_MODES:
        return None
    base = {"ladder": design.get("ladder"), "cost_metric": COST_METRIC, "criterion": psychometric.CRITERION_2AFC,
            "method": "psychometric function (psignifit 4's model: cumulative normal on log10 levels, guess 0.5, "
                      "lapse up to 0.1) by maximum likelihood; detection per level with Clopper-Pearson 95 % "
                      "intervals; the cheapest indistinguishable level is the lowest-cost level whose upper bound "
                      "stays below 75 % correct (docs/methods/thresholds.md)"}
    if answer_format != "2afc":
        return base | {"animations": [], "svg": "", "note": "thresholds are fitted to 2AFC answers; this study "
                                                             f"answers {answer_format}"}
    tallies = counts(rows)
    costs: dict[str, dict[str, float]] = defaultdict(dict)
    for c in clips:
        value = (c.get("metrics") or {}).get(COST_METRIC)
        if value is not None:
            costs[c["animation"]][c["condition"]] = float(value)
    animations, svg = _frontiers(tuple((a, tuple(r)) for a, r in sorted(tallies.items())),
                                 tuple((a, tuple(sorted(c.items()))) for a, c in sorted(costs.items())))
    return base | {"animations": copy.deepcopy(animations), "svg": svg}
