"""The ranking of conditions against a published Bradley-Terry example, independent implementations and simulation."""

import dataclasses
import math
import warnings
from collections import Counter

import numpy as np
import pandas as pd
import pytest
import statsmodels.api as sm
from scipy import optimize
from statsmodels.miscmodels.ordinal_model import OrderedModel

from server.analysis.ranking import GradedComparison, rank_conditions

# Agresti (2002), Categorical Data Analysis, 2nd ed., p. 438: 1987 American League East, (home, away, home wins,
# away wins); the same table is BradleyTerry2's `baseball` data set.
BASEBALL = [
    ("Milwaukee", "Detroit", 4, 3), ("Milwaukee", "Toronto", 4, 2), ("Milwaukee", "New York", 4, 3),
    ("Milwaukee", "Boston", 6, 1), ("Milwaukee", "Cleveland", 4, 2), ("Milwaukee", "Baltimore", 6, 0),
    ("Detroit", "Milwaukee", 3, 3), ("Detroit", "Toronto", 4, 2), ("Detroit", "New York", 4, 3),
    ("Detroit", "Boston", 6, 0), ("Detroit", "Cleveland", 6, 1), ("Detroit", "Baltimore", 4, 3),
    ("Toronto", "Milwaukee", 2, 5), ("Toronto", "Detroit", 4, 3), ("Toronto", "New York", 2, 4),
    ("Toronto", "Boston", 4, 3), ("Toronto", "Cleveland", 4, 2), ("Toronto", "Baltimore", 6, 0),
    ("New York", "Milwaukee", 3, 3), ("New York", "Detroit", 5, 1), ("New York", "Toronto", 2, 5),
    ("New York", "Boston", 4, 3), ("New York", "Cleveland", 4, 2), ("New York", "Baltimore", 6, 1),
    ("Boston", "Milwaukee", 5, 1), ("Boston", "Detroit", 2, 5), ("Boston", "Toronto", 3, 3),
    ("Boston", "New York", 4, 2), ("Boston", "Cleveland", 5, 2), ("Boston", "Baltimore", 6, 0),
    ("Cleveland", "Milwaukee", 2, 5), ("Cleveland", "Detroit", 3, 3), ("Cleveland", "Toronto", 3, 4),
    ("Cleveland", "New York", 4, 3), ("Cleveland", "Boston", 4, 2), ("Cleveland", "Baltimore", 2, 4),
    ("Baltimore", "Milwaukee", 2, 5), ("Baltimore", "Detroit", 1, 5), ("Baltimore", "Toronto", 1, 6),
    ("Baltimore", "New York", 2, 4), ("Baltimore", "Boston", 1, 6), ("Baltimore", "Cleveland", 3, 4),
]
TEAMS = ["Boston", "Cleveland", "Detroit", "Milwaukee", "New York", "Toronto"]  # Baltimore is the anchor


def baseball_votes() -> list[GradedComparison]:
    """Every game as one vote from the home team's point of view: a win is +2, a loss -2; each game its own judge."""
    votes = []
    for i, (home, away, home_wins, away_wins) in enumerate(BASEBALL):
        votes += [GradedComparison(f"{i}w{k}", away, home, 2) for k in range(home_wins)]
        votes += [GradedComparison(f"{i}l{k}", away, home, -2) for k in range(away_wins)]
    return votes


def by_name(ranking):
    return {c.condition: c for c in ranking.conditions}


def test_bradley_terry_against_agresti_baseball():
    ranking = rank_conditions(baseball_votes(), anchor="Baltimore")
    fit = ranking.fit
    assert fit.status == "ok" and fit.answer_levels == (-2, 2) and fit.thresholds == (0.0,)  # plain Bradley-Terry
    # Agresti (2002) Table 10.11, column 3, as pinned by BradleyTerry2's tests/testthat/test-baseball.R:
    # sorted estimates 0.68 1.11 1.25 1.29 1.44 1.58 (Baltimore 0), "standard errors about 0.3".
    assert [c.condition for c in ranking.conditions] == ["Milwaukee", "Detroit", "Toronto", "New York", "Boston",
                                                         "Cleveland", "Baltimore"]
    assert [round(c.value, 2) for c in ranking.conditions] == [1.58, 1.44, 1.29, 1.25, 1.11, 0.68, 0.0]
    assert all(round(c.se_model, 1) == 0.3 for c in ranking.conditions[:-1])
    assert fit.n_votes == fit.n_votes_used == fit.n_participants == 273 and fit.df == 21 - 6


