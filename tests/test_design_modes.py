"""Design modes (issue 27): all-pairs, incomplete and adaptive studies through the real session code."""

from __future__ import annotations

import itertools
from collections import Counter
from pathlib import Path

import pytest
from pydantic import ValidationError

from server.participants.assign import session_batches
from server.participants.service import start_session
from server.research.export import export_rows
from server.studies.assign import pair_comparisons
from server.studies.design import Design
from tests.server_fixtures import answer_all, make_study, start
from tests.test_design import _old_trial_order

FOUR = ["hybrid0", "hybrid1", "hybrid2"]  # with the reference keyframe: 4 conditions, 6 pairs


def _design(mode: str, **fields: object) -> Design:
    return Design(mode=mode, conditions=FOUR, animations=["walk", "run"], **fields)


def _shown(ps) -> Counter:
    return Counter((t.comparison.reference.animation, t.comparison.reference.condition, t.comparison.test.condition,
                    t.reference_side) for t in ps.trials if not t.practice)


def test_design_validation():
    assert _design("all-pairs").trials_total() == 2 * 6 * 2
    assert _design("incomplete").trials_total() == 2 * 3 * 2  # default N - 1 pairs per animation
    assert _design("incomplete", pairs_per_session=4, repeats=2).trials_total() == 2 * 4 * 2 * 2
    assert _design("adaptive").trials_total() == 2 * 3 * 2
    assert Design().mode == "reference" and Design().trials_total() == 16
    with pytest.raises(ValidationError, match="incomplete"):
        _design("all-pairs", pairs_per_session=2)
    with pytest.raises(ValidationError, match="exceeds the 6 pairs"):
        _design("incomplete", pairs_per_session=7)
    with pytest.raises(ValidationError, match="more than 2600"):
        Design(mode="all-pairs", conditions=[f"c{i}" for i in range(16)], animations=["a", "b"], repeats=5)
    with pytest.raises(ValidationError, match="twice in a row"):  # one pair per session: always repeated
        Design(mode="adaptive", conditions=["b"], animations=["walk"])
    with pytest.raises(ValidationError, match='aim is for mode = "adaptive" only'):
        _design("all-pairs", aim="order")
    with pytest.raises(ValidationError, match="aim"):
        _design("adaptive", aim="shape")


def test_reference_sessions_keep_the_old_trials(db):
    study = make_study(db)
    for _ in range(20):
        ps = start_session(db, study, None).session
        ids = sorted(c.id for c in study.comparisons)
        from server.studies.design import ComparisonIds
        old = _old_trial_order(ComparisonIds(ids), 1, ps.seed)
        assert [(t.comparison_id, t.reference_side) for t in ps.trials] == [
            (t.comparison_id, t.reference_side) for t in old]


def test_all_pairs_shows_every_pair_on_both_sides(db):
    study = make_study(db, _design("all-pairs"), slug="allpairs")
    assert len(pair_comparisons(study)) == 12
    ps = start_session(db, study, None).session
    shown = _shown(ps)
    pairs = list(itertools.combinations(["keyframe", *FOUR], 2))
    assert shown == Counter({(a, x, y, s): 1 for a in ("walk", "run") for x, y in pairs for s in ("left", "right")})
    assert all(a.comparison_id != b.comparison_id for a, b in itertools.pairwise(ps.trials))


def test_incomplete_balances_pairs_over_participants(db):
    study = make_study(db, _design("incomplete", pairs_per_session=4), slug="incomplete")
    totals = Counter()
    for _ in range(3):  # 3 sessions x 4 pairs = 2 x 6 pairs per animation
        shown = _shown(start_session(db, study, None).session)
        assert len({k[:3] for k in shown}) == 8 and set(shown.values()) == {1}
        totals.update({k[:3] for k in shown})
    assert len(totals) == 12 and set(totals.values()) == {2}


