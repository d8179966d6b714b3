"""Commands of threshold designs (issue 38), apart from ``server/cli`` so that its split and this work merge:

- ``animstudy study simulate FILE`` / ``study plan FILE`` on a study file whose ``[design] mode`` is
  ``constant-stimuli`` or ``staircase``: planted observers through the design (:mod:`server.analysis.thresholds`),
  and the trials needed for a threshold interval of a given width (``--width``, log10 units);
- ``animstudy study threshold-plan --levels 4,6,8,...``: the same without a study file, both designs side by side
  (the QUEST+ efficiency of docs/methods/thresholds.md);
- ``animstudy study frontier EXPORT --manifest DIR``: the cost/quality frontier of an export's threshold votes
  (JSON on standard output, ``--svg`` for the figure).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from collections import defaultdict
from dataclasses import asdict
from pathlib import Path
from typing import Any

THRESHOLD_MODES = ("constant-stimuli", "staircase")
TRIAL_STEPS = (20, 30, 40, 60, 80, 120, 160, 240, 320, 480, 640)


def add_parsers(st_sub: Any, positive: Any) -> None:
    """``study threshold-plan`` and ``study frontier``; ``--width``/``--threshold`` of simulate/plan."""
    tp = st_sub.add_parser("threshold-plan", help="trials a constant-stimuli and a QUEST+ design need for a "
                           "threshold interval of a given width, by simulation (docs/methods/thresholds.md)")
    tp.add_argument("--levels", required=True, help="the ladder's levels, comma-separated, e.g. 4,6,8,12,16,24,30")
    _observer_args(tp)
    tp.add_argument("--seeds", type=positive, default=30, help="simulated participants per trial count")
    fr = st_sub.add_parser("frontier", help="the cost/quality frontier of a threshold study's export (CSV or "
                           "JSON rows with animation, test_condition, level, correct) and a clip set's costs")
    fr.add_argument("export", type=Path)
    fr.add_argument("--manifest", type=Path, required=True, help="the clip-set directory (its manifest's "
                    "metrics give each condition's cost)")
    fr.add_argument("--metric", default="cost_ms_per_1000", help="cost metric: cost_ms_per_1000 (default), bytes")
    fr.add_argument("--criterion", type=float, default=0.75, help="proportion correct taken as noticed (2AFC 0.75)")
    fr.add_argument("--svg", type=Path, default=None, help="also write the plot as SVG")


def _observer_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--threshold", type=float, default=None, help="the planted observer's threshold (level "
                   "units; default: the geometric middle of the levels)")
    p.add_argument("--slope-width", type=float, default=0.5, help="its width, log10 units (5 %% -> 95 %%)")
    p.add_argument("--width", type=float, default=0.2, help="target: median width of the threshold's 95 %% "
                   "interval, log10 units (0.2: the threshold within about a factor 1.26 either way)")
    p.add_argument("--detectable-at", choices=("low", "high"), default="low")


def extend_simulate_plan(sm: argparse.ArgumentParser, sp: argparse.ArgumentParser) -> None:
    for p in (sm, sp):
        p.add_argument("--threshold", type=float, default=None, help="threshold designs: the planted observer's "
                       "threshold (default: the geometric middle of the ladder)")
        p.add_argument("--slope-width", type=float, default=0.5, help="threshold designs: its width, log10 units")
    sp.add_argument("--width", type=float, default=0.2, help="threshold designs: the target median width of the "
                    "threshold's 95 %% interval, log10 units")


def _observer(levels: list[float], args: argparse.Namespace) -> Any:
    from server.analysis.thresholds import Observer

    thr = args.threshold or math.sqrt(min(levels) * max(levels))
    return Observer(threshold=thr, width=args.slope_width, increasing=args.detectable_at == "high"
                    if hasattr(args, "detectable_at") else False)


def _line(design: str, trials: int, s: Any) -> str:
    return (f"  {design} {trials} trials: threshold interval median {s.median_span:.3f} log10 units "
            f"(95 % {s.span_low:.3f} … {s.span_high:.3f}), planted threshold inside in {100 * s.coverage:.0f} %")


def _plan(design: str, levels: list[float], obs: Any, width: float, seeds: int) -> tuple[int | None, Any]:
    from server.analysis import thresholds as th

    steps = [t for t in TRIAL_STEPS if design == "staircase" or t >= len(levels)]
    if design == "constant-stimuli":
        steps = sorted({max(1, t // len(levels)) * len(levels) for t in steps})
    needed, tried = th.trials_for(design, obs, levels, width, seeds, steps, progress=lambda t, s: print(
        _line(design, t, s), file=sys.stderr, flush=True))
    return needed, tried[-1]


def threshold_plan(args: argparse.Namespace) -> int:
    try:
        levels = sorted(float(v) for v in args.levels.split(","))
    except ValueError:
        print(f"--levels: numbers separated by commas, got {args.levels!r}", file=sys.stderr)
        return 2
    if len(levels) < 3 or len(set(levels)) != len(levels) or min(levels) <= 0:
        print("--levels: 3 or more different positive levels", file=sys.stderr)
        return 2
    obs = _observer(levels, args)
    result = {}
    for design in THRESHOLD_MODES:
        needed, last = _plan(design, levels, obs, args.width, args.seeds)
        result[design] = needed
        print(f"{design}: " + (f"{needed} trials" if needed else f"more than {last.trials} trials")
              + f" for a median threshold interval of {args.width:g} log10 units", flush=True)
    if all(result.values()):
        print(f"QUEST+ / constant stimuli: {result['staircase'] / result['constant-stimuli']:.2f} of the trials")
    return 0


def simulate_or_plan(args: argparse.Namespace, design: Any) -> int:
    """``study simulate``/``plan`` of a study file whose design is a threshold design (``design.level_order()``:
    condition -> level of its ladder, ``design.detectable_at``, ``design.trials``/``repeats``)."""
    from server.analysis import thresholds as th

    levels = sorted(float(v) for v in design.level_order().values())
    args.detectable_at = getattr(design, "detectable_at", "low")
    obs = _observer(levels, args)
    if args.study_command == "simulate":
        trials = design.trials if design.mode == "staircase" else 2 * design.repeats * len(levels)
        s = th.summarize(design.mode, obs, levels, trials, args.seeds)
        print(f"{design.mode} design over {len(levels)} levels, observer threshold {obs.threshold:g}:")
        print(_line(design.mode, trials, s))
        return 0
    needed, last = _plan(design.mode, levels, obs, args.width, args.seeds)
    if needed is None:
        print(f"more than {last.trials} trials per participant and animation", file=sys.stderr)
        return 1
    print(f"{needed} trials per participant and animation for a median threshold interval of {args.width:g} "
          "log10 units")
    return 0


def _truthy(v: Any) -> bool | None:
    if isinstance(v, bool):
        return v
    s = str(v).strip().lower()
    return True if s == "true" else False if s == "false" else None


def read_export(path: Path) -> list[dict[str, Any]]:
    text = path.read_text(encoding="utf-8")
    if path.suffix == ".json":
        data = json.loads(text)
        return list(data["votes"] if isinstance(data, dict) else data)
    return list(csv.DictReader(text.splitlines()))


def counts(rows: list[dict[str, Any]], key: tuple[str, ...] = ("animation",)
           ) -> dict[Any, list[tuple[str, float, int, int]]]:
    """Per animation (or per ``key`` columns, e.g. ``("animation", "session_id")`` for each participant),
    (condition, level, trials, correct) of the rows with a level and a ``correct`` (catch and practice trials
    left out)."""
    acc: dict[Any, dict[tuple[str, float], list[int]]] = defaultdict(lambda: defaultdict(lambda: [0, 0]))
    for r in rows:
        ok = _truthy(r.get("correct"))
        if ok is None or r.get("level") in (None, "") or _truthy(r.get("catch")) or _truthy(r.get("practice")):
            continue
        group = str(r[key[0]]) if len(key) == 1 else tuple(str(r.get(k)) for k in key)
        c = acc[group][(str(r["test_condition"]), float(r["level"]))]
        c[0] += 1
        c[1] += int(ok)
    return {a: [(c, lv, n, k) for (c, lv), (n, k) in sorted(by.items(), key=lambda i: i[0][1])]
            for a, by in acc.items()}


def frontier_command(args: argparse.Namespace) -> int:
    from server.analysis.frontier_plot import svg
    from server.analysis.psychometric import fit, frontier
    from server.clipset.manifest import read_clip_manifest

    try:
        rows = read_export(args.export)
        per_animation = counts(rows)
        manifest = read_clip_manifest(args.manifest)
    except (OSError, ValueError, KeyError) as exc:
        print(str(exc), file=sys.stderr)
        return 1
    if not per_animation:
        print(f"{args.export}: no answered threshold trials (rows with level and correct)", file=sys.stderr)
        return 1
    costs: dict[str, dict[str, float]] = defaultdict(dict)
    for clip in manifest.clips:
        v = clip.metrics.get(args.metric)
        if v is not None:
            costs[clip.animation][clip.condition] = float(v)
    try:
        fronts = [frontier(a, rows, costs[a], cost_metric=args.metric, criterion=args.criterion)
                  for a, rows in sorted(per_animation.items())]
    except ValueError as exc:
        print(str(exc), file=sys.stderr)
        return 1
    out = [asdict(f) for f in fronts]
    for entry in out:  # each participant's own fit (3 levels or more answered), fewer resamples
        entry["participants"] = {}
        for (animation, session), c in sorted(counts(rows, ("animation", "session_id")).items()):
            if animation == entry["animation"] and len({lv for _, lv, _, _ in c}) >= 3:
                f = fit([lv for _, lv, _, _ in c], [n for *_, n, _ in c], [k for *_, k in c], bootstrap=200)
                entry["participants"][session] = asdict(f)
    print(json.dumps(out, indent=2))
    if args.svg:
        args.svg.write_text(svg(fronts), encoding="utf-8")
    return 0
