"""Statistics of a study's votes, with participants as the unit of analysis.

Input is one record per vote (the export rows).  For every analysed comparison each participant contributes one
number, the mean of their two side-swapped showings (practice and catch trials excluded, and every vote of a
participant screened out by the catch trials: export ``outcome`` ``screened_out``); tests run on those
participant means, never on raw votes (which are not independent).  A comparison is one test condition of one
animation against the study's reference condition; scores are from the test condition's point of view (see
``scale``): +2 test significantly better ... -2 reference significantly better.  An undefined statistic is
``None``.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict
from typing import Any

import numpy as np
from scipy import stats
from statsmodels.stats.power import TTestPower

from server.studies.scale import MAX_SCORE, RAW_SCORES, SCORES

from .json_numbers import finite_or_none
from .ranking import GradedComparison, rank_conditions

WILCOXON_ARE = 3 / math.pi  # asymptotic relative efficiency of Wilcoxon against t for a normal parent


#: Up to this many participant means scipy's default Wilcoxon p is exact; with ties or zeros (Likert means always
#: have them) it gets there by a permutation test over all 2**n sign flips: 2.2 s for one comparison at n = 13.
WILCOXON_EXACT_MAX_N = 13


def wilcoxon_p(x: Sequence[float]) -> float | None:
    """Two-sided Wilcoxon signed-rank p against 0 (Pratt's zero handling), the p of scipy's default method.

    Up to ``WILCOXON_EXACT_MAX_N`` values the same exact null distribution scipy enumerates (the sum of the ranks
    of the positive values under every sign flip; zeros are ranked and never signed) is counted instead, as the
    subset sums of the doubled ranks (integers: tied ranks are halves); above it, scipy's normal approximation.
    """
    x = np.asarray(x, dtype=float)
    if x.size == 0 or not np.any(x != 0):
        return None
    if x.size > WILCOXON_EXACT_MAX_N:
        try:
            return finite_or_none(stats.wilcoxon(x, zero_method="pratt").pvalue)
        except ValueError:
            return None
    doubled = np.rint(2 * stats.rankdata(np.abs(x))).astype(np.int64)
    observed = int(doubled[x > 0].sum())
    signed = doubled[x != 0]
    counts = np.zeros(int(signed.sum()) + 1, dtype=np.int64)  # counts[s]: sign flips with sum s
    counts[0] = 1
    for r in signed:
        counts[r:] = counts[r:] + counts[:-r]
    total = counts.sum()
    return min(1.0, 2 * min(counts[:observed + 1].sum() / total, counts[observed:].sum() / total))


def sign_test_p(x: Sequence[float]) -> float | None:
    """Exact two-sided binomial test on the signs, zeros dropped."""
    x = np.asarray(x, dtype=float)
    n = int(np.count_nonzero(x))
    return None if n == 0 else float(stats.binomtest(int(np.sum(x > 0)), n, 0.5).pvalue)


def rank_biserial(x: Sequence[float]) -> float | None:
    """Matched-pairs rank-biserial (T+ - T-)/(T+ + T-) on the ranks of the non-zero |x| (Kerby 2014)."""
    x = np.asarray(x, dtype=float)
    nz = x[x != 0]
    if nz.size == 0:
        return None
    ranks = stats.rankdata(np.abs(nz))
    return float((ranks[nz > 0].sum() - ranks[nz < 0].sum()) / ranks.sum())


def t_interval(x: Sequence[float], level: float = 0.95) -> list[float] | None:
    """Student-t confidence interval of the mean."""
    x = np.asarray(x, dtype=float)
    if x.size < 2:
        return None
    mean, sem = float(x.mean()), float(stats.sem(x))
    if sem == 0:
        return [mean, mean]
    half = float(stats.t.ppf(0.5 + level / 2, x.size - 1)) * sem
    return [mean - half, mean + half]


def holm(pvalues: Sequence[float | None]) -> list[float | None]:
    """Holm-adjusted p-values; ``None`` entries stay ``None`` and do not count towards the family."""
    present = [i for i, p in enumerate(pvalues) if p is not None]
    out: list[float | None] = [None] * len(pvalues)
    if present:
        # Holm (1979) directly: statsmodels' multipletests(method="holm") calls gc.collect(), 0.2 s of a results
        # request in a server's heap.  Sorted ascending, the k-th smallest (from 0) times (m - k), kept monotone.
        p = np.array([pvalues[i] for i in present], dtype=float)
        order = np.argsort(p, kind="stable")
        adjusted = np.empty_like(p)
        adjusted[order] = np.minimum(np.maximum.accumulate(p[order] * np.arange(p.size, 0, -1)), 1.0)
        for i, value in zip(present, adjusted, strict=True):
            out[i] = float(value)
    return out


def weighted_kappa(a: Sequence[int], b: Sequence[int], labels: Sequence[int] = SCORES,
                   weights: str = "quadratic") -> float | None:
    """Cohen's weighted kappa of two paired ratings over a fixed, ordered label set (unused labels count)."""
    index = {label: i for i, label in enumerate(labels)}
    k = len(labels)
    observed = np.zeros((k, k))
    for x, y in zip(a, b, strict=True):
        observed[index[x], index[y]] += 1
    n = observed.sum()
    if n == 0:
        return None
    observed /= n
    expected = np.outer(observed.sum(axis=1), observed.sum(axis=0))
    i, j = np.indices((k, k))
    w = (np.abs(i - j) if weights == "linear" else (i - j) ** 2) / (k - 1) ** (1 if weights == "linear" else 2)
    denominator = float((w * expected).sum())
    return None if denominator == 0 else float(1 - (w * observed).sum() / denominator)


def krippendorff_alpha_ordinal(units: Iterable[Sequence[float]], values: Sequence[float] = SCORES) -> float | None:
    """Krippendorff's alpha with the ordinal metric.

    ``units``: for each unit, the values the coders gave it (missing ones left out); units with fewer than two
    values are not pairable and drop out.  ``values``: the ordered value domain.
    """
    index = {v: i for i, v in enumerate(values)}
    k = len(values)
    coincidence = np.zeros((k, k))
    for unit in units:
        ratings = [index[v] for v in unit]
        m = len(ratings)
        if m < 2:
            continue
        counts = np.bincount(ratings, minlength=k).astype(float)
        # Ordered pairs of different coders: c-k pairs number counts_c * counts_k (minus self-pairs on the diagonal).
        coincidence += (np.outer(counts, counts) - np.diag(counts)) / (m - 1)
    n_c = coincidence.sum(axis=1)
    n = n_c.sum()
    if n <= 1:
        return None
    cumulative = np.concatenate([[0.0], np.cumsum(n_c)])
    c, kk = np.indices((k, k))
    lo, hi = np.minimum(c, kk), np.maximum(c, kk)
    delta2 = (cumulative[hi + 1] - cumulative[lo] - (n_c[c] + n_c[kk]) / 2) ** 2
    observed = float((coincidence * delta2).sum() / n)
    expected = float((np.outer(n_c, n_c) * delta2).sum() / (n * (n - 1)))
    return None if expected == 0 else 1 - observed / expected


def participants_needed(x: Sequence[float], power: float = 0.8, alpha: float = 0.05) -> int | None:
    """Participants for ``power`` at the observed effect d_z = mean/sd (Wilcoxon via the t-test and its ARE)."""
    x = np.asarray(x, dtype=float)
    if x.size < 2 or float(x.std(ddof=1)) == 0 or float(x.mean()) == 0:
        return None
    d = abs(float(x.mean()) / float(x.std(ddof=1)))
    n_t = float(TTestPower().solve_power(effect_size=d, power=power, alpha=alpha, alternative="two-sided"))
    # statsmodels' root finder returns NaN (with a warning) for very large effects: 2 participants already
    # suffice there, and a NaN must not reach the results document.
    return math.ceil(n_t / WILCOXON_ARE) if math.isfinite(n_t) else None


def _summary(x: Sequence[float]) -> dict[str, Any]:
    x = list(x)
    return {"n_participants": len(x), "mean_score": float(np.mean(x)) if x else None, "ci95": t_interval(x),
            "wilcoxon_p": wilcoxon_p(x), "sign_test_p": sign_test_p(x), "rank_biserial": rank_biserial(x)}


def counted(vote: Mapping[str, Any]) -> bool:
    """Whether the results count a vote (an export row, or a mapping with its ``practice``, ``catch`` and
    ``outcome``): a test vote of a participant not screened out (finished or not).  Pilot sessions' votes are not
    among the rows unless pilot sessions are asked for.  The one definition of "counted": the statistics, the
    scale and the adaptive design (``server.participants.assign.counted_votes``) all use it."""
    return not vote["practice"] and not vote["catch"] and vote["outcome"] != "screened_out"


#: How the results document's numbers are computed (its ``methods`` section).
METHODS = {
    "unit": "participant: mean of the two side-swapped showings of a comparison",
    "exclusions": "practice and catch trials; every vote of a participant screened out by the catch trials "
                  "(more failed than [recruitment] catch_failures_allowed)",
    "wilcoxon": "scipy.stats.wilcoxon(participant_means, zero_method='pratt'), two-sided, default method "
                "(its exact sign-flip distribution up to 13 participants counted rather than enumerated)",
    "sign_test": "exact two-sided binomial test on the signs of participant means, zeros dropped",
    "ci95": "Student t interval of the mean of participant means",
    "multiplicity": "Holm over the Wilcoxon p-values of all the study's comparisons",
    "power": "t-test power (statsmodels) at the observed d_z, divided by the Wilcoxon ARE 3/pi",
    "ranking": "ordinal Bradley-Terry (Agresti 1992, logit) per animation, reference at 0; 95 % intervals "
               "from cluster-robust standard errors over participants (server/analysis/ranking.py)",
    "thesis_grouping": "per comparison: negative = reference significantly better (-2); positive = "
                       "everything else",
}

# Showings of one comparison (animation, test condition, reference condition) per participant: (trial index,
# score, test side) of each.
_ByComparison = dict[tuple[str, str, str], dict[str, list[tuple[int, int, str]]]]


def analyse(votes: Iterable[Mapping[str, Any]], participants: Mapping[str, int],
            questions: Sequence[str] = (), anchor: str | None = None) -> dict[str, Any]:
    """The results document of a study from its votes (export rows), participant counts and question ids;
    ``anchor``: the condition at 0 of the scales (the study's reference; needed when pairs have several first
    conditions, as in all-pairs designs)."""
    analysed = [v for v in votes if counted(v)]
    by_comparison: _ByComparison = defaultdict(lambda: defaultdict(list))
    for v in analysed:
        by_comparison[(v["animation"], v["test_condition"], v["reference_condition"])][v["session_id"]].append(
            (v["trial_index"], v["score"], v["test_side"]))
    comparisons = _comparisons(by_comparison)
    # Krippendorff: units = trial kinds (comparison x test side), coders = participants.
    units: dict[tuple[str, str, str], list[int]] = defaultdict(list)
    for v in analysed:
        units[(v["animation"], v["test_condition"], v["test_side"])].append(v["score"])
    return {
        "participants": dict(participants),
        "comparisons": comparisons,
        "conditions": _conditions(comparisons),
        "rankings": _rankings(analysed, anchor),
        "overall": _summary([float(np.mean([v["score"] for v in analysed if v["session_id"] == sid]))
                             for sid in {v["session_id"] for v in analysed}]),
        "side_bias": _side_bias(analysed),
        "swap_consistency": _swap_consistency(by_comparison),
        "krippendorff_alpha_ordinal": krippendorff_alpha_ordinal(units.values()),
        "demographics": _demographics(analysed, questions),
        "methods": dict(METHODS),
    }


def _comparisons(by_comparison: _ByComparison) -> list[dict[str, Any]]:
    """One entry per comparison, in sorted order: the summary of its participant means (two showings each), the
    vote counts, the participants needed for 80 % power, and the Holm-adjusted Wilcoxon p over all of them."""
    comparisons = []
    for (animation, condition, reference), per_person in sorted(by_comparison.items()):
        scores = [s for showings in per_person.values() for _, s, _ in showings]
        means = [float(np.mean([s for _, s, _ in showings])) for showings in per_person.values()
                 if len(showings) == 2]
        counts = {str(s): scores.count(s) for s in SCORES}
        entry = {"animation": animation, "condition": condition, "reference": reference, **_summary(means),
                 "counts": counts, "votes": len(scores), "positive": sum(s > -MAX_SCORE for s in scores),
                 "negative": scores.count(-MAX_SCORE), "test_better": sum(s > 0 for s in scores),
                 "equal": scores.count(0), "reference_better": sum(s < 0 for s in scores),
                 "participants_for_80_power": participants_needed(means)}
        comparisons.append(entry)
    for entry, p in zip(comparisons, holm([c["wilcoxon_p"] for c in comparisons]), strict=True):
        entry["p_holm"] = p
    return comparisons


def _conditions(comparisons: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """The thesis's grouping (and the neutral split) per test condition, over all its animations."""
    conditions = []
    for condition in sorted({c["condition"] for c in comparisons}):
        of = [c for c in comparisons if c["condition"] == condition]
        conditions.append({"condition": condition, "reference": of[0]["reference"],
                           "animations": [c["animation"] for c in of],
                           **{k: sum(c[k] for c in of) for k in ("votes", "positive", "negative", "test_better",
                                                                 "equal", "reference_better")}})
    return conditions


def _rankings(analysed: Sequence[Mapping[str, Any]], anchor: str | None) -> list[dict[str, Any]]:
    """All conditions of each animation on one scale (``anchor``, the reference, at 0), from every graded vote."""
    rankings = []
    for animation in sorted({v["animation"] for v in analysed}):
        ranking = rank_conditions((GradedComparison(v["session_id"], v["reference_condition"], v["test_condition"],
                                                    v["score"]) for v in analysed if v["animation"] == animation),
                                  anchor=anchor)
        rankings.append({"animation": animation, "conditions": [asdict(c) for c in ranking.conditions],
                         "fit": asdict(ranking.fit)})
    return rankings


def _side_bias(analysed: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Side bias: each participant's mean raw answer, left = +2 ... right = -2, whatever is shown where."""
    raw: dict[str, list[int]] = defaultdict(list)
    for v in analysed:
        raw[v["session_id"]].append(RAW_SCORES[v["choice"]])
    side_means = [float(np.mean(r)) for r in raw.values()]
    return {"mean": float(np.mean(side_means)) if side_means else None, "p": wilcoxon_p(side_means),
            "n_participants": len(side_means)}


def _swap_consistency(by_comparison: _ByComparison) -> dict[str, Any]:
    """Swap consistency: first against second showing of each comparison, per participant."""
    first, second = [], []
    for per_person in by_comparison.values():
        for showings in per_person.values():
            if len(showings) == 2:
                a, b = sorted(showings)
                first.append(a[1])
                second.append(b[1])
    pairs = list(zip(first, second, strict=True))
    return {
        "weighted_kappa": weighted_kappa(first, second) if pairs else None,
        "exact_agreement": float(np.mean([a == b for a, b in pairs])) if pairs else None,
        "within_one": float(np.mean([abs(a - b) <= 1 for a, b in pairs])) if pairs else None,
        "pairs": len(pairs),
    }


def _demographics(analysed: Sequence[Mapping[str, Any]], questions: Sequence[str]) -> dict[str, Any]:
    """Mean score and vote count per comparison (``animation-condition``) for each answer to each question."""
    out: dict[str, Any] = {}
    for question in questions:
        groups: dict[str, dict[str, list[int]]] = defaultdict(lambda: defaultdict(list))
        for v in analysed:
            groups[v[question] or "unanswered"][f"{v['animation']}-{v['test_condition']}"].append(v["score"])
        out[question] = {
            answer: {
                "participants": len({v["session_id"] for v in analysed if (v[question] or "unanswered") == answer}),
                "comparisons": {key: {"mean_score": float(np.mean(s)), "votes": len(s)}
                                for key, s in sorted(c.items())},
            }
            for answer, c in sorted(groups.items())
        }
    return out
