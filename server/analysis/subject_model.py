"""The subject model of ITU-T P.910 Annex E / P.913 §12.6: maximum-likelihood estimates of each stimulus's true
score, each participant's bias and inconsistency and each content's ambiguity.

Model (Li & Bampis, "Recover subjective quality scores from noisy measurements", DCC 2017; as Netflix's ``sureal``
implements it, class ``MaximumLikelihoodEstimationModel``)::

    X[e, s, r] = x_e + B[e, s, r] + A[e, s, r],   B ~ N(b_s, v_s^2),   A ~ N(0, a_c(e)^2)

``e`` a stimulus, ``s`` a participant, ``r`` a repetition, ``c(e)`` the content of stimulus ``e``.  Here a
stimulus is one comparison (an animation in a test condition against a reference condition), X its -2..+2 score
from the test condition's point of view (``scale``), the repetitions its side-swapped showings and the content
the animation.  So ``x_e`` is the modelled comparison score, ``b_s`` how much a participant favours test
conditions over everyone else, ``v_s`` how inconsistent they are and ``a_c`` how ambiguous an animation is.

The solver is sureal's ("simplified" gradient: Newton steps per parameter block, damped by 0.1, until the
stimulus scores move less than 1e-8; then the biases are shifted to mean 0, the stimulus scores by the same
amount), ported from sureal 0.9.0 (Apache License 2.0, Copyright Netflix, Inc.) to arrays without its dataset
classes, its iterations compiled (numba: about a thousand of them, and a study refits at each participant's
start: 15 ms instead of 190 ms for 10 comparisons x 80 participants x 2 showings, 2026-12-05); the standard
errors and 95 % intervals are sureal's too (Fisher information of each parameter alone; the inconsistency's
interval from the chi-square distribution).  ``tests/test_subject_model.py`` pins it to
sureal's numbers on sureal's own datasets.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numba
import numpy as np
from scipy import stats

Z95 = 1.95996  # sureal's
REFRESH = 0.1
MAX_ITERATIONS = 10_000
DELTA = 1e-8
# A modelled spread below this (score units) is the solver running into the likelihood's singularity: on such fits
# it ends at 1e-7 or far less; between participants who do vary it stays above 0.2 (seeded random studies of 2 to 20
# participants, 2026-12-05).
DEGENERATE_SD = 1e-6
# A spread over this many times the largest residual it explains is not at a maximum of the likelihood (fit()): a
# stationary one is at most that residual.
RAN_OFF = 1.001


@dataclass(frozen=True)
class SubjectModel:
    """The fitted model; arrays indexed like the input's axes (stimuli, subjects, contents).  Intervals are
    (lower, upper) bounds.  NaN where the data do not determine a value (e.g. a subject without scores)."""

    quality: np.ndarray  # x_e, shape (E,)
    quality_std: np.ndarray
    bias: np.ndarray  # b_s, shape (S,)
    bias_std: np.ndarray
    inconsistency: np.ndarray  # v_s, shape (S,)
    inconsistency_std: np.ndarray
    ambiguity: np.ndarray  # a_c, shape (C,)
    ambiguity_std: np.ndarray
    iterations: int
    converged: bool
    loglikelihood: float  # per observation

    @property
    def quality_ci95(self) -> np.ndarray:
        """shape (E, 2)"""
        return np.stack([self.quality - Z95 * self.quality_std, self.quality + Z95 * self.quality_std], axis=1)

    @property
    def bias_ci95(self) -> np.ndarray:
        return np.stack([self.bias - Z95 * self.bias_std, self.bias + Z95 * self.bias_std], axis=1)

    inconsistency_ci95: np.ndarray | None = None  # shape (S, 2), set by fit()
    # (subject, content) pairs with scores whose modelled spread sqrt(v_s^2 + a_c^2) fell to 0 (below
    # DEGENERATE_SD): the likelihood has no maximum there (see fit()), so the estimates are where the solver stopped.
    degenerate: tuple[tuple[int, int], ...] = ()
    # Subjects whose inconsistency, and contents whose ambiguity, the solver ran off with (see fit()): no maximum of
    # the likelihood is there, whatever ``converged`` says.
    diverged_subjects: tuple[int, ...] = ()
    diverged_contents: tuple[int, ...] = ()

    @property
    def diverged(self) -> bool:
        return bool(self.diverged_subjects or self.diverged_contents)


_jit = numba.njit(cache=True, error_model="numpy")  # IEEE division: 1/0 is inf, 0/0 NaN, as numpy's


@_jit
def _biases(x, content, q, b, v, a, refresh, b_std):
    """(12) each participant's bias ``b`` (and its standard error) in place; a sum skips its NaN terms (as
    ``np.nansum`` over the whole expression: a missing score makes its term NaN)."""
    n_e, n_s, n_r = x.shape
    for s in range(n_s):
        den, num = 0.0, 0.0
        for e in range(n_e):
            var = v[s] ** 2 + a[content[e]] ** 2
            for r in range(n_r):
                t = (x[e, s, r] - x[e, s, r] + 1.0) / var  # 1 / var where scored, NaN where not
                if t == t:
                    den += t
                t = (x[e, s, r] - q[e]) / var
                if t == t:
                    num += t
        b[s] = b[s] * (1 - refresh) + (num / den) * refresh
        b_std[s] = 1 / np.sqrt(max(0.0, den))


@_jit
def _newton_terms(p, o, resid):
    """The two terms one score adds to the Newton step of a standard deviation ``p`` (an inconsistency, or an
    ambiguity) beside the other ``o``: the log-likelihood's first and second derivative in ``p`` (sureal's (14) and
    (15) are this with the roles swapped)."""
    var, diff = p ** 2 + o ** 2, p ** 2 - o ** 2
    poly = o ** 4 - 3 * p ** 4 - 2 * (p ** 2 * o ** 2)
    return -p / var + p * resid ** 2 / var ** 2, diff / var ** 2 + resid ** 2 * poly / var ** 4


@_jit
def _inconsistencies(x, content, q, b, v, a, refresh, v_std):
    """(14) each participant's inconsistency ``v`` in place, a Newton step from the residuals of the new biases."""
    n_e, n_s, n_r = x.shape
    new = np.empty(n_s)
    for s in range(n_s):
        num, lpp, vs = 0.0, 0.0, v[s]
        for e in range(n_e):
            ae = a[content[e]]
            for r in range(n_r):
                t1, t2 = _newton_terms(vs, ae, x[e, s, r] - q[e] - b[s])
                if t1 == t1:
                    num += t1
                if t2 == t2:
                    lpp += t2
        new[s] = vs * (1 - refresh) + (vs - num / lpp) * refresh
        v_std[s] = 1 / np.sqrt(max(0.0, -lpp))
    for s in range(n_s):
        v[s] = 0.0 if new[s] < 0.0 else new[s]  # NaN stays NaN, as np.maximum


