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
classes; the standard errors and 95 % intervals are sureal's too (Fisher information of each parameter alone;
the inconsistency's interval from the chi-square distribution).  ``tests/test_subject_model.py`` pins it to
sureal's numbers on sureal's own datasets.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from scipy import stats

Z95 = 1.95996  # sureal's
REFRESH = 0.1
MAX_ITERATIONS = 10_000
DELTA = 1e-8


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


def _nansum(values: np.ndarray, axis: tuple[int, ...]) -> np.ndarray:
    return np.nansum(values, axis=axis)


def fit(x: np.ndarray, content: np.ndarray | list[int], force_bias_zero_mean: bool = True) -> SubjectModel:
    """Fit the model to ``x[e, s, r]`` (NaN: not scored) with ``content[e]`` in 0..C-1.

    Every stimulus and every subject needs at least one score."""
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
    one = np.where(present, 1.0, np.nan)
    mos = np.nanmean(x, axis=(1, 2))
    residual = x - mos[:, None, None]
    v = np.nanstd(residual, axis=(0, 2))
    a = np.array([np.nanstd(residual[content == c]) if np.any(content == c) else 0.0 for c in range(n_c)])
    q, b = mos.copy(), np.zeros(n_s)
    onehot = np.eye(n_c)[content]  # (E, C): sums over the stimuli of each content

    def by_content(per_e: np.ndarray) -> np.ndarray:
        return per_e @ onehot

    iterations, converged = 0, False
    q_std = b_std = v_std = a_std = np.full(1, np.nan)
    while iterations < MAX_ITERATIONS:
        previous = q
        # (12) b_s
        var = v[None, :, None] ** 2 + a[content][:, None, None] ** 2
        den = _nansum(one / var, (0, 2))
        b = b * (1 - REFRESH) + (_nansum((x - q[:, None, None]) / var, (0, 2)) / den) * REFRESH
        b_std = 1 / np.sqrt(np.maximum(0.0, den))
        # (14) v_s
        ae = a[content][:, None, None]
        vs = v[None, :, None]
        resid = x - q[:, None, None] - b[None, :, None]
        var, diff = vs**2 + ae**2, vs**2 - ae**2
        num = _nansum(-vs / var + vs * resid**2 / var**2, (0, 2))
        poly = ae**4 - 3 * vs**4 - 2 * vs**2 * ae**2
        lpp = _nansum(diff / var**2 + resid**2 * poly / var**4, (0, 2))
        v = v * (1 - REFRESH) + (v - num / lpp) * REFRESH
        v_std = 1 / np.sqrt(np.maximum(0.0, -lpp))
        v = np.maximum(v, 0.0)
        # (15) a_c
        vs = v[None, :, None]
        var, diff = vs**2 + ae**2, vs**2 - ae**2
        num = by_content(_nansum(-ae / var + ae * resid**2 / var**2, (1, 2)))
        poly = vs**4 - 3 * ae**4 - 2 * vs**2 * ae**2
        lpp = by_content(_nansum(-diff / var**2 + resid**2 * poly / var**4, (1, 2)))
        a = a * (1 - REFRESH) + (a - num / lpp) * REFRESH
        a_std = 1 / np.sqrt(np.maximum(0.0, -lpp))
        a = np.maximum(a, 0.0)
        # (11) x_e
        var = v[None, :, None] ** 2 + a[content][:, None, None] ** 2
        den = _nansum(one / var, (1, 2))
        q = q * (1 - REFRESH) + (_nansum((x - b[None, :, None]) / var, (1, 2)) / den) * REFRESH
        q_std = 1 / np.sqrt(np.maximum(0.0, den))
        iterations += 1
        change = float(np.linalg.norm(previous - q))
        if not np.isfinite(change):
            break
        if change < DELTA:
            converged = True
            break

    if force_bias_zero_mean:
        shift = float(np.mean(b))
        b, q = b - shift, q + shift
    var = v[None, :, None] ** 2 + a[content][:, None, None] ** 2
    mean = q[:, None, None] + b[None, :, None]
    loglik = float(np.nansum(stats.norm.logpdf(x, mean, np.sqrt(var))) / present.sum())
    count = present.sum(axis=(0, 2))
    v_ci = np.stack([v - (1 - np.sqrt(count / stats.chi2.ppf(0.975, count))) * v,
                     v + (np.sqrt(count / stats.chi2.ppf(0.025, count)) - 1) * v], axis=1)
    return SubjectModel(quality=q, quality_std=q_std, bias=b, bias_std=b_std, inconsistency=v,
                        inconsistency_std=v_std, ambiguity=a, ambiguity_std=a_std, iterations=iterations,
                        converged=converged, loglikelihood=loglik, inconsistency_ci95=v_ci)
