"""One scale per animation (issue 27): checked against statsmodels' ordinal model, and recovering a known order."""

from __future__ import annotations

import warnings
from itertools import combinations

import numpy as np
import pandas as pd
import pytest
from scipy import optimize
from statsmodels.miscmodels.ordinal_model import OrderedModel

from server.analysis.interval_scale import (
    BOOT_PRIOR_SD,
    _design,
    _ridge_all,
    animation_scale,
    bootstrap_draws,
    jnd_unit,
)
from server.analysis.ranking import GradedComparison, vote_log_likelihood
from server.analysis.simulate import simulate
from server.studies.design import Design

NAMES = ["ref", "a", "b", "c"]
TRUE = np.array([0.0, 0.4, 1.0, 1.8])


def _votes(participants: int, seed: int) -> list[GradedComparison]:
    rng = np.random.default_rng(seed)
    out = []
    for p in range(participants):
        taste = rng.normal(0, 0.3, len(NAMES))
        for i, j in combinations(range(len(NAMES)), 2):
            for _ in range(2):
                latent = TRUE[j] + taste[j] - TRUE[i] - taste[i] + rng.logistic()
                out.append(GradedComparison(f"p{p}", NAMES[i], NAMES[j],
                                            int(np.searchsorted([-2, -0.5, 0.5, 2], latent) - 2)))
    return out


def _statsmodels_values(votes: list[GradedComparison]) -> np.ndarray:
    """Maximum likelihood values (ref at 0) by statsmodels' OrderedModel; the votes and their mirror images, so
    that the cut points are symmetric as in the ranking model (then the log-likelihood is doubled, the values
    are the same)."""
    x = np.zeros((len(votes), len(NAMES) - 1))
    for k, v in enumerate(votes):
        if v.test != "ref":
            x[k, NAMES.index(v.test) - 1] += 1
        if v.reference != "ref":
            x[k, NAMES.index(v.reference) - 1] -= 1
    y = np.array([v.score for v in votes])
    endog = pd.Series(pd.Categorical(np.concatenate([y, -y]), categories=[-2, -1, 0, 1, 2], ordered=True))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = OrderedModel(endog, np.vstack([x, -x]), distr="logit").fit(method="bfgs", disp=False, maxiter=5000,
                                                                          gtol=1e-8)
    return np.concatenate([[0.0], fit.params.iloc[: len(NAMES) - 1].to_numpy()])


def test_scale_and_bootstrap_match_statsmodels():
    votes = _votes(12, seed=3)
    n_boot = 30
    scale = animation_scale("walk", votes, NAMES, n_boot=n_boot, seed=11)
    assert scale.conditions == tuple(NAMES)
    np.testing.assert_allclose(scale.value, _statsmodels_values(votes), atol=1e-4)
    # The bootstrap, independently: the same participant resamples, each fitted by statsmodels.
    people = list(dict.fromkeys(v.participant for v in votes))
    samples = []
    for draw in bootstrap_draws(people, n_boot, 11):
        resample = [v._replace(participant=str(k)) for k, i in enumerate(draw) for v in votes
                    if v.participant == people[i]]
        samples.append(_statsmodels_values(resample))
    low, high = np.percentile(samples, [2.5, 97.5], axis=0)
    for i in range(1, len(NAMES)):
        assert scale.ci95[i] == pytest.approx((low[i], high[i]), abs=0.02)  # the ridge (sd 10) moves them a little
    n = len(NAMES)
    above = np.mean([[[s[i] > s[j] for j in range(n)] for i in range(n)] for s in samples], axis=0)
    for i in range(len(NAMES)):
        for j in range(len(NAMES)):
            if i != j:
                assert scale.p_better[i][j] == pytest.approx(above[i][j], abs=1 / n_boot + 1e-9)
                assert scale.p_better[i][j] + scale.p_better[j][i] == pytest.approx(1.0)
    assert scale.pair_counts[0][1] == scale.pair_counts[1][0] == 12 * 2
    assert scale.participants == 12 and scale.status == "ok"


def test_jnd_unit():
    # With cut points -2, -0.5, 0.5, 2, a difference of 0 is preferred half the time; at the JND 75 %.
    unit = jnd_unit([-2.0, -0.5, 0.5, 2.0])
    better = 1 - 1 / (1 + np.exp(-(0.5 - unit)))
    worse = 1 / (1 + np.exp(-(-0.5 - unit)))
    assert better / (better + worse) == pytest.approx(0.75, abs=1e-9)
    # Binary answers (no tie category worth speaking of): the Bradley-Terry JND, log 3.
    assert jnd_unit([-1e-9, -1e-10, 1e-10, 1e-9]) == pytest.approx(np.log(3), abs=1e-6)


def test_no_votes_and_one_participant_give_no_intervals():
    empty = animation_scale("walk", [], NAMES)
    assert empty.value[0] == 0 and empty.value[1] is None and empty.ci95[1] is None
    one = animation_scale("walk", [v for v in _votes(1, seed=1)], NAMES)
    assert one.ci95[1] is None and one.p_better[1][0] is None


def test_all_pairs_recovers_the_true_order():
    """Issue 27: 40 simulated participants on 6 conditions, all-pairs: Kendall tau >= 0.9 in >= 90 % of seeds."""
    design = Design(mode="all-pairs", reference="c0", conditions=[f"c{i}" for i in range(1, 6)], animations=["walk"])
    truth = {f"c{i}": 0.4 * i for i in range(6)}
    taus = [simulate(design, truth, 40, seed=seed).kendall_tau for seed in range(20)]
    print("Kendall tau over 20 seeds:", np.round(taus, 3))
    assert np.mean(np.array(taus) >= 0.9) >= 0.9