@_jit
def _ambiguities(x, content, q, b, v, a, refresh, a_std):
    """(15) each content's ambiguity ``a`` in place, from the same residuals and the new inconsistencies."""
    n_e, n_s, n_r = x.shape
    num_e, lpp_e = np.zeros(n_e), np.zeros(n_e)
    for e in range(n_e):
        ae = a[content[e]]
        for s in range(n_s):
            for r in range(n_r):
                t1, t2 = _newton_terms(ae, v[s], x[e, s, r] - q[e] - b[s])
                if t1 == t1:
                    num_e[e] += t1
                if t2 == t2:
                    lpp_e[e] += t2
    for c in range(a.shape[0]):  # sums over the stimuli of each content (a matrix product: NaN or inf spread alike)
        num, lpp = 0.0, 0.0
        for e in range(n_e):
            one = 1.0 if content[e] == c else 0.0
            num += num_e[e] * one
            lpp += lpp_e[e] * one
        new = a[c] * (1 - refresh) + (a[c] - num / lpp) * refresh
        a_std[c] = 1 / np.sqrt(max(0.0, -lpp))
        a[c] = 0.0 if new < 0.0 else new


@_jit
def _scores(x, content, q, b, v, a, refresh, q_std):
    """(11) each stimulus's score ``q`` in place; returns how far the scores moved (their difference's norm)."""
    n_e, n_s, n_r = x.shape
    change = 0.0
    for e in range(n_e):
        den, num, ae = 0.0, 0.0, a[content[e]]
        for s in range(n_s):
            var = v[s] ** 2 + ae ** 2
            for r in range(n_r):
                t = (x[e, s, r] - x[e, s, r] + 1.0) / var
                if t == t:
                    den += t
                t = (x[e, s, r] - b[s]) / var
                if t == t:
                    num += t
        new = q[e] * (1 - refresh) + (num / den) * refresh
        q_std[e] = 1 / np.sqrt(max(0.0, den))
        change += (new - q[e]) ** 2
        q[e] = new
    return np.sqrt(change)


@_jit
def _solve(x, content, q, b, v, a, refresh, max_iterations, delta):
    """sureal's iterations (module docstring) on ``x[e, s, r]`` from the starting estimates ``q, b, v, a`` (updated
    in place): (12), (14), (15), (11) until the scores move less than ``delta``.  Compiled: the solver takes about a
    thousand iterations, and a study refits at every participant's start.  Returns the standard errors of the last
    iteration, the iterations and whether it converged."""
    q_std, b_std = np.full(q.shape[0], np.nan), np.full(b.shape[0], np.nan)
    v_std, a_std = np.full(v.shape[0], np.nan), np.full(a.shape[0], np.nan)
    iterations, converged = 0, False
    while iterations < max_iterations:
        _biases(x, content, q, b, v, a, refresh, b_std)
        _inconsistencies(x, content, q, b, v, a, refresh, v_std)
        _ambiguities(x, content, q, b, v, a, refresh, a_std)
        change = _scores(x, content, q, b, v, a, refresh, q_std)
        iterations += 1
        if not np.isfinite(change):
            break
        if change < delta:
            converged = True
            break
    return q_std, b_std, v_std, a_std, iterations, converged


