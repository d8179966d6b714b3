"""The screening thresholds a study's own design supports: calibrated by simulating good observers (issue 36).

A rule's fixed threshold (the standards' defaults in ``screening.Screening``) was chosen for some number of votes
per participant; with fewer (the thesis design: 8 comparisons x 2 showings = 16 test votes) honest participants
cross it far more often.  Here every calibrated rule's threshold is instead the quantile of its measure among
simulated *good* observers that leaves a target share of them flagged, in panels with the study's own shape
(comparisons, showings and each participant's pattern of them, the number of participants):

- Good observers follow the subject model (``subject_model``; P.910 Annex E): score = comparison score + own bias
  + noise of sd sqrt(inconsistency^2 + ambiguity^2), rounded to the scale and clipped.  With at least
  ``FIT_MIN_PARTICIPANTS`` finished participants the model is fitted to the study's votes: the comparison scores,
  the biases' robust sd (the MAD's; a few bad participants must not widen it) and each simulated observer's
  inconsistency drawn from the fitted ones up to their 90th percentile (the least consistent tenth may be the very
  participants to screen out), and a preference for one side of the screen (the median and the robust spread of
  the participants' mean raw answers, less what their noise alone gives).  Before that, the prior: the comparison
  scores evenly spread over -1 ... +1, bias sd 0.25, inconsistency 0.6, side preference sd 0.2.
- ``false_flag_rate`` (default 1 %) is the chance that a good observer is screened out by any calibrated rule,
  split evenly over them (Bonferroni).  36 good observers at 1 % each: at most one flagged in 95 % of panels.
- ``fast`` is not simulated: a good observer answers after one playback (the page enforces it), so a "fast" vote
  is one the page's clock mis-timed; its threshold is the binomial quantile of ``FAST_VOTE_RATE`` per vote (or
  the study's median share, if higher) over the participant's number of votes.
- Power: every simulated panel (of the study's number of participants) holds one random (uniform answers), one
  straight-lining (one answer always) and one inverted (a good observer's answers negated) observer among them,
  the rest good; a rule's power against a kind is the share of them it flags.  A rule *judges* only when its
  power against the kinds it is meant for (``MEANT_FOR``) reaches ``min_power``; otherwise the design is too
  small for it: it reports "too little data" and flags nobody.

Deterministic (``SEED``) and cached on everything it depends on (``calibrate``); bench/screening_design.py times it.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from functools import lru_cache
from typing import Any, Literal

import numpy as np
from scipy import stats

from server.studies.scale import MAX_SCORE

from .subject_model import fit

SEED = 36  # every calibration draws the same simulated panels for the same design and model
FIT_MIN_PARTICIPANTS = 10  # fewer finished participants: the prior instead of a fit
GOOD_DRAWS = 4000  # simulated good observers per calibration (at 1 % / 4 rules: ~10 beyond the threshold)
MIN_PANELS = 100  # and at least this many panels: the power's resolution (one bad observer of a kind each)
MAX_PANELS = 400  # but no more: a tiny panel (a handful of finished participants) would need thousands
MAX_PANEL = 200  # participants in a simulated panel at most: beyond, the rules' measures hardly change with size
FIT_MAX_PARTICIPANTS = 200  # fitted on at most this many (an even sample), for the same reason
FAST_VOTE_RATE = 0.01  # a good observer's votes the page's clock mis-times as before the playback ended

Tail = Literal["lower", "upper"]
BAD_KINDS = ("random", "straight", "inverted")
#: The kinds of bad observer each rule is meant to catch (its power against them decides whether it judges).
MEANT_FOR: dict[str, tuple[str, ...]] = {"straight_lining": ("straight",), "z_outlier": ("random", "inverted"),
                                         "bt500": ("random", "inverted"), "correlation": ("random", "inverted"),
                                         "disagreement": ("random", "inverted"), "fast": ("fast",)}
#: Which way a rule's measure points at a bad observer: the variance and the correlation are low, shares high.
TAILS: dict[str, Tail] = {"straight_lining": "lower", "z_outlier": "upper", "bt500": "upper",
                          "correlation": "lower", "disagreement": "upper"}


@dataclass(frozen=True)
class GoodObservers:
    """The subject model of a good observer for the simulation (see the module docstring)."""

    source: Literal["fitted", "prior"]
    quality: tuple[float, ...]  # per comparison
    ambiguity: tuple[float, ...]  # per comparison (its animation's)
    bias_sd: float
    inconsistency: tuple[float, ...]  # drawn from, per simulated observer
    # A preference for one side of the screen, whatever is shown there (raw answer units, + = left): the subject
    # model has none (its scores are from the test condition's view), but it makes an honest participant's raw
    # answers alike, which is what straight_lining measures.
    side_mean: float = 0.0
    side_sd: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        return {"source": self.source, "comparison_scores": list(self.quality), "ambiguity": list(self.ambiguity),
                "bias_sd": self.bias_sd, "inconsistency_median": float(np.median(self.inconsistency)),
                "side_mean": self.side_mean, "side_sd": self.side_sd}


PRIOR_BIAS_SD = 0.25
PRIOR_INCONSISTENCY = 0.6
PRIOR_SPAN = 1.0  # comparison scores evenly over -PRIOR_SPAN ... +PRIOR_SPAN
PRIOR_SIDE_SD = 0.2  # as server.analysis.simulate's observers


def prior(comparisons: int) -> GoodObservers:
    quality = np.linspace(-PRIOR_SPAN, PRIOR_SPAN, comparisons) if comparisons > 1 else np.zeros(comparisons)
    return GoodObservers("prior", _rounded(quality), (0.0,) * comparisons, PRIOR_BIAS_SD, (PRIOR_INCONSISTENCY,),
                         0.0, PRIOR_SIDE_SD)


def _rounded(values: np.ndarray | list[float], step: float = 0.05) -> tuple[float, ...]:
    """Fitted values on a grid, so that one more vote rarely changes the cache key."""
    return tuple(round(float(v) / step) * step + 0.0 for v in values)


def fitted(x: np.ndarray, content: list[int], leans: np.ndarray | None = None) -> GoodObservers:
    """The subject model fitted to the study's votes x[e, s, r] (see the module docstring); ``leans``: per
    participant (lean, the variance noise alone gives it), their side preference in raw answer units."""
    observers = _fitted(x.tobytes(), x.shape, tuple(content))
    leans = np.asarray(leans if leans is not None else np.empty((0, 2)), dtype=float).reshape(-1, 2)
    leans = leans[np.isfinite(leans).all(axis=1)]
    if len(leans) < FIT_MIN_PARTICIPANTS:
        return observers
    lean, noise = leans[:, 0], leans[:, 1]
    spread = (1.4826 * float(np.median(np.abs(lean - np.median(lean))))) ** 2 - float(np.median(noise))
    return replace(observers, side_mean=round(float(np.median(lean)) / 0.05) * 0.05 + 0.0,
                   side_sd=round(math.sqrt(max(spread, 0.0)) / 0.05) * 0.05)


@lru_cache(maxsize=16)
def _fitted(data: bytes, shape: tuple[int, ...], content: tuple[int, ...]) -> GoodObservers:
    """:func:`fitted`, cached on the votes: a fit takes 15-60 ms at 80-300 participants (compiled, 2026-12-05), and
    the results are polled."""
    x = np.frombuffer(data).reshape(shape)
    content_index = list(content)
    model = fit(x, content_index)
    if model.converged and not model.diverged and np.isfinite(model.quality).all() and np.isfinite(model.bias).all():
        quality, bias, v = model.quality, model.bias, model.inconsistency
        ambiguity = np.nan_to_num(model.ambiguity)[content_index]
    else:
        # sureal's solver can fail to converge or run off (subject_model.fit); the moments it starts from instead
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            quality = np.nanmean(x, axis=(1, 2))
            bias = np.nanmean(x - quality[:, None, None], axis=(0, 2))
            v = np.nanstd(x - quality[:, None, None] - bias[None, :, None], axis=(0, 2))
        ambiguity = np.zeros(len(quality))
    bias = bias[np.isfinite(bias)]
    bias_sd = 1.4826 * float(np.median(np.abs(bias - np.median(bias)))) if bias.size else PRIOR_BIAS_SD
    v = v[np.isfinite(v)]
    v = np.sort(v[v <= np.quantile(v, 0.9)]) if v.size else np.array([PRIOR_INCONSISTENCY])
    # ten quantiles stand for the fitted inconsistencies: a short, stable cache key
    return GoodObservers("fitted", _rounded(np.nan_to_num(quality)), _rounded(ambiguity), round(bias_sd / 0.05) * 0.05,
                         _rounded(np.quantile(v, np.linspace(0.05, 0.95, 10))))


@dataclass(frozen=True)
class RuleCalibration:
    """One rule's threshold for this design, the share of simulated good observers it flags, its power against
    each bad kind, and whether it judges (enough power) or the design is too small for it."""

    threshold: float | None
    tail: Tail
    false_flag: float
    power: dict[str, float]
    judged: bool
    reason: str = ""

    def flags(self, value: float | None) -> bool:
        if not self.judged or value is None or self.threshold is None or not math.isfinite(value):
            return False
        return value < self.threshold if self.tail == "lower" else value > self.threshold

    def as_dict(self) -> dict[str, Any]:
        return {"threshold": self.threshold, "flagged_when": "below" if self.tail == "lower" else "above",
                "false_flag": self.false_flag, "power": self.power, "judged": self.judged, "reason": self.reason}


@dataclass(frozen=True)
class Calibration:
    """Every calibrated rule of one study's design, with how it was made."""

    observers: GoodObservers
    participants: int
    panels: int
    rate_per_rule: float
    rules: dict[str, RuleCalibration] = field(default_factory=dict)
    fast_vote_rate: float = FAST_VOTE_RATE  # a good observer's chance of a vote timed as fast (the ``fast`` rule)
    seconds: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        return {"good_observers": self.observers.as_dict(), "participants": self.participants,
                "panels": self.panels, "false_flag_rate_per_rule": self.rate_per_rule, "seed": SEED,
                "fast_vote_rate": self.fast_vote_rate, "seconds": round(self.seconds, 3),
                "rules": {r: c.as_dict() for r, c in self.rules.items()}}