def test_adaptive_sessions_are_spanning_trees_reproducible_from_the_vote_log(client, db):
    study = make_study(db, _design("adaptive", catch_trials=1), slug="adaptive")
    conditions = ["keyframe", *FOUR]
    for i in range(4):
        sid, headers = start(client, "adaptive")
        # A consistent observer: the later condition of the list is better, much better for far-apart ones.
        trials = answer_all(client, sid, headers, "left_much" if i % 2 else "right_slightly")
        assert len(trials) == 2 * 3 * 2 + 1
    rounds = session_batches(db, study)
    # Catch votes are not test votes, and "left_much" on the catch trial fails it: the second participant is
    # screened out (the study's catch rule), so neither the results nor the design count their votes.
    assert [r.votes_before for r in rounds] == [0, 13 - 1, 12, 2 * 12]
    from server.analysis.adaptive import adaptive_batches
    from server.participants.assign import study_votes
    from server.participants.models import ParticipantSession
    design = Design.model_validate(study.design)
    for r in rounds:
        ps = db.get(ParticipantSession, r.session_id)
        shown = {k[:3] for k in _shown(ps)}
        # What was shown is what the design code chooses again from the stored seed and the votes before it.
        again = adaptive_batches(design, study_votes(db, study, before=ps.created_at), ps.seed)
        for animation in ("walk", "run"):
            edges = [(x, y) for a, x, y in shown if a == animation and x != y]
            assert sorted(edges) == sorted((conditions[i], conditions[j]) for i, j in again[animation].pairs)
            assert sorted(edges) == sorted(r.pairs[animation])  # the dashboard's rounds show what was shown
            # N - 1 edges linking all N conditions: a spanning tree
            linked, grew = {conditions[0]}, True
            while grew:
                grew = False
                for x, y in edges:
                    if (x in linked) != (y in linked):
                        linked |= {x, y}
                        grew = True
            assert len(edges) == 3 and linked == set(conditions)
            assert r.information[animation] > 0
    rows = list(export_rows(db, study))
    assert {r["design_mode"] for r in rows} == {"adaptive"}
    for r in rows:
        left, right = ((r["reference_condition"], r["test_condition"]) if r["reference_side"] == "left"
                       else (r["test_condition"], r["reference_condition"]))
        assert (r["left_condition"], r["right_condition"]) == (left, right)


def test_adaptive_choice_depends_on_the_votes(db):
    """Equal seeds, different vote logs: the batch follows the information, not a fixed pattern."""
    from server.analysis.adaptive import next_batch, posterior
    from server.analysis.ranking import GradedComparison

    conditions = ["keyframe", *FOUR]
    empty = next_batch(posterior([], conditions), seed=5)
    # Many votes on keyframe-hybrid0 and hybrid1-hybrid2: those pairs are known, the others are not.  The answers
    # vary (0, 1, 1, 2 in turn) as people's do: had every vote been the same answer, the ordinal model could not
    # place the cut points and those two differences would stay as uncertain as before any vote.
    votes = [GradedComparison(str(p), x, y, s * (0, 1, 1, 2)[p % 4]) for p in range(30)
             for x, y, s in (("keyframe", "hybrid0", 1), ("hybrid1", "hybrid2", -1))]
    informed = next_batch(posterior(votes, conditions), seed=5)
    assert (0, 1) not in informed.pairs and (2, 3) not in informed.pairs
    assert informed != empty or (0, 1) not in empty.pairs
    assert next_batch(posterior(votes, conditions), seed=5) == informed  # reproducible


def test_adaptive_batches_aim_at_the_values_against_the_reference():
    """The tree is chosen for what the results report, each condition against the reference: before any vote that
    is every condition against it (ASAP's information-gain tree was any tree the seed picked); with conditions far
    apart, a chain of neighbours, never a pair whose answer is sure to be "much better"."""
    from server.analysis.adaptive import next_batch, posterior
    from server.analysis.simulate import simulate

    conditions = ["keyframe", *FOUR]
    for seed in range(5):
        assert next_batch(posterior([], conditions), seed).pairs == ((0, 1), (0, 2), (0, 3))
    votes = simulate(Design(mode="all-pairs", reference="keyframe", conditions=FOUR, animations=["walk"]),
                     {c: 12.0 * i for i, c in enumerate(conditions)}, 10, seed=3).votes["walk"]
    for seed in range(3):
        assert next_batch(posterior(votes, conditions), seed).pairs == ((0, 1), (1, 2), (2, 3))


