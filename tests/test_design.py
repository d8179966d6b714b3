"""Trial order: balanced by construction, no immediate repeats, positions uniform over participants."""

import itertools
from collections import Counter

import numpy as np
import pytest
from scipy.stats import chisquare

from server.studies.design import ComparisonIds, trial_order

TEST = list(range(1, 9))  # the thesis design: 8 comparisons


def test_thousand_sessions_are_balanced_without_repeats_and_uniform():
    n_sessions, n_positions = 1000, 16
    counts = np.zeros((len(TEST), n_positions))
    side_counts = Counter()
    for seed in range(n_sessions):
        trials = trial_order(ComparisonIds(TEST), repeats=1, seed=seed)
        assert len(trials) == n_positions
        # Each comparison exactly once per side.
        assert sorted((t.comparison_id, t.reference_side) for t in trials) == sorted(
            (c, s) for c in TEST for s in ("left", "right"))
        assert all(a.comparison_id != b.comparison_id for a, b in itertools.pairwise(trials))
        for position, t in enumerate(trials):
            counts[t.comparison_id - 1, position] += 1
            side_counts[(position, t.reference_side)] += 1
    # Every comparison equally likely at every position (expected 125 per cell).
    for comparison in range(len(TEST)):
        p = chisquare(counts[comparison]).pvalue
        assert p > 1e-3, f"comparison {comparison + 1}: positions not uniform (p = {p:.2g})"
    p = chisquare(counts.ravel()).pvalue
    print(f"chi-square over all {counts.size} comparison x position cells: p = {p:.3f}")
    assert p > 1e-3
    # And the reference is on the left as often as on the right at each position.
    lefts = np.array([side_counts[(i, "left")] for i in range(n_positions)])
    assert chisquare(np.stack([lefts, n_sessions - lefts]).ravel()).pvalue > 1e-3


def test_order_is_seeded():
    a = trial_order(ComparisonIds(TEST), 1, seed=42)
    assert a == trial_order(ComparisonIds(TEST), 1, seed=42)
    assert a != trial_order(ComparisonIds(TEST), 1, seed=43)


def test_practice_first_catch_trials_and_repeats():
    trials = trial_order(ComparisonIds(TEST, catch=[20, 21], practice=30), repeats=2, seed=1)
    assert trials[0].practice and trials[0].comparison_id == 30
    assert not any(t.practice for t in trials[1:])
    body = Counter((t.comparison_id, t.reference_side) for t in trials[1:])
    assert all(body[(c, s)] == 2 for c in TEST for s in ("left", "right"))
    assert body[(20, "right")] == 1 and body[(21, "right")] == 1
    assert len(trials) == 1 + 8 * 4 + 2


def test_impossible_design_is_refused():
    with pytest.raises(ValueError, match="twice in a row"):
        trial_order(ComparisonIds([1]), repeats=1, seed=0)
