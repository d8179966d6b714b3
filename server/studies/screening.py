"""Observer screening: which participants' answers to leave out, by the rules a study chooses (``[screening]``).

Pure functions over the export rows (``server.research.export.export_rows``: one mapping per vote).  Only finished
(completed) sessions are screened; a rule looks at a participant's *test* trials (practice and catch trials
excluded), except ``catch``, which looks only at catch trials.  A comparison is one animation in one test condition
against one reference condition; its score is from the test condition's point of view (-2..+2, see ``scale``), and
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
- ``fast``: the share of the participant's test votes given before one playback of the pair video had ended
  (``rt_ms`` < the longer clip's duration, frames / fps) above ``max_fast_share`` (0.2: acceptance >= 80 %).
  Measure: that share.

A participant is screened out when any chosen rule flags them; the panel-relative rules (``z_outlier``,
``bt500``, ``correlation``) see every completed participant of the study in one pass (as sureal does), so adding
participants can change who is flagged.
"""

from __future__ import annotations

import math
import warnings
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, Self

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator
from scipy import stats

from .scale import CHOICE_SCORES

RULES = ("catch", "straight_lining", "z_outlier", "bt500", "correlation", "fast")
Rule = Literal["catch", "straight_lining", "z_outlier", "bt500", "correlation", "fast"]
MIN_COMMON_COMPARISONS = 3  # a correlation over fewer points says nothing


class Screening(BaseModel):
    """Which observer-screening rules a study applies, with their thresholds (the standards' defaults)."""

    model_config = ConfigDict(extra="forbid")

    rules: list[Rule] = Field(default_factory=lambda: ["catch"], max_length=len(RULES),
                              description='the rules applied ("all": every one): catch, straight_lining, '
                                          "z_outlier, bt500, correlation, fast")
    min_variance: float = Field(0.15, ge=0, le=4, description="straight_lining: least variance of the raw answers")
    z_limit: float = Field(3.29, gt=0, le=10, description="z_outlier: |z| of a vote counted as an outlier")
    max_rejected_share: float = Field(0.2, ge=0, le=1, description="z_outlier: most outlier votes (share)")
    bt500_ratio: float = Field(0.05, ge=0, le=1, description="bt500: (P+Q)/(J*R) above which a participant may "
                               "be rejected")
    bt500_balance: float = Field(0.3, ge=0, le=1, description="bt500: |P-Q|/(P+Q) below which they are")
    correlation_method: Literal["pearson", "spearman"] = "pearson"
    max_correlation_threshold: float = Field(0.7, ge=-1, le=1, description="correlation: the threshold is "
                                             "min(this, mean - sd of the panel's correlations)")
    max_fast_share: float = Field(0.2, ge=0, le=1, description="fast: most votes given before one playback ended")

    @field_validator("rules", mode="before")
    @classmethod
    def all_rules(cls, value: Any) -> Any:
        if value == "all":
            return list(RULES)
        if isinstance(value, str):
            raise ValueError(f'rules must be a list of rule names or "all", got {value!r}')
        return value

    @model_validator(mode="after")
    def distinct(self) -> Self:
        if len(set(self.rules)) != len(self.rules):
            raise ValueError("rules lists a rule more than once")
        return self


@dataclass(frozen=True)
class RuleResult:
    """One rule's verdict on one participant: the measure, the threshold it was held against, flagged or not.
    ``value`` is None when the rule could not measure (e.g. no catch trials, too few comparisons)."""

    value: float | None
    threshold: float | None
    flagged: bool


@dataclass(frozen=True)
class ParticipantScreening:
    session_id: str
    results: dict[str, RuleResult] = field(default_factory=dict)  # rule -> verdict, for every chosen rule

    @property
    def flagged_by(self) -> list[str]:
        """The rules that flagged the participant, in ``RULES`` order."""
        return [r for r in RULES if r in self.results and self.results[r].flagged]

    @property
    def screened_out(self) -> bool:
        return bool(self.flagged_by)

    def as_dict(self) -> dict[str, Any]:
        return {"session_id": self.session_id, "screened_by": self.flagged_by,
                "rules": {r: {"value": v.value, "threshold": v.threshold, "flagged": v.flagged}
                          for r, v in self.results.items()}}


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


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
        with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # unanimous votes: NaN, hence the sqrt(20) branch
            kurt = float(stats.kurtosis(present, fisher=False))
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
    out = np.full(x.shape[1], np.nan)
    for s in np.flatnonzero(ok.sum(axis=0) >= MIN_COMMON_COMPARISONS):
        a, b = means[ok[:, s], s], panel[ok[:, s], s]
        if np.ptp(a) == 0 or np.ptp(b) == 0:
            continue
        if method == "spearman":
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


