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


# --- constructed orders (issue 26 item 3, issue 27) -------------------------------------------------------------

def _old_trial_order(ids: ComparisonIds, repeats: int, seed: int) -> list:
    """The order of the code before issue 27 (rejection sampling, up to 10,000 shuffles), as the oracle of
    'reference designs keep their trials'."""
    import random

    from server.studies.design import PlannedTrial

    rng = random.Random(seed)
    items = [PlannedTrial(c, side) for c in ids.test for side in ("right", "left") for _ in range(repeats)]
    items += [PlannedTrial(c, "right") for c in ids.catch]
    for _ in range(10_000):
        rng.shuffle(items)
        if all(a.comparison_id != b.comparison_id for a, b in itertools.pairwise(items)):
            break
    else:
        raise ValueError("this design cannot avoid showing a comparison twice in a row")
    head = [PlannedTrial(ids.practice, rng.choice(("right", "left")), practice=True)] if ids.practice else []
    return head + items


def test_thesis_orders_are_unchanged_seeds_included():
    for ids in (ComparisonIds(TEST), ComparisonIds(TEST, catch=[20, 21], practice=30)):
        for seed in range(2000):
            assert trial_order(ids, 1, seed) == _old_trial_order(ids, 1, seed), seed


def _shapes() -> list:
    """Every session shape an accepted design can give, as far as ordering is concerned: k test comparisons
    (animations x pairs per animation), repeats, catch trials; the largest accepted design too."""
    from pydantic import ValidationError

    from server.studies.design import Design

    shapes = set()
    for mode in ("reference", "all-pairs", "incomplete", "adaptive"):
        for n_conditions in (1, 2, 3, 5):
            for n_animations in (1, 2, 3, 4):
                for repeats in range(1, 6):
                    for catch in range(min(n_animations, 2) + 1):
                        try:
                            d = Design(mode=mode, conditions=[f"c{i}" for i in range(n_conditions)],
                                       animations=[f"a{i}" for i in range(n_animations)], repeats=repeats,
                                       catch_trials=catch, practice="c0")
                        except ValidationError:
                            continue
                        shapes.add((n_animations * d.pairs_per_animation(), repeats, catch))
    return sorted(shapes)


def test_every_accepted_design_orders_a_thousand_sessions():
    """1,000 sessions of the tightest shapes (1 or 2 comparisons per session) and of the thesis shapes (8
    comparisons, any repeats: the old search failed with repeats = 5), 100 of the others (where shuffles are
    rarely free of repeats and the repair does the work), to keep the test to seconds."""
    shapes = _shapes()
    assert (8, 5, 0) in shapes and (1, 1, 1) in shapes  # the thesis with repeats = 5; the tightest design
    for k, repeats, catch in shapes:
        ids = ComparisonIds(list(range(k)), catch=list(range(100, 100 + catch)), practice=99)
        for seed in range(1000 if k <= 2 or (k == 8 and catch == 0) else 100):
            trials = trial_order(ids, repeats, seed)
            assert len(trials) == 1 + 2 * repeats * k + catch
            assert all(a.comparison_id != b.comparison_id for a, b in itertools.pairwise(trials)), (k, repeats)
            body = Counter((t.comparison_id, t.reference_side) for t in trials[1:])
            assert all(body[(c, s)] == repeats for c in range(k) for s in ("left", "right"))


def test_largest_design_orders_without_repeats():
    from server.studies.design import Design

    d = Design(conditions=[f"c{i}" for i in range(16)], animations=[f"a{i}" for i in range(16)], repeats=5,
               catch_trials=16)
    assert d.trials_total() == 2576
    ids = ComparisonIds(list(range(256)), catch=list(range(1000, 1016)))
    for seed in range(20):
        trials = trial_order(ids, 5, seed)
        assert len(trials) == 2576
        assert all(a.comparison_id != b.comparison_id for a, b in itertools.pairwise(trials))


def test_repeats_five_positions_stay_uniform():
    """Orders repaired after the shuffle budget still put every comparison at every position alike."""
    counts = np.zeros((len(TEST), 80))
    for seed in range(1000):
        for position, t in enumerate(trial_order(ComparisonIds(TEST), 5, seed)):
            counts[t.comparison_id - 1, position] += 1
    assert chisquare(counts.ravel()).pvalue > 1e-3
