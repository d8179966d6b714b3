"""Observer screening: which participants' answers to leave out, by the rules a study chooses (``[screening]``,
:class:`server.studies.screening.Screening`).

Pure functions over the export rows (``server.research.export.export_rows``: one mapping per vote).  Only finished
(completed) sessions are screened; a rule looks at a participant's *test* trials (practice and catch trials
excluded), except ``catch``, which looks only at catch trials.  A comparison is one animation in one test condition
against one reference condition; its score is from the test condition's point of view (-2..+2, see
``server.studies.scale``), and
each participant sees it ``2 * repeats`` times (sides swapped): those showings are the repetitions ``r`` of the
standards' x[e, s, r] (stimulus e, subject s).

The rules (``RULES``), each with the standard it follows and its default threshold:

- ``catch``: more failed catch trials (a "significantly better" answer with the same clip on both sides) than
  ``[recruitment] catch_failures_allowed`` (0).  Measure: failed catch trials.
- ``straight_lining``: the variance of the participant's raw answers (left much = +2 ... right much = -2,
  whatever is shown where) below ``min_variance`` (0.15, Microsoft's P.910 crowdsourcing implementation: a rater
  giving (nearly) the same answer every time).  Measure: the variance (population, ddof 0).
- ``z_outlier``: the share of the participant's test votes with |z| >= ``z_limit`` (3.29, two-sided p 0.001),
  z = (vote - mean) / sd of the *other* participants' votes on the same comparison, above
  ``max_rejected_share`` (0.2: per-rater acceptance >= 80 %).  Measure: that share.
- ``bt500``: ITU-R BT.500-14 §A1-2.3.1 on the comparison scores, exactly as ``sureal`` implements it: per
  comparison the kurtosis beta2 = m4 / m2^2 of all its votes; a vote counts in P (above) or Q (below) when it is
  beyond mean +- 2 sd (beta2 in [2, 4]) or +- sqrt(20) sd (otherwise); reject when (P + Q) / (J * R) >
  ``bt500_ratio`` (0.05) and |P - Q| / (P + Q) < ``bt500_balance`` (0.3).  If every participant would be
  rejected, none is (as in sureal).  Measure: (P + Q) / (J * R).
- ``correlation``: Pearson (or Spearman, ``correlation_method``) correlation of the participant's per-comparison
  mean with the *other* participants' means (at least 3 comparisons); flagged at r <= threshold, threshold =
  min(``max_correlation_threshold`` (0.7), mean(r) - sd(r)) over the panel, as sureal's P.913-style rejection
  does (sureal correlates with the mean including the participant; leaving them out keeps a participant from
  agreeing with themselves in small panels).  An undefined r (constant answers) flags nobody: that is
  ``straight_lining``'s case.  Measure: r.
- ``disagreement``: the variance of the differences between the participant's votes and the other participants'
  mean vote on the same comparison (around the participant's own bias) above ``max_disagreement`` (1.5; not a
  standard's: a uniformly random answerer's is about 2 plus the variance of the comparison scores).  Measure: that
  variance.  With 16 votes it tells a random answerer from an honest one where ``z_outlier``'s count cannot.
- ``fast``: the share of the participant's test votes given before one playback of the pair video had ended
  (``rt_ms`` < the longer clip's duration, frames / fps, less ``PAGE_CLOCK_MS``) above ``max_fast_share`` (0.2:
  acceptance >= 80 %).  Measure: that share.

Those are the thresholds with ``thresholds = "fixed"``.  By default (``"design"``) the thresholds of
``straight_lining``, ``z_outlier``, ``bt500`` (its ratio), ``correlation``, ``disagreement`` and ``fast`` are
calibrated to the study's own design by simulation (``screening_design``): each leaves a share of good observers
flagged (``false_flag_rate`` over the rules together), and a rule whose power against the bad observers it is
meant for falls short of ``min_power`` says "too little data" (``RuleResult.judged``) and flags nobody.

A participant is screened out when any chosen rule flags them; the panel-relative rules (``z_outlier``,
``bt500``, ``correlation``) see every completed participant of the study in one pass (as sureal does), so adding
participants can change who is flagged.
"""

from __future__ import annotations

import math
import warnings
from collections import defaultdict
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np
from scipy import stats

from server.studies.scale import RAW_SCORES, catch_row_failed
from server.studies.screening import RULES, Screening

from .json_numbers import finite_or_none
from .screening_design import MEANT_FOR, Calibration, calibrate, fast_limit, planned

