"""One interval scale per animation for every design mode, with bootstrap intervals and P(better).

The scale is the ordinal Bradley-Terry scale of :mod:`server.analysis.ranking` (logit link, the study's reference
at 0; for reference designs the same numbers as the ``rankings`` section).  Its uncertainty here is the
nonparametric bootstrap over participants, as pwcmp does (Perez-Ortiz & Mantiuk 2017, "A practical guide and
software for analysing pairwise comparison experiments"): ``n_boot`` resamples of the participants with
replacement, each refitted, the 2.5 and 97.5 percentiles as the 95 % interval, and for every two conditions the
share of resamples in which the first is above the second (``p_better``, the basis of the significance matrix:
below 0.025 or above 0.975 is a difference at the 5 % level, two-sided).

Refits use a weak normal ridge (``BOOT_PRIOR_SD`` logit units) so that a resample in which a condition only ever
got one extreme answer still gives a finite value (the plain maximum likelihood value is then infinite); with it
the refit of the full data differs from the point value by well under its interval's width (the point value
itself is the plain maximum likelihood one).  All resamples are refitted together, by Newton's method from the full
data's fit (``_ridge_all``): one BFGS per resample spent most of a study's results request on flat directions of
nearly separated resamples.

JND units: as in pwcmp, one JND is the difference at which the better condition is preferred 75 % of the time;
here "preferred" is a non-tie answer in its favour, from the fitted cut points:
``P(y > 0) / (P(y > 0) + P(y < 0)) = 0.75``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
from scipy import optimize

from .ranking import GradedComparison, link_cdf_pdf, rank_conditions, vote_log_likelihood
from .statistics import counted

BOOT_PRIOR_SD = 10.0
N_BOOT = 200
_NEWTON_STEPS = 50
_GTOL = 1e-6  # the largest gradient component at a fit (BFGS's gtol in _ridge)
_CUT_START = np.log([0.5, 1.5])


def _design(votes: Sequence[GradedComparison], names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    column = {n: j - 1 for j, n in enumerate(names)}  # names[0] is the anchor
    x = np.zeros((len(votes), len(names) - 1))
    for i, v in enumerate(votes):
        if column[v.test] >= 0:
            x[i, column[v.test]] += 1
        if column[v.reference] >= 0:
            x[i, column[v.reference]] -= 1
    return x, np.array([v.score + 2 for v in votes], dtype=int)


def _prior(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The ridge's precision and centre for ``n`` scale values and the 2 cut log-increments."""
    return np.concatenate([np.full(n, BOOT_PRIOR_SD**-2), np.full(2, 1e-2)]), np.concatenate([np.zeros(n), _CUT_START])


def _ridge(x: np.ndarray, y: np.ndarray, start: np.ndarray | None, weight: np.ndarray) -> np.ndarray:
    """The ridge fit of the rows ``x``, ``y``, each counted ``weight`` times."""
    n = x.shape[1]
    precision, centre = _prior(n)

    def objective(params: np.ndarray) -> tuple[float, np.ndarray]:
        loglik, grad = vote_log_likelihood(params, x, y, False, n, "logit")
        diff = params - centre
        return -float(weight @ loglik) + 0.5 * float(diff @ (precision * diff)), -weight @ grad + precision * diff

    return optimize.minimize(objective, centre if start is None else start, jac=True, method="BFGS",
                             options={"gtol": 1e-6}).x