def screen(votes: Iterable[Mapping[str, Any]], rules: Screening, catch_failures_allowed: int = 0,
           playback_ms: Mapping[tuple[str, str, str], float] | None = None) -> dict[str, ParticipantScreening]:
    """The screening record of every completed participant of ``votes`` (export rows).

    ``playback_ms``: (animation, reference condition, test condition) -> duration of one playback of the pair
    video (the ``fast`` rule; comparisons without one are not judged)."""
    completed = [v for v in votes if v["session_state"] == "completed"]
    tests = [v for v in completed if not v["practice"] and not v["catch"]]
    sessions = sorted({v["session_id"] for v in completed})
    out: dict[str, dict[str, RuleResult]] = {s: {} for s in sessions}
    chosen = set(rules.rules)

    if "catch" in chosen:
        catch: dict[str, list[int]] = defaultdict(list)
        for v in completed:
            if v["catch"]:
                catch[v["session_id"]].append(abs(v["score"]) == 2)
        for s in sessions:
            failed = sum(catch[s]) if s in catch else None
            out[s]["catch"] = RuleResult(failed, catch_failures_allowed,
                                         failed is not None and failed > catch_failures_allowed)

    by_session: dict[str, list[Mapping[str, Any]]] = defaultdict(list)
    for v in tests:
        by_session[v["session_id"]].append(v)

    if "straight_lining" in chosen:
        for s in sessions:
            raw = [CHOICE_SCORES[v["choice"]] for v in by_session[s]]
            variance = float(np.var(raw)) if len(raw) >= 2 else None
            out[s]["straight_lining"] = RuleResult(variance, rules.min_variance,
                                                   variance is not None and variance < rules.min_variance)

    if "fast" in chosen:
        durations = playback_ms or {}
        for s in sessions:
            judged = [v for v in by_session[s]
                      if (v["animation"], v["reference_condition"], v["test_condition"]) in durations]
            fast = sum(v["rt_ms"] < durations[(v["animation"], v["reference_condition"], v["test_condition"])]
                       for v in judged)
            share = fast / len(judged) if judged else None
            out[s]["fast"] = RuleResult(share, rules.max_fast_share, share is not None and share > rules.max_fast_share)

    if chosen & {"z_outlier", "bt500", "correlation"}:
        x, _, subjects = opinion_array(tests)
        index = {s: i for i, s in enumerate(subjects)}
        if "z_outlier" in chosen:
            shares = _z_shares(x, rules.z_limit) if subjects else np.array([])
            for s in sessions:
                value = _finite(shares[index[s]]) if s in index else None
                out[s]["z_outlier"] = RuleResult(value, rules.max_rejected_share,
                                                 value is not None and value > rules.max_rejected_share)
        if "bt500" in chosen:
            rejected, first, _ = bt500(x, rules.bt500_ratio, rules.bt500_balance) if subjects else ([], [], [])
            for s in sessions:
                i = index.get(s)
                out[s]["bt500"] = RuleResult(None if i is None else _finite(first[i]), rules.bt500_ratio,
                                             i is not None and bool(rejected[i]))
        if "correlation" in chosen:
            r = _correlations(x, rules.correlation_method) if subjects else np.array([])
            threshold = correlation_threshold(r, rules.max_correlation_threshold)
            for s in sessions:
                value = _finite(r[index[s]]) if s in index else None
                out[s]["correlation"] = RuleResult(value, threshold, value is not None and threshold is not None
                                                   and value <= threshold)

    return {s: ParticipantScreening(s, results) for s, results in out.items()}


def flagged_counts(records: Iterable[ParticipantScreening], rules: Sequence[str]) -> dict[str, int]:
    """How many participants each rule flagged (a participant can count under several)."""
    records = list(records)
    return {r: sum(r in p.flagged_by for p in records) for r in rules}