def _baseball_glm(link):
    """The same model as a binomial GLM (statsmodels), one row per unordered pair, no intercept."""
    pairs: dict[tuple[str, str], list[int]] = {}
    for home, away, home_wins, away_wins in BASEBALL:
        a, b = sorted((home, away))
        wins = pairs.setdefault((a, b), [0, 0])
        wins[0] += home_wins if home == b else away_wins  # wins of b (the "test" side) over a
        wins[1] += away_wins if home == b else home_wins
    x = np.array([[(t == b) - (t == a) for t in TEAMS] for a, b in pairs], dtype=float)
    y = np.array(list(pairs.values()), dtype=float)
    # Newton with the observed information, as the ranking uses (IRLS would give the expected one for probit).
    return sm.GLM(y, x, family=sm.families.Binomial(link=link)).fit(method="newton", tol=1e-12)


@pytest.mark.parametrize("link", ["logit", "probit"])
def test_binary_case_equals_a_binomial_glm(link):
    glm = _baseball_glm(sm.families.links.Logit() if link == "logit" else sm.families.links.Probit())
    ranking = rank_conditions(baseball_votes(), anchor="Baltimore", link=link)
    conditions = by_name(ranking)
    for j, team in enumerate(TEAMS):
        assert conditions[team].value == pytest.approx(glm.params[j], abs=1e-6)
        assert conditions[team].se_model == pytest.approx(glm.bse[j], rel=1e-4)
    assert ranking.fit.deviance == pytest.approx(glm.deviance, abs=1e-6)
    assert ranking.fit.df == glm.df_resid


def simulate(rng, true, pairs, n_participants, repeats=2, cuts=(-2.0, -0.5, 0.5, 2.0), copy=0.0, link="logit"):
    """Votes from the symmetric cumulative model; with probability ``copy`` a repeat copies the first answer.

    Copying makes a participant's answers dependent while every single vote still follows the model exactly.
    """
    noise = rng.logistic if link == "logit" else rng.standard_normal
    votes = []
    for p in range(n_participants):
        for reference, test in pairs:
            first = None
            for _ in range(repeats):
                if first is not None and rng.random() < copy:
                    score = first
                else:
                    score = int(np.searchsorted(cuts, noise() + true[test] - true[reference])) - 2
                first = score if first is None else first
                votes.append(GradedComparison(f"p{p}", reference, test, score))
    return votes


TRUE = {"ref": 0.0, "a": 0.7, "b": -0.4, "c": 1.2}
ROUND_ROBIN = [("ref", "a"), ("ref", "b"), ("ref", "c"), ("a", "b"), ("b", "c"), ("c", "a")]