# (x[e, s, r] scores, raw[e, s, r] answers) -> rule -> measure per participant (``screening.panel_measures``)
Measures = Callable[[np.ndarray, np.ndarray], dict[str, np.ndarray]]


def _simulate(observers: GoodObservers, patterns: np.ndarray, good: int, rng: np.random.Generator,
              kinds: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """One panel: ``good`` good observers, then one of each of ``kinds``; each with the pattern of showings of a
    random real participant.  Returns (scores x[e, s, r], raw answers).  Showing r has the reference on the right
    for even r (raw = score), on the left for odd r, as the designs balance the sides."""
    e_count, r_count = patterns.shape[1], patterns.shape[2]
    count = good + len(kinds)
    mask = patterns[rng.integers(len(patterns), size=count)].transpose(1, 0, 2)  # (E, S, R)
    quality = np.asarray(observers.quality)[:, None, None]
    sd = np.sqrt(rng.choice(np.asarray(observers.inconsistency), size=count)[None, :, None] ** 2
                 + np.asarray(observers.ambiguity)[:, None, None] ** 2)
    side = np.where(np.arange(r_count) % 2 == 0, 1.0, -1.0)[None, None, :]  # raw = score * side
    lean = rng.normal(observers.side_mean, observers.side_sd, count)[None, :, None]  # in raw answer units
    latent = quality + rng.normal(0, observers.bias_sd, count)[None, :, None] + lean * side + sd * rng.standard_normal(
        (e_count, count, r_count))
    x = np.clip(np.rint(latent), -MAX_SCORE, MAX_SCORE)
    for i, kind in enumerate(kinds, start=good):
        if kind == "random":
            x[:, i] = rng.integers(-MAX_SCORE, MAX_SCORE + 1, size=(e_count, r_count))
        elif kind == "straight":
            x[:, i] = rng.integers(-MAX_SCORE, MAX_SCORE + 1) * side[0]
        elif kind == "inverted":
            x[:, i] = -x[:, i]
    x = np.where(mask, x, np.nan)
    return x, x * side


def _threshold(values: np.ndarray, tail: Tail, rate: float) -> float | None:
    """The threshold that flags at most ``rate`` of ``values`` (flagged strictly below it for the lower tail,
    strictly above for the upper); None when even the most extreme value would flag too many."""
    values = np.sort(values[np.isfinite(values)])
    k = math.floor(rate * values.size)
    if values.size == 0:
        return None
    if tail == "lower":
        return float(values[k]) if k < values.size else None
    return float(values[values.size - 1 - k]) if k < values.size else None


def calibrate(x: np.ndarray, content: list[int], rules: tuple[str, ...], false_flag_rate: float, min_power: float,
              measures: Measures, fast_votes: Mapping[str, tuple[int, int]] | None = None,
              leans: np.ndarray | None = None) -> Calibration:
    """The calibration for the study whose finished participants' test votes are x[e, s, r] (``content``: the
    animation index of each comparison).  ``rules``: the chosen rules to calibrate (``MEANT_FOR``'s);
    ``fast_votes``: participant -> (fast votes, votes judged), for ``fast``; ``leans``: per participant (in x's
    order) their side preference and the variance noise alone gives it (``fitted``)."""
    patterns = ~np.isnan(x).transpose(1, 0, 2)  # (S, E, R)
    patterns = patterns[patterns.any(axis=(1, 2))]
    if len(patterns) >= FIT_MIN_PARTICIPANTS:
        # a large study is fitted on an even sample of its participants: the fit's cost grows with them
        sample = np.unique(np.linspace(0, x.shape[1] - 1, min(x.shape[1], FIT_MAX_PARTICIPANTS)).round().astype(int))
        observers = fitted(x[:, sample], content, None if leans is None else np.asarray(leans)[sample])
    else:
        observers = prior(x.shape[0])
    simulated = tuple(r for r in rules if r in TAILS)
    shares = sorted((fast_votes or {}).values())
    median_fast = float(np.median([f / n for f, n in shares if n])) if shares else 0.0
    # The distinct patterns of showings stand for the participants (every finished participant of a reference
    # design has the same one), so the cache holds while participants finish alike.
    unique = (np.unique(patterns.reshape(len(patterns), -1), axis=0).reshape(-1, *patterns.shape[1:])
              if len(patterns) else patterns)
    return _calibrate(observers, np.packbits(unique, axis=None).tobytes(), unique.shape,
                      min(len(patterns), MAX_PANEL), simulated, "fast" in rules, round(false_flag_rate, 6),
                      round(min_power, 6), measures, round(max(FAST_VOTE_RATE, median_fast), 3))


#: Before anyone has finished: the planned calibration is for a panel this size (the issue-36 panel's).
PLANNED_PARTICIPANTS = 40


def planned(comparisons: int, showings: int, rules: tuple[str, ...], false_flag_rate: float, min_power: float,
            measures: Measures, participants: int = PLANNED_PARTICIPANTS) -> Calibration:
    """The calibration before data exist: the prior, ``participants`` who each see all ``comparisons`` (those one
    participant sees) ``showings`` times (an incomplete or adaptive design's participants overlap less than this)."""
    patterns = np.ones((1, comparisons, showings), dtype=bool)
    return _calibrate(prior(comparisons), np.packbits(patterns, axis=None).tobytes(), patterns.shape, participants,
                      tuple(r for r in rules if r in TAILS), "fast" in rules, round(false_flag_rate, 6),
                      round(min_power, 6), measures, FAST_VOTE_RATE)


@lru_cache(maxsize=64)
def _calibrate(observers: GoodObservers, packed: bytes, shape: tuple[int, int, int], participants: int,
               simulated: tuple[str, ...], fast: bool, false_flag_rate: float, min_power: float, measures: Measures,
               fast_rate: float) -> Calibration:
    start = time.perf_counter()
    patterns = np.unpackbits(np.frombuffer(packed, dtype=np.uint8), count=math.prod(shape)).reshape(shape) > 0
    rng = np.random.default_rng(SEED)
    panels = max(MIN_PANELS, min(MAX_PANELS, math.ceil(GOOD_DRAWS / max(participants - len(BAD_KINDS), 1))))
    good: dict[str, list[np.ndarray]] = {r: [] for r in simulated}
    bad: dict[str, dict[str, list[float]]] = {r: {k: [] for k in BAD_KINDS} for r in simulated}
    # A panel of the study's size, one of each bad kind among its participants (the panel-relative rules see them
    # as they would see real ones), at least one good observer.
    honest = max(participants - len(BAD_KINDS), 1)
    for _ in range(panels if simulated and participants else 0):
        x, raw = _simulate(observers, patterns, honest, rng, BAD_KINDS)
        got = measures(x, raw)
        for r in simulated:
            good[r].append(got[r][:honest])
            for i, kind in enumerate(BAD_KINDS):
                bad[r][kind].append(float(got[r][honest + i]))
    votes = int(np.median(patterns.sum(axis=(1, 2)))) if participants else 0  # fast's typical count

    def at(rate: float) -> dict[str, RuleCalibration]:
        out: dict[str, RuleCalibration] = {}
        for r in simulated:
            values = np.concatenate(good[r]) if good[r] else np.array([])
            threshold = _threshold(values, TAILS[r], rate)
            probe = RuleCalibration(threshold, TAILS[r], 0.0, {}, True)
            power = {k: float(np.mean([probe.flags(v) for v in bad[r][k]])) if bad[r][k] else 0.0
                     for k in BAD_KINDS}
            false_flag = float(np.mean([probe.flags(v) for v in values])) if values.size else 0.0
            out[r] = _judge(threshold, TAILS[r], false_flag, power, r, min_power)
        if fast:
            # the binomial quantile for a typical number of votes (per participant: for their own count)
            limit = fast_limit(votes, fast_rate, rate)
            out["fast"] = _judge(limit / votes if votes else None, "upper",
                                 float(stats.binom.sf(limit, votes, fast_rate)) if votes else 0.0,
                                 {"fast": 1.0 if votes and limit < votes else 0.0}, "fast", min_power)
        return out

    # The false-flag rate is shared by the rules that judge: a rule too weak for the design flags nobody, so its
    # share goes to the others (one pass: a larger share only adds power).
    rate = false_flag_rate / max(len(simulated) + fast, 1)
    out = at(rate)
    judging = [r for r, c in out.items() if c.judged]
    if judging and len(judging) < len(out):
        rate = false_flag_rate / len(judging)
        out |= {r: c for r, c in at(rate).items() if r in judging}
    return Calibration(observers, participants, panels if simulated else 0, rate, out, fast_rate,
                       time.perf_counter() - start)


def fast_limit(votes: int, vote_rate: float, rate: float) -> int:
    """The most fast votes of ``votes`` a good observer gives with probability at least 1 - ``rate``."""
    return int(stats.binom.ppf(1 - rate, votes, vote_rate)) if votes else 0


def _judge(threshold: float | None, tail: Tail, false_flag: float, power: dict[str, float], rule: str,
           min_power: float) -> RuleCalibration:
    meant = MEANT_FOR[rule]
    best = max(power.get(k, 0.0) for k in meant)
    if threshold is None or best < min_power:
        reason = (f"too little data for this design: catches at most {best:.0%} of "
                  f"{' or '.join(meant)} observers at this false-flag rate (needs {min_power:.0%})")
        return RuleCalibration(threshold, tail, false_flag, power, False, reason)
    return RuleCalibration(threshold, tail, false_flag, power, True)