def test_aim_order_takes_asaps_information_tree():
    """``aim = "order"`` chooses the batches by ASAP's expected information gain about the whole scale: before any
    vote every pair tells the same, so the seed picks any tree (not always the star around the reference that the
    default aim takes); with conditions far apart it links neighbours, as the default does."""
    from server.analysis.adaptive import adaptive_batches
    from server.analysis.simulate import simulate

    default, order = _design("adaptive"), _design("adaptive", aim="order")
    trees = {adaptive_batches(order, {}, seed)["walk"].pairs for seed in range(8)}
    assert {adaptive_batches(default, {}, seed)["walk"].pairs for seed in range(8)} == {((0, 1), (0, 2), (0, 3))}
    assert len(trees) > 1 and trees != {((0, 1), (0, 2), (0, 3))}
    conditions = order.all_conditions()
    votes = simulate(Design(mode="all-pairs", reference="keyframe", conditions=FOUR, animations=["walk"]),
                     {c: 12.0 * i for i, c in enumerate(conditions)}, 10, seed=3).votes
    assert adaptive_batches(order, votes, 0)["walk"].pairs == ((0, 1), (1, 2), (2, 3))


def test_results_show_the_scale_pair_counts_and_adaptive_rounds(client, db, researcher_headers):
    make_study(db, _design("adaptive"), slug="adaptive")
    for i in range(3):
        sid, headers = start(client, "adaptive")
        answer_all(client, sid, headers, ("right_much", "right_slightly", "left_slightly")[i])
    res = client.get("/api/v1/studies/adaptive/results", headers=researcher_headers)
    assert res.status_code == 200, res.text
    body = res.json()
    assert body["overview"]["design_mode"] == "adaptive"
    assert [s["animation"] for s in body["scale"]] == ["run", "walk"]
    walk = body["scale"][1]
    assert walk["conditions"] == ["keyframe", *FOUR] and walk["value"][0] == 0
    assert sum(map(sum, walk["pair_counts"])) == 2 * 3 * 3 * 2  # 3 sessions x 3 pairs x 2 sides, both halves
    assert [r["round"] for r in body["adaptive_rounds"]] == [1, 2, 3]
    assert [r["votes_before"] for r in body["adaptive_rounds"]] == [0, 12, 24]
    # For the thesis design the scale's values are the ranking's (one model, one number).
    thesis = make_study(db)
    sid, headers = start(client)
    answer_all(client, sid, headers, "left_slightly")
    sid, headers = start(client)
    answer_all(client, sid, headers, "right_slightly")
    body = client.get(f"/api/v1/studies/{thesis.slug}/results", headers=researcher_headers).json()
    assert body["adaptive_rounds"] is None and body["overview"]["design_mode"] == "reference"
    for scale, ranking in zip(body["scale"], body["rankings"], strict=True):
        values = {c["condition"]: c["value"] for c in ranking["conditions"]}
        assert dict(zip(scale["conditions"], scale["value"], strict=True)) == pytest.approx(values)


def test_a_draft_stored_before_the_modes_can_still_be_edited(db):
    """Designs stored before issue 27 have no mode: they read as reference designs and editing another section of
    such a draft is not taken for a design change."""
    from server.participants.service import update_study
    from server.studies.models import StudyState
    from server.studies.service import definition

    study = make_study(db, state=StudyState.draft)
    study.design = {k: v for k, v in study.design.items() if k not in ("mode", "pairs_per_session")}
    db.commit()
    assert definition(study).design.mode == "reference"
    update_study(db, study, {"title": "Renamed"})  # no render manifest given: a design change would be refused
    assert study.title == "Renamed"


def test_simulate_and_plan_commands(tmp_path, capsys):
    from server import cli

    study = tmp_path / "s.toml"
    text = (Path(__file__).resolve().parents[1] / "studies" / "adaptive-walk.toml").read_text(encoding="utf-8")
    study.write_text(text.replace('mode = "adaptive"', 'mode = "all-pairs"').replace('aim = "order"', "").replace(
        '"hybrid0", "hybrid_ik0", "hybrid_c2_0", "reduced2", "quantized12"', '"hybrid0", "reduced2"'),
        encoding="utf-8")
    truth = tmp_path / "truth.toml"
    truth.write_text("keyframe = 0\nhybrid0 = -1.5\nreduced2 = -3\n", encoding="utf-8")
    assert cli.main(["study", "simulate", str(study), "--participants", "12", "--seeds", "3",
                     "--truth", str(truth)]) == 0
    out = capsys.readouterr()
    assert "truth: keyframe 0, hybrid0 -1.5, reduced2 -3" in out.out
    assert "3 simulated studies: 72 trials per study" in out.out  # 12 participants x 3 pairs x 2 sides
    assert "simulated study 3 of 3" in out.err
    truth.write_text("keyframe = 0\nhybrid0 = true\n", encoding="utf-8")
    assert cli.main(["study", "simulate", str(study), "--participants", "2", "--truth", str(truth)]) == 2
    err = capsys.readouterr().err
    assert "missing: reduced2" in err and "not a number: hybrid0" in err
    assert cli.main(["study", "plan", str(study), "--effect", "3", "--seeds", "4"]) == 0
    out = capsys.readouterr()
    assert "participants (" in out.out and "power" in out.err


