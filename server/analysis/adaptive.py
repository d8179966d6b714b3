"""Choosing the next pairs to show from the answers so far (ASAP-style active sampling).

Mikhailiuk, Wilmot, Perez-Ortiz, Yue, Mantiuk (2021), "Active sampling for pairwise comparisons via approximate
message passing and information gain maximization" (ASAP): a round shows a batch of N-1 pairs of the N
conditions that form a spanning tree of the comparison graph, so that one round links every condition and spends
its trials where they tell most.

Here the model is the ordinal Bradley-Terry model of :mod:`server.analysis.ranking` (the cumulative logit model of
the 5-point answers, the anchor condition at 0).  The posterior of the scale values is its Laplace approximation:
the maximum a posteriori values under a weak normal prior (``PRIOR_SD`` logit units, which keeps them finite
with few or one-sided answers) and the inverse of the posterior precision, the prior precision plus the
*expected* Fisher information of the pairs answered so far at those values (the cut points taken as known).  The
observed (BHHH) information, which this module used before, scatters with the few answers given and chose worse
trees.

Which tree (the design's ``aim``): ASAP weights every pair by its expected information gain about the whole scale
(the mutual information between the next answer and the scale, :func:`information_gain`) and takes the minimum
spanning tree over 1 / gain (:func:`information_tree`, ``aim = "order"``).  A study that reports each condition's
value against the anchor can have the tree chosen for that (:func:`next_batch`, ``aim = "reference"``, the
default): greedily, the pair whose answers are expected to shrink the summed posterior variances of the
conditions against the anchor most
(the Fisher information of the pair's answers, averaged over the posterior of its difference, as a rank-one
update of the covariance), among the pairs joining two parts of the tree not yet linked, the covariance updated
after each pick (Kruskal's algorithm on gains that account for the pairs already in the batch).  Pairs of
near-equal conditions carry more information per answer than pairs of far-apart ones (an answer to a pair 6
logit units apart is almost surely "much better"), and the anchor's pairs count more for the anchored values;
both enter through this one criterion.  The two are measured against each other in docs/designs.md: neither is
better on both precisions at every spread of the conditions.

Everything here is a pure function of the votes and a seed: the pairs a session was given can be recomputed from
the study's vote log (the votes answered before the session started) and the session's stored seed.
"""

from __future__ import annotations

import hashlib
import threading
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from itertools import combinations

import numpy as np
from scipy import optimize
from scipy.sparse.csgraph import minimum_spanning_tree

from server.studies.design import Design
from server.studies.scale import MAX_SCORE, SCORES

from .ranking import GradedComparison, link_cdf_pdf, symmetric_cuts, vote_log_likelihood

PRIOR_SD = 2.0  # logit units: a weak prior, a 2-point difference is 'much better' most of the time
# Prior of the log-increments of the positive cut points (a ~ 0.5, b ~ 2 logit units), sd 1.
CUT_PRIOR = np.log([0.5, 1.5])
_NODES, _WEIGHTS = np.polynomial.hermite_e.hermegauss(24)
_WEIGHTS = _WEIGHTS / _WEIGHTS.sum()


@dataclass(frozen=True)
class Posterior:
    """Laplace approximation of the scale values of ``conditions`` (``conditions[0]`` is the anchor, at 0)."""

    conditions: tuple[str, ...]
    mean: np.ndarray  # (N,) logit units, mean[0] == 0
    # (N, N) of the values before the anchor is subtracted (only differences matter): the inverse of the prior
    # precision plus the *expected* Fisher information of the votes' pairs at the posterior mean (cut points taken
    # as known).  The observed (BHHH) information of a few votes, which this was before, scatters with the
    # answers given; planning on it chose worse trees (measured in docs/designs.md).
    cov: np.ndarray
    cuts: np.ndarray  # (4,) the cut points -b, -a, a, b
    n_votes: int


def vote_counts(votes: Iterable[GradedComparison], conditions: Sequence[str]) -> np.ndarray:
    """The sufficient statistics of ``votes`` for the posterior: (N, N, answers) counts of [reference, test,
    answer 0..4 (score + MAX_SCORE)]; votes of other conditions and catch votes (a condition against itself) are
    left out.  Counts add up: the counts of two sets of votes are the sum of their counts."""
    index = {c: i for i, c in enumerate(conditions)}
    counts = np.zeros((len(index), len(index), len(SCORES)), dtype=np.int64)
    for v in votes:
        if v.reference != v.test and v.reference in index and v.test in index:
            counts[index[v.reference], index[v.test], v.score + MAX_SCORE] += 1
    return counts


