"""All conditions of one animation on one scale, from the graded side-by-side comparisons.

Model (Agresti 1992, "Analysis of ordinal paired comparison data", Applied Statistics 41:287-297: the cumulative
link Bradley-Terry model; with the probit link it is Thurstone's Case V for graded answers).  Each condition ``c``
has a scale value ``mu_c``; the anchor condition (the reference) is fixed at 0.  A vote compares a reference
condition ``r`` with a test condition ``t`` and answers ``y`` in -2..+2 from the test condition's point of view
(+2 test much better ... -2 reference much better).  With ``delta = mu_t - mu_r``::

    P(y <= k) = F(c_k - delta)        F = logistic (``link="logit"``) or standard normal (``link="probit"``)

with cut points symmetric about 0: -b < -a < a < b for the five answers.  Symmetry says that swapping which
condition is called the reference mirrors the answers, so "no difference" (delta = 0) predicts a symmetric
answer distribution and the scale has one origin, the anchor.  The unit is the latent logistic (logit) or
standard normal (probit, Case V's unit: the standard deviation of a discriminal difference) scale.

Answer levels nobody used (neither ``s`` nor ``-s``) are merged with their neighbour: the maximum likelihood
puts their cut points on the boundary (at infinity for an unused extreme answer, two cuts coinciding for an
unused middle one), and merging gives the same supremum and the same scale values.  In particular, votes that
only ever say +2 or -2 give exactly the binary Bradley-Terry (or Thurstone-Mosteller) model, which is how the
published Bradley-Terry example in the tests applies.

Repeated answers: a participant answers many comparisons (each twice, sides swapped), and their answers are not
independent (taste, a personal use of the scale, a remembered first answer).  The estimates are the maximum
likelihood ones of the model above as if votes were independent (a consistent estimator whatever the
within-participant dependence), and their standard errors are cluster-robust (sandwich, clusters =
participants, CR1 small-sample factor G/(G-1)); intervals use Student t with G-1 degrees of freedom, G the number
of participants.  So participants remain the unit of analysis, as in ``statistics.py``, without a model of how
one person's answers depend on each other, and deterministically (no bootstrap seed).  The model-based
(independence) standard error is reported beside it; their ratio shows how much repetition matters.  With fewer
than two participants the robust standard error is undefined (``None``).

Degenerate input never raises and never yields NaN; what comes out is stated in ``RankingFit.status``:

- ``"ok"``: every condition is on the scale.
- ``"no_votes"``: no comparison of two different conditions; every value but the anchor's is ``None``.
- ``"single_condition"``: only the anchor; it is at 0.
- ``"all_ties"``: every vote that could be used said "no difference": the model has no unit; values ``None``.
- ``"separated"``: the maximum likelihood value of some condition is infinite: it, or a group of conditions, only
  ever got the extreme answer in one direction against all the others it was compared with, or (the separation
  moving the cut points too) it was never rated worse than the anchor, only "equal" or better, in data where no
  other vote fixes the cut it would carry along (typical of studies that answer almost only "no difference").  Their
  value is ``None`` and ``bound`` says ``"above"`` or ``"below"`` the anchor; conditions never linked to the anchor
  by any vote have ``bound=None``.  The others are fitted on the votes among themselves (the limit of the
  likelihood maximisation).
- ``"not_converged"``: the optimiser stopped early; values are reported, standard errors only if finite.

The anchor itself always has value 0, standard error 0 and interval (0, 0): it is the origin by definition.
Comparisons of a condition with itself (catch trials) carry no information about the scale and are left out.
"""

from __future__ import annotations

import math
from collections import Counter, defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np
from scipy import optimize, special, stats
from scipy.sparse import csr_array
from scipy.sparse.csgraph import breadth_first_order
from statsmodels.tools.numdiff import approx_fprime

from server.studies.scale import MAX_SCORE

Link = Literal["logit", "probit"]
_LP_TOL = 1e-7  # a separating direction's total slack (directions are boxed to [-1, 1])


