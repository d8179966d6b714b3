"""QUEST+ on numpy arrays (server.analysis.quest) against the ``questplus`` package it replaces: for seeded
random ladders, guess rates and answer sequences, the same next stimulus after every answer and the same
posterior (to 1e-12), the same parameter estimates (posterior means)."""

from __future__ import annotations

import numpy as np
import pytest
import questplus

from server.analysis.quest import Grid, next_index, posterior, update


@pytest.mark.parametrize("seed", range(6))
def test_same_stimuli_and_posterior_as_questplus(seed):
    rng = np.random.default_rng(seed)
    xs = tuple(float(x) for x in np.sort(rng.uniform(-1.5, 1.5, int(rng.integers(3, 9)))) * rng.choice([-1, 1]))
    grid = Grid(xs, (0.5,) if seed % 2 else (0.0, 0.1, 0.2))
    detection = grid.detection()
    q = questplus.QuestPlus(stim_domain={"intensity": list(xs)}, param_domain=grid.domain(),
                            outcome_domain={"response": ["Yes", "No"]}, func="norm_cdf", stim_scale="linear",
                            stim_selection_method="min_entropy")
    post = posterior(detection, [])
    history = []
    truth = rng.uniform(min(xs), max(xs))
    for _ in range(40):
        i = next_index(detection, post)
        assert xs[i] == q.next_stim["intensity"]
        seen = bool(rng.random() < 0.5 + 0.48 * (xs[i] > truth))
        q.update(stim={"intensity": xs[i]}, outcome={"response": "Yes" if seen else "No"})
        post = update(post, detection, i, seen)
        history.append((i, seen))
        np.testing.assert_allclose(post, q.posterior.values.ravel(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(posterior(detection, history), post, rtol=0, atol=1e-15)
    expected = q.param_estimate
    assert grid.mean(post) == pytest.approx({k: float(v) for k, v in expected.items()}, abs=1e-12)
    assert len({i for i, _ in history}) > 1  # the staircase moved