def _cells(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The non-empty cells of ``counts``: (cells, N) rows +1 at the test and -1 at the reference, their answers
    0..4 and how many votes gave each: the likelihood of the votes is the cells' likelihoods raised to those
    counts, so fitting costs the same at 100 votes as at 10,000."""
    reference, test, answer = np.nonzero(counts)
    x = np.zeros((reference.size, counts.shape[0]))
    x[np.arange(reference.size), test] += 1
    x[np.arange(reference.size), reference] -= 1
    return x, answer, counts[reference, test, answer].astype(float)


def _planning_cov(x: np.ndarray, weight: np.ndarray, mean: np.ndarray, cuts: np.ndarray) -> np.ndarray:
    """The inverse of the prior precision plus the expected Fisher information of the rows' pairs (each
    ``weight`` times) at ``mean``."""
    precision = np.eye(mean.size) / PRIOR_SD**2  # positive definite: the prior's precision is on the diagonal
    if x.size:
        precision = precision + (x * (weight * answer_information(x @ mean, cuts))[:, None]).T @ x
    return np.linalg.inv(precision)


def posterior(votes: Sequence[GradedComparison], conditions: Sequence[str]) -> Posterior:
    """The posterior of the scale values of ``conditions`` (the first is the anchor) given ``votes``; votes of
    other conditions and catch votes (a condition against itself) are ignored."""
    return counts_posterior(vote_counts(votes, conditions), tuple(conditions))


def counts_posterior(counts: np.ndarray, conditions: tuple[str, ...]) -> Posterior:
    """:func:`posterior` from the votes' :func:`vote_counts`.  A pure function of the counts, remembered for the
    last ``POSTERIORS`` of them: the dashboard replays every adaptive round, and all but the newest rounds saw the
    same votes as at the last request."""
    key = (conditions, hashlib.sha256(counts.tobytes()).digest())
    with _POSTERIORS_LOCK:
        post = _POSTERIORS.pop(key, None)
        if post is not None:
            _POSTERIORS[key] = post  # the most recently used last
            return post
    post = _fit(counts, conditions)
    with _POSTERIORS_LOCK:
        _POSTERIORS[key] = post
        while len(_POSTERIORS) > POSTERIORS:
            _POSTERIORS.pop(next(iter(_POSTERIORS)))  # the least recently used
    return post


# Every round of studies with 20,000 sessions x animations in all (~0.8 kB each at six conditions); a study with
# more rounds than that is refitted in full at every request, as all of them were before issue 36.
POSTERIORS = 20_000
_POSTERIORS: dict[tuple[tuple[str, ...], bytes], Posterior] = {}
_POSTERIORS_LOCK = threading.Lock()


def _fit(counts: np.ndarray, conditions: tuple[str, ...]) -> Posterior:
    x, y, weight = _cells(counts)
    # Every condition has the same prior, the anchor too, so that no pair looks more or less certain because of
    # which condition is called the origin; the values are moved to the anchor's origin afterwards.
    n = len(conditions)
    prior_mean = np.concatenate([np.zeros(n), CUT_PRIOR])
    prior_precision = np.concatenate([np.full(n, 1 / PRIOR_SD**2), np.ones(CUT_PRIOR.size)])

    def objective(params: np.ndarray) -> tuple[float, np.ndarray]:
        diff = params - prior_mean
        value, grad = 0.5 * float(diff @ (prior_precision * diff)), prior_precision * diff
        if y.size:
            loglik, per_cell = vote_log_likelihood(params, x, y, False, n, "logit")
            value, grad = value - float(weight @ loglik), grad - weight @ per_cell
        return value, grad

    opt = optimize.minimize(objective, prior_mean, jac=True, method="BFGS", options={"gtol": 1e-7})
    mean = opt.x[:n] - opt.x[0]
    cuts, _ = symmetric_cuts(opt.x[n:], False)
    cov = _planning_cov(x, weight, mean, cuts)
    for shared in (mean, cov, cuts):  # remembered and handed to every caller: nobody may change them
        shared.flags.writeable = False
    return Posterior(conditions, mean, cov, cuts, int(weight.sum()))


def known_posterior(votes: Sequence[GradedComparison], conditions: Sequence[str], values: dict[str, float],
                    cuts: np.ndarray) -> Posterior:
    """What :func:`posterior` would be if the answers had revealed the true scale ``values`` (condition -> logit
    units) and cut points ``cuts`` (4,): the same covariance, at the truth.  Planning on it shows how much an
    adaptive design loses by learning the values as it goes (the design bench's ``oracle``)."""
    names = list(conditions)
    x, _, weight = _cells(vote_counts(votes, names))
    mean = np.array([values[c] - values[names[0]] for c in names])
    return Posterior(tuple(names), mean, _planning_cov(x, weight, mean, np.asarray(cuts, dtype=float)),
                     np.asarray(cuts), int(weight.sum()))


def _answer_probabilities(delta: np.ndarray, cuts: np.ndarray) -> np.ndarray:
    """P(answer = -2..+2 | delta), shape (len(delta), 5)."""
    cdf, _ = link_cdf_pdf(cuts[None, :] - delta[:, None], "logit")
    ext = np.concatenate([np.zeros((delta.size, 1)), cdf, np.ones((delta.size, 1))], axis=1)
    return np.clip(np.diff(ext, axis=1), 1e-300, 1.0)


def information_gain(post: Posterior, first: int, second: int) -> float:
    """Expected information (nats) the next answer to ``first`` against ``second`` gives about their scale
    difference."""
    m = post.mean[second] - post.mean[first]
    var = post.cov[first, first] + post.cov[second, second] - 2 * post.cov[first, second]
    p = _answer_probabilities(m + np.sqrt(max(var, 0.0)) * _NODES, post.cuts)
    marginal = _WEIGHTS @ p
    conditional = -(p * np.log(p)).sum(axis=1)
    return float(-(marginal * np.log(marginal)).sum() - _WEIGHTS @ conditional)


@dataclass(frozen=True)
class Batch:
    """One round: the N-1 pairs to show (indices into the conditions, first < second) and their gains."""

    pairs: tuple[tuple[int, int], ...]
    gains: tuple[float, ...]

    @property
    def information(self) -> float:
        return float(sum(self.gains))


def answer_information(delta: np.ndarray, cuts: np.ndarray) -> np.ndarray:
    """Fisher information (per logit unit squared) of one answer about the scale difference ``delta``."""
    cdf, pdf = link_cdf_pdf(cuts[None, :] - delta[:, None], "logit")
    zeros, ones = np.zeros((delta.size, 1)), np.ones((delta.size, 1))
    p = np.clip(np.diff(np.concatenate([zeros, cdf, ones], axis=1), axis=1), 1e-300, 1.0)
    dp = np.diff(np.concatenate([zeros, pdf, zeros], axis=1), axis=1)
    return (dp * dp / p).sum(axis=1)


def next_batch(post: Posterior, seed: int, showings: int = 2) -> Batch:
    """The spanning tree of N-1 pairs expected to shrink the variances of the conditions against the anchor
    most (see the module's text); ``showings``: answers a participant gives to each pair of the batch.  Equal
    gains (e.g. before any vote) are ordered by a tiny seeded perturbation, so the seed decides among equal
    trees.  The batch's ``gains`` are the pairs' expected information gains (nats), what the dashboard shows."""
    n = len(post.conditions)
    if n < 2:
        return Batch((), ())
    first, second = np.triu_indices(n, 1)
    cov = post.cov.copy()
    spread = np.sqrt(np.maximum(cov[first, first] + cov[second, second] - 2 * cov[first, second], 0.0))
    delta = post.mean[second] - post.mean[first]
    expected = answer_information((delta[:, None] + spread[:, None] * _NODES[None, :]).ravel(), post.cuts)
    weight = showings * (expected.reshape(delta.size, _NODES.size) @ _WEIGHTS)
    jitter = 1 + np.random.default_rng(seed).uniform(0, 1e-6, delta.size)
    part = np.arange(n)  # the part of the tree each condition is in
    chosen = []
    for _ in range(n - 1):
        moved = cov[:, second] - cov[:, first]  # (N, pairs): cov @ x for every pair's x = e_second - e_first
        against_anchor = moved[1:] - moved[0]
        variance = moved[second, np.arange(delta.size)] - moved[first, np.arange(delta.size)]  # x' cov x
        gain = weight * (against_anchor * against_anchor).sum(axis=0) / (1 + weight * variance) * jitter
        gain[part[first] == part[second]] = -np.inf
        k = int(np.argmax(gain))
        cov = cov - weight[k] * np.outer(moved[:, k], moved[:, k]) / (1 + weight[k] * variance[k])
        part[part == part[second[k]]] = part[first[k]]
        chosen.append((int(first[k]), int(second[k])))
    pairs = sorted(chosen)
    return Batch(tuple(pairs), tuple(information_gain(post, i, j) for i, j in pairs))


def information_tree(post: Posterior, seed: int, showings: int = 2) -> Batch:
    """ASAP's own batch (``aim = "order"``): the minimum spanning tree over 1 / expected information gain, the
    pairs whose next answer tells most about the whole scale.  ``showings`` is unused: the gain of one answer ranks
    the pairs the same."""
    n = len(post.conditions)
    if n < 2:
        return Batch((), ())
    gains = np.zeros((n, n))
    for i, j in combinations(range(n), 2):
        gains[i, j] = gains[j, i] = information_gain(post, i, j)
    jitter = np.random.default_rng(seed).uniform(0, 1e-6, (n, n))
    weights = np.triu(1 / np.maximum(gains, 1e-12) * (1 + jitter + jitter.T), 1)
    tree = minimum_spanning_tree(weights).tocoo()
    pairs = sorted((min(int(i), int(j)), max(int(i), int(j))) for i, j in zip(tree.row, tree.col, strict=True))
    return Batch(tuple(pairs), tuple(float(gains[i, j]) for i, j in pairs))


Belief = Callable[[Sequence[GradedComparison], Sequence[str]], Posterior]


def adaptive_batches(design: Design, votes: dict[str, list[GradedComparison]], seed: int,
                     belief: Belief = posterior) -> dict[str, Batch]:
    """Per animation, the batch of pairs (indices into ``design.all_conditions()``) for a session with ``seed``.
    ``belief``: what the batches are planned on, the posterior of the votes; the design bench swaps in the true
    values to measure how much knowing them would save (its ``oracle``)."""
    conditions = design.all_conditions()
    choose = information_tree if design.aim == "order" else next_batch
    return {a: choose(belief(votes.get(a, []), conditions), seed + i, 2 * design.repeats)
            for i, a in enumerate(design.animations)}