class GradedComparison(NamedTuple):
    """One vote: ``score`` in -2..+2 from the test condition's point of view."""

    participant: str
    reference: str
    test: str
    score: int


@dataclass(frozen=True)
class ConditionScale:
    """One condition's place on the scale (the anchor is 0); ``None`` where the model gives no finite value."""

    condition: str
    value: float | None
    se: float | None  # cluster-robust (participants)
    ci95: tuple[float, float] | None  # value -+ t(0.975, G-1) * se
    se_model: float | None  # model-based, as if votes were independent
    votes: int  # votes comparing this condition with another one
    bound: Literal["above", "below"] | None = None  # for a separated condition: infinitely above/below the anchor


@dataclass(frozen=True)
class RankingFit:
    """How the scale was fitted.

    ``deviance``/``df`` compare with the saturated model (one answer distribution per pair of conditions); a
    descriptive measure of how well one scale explains all pairs: no chi-square p-value is given, because a
    participant's votes are not independent.
    """

    status: Literal["ok", "no_votes", "single_condition", "all_ties", "separated", "not_converged"]
    message: str
    link: Link
    anchor: str | None
    n_votes: int  # votes given, self-comparisons included
    n_votes_used: int  # votes in the fit
    n_participants: int  # participants with a vote in the fit (the clusters)
    answer_levels: tuple[int, ...]  # the answers kept after merging unused ones, e.g. (-2, -1, 0, 1, 2)
    thresholds: tuple[float, ...]  # cut points between those levels on the latent scale
    log_likelihood: float | None
    n_parameters: int
    aic: float | None
    deviance: float | None
    df: int | None
    converged: bool


@dataclass(frozen=True)
class Ranking:
    """Conditions from best to worst: ``"above"`` ones, then by value, then those without value or bound, then
    ``"below"`` ones (ties by name)."""

    conditions: tuple[ConditionScale, ...]
    fit: RankingFit


def link_cdf_pdf(x: np.ndarray, link: Link) -> tuple[np.ndarray, np.ndarray]:
    if link == "logit":
        cdf = special.expit(x)
        return cdf, cdf * (1 - cdf)
    clipped = np.clip(x, -40.0, 40.0)  # the density is 0 to double precision beyond; avoids overflow in x * x
    return special.ndtr(x), np.exp(-0.5 * clipped * clipped) / math.sqrt(2 * math.pi)


def symmetric_cuts(eta: np.ndarray, zero_cut: bool) -> tuple[np.ndarray, np.ndarray]:
    """Symmetric cut points from log-increments ``eta`` (positive cuts t_j = sum_{i<=j} exp(eta_i)) and d cuts/d eta."""
    inc = np.exp(np.clip(eta, -50.0, 50.0))  # an optimiser's trial step must not overflow
    t = np.cumsum(inc)
    m = t.size
    dt = np.tril(np.ones((m, m))) * inc  # dt_j / d eta_i
    middle = [np.zeros((1,))] if zero_cut else []
    cuts = np.concatenate([-t[::-1], *middle, t])
    jac = np.concatenate([-dt[::-1], *([np.zeros((1, m))] if zero_cut else []), dt])
    return cuts, jac