@pytest.mark.parametrize("link", ["logit", "probit"])
def test_ordinal_model_equals_statsmodels_ordered_model_on_mirrored_data(link):
    # The symmetric-threshold model is the free-threshold cumulative model fitted to the votes plus their mirror
    # images (reference and test swapped, answer negated): the doubled log-likelihood is mirror-invariant and
    # concave, so its maximum has symmetric cuts and the same scale values; the doubled information halves the
    # model-based variances, and the mirrored scores cancel in the threshold direction, so the cluster-robust
    # covariance is the same.
    rng = np.random.default_rng(20261201)
    votes = simulate(rng, TRUE, ROUND_ROBIN, 30, link=link)
    ranking = rank_conditions(votes, anchor="ref", link=link)
    names = ["a", "b", "c"]
    x = np.array([[(v.test == n) - (v.reference == n) for n in names] for v in votes], dtype=float)
    y = np.array([v.score for v in votes])
    groups = np.array([int(v.participant[1:]) for v in votes])
    endog = pd.Series(pd.Categorical(np.concatenate([y, -y]), categories=[-2, -1, 0, 1, 2], ordered=True))
    model = OrderedModel(endog, np.vstack([x, -x]), distr=link)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # statsmodels' convergence chatter at a tight tolerance
        plain = model.fit(method="bfgs", disp=False, maxiter=5000, gtol=1e-9)
        clustered = model.fit(method="bfgs", disp=False, maxiter=5000, gtol=1e-9, cov_type="cluster",
                              cov_kwds={"groups": np.concatenate([groups, groups]), "use_correction": False})
    got = by_name(ranking)
    g = 30
    for j, name in enumerate(names):
        assert got[name].value == pytest.approx(plain.params.iloc[j], abs=1e-5)
        assert got[name].se_model == pytest.approx(math.sqrt(2) * plain.bse.iloc[j], rel=1e-4)
        assert got[name].se == pytest.approx(math.sqrt(g / (g - 1)) * clustered.bse.iloc[j], rel=1e-4)
    assert ranking.fit.log_likelihood == pytest.approx(plain.llf / 2, abs=1e-6)
    assert ranking.fit.thresholds == pytest.approx(model.transform_threshold_params(plain.params)[1:-1], abs=1e-5)


def test_mirroring_and_changing_the_anchor():
    rng = np.random.default_rng(7)
    votes = simulate(rng, TRUE, ROUND_ROBIN, 25)
    base = by_name(rank_conditions(votes, anchor="ref"))
    mirrored = by_name(rank_conditions([GradedComparison(v.participant, v.test, v.reference, -v.score)
                                        for v in votes], anchor="ref"))
    moved = by_name(rank_conditions(votes, anchor="a"))
    for name in TRUE:
        assert mirrored[name].value == pytest.approx(base[name].value, abs=1e-6)
        assert moved[name].value == pytest.approx(base[name].value - base["a"].value, abs=1e-6)
    # The difference a - ref has the same standard error whichever is the anchor.
    assert moved["ref"].se == pytest.approx(base["a"].se, rel=1e-4)


def test_simulation_recovers_the_scale():
    rng = np.random.default_rng(18)
    votes = simulate(rng, TRUE, ROUND_ROBIN, 400)
    ranking = rank_conditions(votes, anchor="ref")
    got = by_name(ranking)
    assert [c.condition for c in ranking.conditions] == ["c", "a", "ref", "b"]
    for name, value in TRUE.items():
        # 400 participants x 6 pairs x 2: standard errors ~0.05; 4 of them is a deterministic (seeded) margin.
        assert abs(got[name].value - value) < 4 * max(got[name].se, 1e-9) + 1e-9
        assert got[name].se < 0.07
    assert ranking.fit.thresholds == pytest.approx([-2.0, -0.5, 0.5, 2.0], abs=0.15)


def test_interval_coverage_with_dependent_repeats():
    # The study's design: every condition against the reference, twice per participant; 70 % of repeats copy the
    # first answer.  Cluster-robust 95 % intervals should cover at about the nominal rate; intervals that treat
    # votes as independent cover less.
    rng = np.random.default_rng(1952)
    true = {"ref": 0.0, "a": 0.5, "b": -0.3, "c": 1.0}
    pairs = [("ref", "a"), ("ref", "b"), ("ref", "c")]
    covered = naive = total = 0
    for _ in range(200):
        got = by_name(rank_conditions(simulate(rng, true, pairs, 30, copy=0.7), anchor="ref"))
        for name in ("a", "b", "c"):
            c = got[name]
            covered += c.ci95[0] <= true[name] <= c.ci95[1]
            naive += abs(c.value - true[name]) <= 1.96 * c.se_model
            total += 1
    assert 0.92 <= covered / total <= 0.98, covered / total
    assert naive / total < 0.90, naive / total


def _no_nan(ranking) -> bool:
    def walk(value):
        if isinstance(value, float):
            return math.isfinite(value)
        if isinstance(value, dict):
            return all(walk(v) for v in value.values())
        if isinstance(value, list | tuple):
            return all(walk(v) for v in value)
        return True
    return walk(dataclasses.asdict(ranking))


