"""Adaptive designs, issue 36: only the votes the results count steer the design (finding 3), and the results'
adaptive rounds cost the same per vote however many sessions came before (finding 4)."""

from __future__ import annotations

import random
import secrets
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from scipy import optimize
from sqlalchemy import event

from server.analysis import adaptive
from server.analysis.adaptive import information_gain, next_batch, posterior
from server.analysis.ranking import GradedComparison, symmetric_cuts, vote_log_likelihood
from server.analysis.simulate import simulate
from server.participants import service
from server.participants.assign import session_batches, study_votes
from server.participants.rows import screened_rows
from server.research.results import study_results
from server.studies.design import Design
from server.studies.scale import CHOICES
from tests.server_fixtures import make_study

CONDITIONS = ["hybrid0", "hybrid1", "hybrid2"]  # with the reference keyframe: 4 conditions, 6 pairs
QUALITY = {"keyframe": 0.0, "hybrid0": -0.7, "hybrid1": -1.4, "hybrid2": -2.1}  # logit units, keyframe best
SCREENING = {"rules": ["catch", "fast"]}  # the bots answer in 0.1 s, before one playback (1.33 s) has ended
TOLERANCE = 1e-6  # the posterior from counts against today's per-vote fit: measured differences were <= 2e-8


def _design() -> Design:
    return Design(mode="adaptive", conditions=CONDITIONS, animations=["walk", "run"], catch_trials=1)


def _choice(trial, key: str) -> str:
    """An honest observer's answer to ``trial``, a pure function of ``key`` and what the trial shows (not of its
    id or position, so two studies with the same sessions get the same answers)."""
    c = trial.comparison
    if c.test_id == c.reference_id:
        return "equal"
    rng = random.Random(f"{key}/{c.reference.animation}/{c.reference.condition}/{c.test.condition}/"
                        f"{trial.reference_side}")
    score = max(-2, min(2, round(QUALITY[c.test.condition] - QUALITY[c.reference.condition] + rng.gauss(0, 0.8))))
    raw = score if trial.reference_side == "right" else -score  # left = +2
    return CHOICES[2 - raw]


def _session(db, study, monkeypatch, seed: int, answer, rt_ms: int = 4000, pilot: bool = False, trials=None):
    """A session started with ``seed``, answering ``trials`` (all by default) with ``answer(trial)``."""
    with monkeypatch.context() as patch:
        patch.setattr(secrets, "randbits", lambda _bits: seed)
        ps = service.start_session(db, study, None, pilot=pilot).session
    for trial in ps.trials[:trials]:
        service.cast_vote(db, ps, trial, answer(trial), rt_ms, f"k{trial.id}", {})
    return ps


def _pairs(ps) -> list[tuple[str, str, str]]:
    return sorted({(t.comparison.reference.animation, t.comparison.reference.condition, t.comparison.test.condition)
                   for t in ps.trials if t.comparison.test_id != t.comparison.reference_id})


# --- finding 3 -------------------------------------------------------------------------------------------------


@pytest.mark.slow  # tens of seconds (the parallel run's slowest; still run by `make test`)
def test_bots_pilots_and_screened_out_sessions_do_not_steer_the_design(db, monkeypatch):
    """Issue 36's reproduction: after 40 bot sessions (every answer "left much better", each in 0.1 s: screened out
    by the catch and fast rules) and 10 pilot sessions (answering the opposite of the real observers), the next
    real participants get exactly the pairs they get in the same study without them, seed for seed."""
    clean = make_study(db, _design(), slug="clean", screening=SCREENING)
    dirty = make_study(db, _design(), slug="dirty", screening=SCREENING)
    real = []
    for k in range(4):
        real.append([_session(db, s, monkeypatch, 1000 + k, lambda t, k=k: _choice(t, f"real{k}"))
                     for s in (clean, dirty)])
    for k in range(40):
        _session(db, dirty, monkeypatch, 5000 + k, lambda _t: "left_much", rt_ms=100)
    for k in range(10):
        _session(db, dirty, monkeypatch, 6000 + k, lambda t: CHOICES[4 - CHOICES.index(_choice(t, "pilot"))],
                 pilot=True)
    for k in range(12):
        real.append([_session(db, s, monkeypatch, 2000 + k, lambda t, k=k: _choice(t, f"later{k}"))
                     for s in (clean, dirty)])
    for clean_ps, dirty_ps in real:
        assert _pairs(clean_ps) == _pairs(dirty_ps)
    # The design did adapt: the later participants do not all get the first participant's star.
    assert len({tuple(_pairs(ps)) for ps, _ in real}) > 1
    # The bots and the pilot sessions are what the results leave out: no vote of theirs is counted.
    from server.analysis.statistics import counted  # (imported here: the test runs on the code before issue 36)

    rows, records = screened_rows(db, dirty)
    assert sum(r.screened_out for r in records.values()) == 40
    assert {r["session_id"] for r in rows if counted(r)} == {ps.id for _, ps in real}
    # The dashboard's rounds of the real sessions show the same votes and information in both studies.
    by_session = {r.session_id: r for r in session_batches(db, dirty)}
    for clean_round, (_, dirty_ps) in zip(session_batches(db, clean), real, strict=True):
        dirty_round = by_session[dirty_ps.id]
        assert dirty_round.votes_before == clean_round.votes_before
        assert dirty_round.information == pytest.approx(clean_round.information, abs=TOLERANCE)