def vote_log_likelihood(params: np.ndarray, x: np.ndarray, y: np.ndarray, zero_cut: bool, n_beta: int,
            link: Link) -> tuple[np.ndarray, np.ndarray]:
    """Per-vote log-likelihood (n,) and its gradient (n, p) at ``params`` = (scale values, threshold log-increments)."""
    beta, eta = params[:n_beta], params[n_beta:]
    cuts, jac = symmetric_cuts(eta, zero_cut)
    ext = np.concatenate([[-np.inf], cuts, [np.inf]])
    delta = x @ beta
    upper, lower = ext[y + 1] - delta, ext[y] - delta
    f_up, d_up = link_cdf_pdf(upper, link)
    f_lo, d_lo = link_cdf_pdf(lower, link)
    # Upper tail by symmetry keeps precision where both cdf values are near 1.
    p = np.where(lower > 0, link_cdf_pdf(-lower, link)[0] - link_cdf_pdf(-upper, link)[0], f_up - f_lo)
    p = np.maximum(p, 1e-300)
    grad = np.empty((y.size, params.size))
    grad[:, :n_beta] = (-(d_up - d_lo) / p)[:, None] * x
    dcut = np.zeros((y.size, cuts.size))
    rows = np.arange(y.size)
    has_up, has_lo = y < cuts.size, y > 0
    dcut[rows[has_up], y[has_up]] = d_up[has_up] / p[has_up]
    dcut[rows[has_lo], y[has_lo] - 1] -= d_lo[has_lo] / p[has_lo]
    grad[:, n_beta:] = dcut @ jac
    return np.log(p), grad


def _reach(adjacency: csr_array, start: int) -> set[int]:
    return {int(i) for i in breadth_first_order(adjacency, start, directed=True, return_predecessors=False)}


def _finite_component(votes: list[GradedComparison], names: list[str], anchor: str,
                      ) -> tuple[list[GradedComparison], dict[str, Literal["above", "below"] | None]]:
    """The votes among the conditions with a finite scale value, and where the others lie.

    Edge a -> b when some vote says a is not infinitely below b (any answer but the extreme one against a).  The
    maximum likelihood values are finite exactly on the anchor's strongly connected component (the ordinal form
    of Zermelo's / Ford's condition); a condition the anchor reaches but that cannot reach it is infinitely below.
    Dropping the separated votes can leave the extreme answer unused among the rest, which moves the extreme
    level and can separate again, hence the loop.
    """
    index = {name: i for i, name in enumerate(names)}
    bounds: dict[str, Literal["above", "below"] | None] = {}
    while votes:
        top = max(abs(v.score) for v in votes)
        if top == 0:
            break
        edges = [(index[v.test], index[v.reference]) for v in votes if v.score > -top]
        edges += [(index[v.reference], index[v.test]) for v in votes if v.score < top]
        sources, targets = zip(*edges, strict=True)
        adjacency = csr_array((np.ones(len(edges)), (sources, targets)), shape=(len(names), len(names)))
        from_anchor = _reach(adjacency, index[anchor])
        to_anchor = _reach(adjacency.T.tocsr(), index[anchor])
        component = from_anchor & to_anchor
        inside = [v for v in votes if index[v.reference] in component and index[v.test] in component]
        if len(inside) == len(votes):
            through_cuts = _threshold_separation(votes, anchor)
            if not through_cuts:
                break
            bounds.update(through_cuts)
            votes = [v for v in votes if v.reference not in through_cuts and v.test not in through_cuts]
            continue
        for name in names:
            i = index[name]
            if i not in component and name not in bounds:
                bounds[name] = "below" if i in from_anchor else "above" if i in to_anchor else None
        votes = inside
    return votes, bounds


def _answer_levels(votes: list[GradedComparison]) -> tuple[bool, list[int]]:
    """Whether the middle cut is fixed at 0 (no "no difference" answer used), and the used answer levels, unused
    ones merged into their neighbours: the scores of every used magnitude with both signs."""
    magnitudes = sorted({abs(v.score) for v in votes})
    return magnitudes[0] != 0, sorted({s * m for m in magnitudes for s in (-1, 1)})


def _contrasts(votes: list[GradedComparison], free: list[str]) -> np.ndarray:
    """(votes, free conditions): +1 in the test condition's column, -1 in the reference's (the anchor has none)."""
    column = {n: j for j, n in enumerate(free)}
    x = np.zeros((len(votes), len(free)))
    for i, v in enumerate(votes):
        if v.test in column:
            x[i, column[v.test]] += 1
        if v.reference in column:
            x[i, column[v.reference]] -= 1
    return x