def test_degenerate_input():
    empty = rank_conditions([], conditions=["ref", "a"])
    assert empty.fit.status == "no_votes" and _no_nan(empty)
    assert [(c.condition, c.value) for c in empty.conditions] == [("ref", 0.0), ("a", None)]
    assert rank_conditions([]).fit.status == "no_votes" and rank_conditions([]).conditions == ()

    catch_only = rank_conditions([("p1", "ref", "ref", 0), ("p2", "ref", "ref", 1)])
    assert catch_only.fit.status == "single_condition" and catch_only.fit.n_votes == 2
    assert [(c.condition, c.value, c.se) for c in catch_only.conditions] == [("ref", 0.0, 0.0)]

    ties = rank_conditions([(f"p{i}", "ref", t, 0) for i in range(5) for t in ("a", "b")])
    assert ties.fit.status == "all_ties" and ties.fit.answer_levels == (0,) and _no_nan(ties)
    assert {c.condition: c.value for c in ties.conditions} == {"ref": 0.0, "a": None, "b": None}

    # "b" always loses at the extreme, "c" always wins at the extreme, "d" is only compared with "c":
    # a and ref are fitted on their own votes, the others are bounded.
    votes = [(f"p{i}", "ref", "a", s) for i, s in enumerate([2, 1, 0, -1, 1, 2, 0, 1])]
    votes += [(f"p{i}", "ref", "b", -2) for i in range(6)] + [(f"p{i}", "ref", "c", 2) for i in range(6)]
    votes += [("p0", "c", "d", 1), ("p1", "c", "d", -1)]
    separated = rank_conditions(votes, anchor="ref")
    got = by_name(separated)
    assert separated.fit.status == "separated" and _no_nan(separated)
    assert (got["b"].bound, got["c"].bound, got["d"].bound) == ("below", "above", "above")
    assert got["b"].value is None and got["b"].ci95 is None and got["b"].votes == 6
    assert got["a"].value is not None and got["a"].value > 0 and got["a"].ci95 is not None
    assert separated.fit.n_votes_used == 8
    assert [c.condition for c in separated.conditions] == ["c", "d", "a", "ref", "b"]
    assert "b infinitely below" in separated.fit.message

    # Every test condition loses every time: nothing but the anchor is finite.
    lost = rank_conditions([(f"p{i}", "ref", "a", -1) for i in range(4)])
    assert lost.fit.status == "separated" and by_name(lost)["a"].bound == "below" and _no_nan(lost)

    # A condition never linked to the anchor, and one participant only (no robust standard error).
    lone = rank_conditions([("p1", "ref", "a", 1), ("p1", "ref", "a", -1), ("p1", "x", "y", 2)], anchor="ref")
    got = by_name(lone)
    assert got["x"].bound is None and got["x"].value is None and "not linked" in lone.fit.message
    assert got["a"].value == pytest.approx(0.0, abs=1e-6) and got["a"].se is None and got["a"].ci95 is None
    assert got["a"].se_model is not None and _no_nan(lone)


def _loglik(votes, values, cut):
    """The three-level model's log-likelihood written out here (not the module's): P(y <= k) = F(c_k - delta)."""
    f = lambda z: 1 / (1 + math.exp(-z))  # noqa: E731
    total = 0.0
    for _, reference, test, score in votes:
        delta = values[test] - values[reference]
        upper = 1.0 if score == 1 else f((cut if score == 0 else -cut) - delta)
        lower = 0.0 if score == -1 else f((-cut if score == 0 else cut) - delta)
        total += math.log(upper - lower)
    return total