def test_the_design_counts_exactly_the_votes_the_results_count(db, monkeypatch):
    """One definition (``statistics.counted``): the design's votes are the results' counted rows, with a finished
    participant, an unfinished one (counted, as the results count them), one screened out by the catch trial, one
    by the fast rule, and a pilot session."""
    from server.analysis.statistics import counted
    from server.participants.assign import counted_votes

    study = make_study(db, _design(), slug="mixed", screening=SCREENING)
    _session(db, study, monkeypatch, 1, lambda t: _choice(t, "a"))
    _session(db, study, monkeypatch, 2, lambda t: _choice(t, "b"), trials=5)  # unfinished
    _session(db, study, monkeypatch, 3, lambda _t: "left_much")  # fails the catch trial
    _session(db, study, monkeypatch, 4, lambda t: _choice(t, "c"), rt_ms=100)  # fast
    _session(db, study, monkeypatch, 5, lambda t: _choice(t, "d"), pilot=True)
    rows, _ = screened_rows(db, study)
    expected = Counter((r["session_id"], r["animation"], r["reference_condition"], r["test_condition"], r["score"])
                       for r in rows if counted(r))
    got = Counter((v.vote.participant, v.animation, v.vote.reference, v.vote.test, v.vote.score)
                  for v in counted_votes(db, study))
    assert got == expected and len({k[0] for k in got}) == 2
    # The same when the finished sessions are read with all the others (as a new server process reads many).
    from server.participants import assign

    assign._FINISHED.clear()
    monkeypatch.setattr(assign, "NAMED_SESSIONS", 0)
    assert Counter((v.vote.participant, v.animation, v.vote.reference, v.vote.test, v.vote.score)
                   for v in counted_votes(db, study)) == expected
    assert sum(len(v) for v in study_votes(db, study).values()) == sum(expected.values())


# --- finding 4 -------------------------------------------------------------------------------------------------


def _work(db, monkeypatch, study) -> tuple[int, int]:
    """(posterior fits of ``server.analysis.adaptive``, SQL statements) of one results request."""
    fits, statements = [], []
    minimize = optimize.minimize

    def counting(*args, **kwargs):
        if sys._getframe(1).f_globals["__name__"] == adaptive.__name__:
            fits.append(1)
        return minimize(*args, **kwargs)

    def count(*_args):
        statements.append(1)

    engine = db.get_bind().engine
    event.listen(engine, "before_cursor_execute", count)
    try:
        with monkeypatch.context() as patch:
            patch.setattr(optimize, "minimize", counting)
            study_results(db, study, Path("/nonexistent/benchmark.json"))
    finally:
        event.remove(engine, "before_cursor_execute", count)
    return len(fits), len(statements)


@pytest.mark.slow  # tens of seconds (the parallel run's slowest; still run by `make test`)
def test_results_work_per_vote_does_not_grow_with_the_sessions(db, monkeypatch):
    """The results request after one more participant (the dashboard polling while votes arrive) refits the
    posterior and queries the database as often with 16 sessions before it as with 8: today it refitted every
    round (one fit per session and animation) and queried the votes once per session."""
    study = make_study(db, _design(), slug="grow")
    work = []
    seed = 0
    for sessions in (8, 16):
        while len(session_batches(db, study)) < sessions:
            seed += 1
            _session(db, study, monkeypatch, seed, lambda t, s=seed: _choice(t, f"p{s}"))
        _work(db, monkeypatch, study)  # the dashboard's last request
        seed += 1
        _session(db, study, monkeypatch, seed, lambda t, s=seed: _choice(t, f"p{s}"), trials=3)  # one more arrives
        work.append(_work(db, monkeypatch, study))
    (fits_small, statements_small), (fits_large, statements_large) = work
    assert fits_large == fits_small <= 2  # the new round, one fit per animation
    assert statements_large == statements_small


