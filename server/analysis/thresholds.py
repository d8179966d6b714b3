"""Planted observers through threshold designs (issue 38): constant stimuli and QUEST+ (:mod:`.quest`), the
psychometric fit of :mod:`server.analysis.psychometric` on what they answered, and the trials each design needs
for a threshold interval of a given width (``animstudy study plan --thresholds``; docs/methods/thresholds.md).

An observer answers a 2AFC trial at level ``v`` correctly with probability
``0.5 + (0.5 - lapse) * Phi(sign * (log10 v - log10 threshold) / s)``, ``s = width / (2 Phi^-1(0.95))``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats

from . import quest
from .psychometric import GUESS_2AFC, Z_WIDTH, Fit, fit

#: the ladder of the issue's example (poses per second) and a planted observer on it
PPS_LEVELS: tuple[float, ...] = (4, 6, 8, 12, 16, 24, 30)


@dataclass(frozen=True)
class Observer:
    threshold: float  # level units
    width: float = 0.5  # log10 units, 5 % -> 95 % of the sigmoid
    lapse: float = 0.02
    increasing: bool = False  # an update rate is detected at its low levels
    guess: float = GUESS_2AFC

    def p(self, levels: np.ndarray) -> np.ndarray:
        z = (np.log10(levels) - math.log10(self.threshold)) / (self.width / (2 * Z_WIDTH))
        return self.guess + (1 - self.guess - self.lapse) * stats.norm.cdf(z if self.increasing else -z)


@dataclass(frozen=True)
class Counts:
    levels: np.ndarray
    trials: np.ndarray
    correct: np.ndarray


def constant_stimuli(observer: Observer, levels: Sequence[float], repeats: int,
                     rng: np.random.Generator) -> Counts:
    lv = np.asarray(levels, dtype=float)
    n = np.full(len(lv), repeats)
    return Counts(lv, n, rng.binomial(n, observer.p(lv)))


def quest_plus(observer: Observer, levels: Sequence[float], trials: int, rng: np.random.Generator) -> Counts:
    """One QUEST+ staircase (:mod:`.quest`: minimum expected entropy, cumulative normal on the log10 levels,
    signed so that detection grows with them; the staircase designs' grid) of ``trials`` trials over ``levels``;
    the observer's answers drawn from ``rng``."""
    xs = tuple((1 if observer.increasing else -1) * math.log10(v) for v in levels)
    detection = quest.Grid(xs, (GUESS_2AFC,)).detection()
    lv = np.asarray(levels, dtype=float)
    n = np.zeros(len(lv), dtype=int)
    k = np.zeros(len(lv), dtype=int)
    post = quest.posterior(detection, [])
    for _ in range(trials):
        i = quest.next_index(detection, post)
        ok = bool(rng.random() < observer.p(lv[i : i + 1])[0])
        n[i] += 1
        k[i] += ok
        post = quest.update(post, detection, i, ok)
    return Counts(lv, n, k)


@dataclass(frozen=True)
class Run:
    fit: Fit
    covered: bool  # the planted threshold inside the bootstrap interval
    covered_profile: bool  # ... inside the profile-likelihood interval
    log_span: float  # width of the threshold's bootstrap interval, log10 units


def run(design: str, observer: Observer, levels: Sequence[float], trials: int, seed: int,
        bootstrap: int = 400) -> Run:
    """One simulated participant: ``design`` ``constant-stimuli`` (``trials`` spread evenly over the levels,
    rounded down) or ``staircase`` (QUEST+), fitted with the direction known."""
    rng = np.random.default_rng(seed)
    if design == "constant-stimuli":
        c = constant_stimuli(observer, levels, max(1, trials // len(levels)), rng)
    elif design == "staircase":
        c = quest_plus(observer, levels, trials, rng)
    else:
        raise ValueError(f"design {design!r}: constant-stimuli or staircase")
    f = fit(c.levels, c.trials, c.correct, increasing=observer.increasing, bootstrap=bootstrap, seed=seed)
    assert f.threshold_profile is not None
    return Run(f, f.threshold.contains(observer.threshold), f.threshold_profile.contains(observer.threshold),
               f.log_threshold.span)


@dataclass(frozen=True)
class Summary:
    design: str
    trials: int
    seeds: int
    coverage: float
    median_span: float  # median width of the threshold's 95 % interval, log10 units
    span_low: float  # bootstrap 95 % interval of that median (over seeds)
    span_high: float


def summarize(design: str, observer: Observer, levels: Sequence[float], trials: int, seeds: int,
              bootstrap: int = 400, progress: Callable[[int], None] | None = None) -> Summary:
    runs = []
    for s in range(seeds):
        runs.append(run(design, observer, levels, trials, s, bootstrap))
        if progress:
            progress(s + 1)
    spans = np.array([r.log_span for r in runs])
    rng = np.random.default_rng(12345)
    meds = np.median(rng.choice(spans, size=(2000, len(spans))), axis=1)
    lo, hi = np.percentile(meds, [2.5, 97.5])
    return Summary(design, trials, seeds, float(np.mean([r.covered for r in runs])), float(np.median(spans)),
                   float(lo), float(hi))


def trials_for(design: str, observer: Observer, levels: Sequence[float], target_span: float, seeds: int,
               candidates: Sequence[int], bootstrap: int = 400,
               progress: Callable[[int, Summary], None] | None = None) -> tuple[int | None, list[Summary]]:
    """The fewest trials among ``candidates`` (ascending) whose median threshold interval (log10 units) is at
    most ``target_span``; None if none reaches it."""
    tried = []
    for t in candidates:
        s = summarize(design, observer, levels, t, seeds, bootstrap)
        tried.append(s)
        if progress:
            progress(t, s)
        if s.median_span <= target_span:
            return t, tried
    return None, tried
