"""Psychometric functions of threshold designs (issue 38): a fit per animation on (level, trials, correct) counts,
detection per level with intervals, the cheapest indistinguishable level and the cost/detection Pareto set.

The model is psignifit 4's default (docs/methods/thresholds.md)::

    P(correct | x) = gamma + (1 - gamma - lapse) * Phi((x - m) / s),   width = 2 * Phi^-1(0.95) * s

with x the level on a log10 scale (all levels positive) or the level itself, gamma the guess rate (0.5 for 2AFC),
``m`` the threshold (the sigmoid's midpoint: 75 % correct in 2AFC without lapses), ``width`` the span of x over
which the sigmoid rises from 5 % to 95 % (psignifit's ``width_alpha = 0.05``) and a lapse rate bounded by
``max_lapse``.  The fit is maximum likelihood on a grid (refined locally for the point estimate), and the
intervals are a parametric bootstrap (counts redrawn from the fitted function at each level's trial count, each
refitted on the grid: one matrix product for every resample), percentile intervals.  Pure numpy/scipy.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import optimize, stats

#: psignifit's width: the sigmoid's rise from ALPHA to 1 - ALPHA
WIDTH_ALPHA = 0.05
#: width = 2 * Z_WIDTH * s (the normal sigmoid from 5 % to 95 %)
Z_WIDTH = float(stats.norm.ppf(1 - WIDTH_ALPHA))
GUESS_2AFC = 0.5
CRITERION_2AFC = 0.75
_EPS = 1e-9


@dataclass(frozen=True)
class LevelDetection:
    """One level's answers: ``p`` = correct / trials with its interval (Clopper-Pearson by default)."""

    level: float
    trials: int
    correct: int
    p: float
    low: float
    high: float


def detection(levels: Sequence[float], trials: Sequence[int], correct: Sequence[int], *, confidence: float = 0.95,
              method: str = "beta") -> list[LevelDetection]:
    """Proportion correct per level with a two-sided ``confidence`` interval (``method``: statsmodels'
    ``proportion_confint``: ``beta`` = Clopper-Pearson, ``wilson``); levels without trials are left out."""
    from statsmodels.stats.proportion import proportion_confint

    out = []
    for x, n, k in zip(levels, trials, correct, strict=True):
        if n <= 0:
            continue
        if not 0 <= k <= n:
            raise ValueError(f"level {x}: {k} correct of {n} trials")
        lo, hi = proportion_confint(int(k), int(n), alpha=1 - confidence, method=method)
        out.append(LevelDetection(float(x), int(n), int(k), k / n, float(lo), float(hi)))
    return out


@dataclass(frozen=True)
class Interval:
    estimate: float
    low: float
    high: float

    def contains(self, value: float) -> bool:
        return self.low <= value <= self.high

    @property
    def span(self) -> float:
        return self.high - self.low


@dataclass(frozen=True)
class Fit:
    """A fitted psychometric function.  ``threshold`` is in level units (the log-scale midpoint transformed back);
    ``log_threshold``, ``width`` and ``slope`` (dP/dx at the threshold) are on the fitting scale ``x`` (log10 of
    the level when ``log_scale``); ``increasing``: detection grows with the level."""

    threshold: Interval
    log_threshold: Interval
    width: Interval
    slope: Interval
    lapse: Interval
    guess: float
    log_scale: bool
    increasing: bool
    trials: int
    bootstrap: int
    confidence: float
    #: the threshold's profile-likelihood interval (level units, and on the fitting scale): the thresholds whose
    #: likelihood, maximised over width and lapse, is within chi2(1) of the best.  Valid for adaptive (QUEST+)
    #: data too, where the bootstrap at the observed counts per level ignores how the levels were chosen.
    threshold_profile: Interval | None = None
    log_threshold_profile: Interval | None = None

    def x(self, level: float | np.ndarray) -> np.ndarray:
        return _to_x(np.asarray(level, dtype=float), self.log_scale)

    def p(self, level: float | np.ndarray) -> np.ndarray:
        """The fitted probability correct at ``level``."""
        s = self.width.estimate / (2 * Z_WIDTH) * (1 if self.increasing else -1)
        return _pc(self.x(level), self.log_threshold.estimate, s, self.lapse.estimate, self.guess)


