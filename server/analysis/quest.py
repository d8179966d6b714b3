"""QUEST+ (Watson 2017) on a grid: the posterior over a psychometric function's parameters after a staircase's
answers, and the next stimulus by minimum expected entropy.

The same procedure as the ``questplus`` package's ``QuestPlus(func="norm_cdf", stim_scale="linear",
stim_selection_method="min_entropy")`` with a uniform prior, which ``tests/test_quest.py`` checks it against
(the same stimuli, the same posterior); written on numpy arrays because ``questplus`` computes on xarray objects,
about 5 ms a trial (0.28 s a 60-trial staircase, 2026-12-05), most of a simulated study's time, where these
arrays take 4 ms for the whole staircase.

The model: ``P(detected | x) = guess + (1 - guess - lapse) * Phi((x - mean) / sd)``, intensity ``x`` growing
with detectability; the parameter grid is every combination of the ``mean``, ``sd``, ``guess`` and ``lapse``
values given.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from scipy import stats

# Grid sizes of the parameter domain: thresholds over the intensities' span and a quarter of it either side,
# slopes (sd as a fraction of the span) and lapse rates.
THRESHOLDS = 21
SLOPES = (0.05, 0.1, 0.2, 0.4, 0.8)
LAPSES = (0.01, 0.05)


@dataclass(frozen=True)
class Grid:
    """The parameter grid over a ladder's intensities ``xs`` (any order), with the guess rates ``guesses``
    (0.5 for 2AFC; false-alarm rates for a yes/no format)."""

    xs: tuple[float, ...]
    guesses: tuple[float, ...]

    def domain(self) -> dict[str, list[float]]:
        """The parameter values per dimension, in ``questplus``' names and order."""
        lo, hi = min(self.xs), max(self.xs)
        span = hi - lo or 1.0
        return {"mean": list(np.linspace(lo - span / 4, hi + span / 4, THRESHOLDS)),
                "sd": [s * span for s in SLOPES], "lower_asymptote": list(self.guesses), "lapse_rate": list(LAPSES)}

    def detection(self) -> np.ndarray:
        """P(detected) ``(len(xs), parameters)``: the grid flattened in C order of :meth:`domain`'s dimensions."""
        d = self.domain()
        mean, sd, guess, lapse = (a.ravel() for a in np.meshgrid(*d.values(), indexing="ij"))
        x = np.asarray(self.xs, dtype=float)[:, None]
        return guess + (1 - guess - lapse) * stats.norm.cdf(x, loc=mean, scale=sd)

    def mean(self, post: np.ndarray) -> dict[str, float]:
        """Each parameter's posterior mean (``questplus``' ``param_estimate``) under ``post`` ``(parameters,)``."""
        d = self.domain()
        grid = post.reshape([len(v) for v in d.values()])
        axes = range(len(d))
        return {name: float(grid.sum(axis=tuple(a for a in axes if a != k)) @ np.asarray(values))
                for k, (name, values) in enumerate(d.items())}


def update(post: np.ndarray, detection: np.ndarray, index: int, detected: bool) -> np.ndarray:
    """The posterior ``(parameters,)`` after one more answer: intensity ``index`` was (not) ``detected``."""
    post = post * (detection[index] if detected else 1.0 - detection[index])
    return post / post.sum()


def posterior(detection: np.ndarray, history: Iterable[tuple[int, bool]]) -> np.ndarray:
    """The posterior ``(parameters,)`` from a uniform prior after ``history``: (index into the intensities,
    detected) per answered trial, in order (normalized after each, as QUEST+ does)."""
    post = np.full(detection.shape[1], 1.0 / detection.shape[1])
    for index, detected in history:
        post = update(post, detection, index, detected)
    return post


def next_index(detection: np.ndarray, post: np.ndarray) -> int:
    """The intensity (index) whose answer leaves the least expected entropy of the posterior (the first of
    equals)."""
    joint = post * np.stack([detection, 1.0 - detection])  # (answer, intensity, parameters)
    marginal = joint.sum(axis=2)  # P(answer | intensity)
    updated = joint / marginal[..., None]
    with np.errstate(divide="ignore", invalid="ignore"):
        entropy = -np.nansum(updated * np.log(updated), axis=2)  # 0 log 0 counts 0
    return int(np.argmin((marginal * entropy).sum(axis=0)))
