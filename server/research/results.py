"""The results document of a study: progress, statistics, and the objective metrics of its clips."""

from __future__ import annotations

import copy
import json
import statistics as pystats
from functools import lru_cache
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy.orm import Session

from server.analysis.interval_scale import study_scales
from server.analysis.json_numbers import finite_or_none
from server.analysis.screening import flagged_counts, opinion_array, planned_calibration
from server.analysis.statistics import analyse
from server.analysis.subject_model import fit
from server.participants.assign import session_batches
from server.participants.rows import screened_rows
from server.participants.service import completion_times
from server.research.thresholds import threshold_results
from server.stimuli import service as stimulus_sets
from server.studies import scale
from server.studies.design import Design
from server.studies.models import Study
from server.studies.screening import RULES
from server.studies.service import screening_rules

from .service import participant_counts


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


@lru_cache(maxsize=16)
def _analyse_cached(votes: tuple[tuple[tuple[str, Any], ...], ...], counts: tuple[tuple[str, int], ...],
                    questions: tuple[str, ...], anchor: str | None = None) -> dict[str, Any]:
    return analyse([dict(v) for v in votes], dict(counts), questions, anchor)


@lru_cache(maxsize=16)
def _scales_cached(votes: tuple[tuple[tuple[str, Any], ...], ...], conditions: tuple[str, ...]) -> list[dict]:
    return study_scales([dict(v) for v in votes], conditions)


def adaptive_rounds(session: Session, study: Study) -> list[dict[str, Any]]:
    """Per session of an adaptive study, in order: the votes before it and the information its batch promised
    (``session_batches``: one pass over the counted votes; only rounds whose votes changed are refitted)."""
    return [{"round": i + 1, "votes_before": r.votes_before, "information": r.information, "pairs": r.pairs}
            for i, r in enumerate(session_batches(session, study))]


@lru_cache(maxsize=16)
def _subject_model_cached(votes: tuple[tuple[tuple[str, Any], ...], ...]) -> dict[str, Any]:
    """The P.910/P.913 subject model (``subject_model.fit``) of the test votes of the participants who finished
    and were not screened out: comparisons are the stimuli, their showings the repetitions, animations the
    contents."""
    x, comparisons, subjects = opinion_array([dict(v) for v in votes])
    if len(subjects) < 2 or len(comparisons) < 2:
        return {"status": "too_few", "note": "needs at least two participants and two comparisons"}
    animations = sorted({a for a, _, _ in comparisons})
    model = fit(x, [animations.index(a) for a, _, _ in comparisons])
    status = "degenerate" if model.degenerate else "ok" if model.converged and not model.diverged else "not_converged"
    note = None
    if status == "not_converged" and model.diverged:
        who = [f"participant {subjects[s][:8]}'s inconsistency ({model.inconsistency[s]:.3g})"
               for s in model.diverged_subjects]
        who += [f"{animations[c]}'s ambiguity ({model.ambiguity[c]:.3g})" for c in model.diverged_contents]
        note = (f"No maximum likelihood fit: the solver ran off with {'; '.join(who)}, beyond every difference "
                "between the answers it explains and the model, where a smaller value is more likely. The numbers are "
                "where the solver stopped (as sureal's), not estimates.")
    if model.degenerate:
        on: dict[int, list[str]] = {}
        for s, c in model.degenerate:
            on.setdefault(s, []).append(animations[c])
        who = "; ".join(f"participant {subjects[s][:8]} on {', '.join(names)}" for s, names in on.items())
        note = (f"No maximum likelihood fit: {who} answered exactly as the model predicts (both showings alike, the "
                "animation adding no spread of its own), so the likelihood grows without end as that participant's "
                "inconsistency and the animation's ambiguity go to 0. The numbers are where the solver stopped (as "
                "sureal's), not estimates.")
    return {
        "status": status, "note": note, "iterations": model.iterations,
        "degenerate": [{"session_id": subjects[s], "animation": animations[c]} for s, c in model.degenerate],
        "diverged": {"session_ids": [subjects[s] for s in model.diverged_subjects],
                     "animations": [animations[c] for c in model.diverged_contents]},
        "comparisons": [{"animation": a, "reference": r, "condition": t, "score": finite_or_none(model.quality[e]),
                         "ci95": [finite_or_none(v) for v in model.quality_ci95[e]]}
                        for e, (a, r, t) in enumerate(comparisons)],
        "participants": [{"session_id": sid, "bias": finite_or_none(model.bias[s]),
                          "bias_ci95": [finite_or_none(v) for v in model.bias_ci95[s]],
                          "inconsistency": finite_or_none(model.inconsistency[s]),
                          "inconsistency_ci95": [finite_or_none(v) for v in model.inconsistency_ci95[s]]}
                         for s, sid in enumerate(subjects)],
        "animations": [{"animation": a, "ambiguity": finite_or_none(model.ambiguity[c])}
                       for c, a in enumerate(animations)],
    }