def _to_x(level: np.ndarray, log_scale: bool) -> np.ndarray:
    return np.log10(level) if log_scale else level


def _pc(x: np.ndarray, m: float | np.ndarray, s: float | np.ndarray, lapse: float | np.ndarray,
        guess: float) -> np.ndarray:
    return guess + (1 - guess - lapse) * stats.norm.cdf((x - m) / s)


@dataclass
class _Grid:
    m: np.ndarray
    w: np.ndarray
    lapse: np.ndarray
    logit: np.ndarray = field(repr=False)  # levels x grid: log P(correct) - log P(wrong), float32
    logq: np.ndarray = field(repr=False)  # levels x grid: log P(wrong)


def _grid(x: np.ndarray, guess: float, sign: float, max_lapse: float, steps: tuple[int, int, int]) -> _Grid:
    lo, hi = float(x.min()), float(x.max())
    span = hi - lo
    gap = float(np.diff(np.unique(x)).min())
    m = np.linspace(lo - span / 4, hi + span / 4, steps[0])
    w = np.geomspace(gap / 2, 3 * span, steps[1])
    la = np.linspace(0.0, max_lapse, steps[2]) if max_lapse > 0 else np.zeros(1)
    M, W, L = (a.ravel() for a in np.meshgrid(m, w, la, indexing="ij"))
    p = _pc(x[:, None], M[None, :], sign * W[None, :] / (2 * Z_WIDTH), L[None, :], guess)
    p = np.clip(p, _EPS, 1 - _EPS)
    return _Grid(M, W, L, (np.log(p) - np.log1p(-p)).astype(np.float32), np.log1p(-p))


