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
itself is the plain maximum likelihood one).

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


def _ridge(x: np.ndarray, y: np.ndarray, start: np.ndarray | None, weight: np.ndarray) -> np.ndarray:
    """The ridge fit of the rows ``x``, ``y``, each counted ``weight`` times."""
    n = x.shape[1]
    precision = np.concatenate([np.full(n, BOOT_PRIOR_SD**-2), np.full(2, 1e-2)])
    centre = np.concatenate([np.zeros(n), _CUT_START])

    def objective(params: np.ndarray) -> tuple[float, np.ndarray]:
        loglik, grad = vote_log_likelihood(params, x, y, False, n, "logit")
        diff = params - centre
        return -float(weight @ loglik) + 0.5 * float(diff @ (precision * diff)), -weight @ grad + precision * diff

    return optimize.minimize(objective, centre if start is None else start, jac=True, method="BFGS",
                             options={"gtol": 1e-6}).x


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
    point = {c.condition: c.value for c in ranking.conditions}
    value = tuple(point[n] for n in names)
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
        samples = np.zeros((n_boot, n))
        for b, draw in enumerate(bootstrap_draws(people, n_boot, seed)):
            weight = np.bincount(draw, minlength=len(people)) @ per_person
            taken = weight > 0
            samples[b, 1:] = _ridge(cx[taken], cy[taken], start, weight[taken])[: n - 1]
        low, high = np.percentile(samples, [2.5, 97.5], axis=0)
        ci = [(0.0, 0.0) if i == 0 else (float(low[i]), float(high[i])) for i in range(n)]
        above = (samples[:, :, None] > samples[:, None, :]).mean(axis=0)
        ties = (samples[:, :, None] == samples[:, None, :]).mean(axis=0)
        p_better = [[None if i == j else float(above[i, j] + ties[i, j] / 2) for j in range(n)] for i in range(n)]
    return AnimationScale(
        animation, tuple(names), value, tuple(ci),
        tuple(None if v is None or jnd is None else v / jnd for v in value), jnd,
        tuple(tuple(row) for row in p_better), tuple(tuple(int(c) for c in row) for row in counts),
        len(people), n_boot, ranking.fit.status, ranking.fit.message)


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