def _analysed_tests(rows: list[dict[str, Any]]) -> tuple[tuple[tuple[str, Any], ...], ...]:
    return tuple(tuple(sorted(v.items())) for v in rows
                 if not v["practice"] and not v["catch"] and v["outcome"] == "completed")


NUMBER_BINS = 4


def number_bins(values: list[float], unit: str | None = None, bins: int = NUMBER_BINS) -> list[tuple[float, float,
                                                                                                        str]]:
    """Up to ``bins`` bins of about equal count (quantiles of the participants' answers): (low, high, label);
    the last bin includes its upper edge."""
    if not values:
        return []
    edges = list(np.unique(np.quantile(values, np.linspace(0, 1, bins + 1))))
    if len(edges) == 1:
        edges = edges * 2
    suffix = f" {unit}" if unit else ""
    return [(lo, hi, f"{lo:g}–{hi:g}{suffix}") for lo, hi in pairwise(edges)]


def demographic_rows(rows: list[dict[str, Any]], questions: list[dict[str, Any]]
                     ) -> tuple[list[dict[str, Any]], tuple[str, ...]]:
    """The rows with each number answer replaced by its bin's label (``number_bins`` over the participants) and
    the question ids to break the results down by: every question but free text."""
    out = [dict(r) for r in rows]
    for q in questions:
        if q.get("type", "choice") != "number":
            continue
        per_participant = {r["session_id"]: r[q["id"]] for r in rows if r.get(q["id"]) is not None}
        bins = number_bins(list(per_participant.values()), q.get("unit"))
        for r in out:
            value = r.get(q["id"])
            if value is not None:
                r[q["id"]] = next((label for lo, hi, label in bins if lo <= value < hi), bins[-1][2])
    return out, tuple(q["id"] for q in questions if q.get("type", "choice") != "text")