def _threshold_separation(votes: list[GradedComparison], anchor: str) -> dict[str, Literal["above", "below"] | None]:
    """The conditions whose maximum likelihood value is infinite by a separation that moves the cut points too.

    The graph test of :func:`_finite_component` sees a condition that only ever got the extreme answer one way.  A
    subtler separation moves cut points with the values: a condition never rated below the anchor (only "equal"
    and "better") goes up while the cut between "equal" and "better" follows it, so its "better" answers keep
    their probability and its "worse" probability, never observed, falls to 0.  In general the likelihood has no
    maximum exactly when some direction ``d`` in (scale values, positive cut positions) leaves every vote's upper
    bound ``c_y - delta`` not lower and its lower bound ``c_(y-1) - delta`` not higher, one of them strictly
    (each vote's probability is strictly monotone in both, the log-likelihood concave in these coordinates): the
    linear programme below finds such a direction (as for separation in logistic regression, Konis 2007).  A
    condition is infinitely above (below) the anchor when some such direction moves it up (down).
    """
    free = sorted({c for v in votes for c in (v.reference, v.test)} - {anchor})
    zero_cut, levels = _answer_levels(votes)
    if not free or levels == [0]:
        return {}
    m = (len(levels) - 1) // 2  # positive cut positions t_1 < ... < t_m
    # Cut k as a linear function of t: -t_m .. -t_1, (0), t_1 .. t_m.
    cut_map = np.concatenate([-np.eye(m)[::-1], np.zeros((1, m))[:int(zero_cut)], np.eye(m)])
    category = np.searchsorted(levels, [v.score for v in votes])
    cells = np.unique(np.column_stack([_contrasts(votes, free), category]), axis=0)
    x, k = cells[:, :-1], cells[:, -1].astype(int)
    # Each row g with g . d >= 0 for a direction d = (values, t): upper bounds may not fall, lower ones not rise.
    upper, lower = k < len(cut_map), k > 0
    g = np.concatenate([np.column_stack([-x[upper], cut_map[k[upper]]]),
                        np.column_stack([x[lower], -cut_map[k[lower] - 1]])])
    # The cut positions stay ordered along d (implied when every level is used; stated for the solver).
    order = np.column_stack([np.zeros((m, len(free))), np.eye(m) - np.eye(m, k=-1)])  # t_j - t_(j-1) >= 0
    constraints = np.concatenate([-g, -order])

    def most(objective: np.ndarray) -> float:
        result = optimize.linprog(-objective, A_ub=constraints, b_ub=np.zeros(len(constraints)),
                                  bounds=(-1, 1), method="highs")
        return -float(result.fun) if result.status == 0 else 0.0

    if most(g.sum(axis=0)) <= _LP_TOL:
        return {}
    bounds: dict[str, Literal["above", "below"] | None] = {}
    for j, name in enumerate(free):
        unit = np.zeros(len(free) + m)
        unit[j] = 1
        up, down = most(unit) > _LP_TOL, most(-unit) > _LP_TOL
        if up or down:
            bounds[name] = None if up and down else "above" if up else "below"
    return bounds


def _separation_message(bounds: dict[str, Literal["above", "below"] | None]) -> str:
    return "separation: " + "; ".join(f"{name} {'infinitely ' + bound if bound else 'not linked to'} the anchor"
                                      for name, bound in sorted(bounds.items()))