def _loglik(g: _Grid, k: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Log-likelihood of every grid point for each row of counts ``k`` (resamples x levels) with trials ``n``
    (levels): k log p + (n - k) log q = k (log p - log q) + n log q, the second term shared by every row."""
    return k.astype(np.float32) @ g.logit + (n @ g.logq)[None, :].astype(np.float32)


def _refine(x: np.ndarray, k: np.ndarray, n: np.ndarray, guess: float, sign: float, max_lapse: float,
            start: tuple[float, float, float], gap: float, span: float) -> tuple[float, float, float]:
    def nll(theta: np.ndarray) -> float:
        m, logw, lapse = theta
        p = np.clip(_pc(x, m, sign * np.exp(logw) / (2 * Z_WIDTH), lapse, guess), _EPS, 1 - _EPS)
        return -float(np.sum(k * np.log(p) + (n - k) * np.log1p(-p)))

    m0, w0, l0 = start
    bounds = [(x.min() - span / 4, x.max() + span / 4), (np.log(gap / 2), np.log(3 * span)), (0.0, max_lapse)]
    r = optimize.minimize(nll, np.array([m0, np.log(w0), l0]), method="L-BFGS-B", bounds=bounds)
    best = r.x if r.fun <= nll(np.array([m0, np.log(w0), l0])) else np.array([m0, np.log(w0), l0])
    return float(best[0]), float(np.exp(best[1])), float(best[2])


def _nll_at(x: np.ndarray, k: np.ndarray, n: np.ndarray, guess: float, sign: float, m: float, w: float,
            lapse: float) -> float:
    p = np.clip(_pc(x, m, sign * w / (2 * Z_WIDTH), lapse, guess), _EPS, 1 - _EPS)
    return -float(np.sum(k * np.log(p) + (n - k) * np.log1p(-p)))


def fit(levels: Sequence[float], trials: Sequence[int], correct: Sequence[int], *, guess: float = GUESS_2AFC,
        log_scale: bool | None = None, increasing: bool | None = None, max_lapse: float = 0.1,
        bootstrap: int = 1000, confidence: float = 0.95, seed: int = 0,
        steps: tuple[int, int, int] = (121, 41, 6)) -> Fit:
    """Fit the psychometric function to counts per level (levels without trials are ignored).

    ``log_scale`` None: log10 when every level is positive.  ``increasing`` None: the direction with the higher
    likelihood (an update rate is detected at its *low* levels).  ``bootstrap`` resamples for the intervals
    (seeded by ``seed``); ``steps``: grid points of threshold, width and lapse."""
    lv = np.asarray(levels, dtype=float)
    n = np.asarray(trials, dtype=float)
    k = np.asarray(correct, dtype=float)
    keep = n > 0
    lv, n, k = lv[keep], n[keep], k[keep]
    if len(np.unique(lv)) < 3:
        raise ValueError("a psychometric fit needs answers at 3 levels or more")
    if np.any(k < 0) or np.any(k > n):
        raise ValueError("correct answers outside 0 … trials")
    if log_scale is None:
        log_scale = bool(np.all(lv > 0))
    x = _to_x(lv, log_scale)
    span = float(x.max() - x.min())
    gap = float(np.diff(np.unique(x)).min())
    signs = [1.0, -1.0] if increasing is None else [1.0 if increasing else -1.0]
    best: tuple[float, float, _Grid, int] | None = None
    for sign in signs:
        g = _grid(x, guess, sign, max_lapse, steps)
        ll = _loglik(g, k[None, :], n)[0]
        i = int(np.argmax(ll))
        if best is None or ll[i] > best[0]:
            best = (float(ll[i]), sign, g, i)
    assert best is not None
    _, sign, g, i = best
    m, w, lapse = _refine(x, k, n, guess, sign, max_lapse, (g.m[i], g.w[i], g.lapse[i]), gap, span)

    rng = np.random.default_rng(seed)
    p_fit = _pc(x, m, sign * w / (2 * Z_WIDTH), lapse, guess)
    bm, bw, bl = np.empty(bootstrap), np.empty(bootstrap), np.empty(bootstrap)
    chunk = max(1, 2_000_000 // len(g.m))
    for start in range(0, bootstrap, chunk):
        size = min(chunk, bootstrap - start)
        kb = rng.binomial(n.astype(int)[None, :], p_fit[None, :], size=(size, len(n))).astype(float)
        j = np.argmax(_loglik(g, kb, n), axis=1)
        bm[start:start + size], bw[start:start + size], bl[start:start + size] = g.m[j], g.w[j], g.lapse[j]
    q = ((1 - confidence) / 2 * 100, (1 + confidence) / 2 * 100)

    def interval(est: float, sample: np.ndarray) -> Interval:
        lo, hi = np.percentile(sample, q)
        return Interval(est, float(min(lo, est)), float(max(hi, est)))

    def slope(mm: np.ndarray | float, ww: np.ndarray | float, ll: np.ndarray | float) -> np.ndarray:
        return np.asarray((1 - guess - np.asarray(ll)) * stats.norm.pdf(0) * 2 * Z_WIDTH / np.asarray(ww))

    thr = interval(m, bm)
    back = (lambda v: 10 ** v) if log_scale else (lambda v: v)
    ll = _loglik(g, k[None, :], n)[0].astype(float)
    ms, inverse = np.unique(g.m, return_inverse=True)
    prof = np.full(len(ms), -np.inf)
    np.maximum.at(prof, inverse, ll)
    inside = ms[2 * (max(prof.max(), -_nll_at(x, k, n, guess, sign, m, w, lapse)) - prof)
                <= stats.chi2.ppf(confidence, 1)]
    half = (ms[1] - ms[0]) / 2
    lp = Interval(m, float(min(inside.min() - half, m)), float(max(inside.max() + half, m))) if len(inside) else thr
    return Fit(threshold=Interval(back(thr.estimate), back(thr.low), back(thr.high)), log_threshold=thr,
               width=interval(w, bw), slope=interval(float(slope(m, w, lapse)), slope(bm, bw, bl)),
               lapse=interval(lapse, bl), guess=guess, log_scale=log_scale, increasing=sign > 0,
               trials=int(n.sum()), bootstrap=bootstrap, confidence=confidence,
               threshold_profile=Interval(back(lp.estimate), back(lp.low), back(lp.high)), log_threshold_profile=lp)


# ----------------------------------------------------------------------------------------------- cost and quality


@dataclass(frozen=True)
class FrontierPoint:
    """One level of a ladder on the cost/quality plane: its cost (x) and detection (y, with interval)."""

    condition: str
    level: float
    cost: float
    detection: LevelDetection
    pareto: bool
    indistinguishable: bool  # the detection's upper bound is below the criterion


@dataclass(frozen=True)
class Frontier:
    animation: str
    cost_metric: str
    criterion: float
    points: list[FrontierPoint]
    cheapest_indistinguishable: FrontierPoint | None
    fit: Fit | None = None


def pareto(costs: Sequence[float], detections: Sequence[float]) -> list[bool]:
    """Which points no other point dominates (cost and detection both lower or equal, one strictly lower)."""
    c, d = np.asarray(costs, dtype=float), np.asarray(detections, dtype=float)
    le = (c[None, :] <= c[:, None]) & (d[None, :] <= d[:, None])
    lt = (c[None, :] < c[:, None]) | (d[None, :] < d[:, None])
    return [not bool(np.any(le[i] & lt[i])) for i in range(len(c))]


def cheapest_indistinguishable(points: Sequence[FrontierPoint]) -> FrontierPoint | None:
    """The lowest-cost level whose detection's upper bound stays below the criterion (ties: the lower
    detection); None when no level qualifies."""
    ok = [p for p in points if p.indistinguishable]
    return min(ok, key=lambda p: (p.cost, p.detection.p)) if ok else None


def frontier(animation: str, rows: Sequence[tuple[str, float, int, int]], costs: Mapping[str, float], *,
             cost_metric: str = "cost_ms_per_1000", criterion: float = CRITERION_2AFC, confidence: float = 0.95,
             method: str = "beta", fit_function: bool = True, guess: float = GUESS_2AFC,
             bootstrap: int = 1000, seed: int = 0) -> Frontier:
    """The cost/quality frontier of one animation: ``rows`` are (condition, level, trials, correct) of its
    ladder, ``costs`` the cost of each condition (a manifest metric, e.g. ``cost_ms_per_1000`` or ``bytes``).
    A condition without a cost is left out (named in the error when none has one)."""
    rows = [r for r in rows if r[2] > 0]
    missing = [r[0] for r in rows if costs.get(r[0]) is None]
    rows = [r for r in rows if costs.get(r[0]) is not None]
    if not rows:
        raise ValueError(f"{animation}: no condition with answers has a {cost_metric} ({', '.join(missing)})")
    det = detection([r[1] for r in rows], [r[2] for r in rows], [r[3] for r in rows], confidence=confidence,
                    method=method)
    cost = [float(costs[r[0]]) for r in rows]
    front = pareto(cost, [d.p for d in det])
    points = [FrontierPoint(r[0], float(r[1]), c, d, f, d.high < criterion)
              for r, c, d, f in zip(rows, cost, det, front, strict=True)]
    points.sort(key=lambda p: (p.cost, p.level))
    fitted = None
    if fit_function and len({r[1] for r in rows}) >= 3:
        fitted = fit([r[1] for r in rows], [r[2] for r in rows], [r[3] for r in rows], guess=guess,
                     bootstrap=bootstrap, seed=seed, confidence=confidence)
    return Frontier(animation, cost_metric, criterion, points, cheapest_indistinguishable(points), fitted)