def _per_vote_posterior(votes: list[GradedComparison], conditions: list[str]) -> adaptive.Posterior:
    """The posterior as it was computed before issue 36: the fit summed over every vote (the reference the counts'
    fit is held against)."""
    index = {c: i for i, c in enumerate(conditions)}
    used = [v for v in votes if v.reference != v.test]
    n = len(conditions)
    x = np.zeros((len(used), n))
    for row, v in enumerate(used):
        x[row, index[v.test]] += 1
        x[row, index[v.reference]] -= 1
    y = np.array([v.score + 2 for v in used], dtype=int)
    prior_mean = np.concatenate([np.zeros(n), adaptive.CUT_PRIOR])
    prior_precision = np.concatenate([np.full(n, 1 / adaptive.PRIOR_SD**2), np.ones(adaptive.CUT_PRIOR.size)])

    def objective(params):
        diff = params - prior_mean
        value, grad = 0.5 * float(diff @ (prior_precision * diff)), prior_precision * diff
        if y.size:
            loglik, per_vote = vote_log_likelihood(params, x, y, False, n, "logit")
            value, grad = value - float(loglik.sum()), grad - per_vote.sum(axis=0)
        return value, grad

    opt = optimize.minimize(objective, prior_mean, jac=True, method="BFGS", options={"gtol": 1e-7})
    mean = opt.x[:n] - opt.x[0]
    cuts, _ = symmetric_cuts(opt.x[n:], False)
    precision = np.eye(n) / adaptive.PRIOR_SD**2
    if y.size:
        precision = precision + (x * adaptive.answer_information(x @ mean, cuts)[:, None]).T @ x
    return adaptive.Posterior(tuple(conditions), mean, np.linalg.inv(precision), cuts, int(y.size))


def test_posterior_from_counts_equals_the_per_vote_fit():
    """On simulated studies of six conditions (1 to 40 participants, all pairs): the same values, covariance and
    cut points to ``TOLERANCE``, and the same batches."""
    conditions = ["keyframe", "a", "b", "c", "d", "e"]
    design = Design(mode="all-pairs", reference="keyframe", conditions=conditions[1:], animations=["walk"])
    for seed in range(3):
        for participants in (1, 5, 40):
            votes = simulate(design, {c: 0.5 * i for i, c in enumerate(conditions)}, participants,
                             seed=seed).votes["walk"]
            new, old = posterior(votes, conditions), _per_vote_posterior(votes, conditions)
            assert new.n_votes == old.n_votes == len(votes)
            for a, b in ((new.mean, old.mean), (new.cov, old.cov), (new.cuts, old.cuts)):
                np.testing.assert_allclose(a, b, rtol=0, atol=TOLERANCE)
            for s in range(3):
                assert next_batch(new, s).pairs == next_batch(old, s).pairs
                assert adaptive.information_tree(new, s).pairs == adaptive.information_tree(old, s).pairs


def test_results_rounds_equal_todays_computation(db, monkeypatch):
    """The results' adaptive rounds (one pass, counts remembered) against today's computation: per session the
    counted votes answered before it, fitted vote by vote, and the information of its pairs."""
    study = make_study(db, _design(), slug="rounds")
    for k in range(10):
        _session(db, study, monkeypatch, 300 + k, lambda t, k=k: _choice(t, f"r{k}"))
    rounds = study_results(db, study, Path("/nonexistent/benchmark.json"))["adaptive_rounds"]
    conditions = _design().all_conditions()
    index = {c: i for i, c in enumerate(conditions)}
    for got, r in zip(rounds, session_batches(db, study), strict=True):
        votes = study_votes(db, study, before=r.started_at)
        assert got["votes_before"] == sum(len(v) for v in votes.values())
        for animation, pairs in got["pairs"].items():
            post = _per_vote_posterior(votes.get(animation, []), conditions)
            expected = sum(information_gain(post, index[x], index[y]) for x, y in pairs)
            assert got["information"][animation] == pytest.approx(expected, abs=TOLERANCE)


def test_scale_bootstrap_from_counts_equals_the_per_vote_resamples():
    """The scale's bootstrap (the rest of a results request that grew with the votes) fits each resample over the
    cells (pair, answer) with counts; today's fitted every resampled vote.  Same intervals to ``TOLERANCE``."""
    from server.analysis import interval_scale

    conditions = ["keyframe", "a", "b", "c", "d", "e"]
    design = Design(mode="all-pairs", reference="keyframe", conditions=conditions[1:], animations=["walk"])
    votes = simulate(design, {c: 0.5 * i for i, c in enumerate(conditions)}, 30, seed=4).votes["walk"]
    got = interval_scale.animation_scale("walk", votes, conditions, n_boot=40)
    used = [v for v in votes if v.reference != v.test]
    people = list(dict.fromkeys(v.participant for v in used))
    x, y = interval_scale._design(used, conditions)
    rows = {p: [i for i, v in enumerate(used) if v.participant == p] for p in people}
    start = interval_scale._ridge(x, y, None, np.ones(len(y)))
    samples = np.zeros((40, len(conditions)))
    for b, draw in enumerate(interval_scale.bootstrap_draws(people, 40, 0)):
        take = np.concatenate([rows[people[i]] for i in draw])
        samples[b, 1:] = interval_scale._ridge(x[take], y[take], start, np.ones(take.size))[: len(conditions) - 1]
    low, high = np.percentile(samples, [2.5, 97.5], axis=0)
    for i, interval in enumerate(got.ci95[1:], start=1):
        assert interval == pytest.approx((low[i], high[i]), abs=TOLERANCE)