def rank_conditions(comparisons: Iterable[GradedComparison | tuple[str, str, str, int]], *,
                    anchor: str | None = None, conditions: Sequence[str] = (), link: Link = "logit",
                    level: float = 0.95) -> Ranking:
    """Scale values of all conditions of one animation, the anchor at 0, with cluster-robust intervals.

    ``comparisons``: the votes (participant, reference condition, test condition, score -2..+2 from the test
    condition's point of view).  ``anchor``: the condition fixed at 0; default the reference condition of the
    votes when they all share one (otherwise it must be given), or the first of ``conditions`` without votes.
    ``conditions``: conditions to report even if they have no votes.  ``link``: ``"logit"`` (ordinal
    Bradley-Terry) or ``"probit"`` (Thurstone Case V).  ``level``: interval coverage (the field is called ``ci95``
    whatever the level).

    Raises ``ValueError`` only for malformed input: a score outside -2..+2 or not an integer, an unknown link or
    level, or an anchor that cannot be inferred.
    """
    if link not in ("logit", "probit"):
        raise ValueError(f"link must be 'logit' or 'probit', not {link!r}")
    if not 0 < level < 1:
        raise ValueError(f"level must be in (0, 1), not {level!r}")
    votes = [GradedComparison(*c) for c in comparisons]
    for v in votes:
        if isinstance(v.score, bool) or not isinstance(v.score, int | np.integer) or abs(v.score) > MAX_SCORE:
            raise ValueError(f"score must be an integer in -2..+2, not {v.score!r}")
    used = [v for v in votes if v.reference != v.test]
    if anchor is None:
        references = {v.reference for v in votes}
        if len(references) > 1:
            raise ValueError(f"the votes have several reference conditions {sorted(references)}: give anchor=")
        anchor = next(iter(references), conditions[0] if conditions else None)
    names = list(dict.fromkeys([*([anchor] if anchor is not None else []), *conditions,
                                *(c for v in votes for c in (v.reference, v.test))]))
    counts = Counter(c for v in used for c in (v.reference, v.test))

    def ranking(fit: RankingFit, scales: Sequence[ConditionScale] = ()) -> Ranking:
        given = {s.condition: s for s in scales}
        rows = [ConditionScale(n, 0.0, 0.0, (0.0, 0.0), 0.0, counts[n]) if n == anchor
                else given.get(n, ConditionScale(n, None, None, None, None, counts[n])) for n in names]
        side = {"above": 0, None: 2, "below": 3}
        rows.sort(key=lambda r: (1, -r.value, r.condition) if r.value is not None else (side[r.bound], 0, r.condition))
        return Ranking(tuple(rows), fit)

    def info(status: str, message: str, **fields: object) -> RankingFit:
        base: dict = {"n_votes_used": 0, "n_participants": 0, "answer_levels": (), "thresholds": (),
                      "log_likelihood": None, "n_parameters": 0, "aic": None, "deviance": None, "df": None,
                      "converged": False}
        return RankingFit(status=status, message=message, link=link, anchor=anchor, n_votes=len(votes),
                          **{**base, **fields})

    if anchor is not None and len(names) == 1:
        return ranking(info("single_condition", "only one condition: it is the anchor, at 0"))
    if anchor is None or not used:
        return ranking(info("no_votes", "no votes comparing two different conditions"))
    fitted, bounds = _finite_component(used, names, anchor)
    separated = [ConditionScale(n, None, None, None, None, counts[n], bound) for n, bound in bounds.items()]
    status = "separated" if bounds else "all_ties"
    if not fitted:
        return ranking(info(status, _separation_message(bounds), n_participants=len({v.participant for v in used})),
                       separated)
    participants = len({v.participant for v in fitted})
    if max(abs(v.score) for v in fitted) == 0:
        message = "every vote said 'no difference' between the conditions left: the scale has no unit"
        if bounds:
            message = f"{_separation_message(bounds)}; {message}"
        return ranking(info(status, message, n_votes_used=len(fitted), n_participants=participants,
                            answer_levels=(0,)), separated)
    scales, fields = _fit(fitted, [n for n in names if n != anchor], link, level)
    if bounds:
        status, message = "separated", _separation_message(bounds)
    elif not fields["converged"]:
        status, message = "not_converged", "the optimiser stopped before the gradient vanished"
    else:
        status, message = "ok", "fitted"
    return ranking(info(status, message, n_votes_used=len(fitted), n_participants=participants, **fields),
                   [*scales, *separated])


