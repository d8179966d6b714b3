"""Simulated observers run through the real design code: how well does a design recover a known scale?

An observer answers like the ordinal Bradley-Terry model of :mod:`server.analysis.ranking`: for a pair shown with
condition ``t`` (the comparison's second, "test") and ``r``, the latent judgement is
``(mu_t + taste_t) - (mu_r + taste_r) + side * bias + noise * L`` with ``L`` standard logistic, cut at
``-CUTS[1] < -CUTS[0] < CUTS[0] < CUTS[1]`` into the five answers -2..+2.  Per observer: ``taste`` is
N(0, ``taste_sd``) per condition (people differ in what they like), ``bias`` is N(0, ``side_sd``) towards the
left side (``side`` is +1 when the test is on the left), ``noise`` is log-normal around 1 (some people answer
more consistently than others).

Sessions are made as the server makes them: the pairs of the mode (``Design.pairs``; ``assign.incomplete_pairs``
for incomplete designs; ``adaptive.adaptive_batches`` over the votes of the simulated observers before, for
adaptive ones), ordered by ``design.trial_order``, each observer finishing before the next starts.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import stats

from server.studies.assign import incomplete_pairs
from server.studies.design import ComparisonIds, Design, trial_order

from .adaptive import Belief, adaptive_batches, posterior
from .ranking import GradedComparison, rank_conditions

CUTS = (0.5, 2.0)  # logit units, as people use the 5-point answers in the thesis data (roughly)


@dataclass(frozen=True)
class Observers:
    taste_sd: float = 0.3
    side_sd: float = 0.2
    noise_sd: float = 0.25  # sd of log(noise scale)


@dataclass(frozen=True)
class SimulatedStudy:
    trials: int  # analysed trials over all participants (practice and catch trials excluded)
    votes: dict[str, list[GradedComparison]]  # per animation
    estimate: dict[str, dict[str, float | None]]  # per animation: condition -> value (anchor 0)
    rmse: float  # over animations and non-anchor conditions with a finite value
    kendall_tau: float  # mean over animations
    failed: int  # conditions without a finite value (separated)


def _answer(rng: np.random.Generator, delta: float, noise: float) -> int:
    """An answer -2..+2 to a scale difference ``delta`` with logistic noise of scale ``noise``."""
    latent = delta + noise * rng.logistic()
    return int(np.searchsorted([-CUTS[1], -CUTS[0], CUTS[0], CUTS[1]], latent) - 2)


def session_pairs(design: Design, position: int, votes: dict[str, list[GradedComparison]],
                  seed: int, belief: Belief = posterior) -> list[tuple[str, str, str]]:
    """(animation, first, second) of the pairs the ``position``-th session sees (as ``assign`` chooses them)."""
    if design.mode == "incomplete":
        return incomplete_pairs(design, "simulated", position)
    if design.mode == "adaptive":
        conditions = design.all_conditions()
        return [(a, conditions[i], conditions[j]) for a, b in adaptive_batches(design, votes, seed, belief).items()
                for i, j in b.pairs]
    return [(a, x, y) for a in design.animations for x, y in design.pairs()]


def simulate(design: Design, truth: dict[str, float], participants: int, seed: int = 0,
             observers: Observers = Observers(), belief: Belief = posterior) -> SimulatedStudy:
    """``participants`` simulated observers through ``design``; ``truth``: condition -> true scale value (logit
    units; the same for every animation; the reference's value is subtracted); ``belief``: what an adaptive
    design plans on (``adaptive.adaptive_batches``)."""
    conditions = design.all_conditions()
    mu = {c: truth[c] - truth[design.reference] for c in conditions}
    votes: dict[str, list[GradedComparison]] = defaultdict(list)
    trials = 0
    for p in range(participants):
        # One random stream per simulated person: participant p of study ``seed`` has the same taste, bias and
        # noise whatever the design and the number of participants, so designs are compared on the same people.
        rng = np.random.default_rng([seed, p])
        session_seed = int(rng.integers(2**62))
        taste = {c: rng.normal(0, observers.taste_sd) for c in conditions}
        bias, noise = rng.normal(0, observers.side_sd), math.exp(rng.normal(0, observers.noise_sd))
        pairs = session_pairs(design, p, votes, session_seed, belief)
        order = trial_order(ComparisonIds(list(range(len(pairs)))), design.repeats, session_seed)
        for t in order:
            animation, first, second = pairs[t.comparison_id]
            side = 1 if t.reference_side == "right" else -1  # the second condition (test) on the left: +1
            delta = (mu[second] + taste[second]) - (mu[first] + taste[first]) + side * bias
            votes[animation].append(GradedComparison(str(p), first, second, _answer(rng, delta, noise)))
            trials += 1
    estimate, errors, taus, failed = {}, [], [], 0
    for animation in design.animations:
        ranking = rank_conditions(votes[animation], anchor=design.reference, conditions=conditions)
        values = {c.condition: c.value for c in ranking.conditions}
        estimate[animation] = values
        for c in conditions[1:]:
            if values[c] is None:
                failed += 1
            else:
                errors.append(values[c] - mu[c])
        ranked = [values[c] if values[c] is not None else (math.inf if mu[c] > 0 else -math.inf)
                  for c in conditions]
        taus.append(float(stats.kendalltau(ranked, [mu[c] for c in conditions]).statistic))
    return SimulatedStudy(trials, dict(votes), estimate, float(np.sqrt(np.mean(np.square(errors)))) if errors
                          else math.nan, float(np.mean(taus)), failed)


def even_truth(design: Design, span: float = 2.5) -> dict[str, float]:
    """The default truth: the conditions in the design's order (the reference first) evenly spaced over
    0..``span`` logit units."""
    conditions = design.all_conditions()
    return {c: span * i / max(len(conditions) - 1, 1) for i, c in enumerate(conditions)}


@dataclass(frozen=True)
class Summary:
    participants: int
    seeds: int
    trials_per_study: int
    rmse: float  # mean over seeds
    kendall_tau: float  # mean over seeds
    tau_at_least_09: float  # share of seeds with Kendall tau >= 0.9
    failed: int  # conditions without a finite value, over all seeds


def summarise(design: Design, truth: dict[str, float], participants: int, seeds: int,
              observers: Observers = Observers(), progress: Callable[[int], None] | None = None) -> Summary:
    """``seeds`` simulated studies; ``progress(done)`` after each."""
    runs = []
    for s in range(seeds):
        runs.append(simulate(design, truth, participants, seed=s, observers=observers))
        if progress:
            progress(s + 1)
    return Summary(participants, seeds, runs[0].trials, float(np.nanmean([r.rmse for r in runs])),
                   float(np.mean([r.kendall_tau for r in runs])),
                   float(np.mean([r.kendall_tau >= 0.9 for r in runs])), sum(r.failed for r in runs))


def power(design: Design, effect: float, participants: int, seeds: int,
          observers: Observers = Observers()) -> float:
    """The share of simulated studies in which the 95 % interval (cluster-robust, ``ranking``) of the first
    condition excludes the reference, or the condition has no finite value (separated: a bound), every condition
    ``effect`` logit units above the reference."""
    truth = {c: 0.0 if c == design.reference else effect for c in design.all_conditions()}
    first = design.conditions[0]
    hits = 0
    for s in range(seeds):
        run = simulate(design, truth, participants, seed=s, observers=observers)
        scale = {c.condition: c for c in rank_conditions(run.votes.get(design.animations[0], []),
                                                         anchor=design.reference,
                                                         conditions=design.all_conditions()).conditions}
        ci = scale[first].ci95
        hits += bool((ci is not None and (ci[0] > 0 or ci[1] < 0)) or scale[first].bound is not None)
    return hits / seeds


def plan(design: Design, effect: float, target: float = 0.8, seeds: int = 100, most: int = 1000,
         observers: Observers = Observers(),
         progress: Callable[[int, float], None] | None = None) -> tuple[int | None, float]:
    """The fewest participants (2..``most``) with simulated power at least ``target`` for ``effect`` (see
    :func:`power`), and that power; ``(None, power at most)`` if even ``most`` are not enough.
    ``progress(participants, power)`` after each count tried."""

    def power_of(participants: int) -> float:
        value = power(design, effect, participants, seeds, observers)
        if progress:
            progress(participants, value)
        return value

    low, high = 1, 2
    high_power = power_of(high)
    while high_power < target:
        if high >= most:
            return None, high_power
        low, high = high, min(high * 2, most)
        high_power = power_of(high)
    while high - low > 1:
        mid = (low + high) // 2
        mid_power = power_of(mid)
        if mid_power >= target:
            high, high_power = mid, mid_power
        else:
            low = mid
    return high, high_power