def _ridge_objective(x, y):
    """The bootstrap's ridge objective and gradient for cells ``x``, ``y`` with weights ``w``, written from the
    ranking's per-vote likelihood and the prior the module documents (values around 0 with sd BOOT_PRIOR_SD, the
    cut log-increments around log 0.5 and log 1.5 with sd 10); and the prior's centre."""
    n = x.shape[1]
    precision = np.concatenate([np.full(n, BOOT_PRIOR_SD**-2), np.full(2, 1e-2)])
    centre = np.concatenate([np.zeros(n), np.log([0.5, 1.5])])

    def objective(params, w):
        loglik, grad = vote_log_likelihood(params, x, y, False, n, "logit")
        diff = params - centre
        return -float(w @ loglik) + 0.5 * float(diff @ (precision * diff)), -w @ grad + precision * diff

    return objective, centre


def test_batched_newton_refits_equal_one_fit_per_resample():
    """The bootstrap fits all resamples at once (Newton); each must be the minimum of its own ridge objective,
    found here one resample at a time by scipy's BFGS at a tight tolerance on that objective written from the
    ranking's per-vote likelihood.  Mostly "no difference" answers: some resamples are nearly separated."""
    rng = np.random.default_rng(5)
    votes = [GradedComparison(f"p{p}", "ref", c, int(rng.choice([-1, 0, 0, 0, 0, 0, 0, 1, 2])))
             for p in range(6) for c in NAMES[1:] for _ in range(2)]
    x, y = _design(votes, NAMES)
    people = list(dict.fromkeys(v.participant for v in votes))
    draws = bootstrap_draws(people, 40, 1)
    weight = np.stack([[np.sum(np.bincount(d, minlength=6)[int(v.participant[1:])]) for v in votes] for d in draws])
    n = len(NAMES) - 1
    objective, centre = _ridge_objective(x, y)
    expected = np.array([optimize.minimize(objective, centre, args=(w,), jac=True, method="BFGS",
                                           options={"gtol": 1e-10, "maxiter": 5000}).x for w in weight])
    got = _ridge_all(x, y, weight.astype(float), expected.mean(axis=0))
    np.testing.assert_allclose(got, expected, atol=1e-5)
    assert np.abs(got[:, :n]).max() > 2  # nearly separated resamples among them


def test_a_separated_condition_has_no_value_and_says_which_way():
    """Almost every vote "no difference", a never rated worse and b never better (the ranking's separation through
    the cut points): no value, the bound the dashboard shows, and still the bootstrap's interval."""
    votes = [GradedComparison(f"p{p}", "ref", c, 0) for p in range(10) for c in ("a", "b") for _ in range(4)]
    votes[0], votes[4] = votes[0]._replace(score=1), votes[4]._replace(score=-1)  # p0: a +1, b -1
    scale = animation_scale("walk", votes, ["ref", "a", "b"], n_boot=50)
    assert scale.status == "separated" and scale.value == (0.0, None, None)
    assert scale.bound == (None, "above", "below")
    assert scale.ci95[1][0] >= 0 and scale.ci95[2][1] <= 0



def test_batched_newton_takes_no_overflowing_step():
    """A Newton step far out can give a vote a probability that underflows (its squared derivative overflows): such
    a trial step is halved, never taken, and no warning fails the results request (the suite turns RuntimeWarning
    into an error; this was a 500 in CI).  A simulated all-pairs study (seeded) whose bootstrap met such a step; every
    refit must still be the minimum of its own objective, found one at a time by scipy's BFGS."""
    rng = np.random.default_rng(7)
    k = int(rng.integers(3, 7))
    names = ["ref", *(f"c{i}" for i in range(k - 1))]
    true = np.concatenate([[0.0], rng.normal(0, rng.uniform(0.5, 8), k - 1)])
    people = int(rng.integers(2, 10))
    pairs = list(combinations(range(k), 2)) if rng.random() < 0.5 else [(0, i) for i in range(1, k)]
    votes = [GradedComparison(f"p{p}", names[i], names[j],
                              int(np.digitize(true[j] - true[i] + rng.logistic(), [-3, -1, 1, 3])) - 2)
             for p in range(people) for i, j in pairs]
    scale = animation_scale("walk", votes, names, n_boot=200)  # overflowed here before
    assert scale.status == "separated" and scale.ci95[1] is not None  # one condition never lost: resamples far out
    x, y = _design(votes, names)
    draws = bootstrap_draws([f"p{p}" for p in range(people)], 200, 0)
    weight = np.stack([np.bincount(d, minlength=people)[[int(v.participant[1:]) for v in votes]] for d in draws])
    objective, centre = _ridge_objective(x, y)
    start = optimize.minimize(objective, centre, args=(np.ones(len(votes)),), jac=True, method="BFGS").x
    got = _ridge_all(x, y, weight.astype(float), start)
    got_value = np.array([objective(g, w)[0] for g, w in zip(got, weight, strict=True)])
    best = np.array([optimize.minimize(objective, g, args=(w,), jac=True, method="BFGS",
                                       options={"gtol": 1e-10, "maxiter": 5000}).fun
                     for g, w in zip(got, weight, strict=True)])
    np.testing.assert_allclose(got_value, best, atol=1e-6)