MIN_COMMON_COMPARISONS = 3  # a correlation over fewer points says nothing
# A vote counts as fast when it came this much before one playback had ended: the page counts the first loop on
# the media clock, which can wrap up to a video frame (33 ms at 30 fps) before the clips' nominal duration, so an
# observer answering the moment the page lets them would otherwise look fast now and then.
PAGE_CLOCK_MS = 50.0


@dataclass(frozen=True)
class RuleResult:
    """One rule's verdict on one participant: the measure, the threshold it was held against, flagged or not.
    ``value`` is None when the rule could not measure (e.g. no catch trials, too few comparisons)."""

    value: float | None
    threshold: float | None
    flagged: bool
    judged: bool = True  # False: too little data for this design to judge (then never flagged); see ``note``
    note: str = ""


@dataclass(frozen=True)
class ParticipantScreening:
    session_id: str
    results: dict[str, RuleResult] = field(default_factory=dict)  # rule -> verdict, for every chosen rule
    # the design calibration the thresholds came from (one object shared by the panel's records), None: fixed
    calibration: Calibration | None = field(default=None, compare=False, repr=False)

    @property
    def flagged_by(self) -> list[str]:
        """The rules that flagged the participant, in ``RULES`` order."""
        return [r for r in RULES if r in self.results and self.results[r].flagged]

    @property
    def screened_out(self) -> bool:
        return bool(self.flagged_by)

    def as_dict(self) -> dict[str, Any]:
        return {"session_id": self.session_id, "screened_by": self.flagged_by,
                "rules": {r: {"value": v.value, "threshold": v.threshold, "flagged": v.flagged,
                              "judged": v.judged, **({"note": v.note} if v.note else {})}
                          for r, v in self.results.items()}}


def opinion_array(votes: Iterable[Mapping[str, Any]]) -> tuple[np.ndarray, list[tuple[str, str, str]], list[str]]:
    """x[e, s, r]: the scores of comparison e by participant s in showing r (in trial order), NaN where missing,
    with the comparison keys (animation, reference, test) and the participant ids, both sorted."""
    per: dict[tuple[tuple[str, str, str], str], list[tuple[int, int]]] = defaultdict(list)
    for v in votes:
        key = (v["animation"], v["reference_condition"], v["test_condition"])
        per[(key, v["session_id"])].append((v["trial_index"], v["score"]))
    comparisons = sorted({k for k, _ in per})
    subjects = sorted({s for _, s in per})
    repeats = max((len(x) for x in per.values()), default=0)
    x = np.full((len(comparisons), len(subjects), repeats), np.nan)
    ci, si = {c: i for i, c in enumerate(comparisons)}, {s: i for i, s in enumerate(subjects)}
    for (c, s), showings in per.items():
        for r, (_, score) in enumerate(sorted(showings)):
            x[ci[c], si[s], r] = score
    return x, comparisons, subjects