def _ridge_terms(params: np.ndarray, x: np.ndarray, y: np.ndarray, weight: np.ndarray, precision: np.ndarray,
                 centre: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ridge objective of every resample, its gradient and its Hessian, all resamples at once.

    ``params`` (B, p): scale values then the 2 cut log-increments; ``x`` (C, p-2), ``y`` (C,): the cells (answer
    index 0..4); ``weight`` (B, C): how often each resample counts each cell.  Returns (B,), (B, p), (B, p, p).
    Per cell, with u = c_y - x beta and l = c_(y-1) - x beta, log P = log(F(u) - F(l)) differentiated in (u, l),
    then by the chain rule; the cuts are sums of exp(eta), so their second derivative in eta equals their first.
    """
    n = x.shape[1]
    inc = np.exp(np.clip(params[:, n:], -50.0, 50.0))  # (B, 2): the cut increments
    dt = np.stack([inc * np.array([1.0, 0.0]), inc], axis=1)  # (B, 2 cuts, 2 etas): d t_j / d eta_i
    t = dt.sum(axis=2)  # (B, 2): the positive cuts a < b
    # Cuts -b, -a, a, b and their d/d eta; index 0 and 5 are -inf and +inf (no bound).
    cut = np.stack([-t[:, 1], -t[:, 0], t[:, 0], t[:, 1]], axis=1)  # (B, 4)
    dcut = np.stack([-dt[:, 1], -dt[:, 0], dt[:, 0], dt[:, 1]], axis=1)  # (B, 4, 2)
    delta = params[:, :n] @ x.T  # (B, C)
    has_up, has_lo = y < 4, y > 0
    up_k, lo_k = np.minimum(y, 3), np.maximum(y - 1, 0)
    upper = np.where(has_up, cut[:, up_k] - delta, np.inf)
    lower = np.where(has_lo, cut[:, lo_k] - delta, -np.inf)
    f_up, d_up = link_cdf_pdf(upper, "logit")
    f_lo, d_lo = link_cdf_pdf(lower, "logit")
    d_up, d_lo = np.where(has_up, d_up, 0.0), np.where(has_lo, d_lo, 0.0)
    # The upper tail by symmetry keeps precision where both cdf values are near 1 (as vote_log_likelihood).
    prob = np.where(lower > 0, link_cdf_pdf(-lower, "logit")[0] - link_cdf_pdf(-upper, "logit")[0], f_up - f_lo)
    prob = np.maximum(prob, 1e-300)
    lu, ll = d_up / prob, -d_lo / prob  # d log P / du, / dl
    luu = d_up * (1 - 2 * f_up) / prob - lu * lu
    lll = -d_lo * (1 - 2 * f_lo) / prob - ll * ll
    lul = -lu * ll
    # A cell a resample does not take counts 0 times: no 0 * inf where its probability underflowed.
    unused = weight == 0
    for term in (lu, ll, luu, lll, lul):
        term[unused] = 0.0
    # d u / d params and d l / d params, (B, C, p): -x for the values, the cut's row for the etas.
    grad_u = np.concatenate([np.broadcast_to(-x, (*delta.shape, n)),
                             np.where(has_up[None, :, None], dcut[:, up_k], 0.0)], axis=2)
    grad_l = np.concatenate([np.broadcast_to(-x, (*delta.shape, n)),
                             np.where(has_lo[None, :, None], dcut[:, lo_k], 0.0)], axis=2)
    cell_grad = lu[..., None] * grad_u + ll[..., None] * grad_l
    cell_hess = (np.einsum("bc,bci,bcj->bcij", luu, grad_u, grad_u)
                 + np.einsum("bc,bci,bcj->bcij", lll, grad_l, grad_l)
                 + np.einsum("bc,bci,bcj->bcij", lul, grad_u, grad_l)
                 + np.einsum("bc,bci,bcj->bcij", lul, grad_l, grad_u))
    curvature = lu[..., None] * grad_u[..., n:] + ll[..., None] * grad_l[..., n:]  # the cuts' second derivative
    cell_hess[..., np.arange(n, n + 2), np.arange(n, n + 2)] += curvature
    diff = params - centre
    value = -np.einsum("bc,bc->b", weight, np.log(prob)) + 0.5 * np.einsum("bi,i,bi->b", diff, precision, diff)
    grad = -np.einsum("bc,bci->bi", weight, cell_grad) + precision * diff
    hess = -np.einsum("bc,bcij->bij", weight, cell_hess) + np.diag(precision)
    return value, grad, hess


def _ridge_all(x: np.ndarray, y: np.ndarray, weight: np.ndarray, start: np.ndarray) -> np.ndarray:
    """The ridge fits of all resamples at once (``weight`` (B, C)), by Newton's method from ``start`` with
    step halving; a resample that has not converged after ``_NEWTON_STEPS`` steps, or whose step cannot lower the
    objective, is fitted on its own by :func:`_ridge` (BFGS)."""
    precision, centre = _prior(x.shape[1])
    params = np.tile(start, (len(weight), 1))
    value, grad, hess = _ridge_terms(params, x, y, weight, precision, centre)
    active = np.ones(len(weight), dtype=bool)
    for _ in range(_NEWTON_STEPS):
        active &= np.abs(grad).max(axis=1) >= _GTOL
        if not active.any():
            break
        idx = np.flatnonzero(active)
        # The objective is not convex in the cut log-increments: where the Hessian has a negative eigenvalue, its
        # absolute value (a descent direction still; Dauphin et al. 2014's saddle-free Newton); near the fit the
        # Hessian is positive definite and this is Newton's step.
        eig, vec = np.linalg.eigh(hess[idx])
        eig = np.maximum(np.abs(eig), 1e-10 * np.abs(eig).max(axis=1, keepdims=True))
        step = -np.einsum("bij,bj->bi", vec, np.einsum("bji,bj->bi", vec, grad[idx]) / eig)
        scale = np.ones(len(idx))
        for _ in range(30):  # halve each step until the objective does not rise
            trial = params[idx] + scale[:, None] * step
            # A step far out can give a vote a probability near 0 (floored at 1e-300), whose squared derivative
            # overflows: such a step is not taken (halved), never a warning that fails the request.
            with np.errstate(over="ignore", invalid="ignore"):
                t_value, t_grad, t_hess = _ridge_terms(trial, x, y, weight[idx], precision, centre)
            finite = np.isfinite(t_value) & np.isfinite(t_grad).all(axis=1) & np.isfinite(t_hess).all(axis=(1, 2))
            ok = finite & (t_value <= value[idx] + 1e-12 * np.abs(value[idx]))
            done = idx[ok]
            params[done], value[done], grad[done], hess[done] = trial[ok], t_value[ok], t_grad[ok], t_hess[ok]
            idx, step, scale = idx[~ok], step[~ok], scale[~ok] / 2
            if not idx.size:
                break
        active[idx] = False  # no step lowered the objective: left to BFGS below
    unfinished = np.flatnonzero(np.abs(grad).max(axis=1) >= _GTOL)
    for b in unfinished:
        taken = weight[b] > 0
        params[b] = _ridge(x[taken], y[taken], start, weight[b, taken])
    return params


def jnd_unit(cuts: Sequence[float]) -> float | None:
    """The scale difference (logit units) at which non-tie answers favour the better condition 3 : 1."""
    c = np.asarray(cuts, dtype=float)

    def excess(delta: float) -> float:
        better = 1 - link_cdf_pdf(np.array([c[-2] - delta]), "logit")[0][0]  # P(y > 0)
        worse = link_cdf_pdf(np.array([c[1] - delta]), "logit")[0][0]  # P(y < 0)
        return better / (better + worse) - 0.75

    try:
        return float(optimize.brentq(excess, 0.0, 50.0))
    except ValueError:
        return None


@dataclass(frozen=True)
class AnimationScale:
    animation: str
    conditions: tuple[str, ...]  # the anchor first, then the others as the design lists them
    value: tuple[float | None, ...]  # maximum likelihood (ranking.rank_conditions), logit units, anchor 0
    ci95: tuple[tuple[float, float] | None, ...]  # bootstrap percentile interval over participants
    value_jnd: tuple[float | None, ...]  # value / jnd (None without a JND unit)
    jnd: float | None  # logit units per JND
    p_better: tuple[tuple[float | None, ...], ...]  # [i][j]: share of resamples with condition i above j
    pair_counts: tuple[tuple[int, ...], ...]  # [i][j]: votes comparing i and j (symmetric)
    participants: int
    n_boot: int
    status: str  # ranking.RankingFit.status of the point fit
    message: str
    # Per condition, for a value None because the point fit is separated: "above"/"below" the anchor (or None).
    bound: tuple[str | None, ...] = ()


def bootstrap_draws(participants: Sequence[str], n_boot: int, seed: int) -> np.ndarray:
    """(n_boot, P) indices of the resampled participants (the resamples are reproducible from ``seed``)."""
    return np.random.default_rng(seed).integers(0, len(participants), (n_boot, len(participants)))


def animation_scale(animation: str, votes: Sequence[GradedComparison], conditions: Sequence[str], *,
                    n_boot: int = N_BOOT, seed: int = 0) -> AnimationScale:
    """The scale of one animation's ``votes`` (catch votes, a condition against itself, are ignored);
    ``conditions``: the anchor first."""
    names = list(dict.fromkeys([*conditions, *(c for v in votes for c in (v.reference, v.test))]))
    used = [v for v in votes if v.reference != v.test]
    index = {n: i for i, n in enumerate(names)}
    counts = np.zeros((len(names), len(names)), dtype=int)
    for v in used:
        counts[index[v.reference], index[v.test]] += 1
        counts[index[v.test], index[v.reference]] += 1
    ranking = rank_conditions(used, anchor=names[0], conditions=names)
    point = {c.condition: c for c in ranking.conditions}
    value = tuple(point[n].value for n in names)
    people = list(dict.fromkeys(v.participant for v in used))
    n = len(names)
    ci: list[tuple[float, float] | None] = [None] * n
    p_better: list[list[float | None]] = [[None] * n for _ in range(n)]
    jnd = jnd_unit(ranking.fit.thresholds) if len(ranking.fit.thresholds) == 4 else None
    if len(people) >= 2 and n >= 2 and ranking.fit.status in ("ok", "separated", "not_converged"):
        x, y = _design(used, names)
        # Every vote is one of a few cells (a pair and an answer) and a resample takes each participant's cells as
        # often as it draws them: each fit is over the cells, whatever the number of votes (issue 36).
        cells, cell_of = np.unique(np.column_stack([x, y]), axis=0, return_inverse=True)
        person = {p: i for i, p in enumerate(people)}
        per_person = np.zeros((len(people), len(cells)))
        np.add.at(per_person, ([person[v.participant] for v in used], cell_of.ravel()), 1)
        cx, cy = cells[:, :-1], cells[:, -1].astype(int)
        start = _ridge(cx, cy, None, per_person.sum(axis=0))  # the full data's fit: a close start for resamples
        taken = np.stack([np.bincount(draw, minlength=len(people)) for draw in bootstrap_draws(people, n_boot, seed)])
        samples = np.zeros((n_boot, n))
        samples[:, 1:] = _ridge_all(cx, cy, taken @ per_person, start)[:, : n - 1]
        low, high = np.percentile(samples, [2.5, 97.5], axis=0)
        ci = [(0.0, 0.0) if i == 0 else (float(low[i]), float(high[i])) for i in range(n)]
        above = (samples[:, :, None] > samples[:, None, :]).mean(axis=0)
        ties = (samples[:, :, None] == samples[:, None, :]).mean(axis=0)
        p_better = [[None if i == j else float(above[i, j] + ties[i, j] / 2) for j in range(n)] for i in range(n)]
    return AnimationScale(
        animation, tuple(names), value, tuple(ci),
        tuple(None if v is None or jnd is None else v / jnd for v in value), jnd,
        tuple(tuple(row) for row in p_better), tuple(tuple(int(c) for c in row) for row in counts),
        len(people), n_boot, ranking.fit.status, ranking.fit.message, tuple(point[n].bound for n in names))


def study_scales(rows: Sequence[dict], conditions: Sequence[str], n_boot: int = N_BOOT) -> list[dict]:
    """The scale of every animation from a study's export rows (practice, catch and screened-out participants'
    votes left out, as in the statistics); ``conditions``: the design's, the reference first."""
    analysed = [r for r in rows if counted(r)]
    out = []
    for animation in sorted({r["animation"] for r in analysed}):
        votes = [GradedComparison(r["session_id"], r["reference_condition"], r["test_condition"], r["score"])
                 for r in analysed if r["animation"] == animation]
        out.append(asdict(animation_scale(animation, votes, conditions, n_boot=n_boot)))
    return out