def test_batches_are_planned_with_the_expected_information_of_the_pairs_shown():
    """The covariance the batches are planned with is the inverse of the prior precision plus, per vote, the
    expected Fisher information of one five-point answer at the fitted difference: checked against the answer
    probabilities of the logistic model differentiated numerically (scipy's logistic, not the module's code)."""
    import numpy as np
    from scipy import stats

    from server.analysis.adaptive import PRIOR_SD, posterior
    from server.analysis.ranking import GradedComparison

    answers = (2, 1, 1, 0, 1, 2, 0, 1) * 5  # 40 answers to one pair, the second mostly better
    post = posterior([GradedComparison(str(i), "a", "b", s) for i, s in enumerate(answers)], ["a", "b", "c"])
    delta, cuts = post.mean[1] - post.mean[0], post.cuts

    def probabilities(d: float) -> np.ndarray:
        return np.diff(np.concatenate([[0.0], stats.logistic.cdf(cuts - d), [1.0]]))

    h = 1e-5
    slope = (probabilities(delta + h) - probabilities(delta - h)) / (2 * h)
    info = float((slope**2 / probabilities(delta)).sum())
    precision = np.eye(3) / PRIOR_SD**2
    precision[:2, :2] += len(answers) * info * np.array([[1.0, -1.0], [-1.0, 1.0]])
    assert np.allclose(post.cov, np.linalg.inv(precision), rtol=1e-6, atol=1e-9)
    # The condition without a vote keeps the prior's variance; the pair's difference is far surer than that.
    assert abs(post.cov[2, 2] - PRIOR_SD**2) < 1e-9
    assert post.cov[0, 0] + post.cov[1, 1] - 2 * post.cov[0, 1] < 0.2


def test_the_bench_oracle_plans_on_the_true_values_with_the_same_covariance():
    """``known_posterior`` (what the design bench's oracle plans on) is the truth with the covariance the
    posterior would have there: checked against scipy's logistic differentiated numerically at the true
    difference, and equal to the posterior's own covariance when given the posterior's values and cuts."""
    import numpy as np
    from scipy import stats

    from server.analysis.adaptive import PRIOR_SD, known_posterior, posterior
    from server.analysis.ranking import GradedComparison

    votes = [GradedComparison(str(i), "a", "b", s) for i, s in enumerate((2, 1, 1, 0, 1, 2, 0, 1) * 5)]
    cuts = np.array([-2.0, -0.5, 0.5, 2.0])
    known = known_posterior(votes, ["a", "b", "c"], values={"a": 1.0, "b": 4.0, "c": -1.0}, cuts=cuts)
    assert np.allclose(known.mean, [0.0, 3.0, -2.0]) and np.array_equal(known.cuts, cuts) and known.n_votes == 40

    def probabilities(d: float) -> np.ndarray:
        return np.diff(np.concatenate([[0.0], stats.logistic.cdf(cuts - d), [1.0]]))

    h = 1e-5
    slope = (probabilities(3.0 + h) - probabilities(3.0 - h)) / (2 * h)
    precision = np.eye(3) / PRIOR_SD**2
    precision[:2, :2] += 40 * float((slope**2 / probabilities(3.0)).sum()) * np.array([[1.0, -1.0], [-1.0, 1.0]])
    assert np.allclose(known.cov, np.linalg.inv(precision), rtol=1e-6, atol=1e-9)

    post = posterior(votes, ["a", "b", "c"])
    same = known_posterior(votes, ["a", "b", "c"], values=dict(zip("abc", post.mean, strict=True)), cuts=post.cuts)
    assert np.allclose(same.cov, post.cov, rtol=1e-12, atol=1e-15)