def test_separation_through_the_cut_points():
    """Almost every vote "no difference"; one "+1" for a (never rated worse), one "-1" for b (never better).
    The graph test sees nothing (no extreme answer is one-sided), yet the likelihood has no maximum: moving a up, b
    down and the cut between "equal" and "better" with them raises it without end.  Before the check, the fit
    said "ok" with a at +12.7 and b at -12.7 logit units (where the optimiser happened to stop)."""
    votes = [(f"p{p}", "ref", c, 0) for p in range(20) for c in ("a", "b") for _ in range(4)]
    votes[0], votes[1] = ("p0", "ref", "a", 1), ("p0", "ref", "b", -1)
    along = [_loglik(votes, {"ref": 0.0, "a": 0.5 + s, "b": -0.5 - s}, 1.0 + s) for s in (0, 2, 5, 10, 20)]
    assert np.all(np.diff(along) > 0) and along[-1] < 0

    separated = rank_conditions(votes, anchor="ref")
    got = by_name(separated)
    assert separated.fit.status == "separated" and _no_nan(separated)
    assert (got["a"].bound, got["a"].value, got["b"].bound, got["b"].value) == ("above", None, "below", None)
    assert "a infinitely above" in separated.fit.message and "b infinitely below" in separated.fit.message

    # One "-1" for a as well pins the cut, and a finite maximum exists: the fit is the one found here by
    # Nelder-Mead on the likelihood above.
    pinned_votes = [*votes, ("p1", "ref", "a", -1)]
    pinned = rank_conditions(pinned_votes, anchor="ref")
    got = by_name(pinned)
    assert pinned.fit.status == "ok" and got["a"].bound is None and got["b"].bound is None

    def minus(p):
        return -_loglik(pinned_votes, {"ref": 0.0, "a": p[0], "b": p[1]}, math.exp(p[2]))

    best = optimize.minimize(minus, [0.0, 0.0, 0.0], method="Nelder-Mead",
                             options={"xatol": 1e-8, "fatol": 1e-12, "maxiter": 20000}).x
    assert (got["a"].value, got["b"].value, pinned.fit.thresholds[1]) == pytest.approx(
        (best[0], best[1], math.exp(best[2])), abs=1e-4)


def test_sparse_answers_ok_only_where_the_likelihood_has_a_maximum():
    """Seeded: 30 small studies answering mostly "no difference" (levels -1, 0, +1).  Where the ranking says "ok",
    its values are the maximum that Nelder-Mead finds on the likelihood written out above; where it says
    "separated", pushing the bounded conditions out (with the cut) raises that likelihood."""
    rng = np.random.default_rng(20261205)
    seen = Counter()
    for _ in range(30):
        votes = [(f"p{p}", "ref", c, int(rng.choice([-1, 0, 1], p=[0.06, 0.88, 0.06])))
                 for p in range(4) for c in ("a", "b") for _ in range(3)]
        if {s for *_, s in votes} != {-1, 0, 1}:
            continue
        ranking = rank_conditions(votes, anchor="ref")
        got = by_name(ranking)
        seen[ranking.fit.status] += 1
        if ranking.fit.status == "ok":
            best = optimize.minimize(
                lambda p: -_loglik(votes, {"ref": 0.0, "a": p[0], "b": p[1]}, math.exp(p[2])),  # noqa: B023
                [0.0, 0.0, 0.0], method="Nelder-Mead", options={"xatol": 1e-8, "fatol": 1e-12, "maxiter": 20000}).x
            assert (got["a"].value, got["b"].value) == pytest.approx((best[0], best[1]), abs=1e-3)
        else:
            assert ranking.fit.status == "separated"
            sign = {"above": 1, "below": -1, None: 0}
            values = [{"ref": 0.0, **{c: 0.3 * sign[got[c].bound] * s for c in ("a", "b")}} for s in (1, 5, 20)]
            likelihoods = [max(_loglik(votes, v, cut) for cut in np.linspace(0.1, 30, 300)) for v in values]
            assert np.all(np.diff(likelihoods) > 0)
    assert seen["ok"] >= 3 and seen["separated"] >= 3


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="score"):
        rank_conditions([("p1", "ref", "a", 3)])
    with pytest.raises(ValueError, match="score"):
        rank_conditions([("p1", "ref", "a", 0.5)])
    with pytest.raises(ValueError, match="anchor"):
        rank_conditions([("p1", "ref", "a", 1), ("p1", "a", "b", 1)])
    with pytest.raises(ValueError, match="link"):
        rank_conditions([], link="cauchit")