def _fit(votes: list[GradedComparison], others: list[str], link: Link,
         level: float) -> tuple[list[ConditionScale], dict[str, object]]:
    """Maximum likelihood fit on votes whose conditions all have finite values; ``others``: all but the anchor."""
    zero_cut, levels = _answer_levels(votes)
    category = {s: i for i, s in enumerate(levels)}  # every used score is a level
    free = [n for n in others if any(n in (v.reference, v.test) for v in votes)]
    column = {n: j for j, n in enumerate(free)}
    x = _contrasts(votes, free)
    y = np.array([category[v.score] for v in votes])
    n_beta = len(free)

    def objective(params: np.ndarray) -> tuple[float, np.ndarray]:
        loglik, grad = vote_log_likelihood(params, x, y, zero_cut, n_beta, link)
        return -float(loglik.sum()), -grad.sum(axis=0)

    opt = optimize.minimize(objective, np.zeros(n_beta + (len(levels) - 1) // 2), jac=True, method="BFGS",
                            options={"gtol": 1e-9, "maxiter": 2000})
    params = opt.x
    # BFGS reports "precision loss" at a gradient already ~1e-8 on easy problems: judge by the gradient itself.
    converged = bool(opt.success or np.max(np.abs(opt.jac)) < 1e-5)
    hessian = approx_fprime(params, lambda p: objective(p)[1], centered=True)
    hessian = (hessian + hessian.T) / 2
    _, per_vote = vote_log_likelihood(params, x, y, zero_cut, n_beta, link)
    clusters = {p: i for i, p in enumerate(dict.fromkeys(v.participant for v in votes))}
    g = len(clusters)
    cluster_scores = np.zeros((g, params.size))
    np.add.at(cluster_scores, np.array([clusters[v.participant] for v in votes]), per_vote)
    bread = None
    if np.all(np.isfinite(hessian)) and np.linalg.matrix_rank(hessian) == params.size:
        bread = np.linalg.inv(hessian)
        if not (np.all(np.isfinite(bread)) and np.all(np.diag(bread) > 0)):
            bread = None
    se_model = np.sqrt(np.diag(bread)) if bread is not None else None
    se_robust = None
    if bread is not None and g >= 2:
        robust = bread @ (cluster_scores.T @ cluster_scores) @ bread * (g / (g - 1))
        se_robust = np.sqrt(np.maximum(np.diag(robust), 0.0))
    quantile = float(stats.t.ppf(0.5 + level / 2, g - 1)) if g >= 2 else None

    scales = []
    for name, j in column.items():
        value = float(params[j])
        se = float(se_robust[j]) if se_robust is not None else None
        ci = (value - quantile * se, value + quantile * se) if se is not None and quantile is not None else None
        scales.append(ConditionScale(name, value, se, ci, float(se_model[j]) if se_model is not None else None,
                                     int(np.count_nonzero(x[:, j]))))

    loglik = -float(opt.fun)
    cuts, _ = symmetric_cuts(params[n_beta:], zero_cut)
    # Saturated model: one multinomial per unordered pair, answers mirrored to one orientation (the model is
    # symmetric under swapping reference and test, so the orientation does not matter).
    cells: dict[tuple[str, str], Counter[int]] = defaultdict(Counter)
    for v, k in zip(votes, y, strict=True):
        if v.reference <= v.test:
            cells[(v.reference, v.test)][int(k)] += 1
        else:
            cells[(v.test, v.reference)][len(levels) - 1 - int(k)] += 1
    saturated = sum(n * math.log(n / sum(c.values())) for c in cells.values() for n in c.values())
    return scales, {
        "answer_levels": tuple(levels), "thresholds": tuple(float(c) for c in cuts), "log_likelihood": loglik,
        "n_parameters": params.size, "aic": 2 * params.size - 2 * loglik,
        "deviance": max(2 * (saturated - loglik), 0.0), "df": len(cells) * (len(levels) - 1) - params.size,
        "converged": converged}