def bt500(x: np.ndarray, ratio: float = 0.05, balance: float = 0.3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ITU-R BT.500-14 §A1-2.3.1 screening of x[e, s, r] (NaN: missing) as sureal implements it.

    Returns (rejected[s], (P+Q)/(J*R)[s], |P-Q|/(P+Q)[s]) (the last NaN where P + Q = 0)."""
    e_count, s_count, r_count = x.shape
    p, q = np.zeros(s_count), np.zeros(s_count)
    for row in x:  # one stimulus: every subject's every repetition
        present = row[~np.isnan(row)]
        if present.size == 0:
            continue
        mu, sigma = float(present.mean()), float(present.std())
        # beta2 = m4 / m2^2 with scipy.stats.kurtosis's arithmetic (fisher=False), without its per-call overhead
        # (the calibration runs this on many panels); unanimous votes: NaN, hence the sqrt(20) branch
        squared = (present - present.mean()) ** 2
        m2, m4 = squared.mean(), (squared**2).mean()
        with np.errstate(invalid="ignore", divide="ignore"):
            kurt = math.nan if m2 <= (np.finfo(float).eps * mu) ** 2 else float(m4 / m2**2.0)
        k = 2.0 if 2 <= kurt <= 4 else math.sqrt(20)
        with np.errstate(invalid="ignore"):
            p += np.sum(row >= mu + k * sigma, axis=1)
            q += np.sum(row <= mu - k * sigma, axis=1)
    first = (p + q) / (e_count * r_count)
    with np.errstate(invalid="ignore", divide="ignore"):
        second = np.abs((p - q) / (p + q))
    rejected = (first > ratio) & (second < balance)  # NaN compares False: P + Q = 0 never rejects
    if rejected.all():
        rejected[:] = False
    return rejected, first, second


def _correlations(x: np.ndarray, method: str) -> np.ndarray:
    """Each participant's per-comparison mean against the other participants' means (NaN: undefined).

    Vectorised over the participants (the calibration runs it on many simulated panels)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        means = np.nanmean(x, axis=2) if x.shape[2] else np.full(x.shape[:2], np.nan)
    seen = ~np.isnan(means)
    total, count = np.where(seen, means, 0.0).sum(axis=1), seen.sum(axis=1)
    others_count = count[:, None] - seen  # a comparison nobody else saw: left out below
    with np.errstate(invalid="ignore", divide="ignore"):
        panel = (total[:, None] - np.where(seen, means, 0.0)) / others_count
    ok = seen & (others_count > 0)
    n = ok.sum(axis=0)
    if method == "pearson":
        with np.errstate(invalid="ignore", divide="ignore"):
            a_mean = np.where(ok, means, 0.0).sum(axis=0) / n
            b_mean = np.where(ok, panel, 0.0).sum(axis=0) / n
            a, b = np.where(ok, means - a_mean, 0.0), np.where(ok, panel - b_mean, 0.0)
            r = np.clip((a * b).sum(axis=0) / np.sqrt((a * a).sum(axis=0) * (b * b).sum(axis=0)), -1, 1)
        constant = (np.where(ok, means, -np.inf).max(axis=0) == np.where(ok, means, np.inf).min(axis=0)) | (
            np.where(ok, panel, -np.inf).max(axis=0) == np.where(ok, panel, np.inf).min(axis=0))
        return np.where((n >= MIN_COMMON_COMPARISONS) & ~constant, r, np.nan)
    out = np.full(x.shape[1], np.nan)
    for s in np.flatnonzero(n >= MIN_COMMON_COMPARISONS):
        a, b = means[ok[:, s], s], panel[ok[:, s], s]
        if np.ptp(a) == 0 or np.ptp(b) == 0:
            continue
        a, b = stats.rankdata(a), stats.rankdata(b)
        a, b = a - a.mean(), b - b.mean()
        out[s] = float(np.clip(a @ b / math.sqrt((a @ a) * (b @ b)), -1, 1))
    return out


def correlation_threshold(r: np.ndarray, cap: float = 0.7) -> float | None:
    """min(cap, mean - sd) of the defined correlations (population sd, as sureal)."""
    defined = r[~np.isnan(r)]
    if defined.size == 0:
        return None
    return float(min(cap, defined.mean() - defined.std()))


def _others_means(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per comparison and participant: the mean of the *other* participants' votes and how many there are."""
    present = ~np.isnan(x)
    n_own, s_own = present.sum(axis=2), np.where(present, x, 0.0).sum(axis=2)
    n = n_own.sum(axis=1, keepdims=True) - n_own
    with np.errstate(invalid="ignore", divide="ignore"):
        return (s_own.sum(axis=1, keepdims=True) - s_own) / n, n


def _disagreements(x: np.ndarray) -> np.ndarray:
    """Per participant: the variance of the differences between their votes and the other participants' mean vote
    on the same comparison (comparisons nobody else saw left out; NaN with fewer than 2 votes).  The variance, not
    the mean square: a participant's own bias (the subject model's b_s) is a taste, not inattention.  It is the
    continuous form of z_outlier's count, which with few votes is too coarse to tell a random answerer from an
    honest one (docs/screening.md)."""
    mu, n = _others_means(x)
    difference = np.where(n[:, :, None] > 0, x - mu[:, :, None], np.nan)
    counted = (~np.isnan(difference)).sum(axis=(0, 2))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.where(counted >= 2, np.nanvar(difference, axis=(0, 2)), np.nan)


def _z_shares(x: np.ndarray, limit: float) -> np.ndarray:
    """Per participant: the share of their votes with |z| >= limit against the other participants' votes on the
    same comparison (at least 3 of them with some spread, or unanimous: then any other answer is an outlier).

    Vectorised over the participants from per-comparison sums (the calibration runs it on many panels)."""
    present = ~np.isnan(x)
    values = np.where(present, x, 0.0)
    n_own, s1_own, s2_own = present.sum(axis=2), values.sum(axis=2), (values**2).sum(axis=2)  # (E, S)
    n = n_own.sum(axis=1, keepdims=True) - n_own
    s1 = s1_own.sum(axis=1, keepdims=True) - s1_own
    s2 = s2_own.sum(axis=1, keepdims=True) - s2_own
    with np.errstate(invalid="ignore", divide="ignore"):
        mu = s1 / n
        spread = n * s2 - s1**2  # n (n - 1) var: exactly 0 for unanimous whole-number votes
        sd = np.sqrt(np.maximum(spread, 0.0) / (n * (n - 1)))
        unanimous = spread <= 1e-9 * np.maximum(n * s2, 1.0)
        z = np.abs(x - mu[:, :, None]) / sd[:, :, None]
        outlier = np.where(unanimous[:, :, None], x != mu[:, :, None], z >= limit) & present
    outliers = np.where(n >= 3, outlier.sum(axis=2), 0).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return outliers / n_own.sum(axis=0)


def panel_measures(x: np.ndarray, raw: np.ndarray, rules: Screening) -> dict[str, np.ndarray]:
    """The measure per participant of each rule the calibration simulates, on scores x[e, s, r] and raw answers
    raw[e, s, r] (NaN: not shown): the same functions ``screen`` applies to the real votes.  ``bt500``'s is
    (P+Q)/(J*R) where |P-Q|/(P+Q) is below ``bt500_balance`` and 0 elsewhere (only the ratio is calibrated)."""
    counts = (~np.isnan(raw)).sum(axis=(0, 2))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        variance = np.where(counts >= 2, np.nanvar(raw, axis=(0, 2)), np.nan)
    _, first, second = bt500(x, 1.0, rules.bt500_balance)
    with np.errstate(invalid="ignore"):
        balanced = np.where(second < rules.bt500_balance, first, 0.0)
    return {"straight_lining": variance, "z_outlier": _z_shares(x, rules.z_limit), "bt500": balanced,
            "correlation": _correlations(x, rules.correlation_method), "disagreement": _disagreements(x)}


@lru_cache(maxsize=16)
def _measures_for(z_limit: float, bt500_balance: float, correlation_method: str
                  ) -> Callable[[np.ndarray, np.ndarray], dict[str, np.ndarray]]:
    """One callable per setting of the measures: the calibration's cache keys on it."""
    rules = Screening(z_limit=z_limit, bt500_balance=bt500_balance, correlation_method=correlation_method)
    return lambda x, raw: panel_measures(x, raw, rules)


def calibration(votes: Iterable[Mapping[str, Any]], rules: Screening,
                playback_ms: Mapping[tuple[str, str, str], float] | None = None) -> Calibration | None:
    """The design calibration ``screen`` applies (``screening_design``), None with fixed thresholds or no rule
    to calibrate.  Cached: the results ask for it again to show it."""
    chosen = tuple(r for r in RULES if r in rules.rules and r in MEANT_FOR)
    if rules.thresholds != "design" or not chosen:
        return None
    tests = [v for v in votes if v["session_state"] == "completed" and not v["practice"] and not v["catch"]]
    x, comparisons, subjects = opinion_array(tests)
    animations = sorted({c[0] for c in comparisons})
    content = [animations.index(c[0]) for c in comparisons]
    fast = _fast_votes(tests, playback_ms or {}) if "fast" in chosen else None
    # Each participant's side preference: their raw answers less the panel's mean score of each comparison turned
    # to the side it was shown on; the mean is the lean, its variance over the votes what noise alone gives it.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        panel_mean = dict(zip(comparisons, np.nanmean(x, axis=(1, 2)), strict=True)) if subjects else {}
    residual: dict[str, list[float]] = defaultdict(list)
    for v in tests:
        toward = 1.0 if v["reference_side"] == "right" else -1.0  # raw = score * toward
        key = (v["animation"], v["reference_condition"], v["test_condition"])
        residual[v["session_id"]].append(RAW_SCORES[v["choice"]] - toward * panel_mean[key])
    leans = np.array([[np.mean(residual[s]), np.var(residual[s], ddof=1) / len(residual[s])]
                      if len(residual[s]) >= 2 else [np.nan, np.nan] for s in subjects]).reshape(-1, 2)
    return calibrate(x, content, chosen, rules.false_flag_rate, rules.min_power,
                     _measures_for(rules.z_limit, rules.bt500_balance, rules.correlation_method), fast, leans)


def planned_calibration(comparisons: int, showings: int, rules: Screening) -> Calibration | None:
    """The design calibration before anyone has finished (``screening_design.planned``): the prior, for a panel of
    ``PLANNED_PARTICIPANTS`` each seeing ``comparisons`` comparisons ``showings`` times."""
    chosen = tuple(r for r in RULES if r in rules.rules and r in MEANT_FOR)
    if rules.thresholds != "design" or not chosen or not comparisons or not showings:
        return None
    return planned(comparisons, showings, chosen, rules.false_flag_rate, rules.min_power,
                   _measures_for(rules.z_limit, rules.bt500_balance, rules.correlation_method))


def _fast_votes(tests: list[Mapping[str, Any]], playback_ms: Mapping[tuple[str, str, str], float]
                ) -> dict[str, tuple[int, int]]:
    """Per participant: (votes given before one playback ended, votes with a known playback)."""
    out: dict[str, tuple[int, int]] = {}
    for v in tests:
        duration = playback_ms.get((v["animation"], v["reference_condition"], v["test_condition"]))
        if duration is None:
            continue
        fast, judged = out.get(v["session_id"], (0, 0))
        out[v["session_id"]] = (fast + (v["rt_ms"] < duration - PAGE_CLOCK_MS), judged + 1)
    return out


def screen(votes: Iterable[Mapping[str, Any]], rules: Screening, catch_failures_allowed: int = 0,
           playback_ms: Mapping[tuple[str, str, str], float] | None = None) -> dict[str, ParticipantScreening]:
    """The screening record of every completed participant of ``votes`` (export rows).

    ``playback_ms``: (animation, reference condition, test condition) -> duration of one playback of the pair
    video (the ``fast`` rule; comparisons without one are not judged).  With ``rules.thresholds == "design"``
    the thresholds of the calibrated rules come from :func:`calibration`."""
    votes = list(votes)
    completed = [v for v in votes if v["session_state"] == "completed"]
    tests = [v for v in completed if not v["practice"] and not v["catch"]]
    sessions = sorted({v["session_id"] for v in completed})
    chosen = set(rules.rules)
    design = calibration(votes, rules, playback_ms)
    by_rule: dict[str, dict[str, RuleResult]] = {}  # rule -> session -> verdict, in the order the record lists them
    if "catch" in chosen:
        by_rule["catch"] = _catch_results(completed, sessions, catch_failures_allowed)
    if "straight_lining" in chosen:
        by_rule["straight_lining"] = _straight_lining_results(tests, sessions, rules, design)
    if "fast" in chosen:
        by_rule["fast"] = _fast_results(tests, sessions, rules, design, playback_ms or {})
    if chosen & {"z_outlier", "bt500", "correlation", "disagreement"}:
        by_rule.update(_panel_results(tests, sessions, rules, chosen, design))
    return {s: ParticipantScreening(s, {rule: results[s] for rule, results in by_rule.items()}, design)
            for s in sessions}


def _verdict(design: Calibration | None, rule: str, value: float | None, fixed_threshold: float | None,
             fixed_flag: bool) -> RuleResult:
    """The fixed rule's verdict, or the calibrated one's."""
    if design is None or rule not in design.rules:
        return RuleResult(value, fixed_threshold, fixed_flag)
    c = design.rules[rule]
    return RuleResult(value, c.threshold, c.flags(value), c.judged, c.reason)


def _catch_results(completed: list[Mapping[str, Any]], sessions: list[str],
                   catch_failures_allowed: int) -> dict[str, RuleResult]:
    """``catch``: failed catch trials (by the study's answer format) against the number allowed."""
    catch: dict[str, list[int]] = defaultdict(list)
    for v in completed:
        if v["catch"]:
            catch[v["session_id"]].append(catch_row_failed(v))
    out = {}
    for s in sessions:
        failed = sum(catch[s]) if s in catch else None
        out[s] = RuleResult(failed, catch_failures_allowed, failed is not None and failed > catch_failures_allowed,
                            judged=failed is not None, note="" if failed is not None else "no catch trials to judge")
    return out


def _straight_lining_results(tests: list[Mapping[str, Any]], sessions: list[str], rules: Screening,
                             design: Calibration | None) -> dict[str, RuleResult]:
    """``straight_lining``: the variance of each participant's raw answers."""
    by_session: dict[str, list[Mapping[str, Any]]] = defaultdict(list)
    for v in tests:
        by_session[v["session_id"]].append(v)
    out = {}
    for s in sessions:
        raw = [RAW_SCORES[v["choice"]] for v in by_session[s]]
        variance = float(np.var(raw)) if len(raw) >= 2 else None
        out[s] = _verdict(design, "straight_lining", variance, rules.min_variance,
                          variance is not None and variance < rules.min_variance)
    return out


def _fast_results(tests: list[Mapping[str, Any]], sessions: list[str], rules: Screening, design: Calibration | None,
                  playback_ms: Mapping[tuple[str, str, str], float]) -> dict[str, RuleResult]:
    """``fast``: the share of votes given before one playback had ended; calibrated, a count limit for the
    participant's own number of judged votes."""
    counts = _fast_votes(tests, playback_ms)
    out = {}
    for s in sessions:
        fast, judged = counts.get(s, (0, 0))
        share = fast / judged if judged else None
        if design is not None and "fast" in design.rules:
            c = design.rules["fast"]
            limit = fast_limit(judged, design.fast_vote_rate, design.rate_per_rule)
            threshold = limit / judged if judged else None
            out[s] = RuleResult(share, threshold, c.judged and share is not None and fast > limit, c.judged, c.reason)
        else:
            out[s] = RuleResult(share, rules.max_fast_share, share is not None and share > rules.max_fast_share)
    return out


def _panel_results(tests: list[Mapping[str, Any]], sessions: list[str], rules: Screening, chosen: set[str],
                   design: Calibration | None) -> dict[str, dict[str, RuleResult]]:
    """The chosen panel-relative rules (``z_outlier``, ``bt500``, ``disagreement``, ``correlation``), each
    participant measured against the others on the opinion array of all of them."""
    x, _, subjects = opinion_array(tests)
    index = {s: i for i, s in enumerate(subjects)}
    out: dict[str, dict[str, RuleResult]] = {}
    if "z_outlier" in chosen:
        shares = _z_shares(x, rules.z_limit) if subjects else np.array([])
        values = {s: finite_or_none(shares[index[s]]) if s in index else None for s in sessions}
        out["z_outlier"] = {s: _verdict(design, "z_outlier", v, rules.max_rejected_share,
                                        v is not None and v > rules.max_rejected_share) for s, v in values.items()}
    if "bt500" in chosen:
        out["bt500"] = _bt500_results(x, subjects, index, sessions, rules, design)
    if "disagreement" in chosen:
        spread = _disagreements(x) if subjects else np.array([])
        values = {s: finite_or_none(spread[index[s]]) if s in index else None for s in sessions}
        out["disagreement"] = {s: _verdict(design, "disagreement", v, rules.max_disagreement,
                                           v is not None and v > rules.max_disagreement) for s, v in values.items()}
    if "correlation" in chosen:
        r = _correlations(x, rules.correlation_method) if subjects else np.array([])
        threshold = correlation_threshold(r, rules.max_correlation_threshold)
        values = {s: finite_or_none(r[index[s]]) if s in index else None for s in sessions}
        out["correlation"] = {s: _verdict(design, "correlation", v, threshold,
                                          v is not None and threshold is not None and v <= threshold)
                              for s, v in values.items()}
    return out


def _bt500_results(x: np.ndarray, subjects: list[str], index: Mapping[str, int], sessions: list[str],
                   rules: Screening, design: Calibration | None) -> dict[str, RuleResult]:
    """``bt500`` on the opinion array ``x``: calibrated, its ratio is the design's and a rule judged too weak
    flags nobody."""
    if design is not None and "bt500" in design.rules and subjects:
        c = design.rules["bt500"]
        ratio = c.threshold if c.threshold is not None else math.inf
        rejected, first, _ = bt500(x, ratio, rules.bt500_balance)
        rejected &= c.judged
    else:
        rejected, first, _ = bt500(x, rules.bt500_ratio, rules.bt500_balance) if subjects else ([], [], [])
    out = {}
    for s in sessions:
        i = index.get(s)
        value = None if i is None else finite_or_none(first[i])
        result = _verdict(design, "bt500", value, rules.bt500_ratio, i is not None and bool(rejected[i]))
        # bt500 flags on two measures and spares everyone when it would flag everyone: its own verdict
        out[s] = RuleResult(value, result.threshold, i is not None and bool(rejected[i]), result.judged, result.note)
    return out


def flagged_counts(records: Iterable[ParticipantScreening], rules: Sequence[str]) -> dict[str, int]:
    """How many participants each rule flagged (a participant can count under several)."""
    records = list(records)
    return {r: sum(r in p.flagged_by for p in records) for r in rules}