def fit(x: np.ndarray, content: np.ndarray | list[int], force_bias_zero_mean: bool = True) -> SubjectModel:
    """Fit the model to ``x[e, s, r]`` (NaN: not scored) with ``content[e]`` in 0..C-1.

    Every stimulus and every subject needs at least one score.

    The likelihood can have no maximum: when a subject's scores of every stimulus of one content are explained
    exactly (both showings alike, and the content adding no spread of its own), letting that subject's
    inconsistency and the content's ambiguity go to 0 raises it without end.  sureal's solver then stops near 0
    and reports converged; so does this port (its numbers stay sureal's), and ``degenerate`` names those pairs.
    It is common with whole-number answers: of 200 seeded studies of 8 comparisons (4 contents) answered at
    random, 90 to 130 were so at every panel size tried from 2 to 20 participants (2026-12-05).

    The solver can also run off: its Newton step on a spread goes the wrong way where the likelihood is not concave
    in it, and the spread grows to 1e18 or beyond while the scores settle (the subject's weight 1/var goes to 0), so
    it "converges" (sureal too; on such data sureal's own run fails or stops elsewhere).  No maximum is there: where a
    subject's inconsistency exceeds every residual of its scores, each score's term of the log-likelihood's
    derivative in it, (r^2 - var) / var^2, is negative, so a smaller inconsistency is more likely; the same holds for
    a content's ambiguity.  ``diverged_subjects`` and ``diverged_contents`` name those."""
    x = np.asarray(x, dtype=float)
    if x.ndim != 3:
        raise ValueError(f"scores must have shape (stimuli, subjects, repetitions), got {x.shape}")
    content = np.asarray(content, dtype=int)
    if content.shape != (x.shape[0],):
        raise ValueError(f"content must have one entry per stimulus ({x.shape[0]}), got {content.shape}")
    present = ~np.isnan(x)
    if not present.any(axis=(1, 2)).all() or not present.any(axis=(0, 2)).all():
        raise ValueError("every stimulus and every subject needs at least one score")
    n_e, n_s, _ = x.shape
    n_c = int(content.max()) + 1
    with warnings.catch_warnings(), np.errstate(divide="ignore", invalid="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)
        return _fit(x, content, present, n_e, n_s, n_c, force_bias_zero_mean)


def _fit(x: np.ndarray, content: np.ndarray, present: np.ndarray, n_e: int, n_s: int, n_c: int,
         force_bias_zero_mean: bool) -> SubjectModel:
    mos = np.nanmean(x, axis=(1, 2))
    residual = x - mos[:, None, None]
    v = np.nanstd(residual, axis=(0, 2))
    a = np.array([np.nanstd(residual[content == c]) if np.any(content == c) else 0.0 for c in range(n_c)])
    q, b = mos.copy(), np.zeros(n_s)

    q_std, b_std, v_std, a_std, iterations, converged = _solve(x, content, q, b, v, a, REFRESH, MAX_ITERATIONS, DELTA)

    if force_bias_zero_mean:
        shift = float(np.mean(b))
        b, q = b - shift, q + shift
    var = v[None, :, None] ** 2 + a[content][:, None, None] ** 2
    mean = q[:, None, None] + b[None, :, None]
    loglik = float(np.nansum(stats.norm.logpdf(x, mean, np.sqrt(var))) / present.sum())
    count = present.sum(axis=(0, 2))
    v_ci = np.stack([v - (1 - np.sqrt(count / stats.chi2.ppf(0.975, count))) * v,
                     v + (np.sqrt(count / stats.chi2.ppf(0.025, count)) - 1) * v], axis=1)
    spread = np.sqrt(v[None, :] ** 2 + a[content][:, None] ** 2)  # (E, S)
    scored = present.any(axis=2)
    degenerate = sorted({(int(s), int(content[e])) for e, s in zip(*np.nonzero(scored & (spread < DEGENERATE_SD)),
                                                                      strict=True)})
    residual = np.abs(x - mean)
    reach_s = np.nanmax(residual, axis=(0, 2))
    reach_c = np.array([np.nanmax(residual[content == c]) if np.any(content == c) else np.inf for c in range(n_c)])
    # (a spread the solver left at DEGENERATE_SD or below is the degenerate case's, not this)
    ran_off_s = ~(v <= RAN_OFF * reach_s + DEGENERATE_SD)  # NaN counts as run off
    ran_off_c = ~(a <= RAN_OFF * reach_c + DEGENERATE_SD)
    return SubjectModel(quality=q, quality_std=q_std, bias=b, bias_std=b_std, inconsistency=v,
                        inconsistency_std=v_std, ambiguity=a, ambiguity_std=a_std, iterations=iterations,
                        converged=converged, loglikelihood=loglik, inconsistency_ci95=v_ci,
                        degenerate=tuple(degenerate), diverged_subjects=tuple(np.flatnonzero(ran_off_s).tolist()),
                        diverged_contents=tuple(np.flatnonzero(ran_off_c).tolist()))