def study_results(session: Session, study: Study, benchmark_path: Path,
                  include_pilot: bool = False) -> dict[str, Any]:
    """Everything the dashboard shows.  The statistics are cached on their input: scipy's exact Wilcoxon for
    up to 13 participants with ties enumerates sign patterns and takes seconds, and a dashboard polls.

    The statistics apply the study's screening rules; ``without_screening`` has the same statistics with every
    finished participant counted, and ``screening`` every participant's record.  Pilot sessions are left out
    unless ``include_pilot``."""
    rows, records = screened_rows(session, study, include_pilot)
    binned, questions = demographic_rows(rows, study.questions)
    votes = tuple(tuple(sorted(v.items())) for v in binned)
    unscreened = [{**v, "outcome": "completed" if v["outcome"] else None, "screened_by": None} for v in binned]
    counts_map = participant_counts(session, study, include_pilot, records)
    counts = tuple(sorted(counts_map.items()))
    results = copy.deepcopy(_analyse_cached(votes, counts, questions, study.design["reference"]))
    if any(r.screened_out for r in records.values()):  # else the same numbers: spare the (slow) exact tests
        plain = _analyse_cached(tuple(tuple(sorted(v.items())) for v in unscreened),
                                tuple(sorted({**counts_map, "screened_out": 0}.items())), questions,
                                study.design["reference"])
    else:
        plain = results
    results["without_screening"] = copy.deepcopy({k: plain[k] for k in ("participants", "comparisons", "overall",
                                                                       "side_bias", "krippendorff_alpha_ordinal")})
    rules = screening_rules(study)
    calibration = next((r.calibration for r in records.values() if r.calibration), None)
    if calibration is None and not records:  # before anyone finished: what the design will support, on the prior
        design = Design.model_validate(study.design)
        calibration = planned_calibration(len(design.animations) * design.pairs_per_animation(),
                                          2 * design.repeats, rules)
    results["screening"] = {
        "rules": rules.rules, "settings": rules.model_dump(exclude={"rules"}),
        "catch_failures_allowed": study.recruitment.get("catch_failures_allowed", 0),
        "flagged": flagged_counts(records.values(), rules.rules),
        "excluded": [r.as_dict() for r in records.values() if r.screened_out],
        "participants": [r.as_dict() for r in records.values()],
        # how the design-calibrated thresholds came about: the simulated good observers, each rule's threshold,
        # false-flag rate and power, and which rules the design is too small for (None: fixed thresholds)
        "calibration": calibration.as_dict() | {"planned": not records} if calibration else None,
        "too_little_data": sorted({rule for r in records.values() for rule, v in r.results.items() if not v.judged}
                                  if records else {r for r, c in (calibration.rules if calibration else {}).items()
                                                   if not c.judged}, key=RULES.index),
    }
    results["subject_model"] = copy.deepcopy(_subject_model_cached(_analysed_tests(rows)))
    results["methods"]["exclusions"] = (
        "practice and catch trials; every vote of a participant screened out by the study's screening rules "
        f"({', '.join(rules.rules) or 'none'}; docs/screening.md); pilot sessions unless asked for")
    results["methods"]["subject_model"] = (
        "ITU-T P.910 Annex E / P.913 12.6 maximum likelihood (sureal's MLE): score = comparison score + "
        "participant bias + participant inconsistency + animation ambiguity, over the finished, kept participants")
    results["pilot_included"] = include_pilot
    durations = completion_times(session, study, include_pilot)
    results["overview"] = {
        "slug": study.slug, "title": study.title, "state": study.state,
        "reference": study.design["reference"], "conditions": study.design["conditions"],
        "questions": [{"id": q["id"], "text": q["text"], "type": q.get("type", "choice")} for q in study.questions],
        "votes": len(rows),
        "median_completion_s": pystats.median(durations) if durations else None,
    }
    # The clips of the study's stimulus set, as they were when the set was made: not the clip set on disk, which
    # may have been rebuilt since (and holds other researchers' clips).
    content = stimulus_sets.content_of(study.stimulus_set) if study.stimulus_set is not None else None
    results["stimulus_set"] = study.stimulus_set.digest if study.stimulus_set is not None else None
    results["clips"] = [{"id": c.id, "animation": c.animation, "condition": c.condition, "method": c.method,
                         "params": c.params, "key_count": c.key_count, "metrics": c.metrics, "shown": True,
                         "identical_to": c.identical_to} for c in (content.clips if content else [])]
    results["thresholds"] = threshold_results(study.design, study.scale.get("format", "rating5"), rows,
                                              results["clips"])
    results["benchmark"] = _read_json(benchmark_path)
    mode = study.design.get("mode", "reference")
    results["overview"]["design_mode"] = mode
    results["scale"] = copy.deepcopy(_scales_cached(votes, (study.design["reference"], *study.design["conditions"])))
    results["adaptive_rounds"] = adaptive_rounds(session, study) if mode == "adaptive" else None
    results["answer_scale"] = scale.describe()
    return results
