"""Observer screening (server/analysis/screening.py): each rule on small hand-made cases with known outcomes, the
BT.500 rule against sureal on sureal's datasets, and the simulated panel with planted bad observers."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
from pydantic import ValidationError

from server.analysis.screening import bt500, screen
from server.studies.screening import RULES, Screening
from tests.screening_sim import MEANT, PLAYBACK, panel
from tests.test_subject_model import dataset, sureal_run


def vote(sid: str, animation: str, test: str, score: int, index: int, *, choice: str | None = None,
         catch: bool = False, rt_ms: int = 5000, state: str = "completed") -> dict:
    """An export row; the reference is on the right, so the raw answer equals the score."""
    raw = {2: "left_much", 1: "left_slightly", 0: "equal", -1: "right_slightly", -2: "right_much"}
    # reference on the right: left = test, so left_much (+2 raw) is +2 for the test
    return {"session_id": sid, "trial_index": index, "practice": False, "catch": catch, "animation": animation,
            "reference_condition": "ref", "test_condition": "ref" if catch else test, "reference_side": "right",
            "test_side": "left", "choice": choice or raw[score], "score": score, "rt_ms": rt_ms,
            "session_state": state, "outcome": "completed"}


def scored(sid: str, scores: list[int], **kw) -> list[dict]:
    """One vote per comparison a0..aN (condition t) with the given scores."""
    return [vote(sid, f"a{i}", "t", s, i, **kw) for i, s in enumerate(scores)]


def test_config_defaults_all_and_errors():
    """The hand-made cases below test the rules with the standards' fixed thresholds (``thresholds = "fixed"``);
    the design-calibrated ones (the default) are tested in test_screening_design.py."""
    assert Screening().rules == ["catch"]  # today's behaviour
    assert Screening(rules="all").rules == list(RULES)
    s = Screening()
    assert (s.min_variance, s.z_limit, s.max_rejected_share, s.bt500_ratio, s.bt500_balance,
            s.max_correlation_threshold, s.max_fast_share) == (0.15, 3.29, 0.2, 0.05, 0.3, 0.7, 0.2)
    assert (s.thresholds, s.false_flag_rate, s.min_power) == ("design", 0.01, 0.9)
    for bad in ({"rules": ["catch", "psychic"]}, {"rules": "some"}, {"rules": ["fast", "fast"]},
                {"min_variance": -1}, {"threshold": 2}, {"correlation_method": "kendall"}):
        with pytest.raises(ValidationError):
            Screening.model_validate(bad)


def test_straight_lining_flags_the_same_answer_every_time_and_nothing_else():
    rows = (scored("same", [0] * 8) + scored("nearly", [0] * 7 + [1])  # variance 7/64 = 0.109 < 0.15
            + scored("varied", [0, 0, 0, 0, 0, 0, 1, -1]))  # 2/8 = 0.25
    got = screen(rows, Screening(rules=["straight_lining"], thresholds="fixed"))
    assert {s: r.flagged_by for s, r in got.items()} == {"same": ["straight_lining"], "nearly": ["straight_lining"],
                                                         "varied": []}
    assert got["same"].results["straight_lining"].value == 0
    assert got["nearly"].results["straight_lining"].value == pytest.approx(7 / 64)
    assert got["varied"].results["straight_lining"].threshold == 0.15


def test_straight_lining_reads_the_raw_answer_not_the_score():
    """Always 'left much better' is straight-lining even though the test side alternates (scores +2, -2)."""
    rows = [{**vote("left", f"a{i}", "t", 2, i), "reference_side": "left" if i % 2 else "right",
             "score": -2 if i % 2 else 2} for i in range(8)]
    got = screen(rows, Screening(rules=["straight_lining"], thresholds="fixed"))
    assert got["left"].flagged_by == ["straight_lining"]


def test_z_outlier_counts_votes_far_from_the_others():
    # Ten participants split between two neighbouring answers on every comparison (sd about 0.5); "odd" answers
    # the opposite on 2 of 6 comparisons (|z| about 7), "one_off" on 1 of 6.
    base = [2, 1, 0, -1, -2, 1]
    rows = []
    for k in range(10):
        rows += scored(f"p{k}", [b - 1 if k % 2 and b > -2 else (b + 1 if k % 2 else b) for b in base])
    rows += scored("odd", [-2, -2, 0, -1, -1, 1])
    rows += scored("one_off", [2, 1, 0, -1, 2, 1])
    got = screen(rows, Screening(rules=["z_outlier"], thresholds="fixed"))
    assert got["odd"].flagged_by == ["z_outlier"]
    assert got["odd"].results["z_outlier"].value == pytest.approx(2 / 6)
    assert got["one_off"].results["z_outlier"].value == pytest.approx(1 / 6)
    assert not got["one_off"].flagged_by
    assert all(got[f"p{k}"].results["z_outlier"].value == 0 for k in range(10))


def test_correlation_flags_the_inverted_participant_with_sureals_threshold():
    truth = [2, 1, 1, 0, -1, -2]
    rows = [*scored("a", truth), *scored("b", truth), *scored("c", [2, 1, 0, 0, -1, -2]),
            *scored("inv", [-t for t in truth])]
    got = screen(rows, Screening(rules=["correlation"], thresholds="fixed"))
    r = {s: got[s].results["correlation"].value for s in got}
    # by hand: a, b and c correlate with the others' means; inv at -1 (the others' means are monotone in truth)
    assert r["inv"] == pytest.approx(-np.corrcoef(truth, [(2 * t + c) / 3 for t, c in
                                                          zip(truth, [2, 1, 0, 0, -1, -2], strict=True)])[0, 1])
    values = np.array(list(r.values()))
    assert got["a"].results["correlation"].threshold == pytest.approx(min(0.7, values.mean() - values.std()))
    assert {s for s in got if got[s].flagged_by} == {"inv"}


def test_correlation_undefined_for_constant_answers_flags_nobody_and_needs_three_comparisons():
    truth = [2, 1, 0, -1]
    rows = scored("a", truth) + scored("b", truth) + scored("flat", [0, 0, 0, 0])
    got = screen(rows, Screening(rules=["correlation"], thresholds="fixed"))
    assert got["flat"].results["correlation"].value is None and not got["flat"].flagged_by
    two = screen(scored("a", [1, 2]) + scored("b", [2, 1]), Screening(rules=["correlation"], thresholds="fixed"))
    assert all(p.results["correlation"].value is None for p in two.values())


def test_catch_and_fast():
    rows = [*scored("ok", [1, 0, -1, 1, 2]), vote("ok", "a0", "", 1, 9, catch=True)]
    rows += [*scored("failed", [1, 0, -1, 1, 2]), vote("failed", "a0", "", -2, 9, catch=True)]
    rows += scored("fast", [1, 0, -1, 1, 2], rt_ms=900)  # every vote before the 4 s playback ended
    rows += scored("active", [2, 2, 2], state="active")  # not finished: not screened at all
    playback = {(f"a{i}", "ref", "t"): 4000.0 for i in range(5)}
    got = screen(rows, Screening(rules=["catch", "fast"], thresholds="fixed"), catch_failures_allowed=0,
                 playback_ms=playback)
    assert set(got) == {"ok", "failed", "fast"}
    assert got["failed"].flagged_by == ["catch"] and got["failed"].results["catch"].value == 1
    assert got["fast"].flagged_by == ["fast"] and got["fast"].results["fast"].value == 1.0
    assert got["fast"].results["catch"].value is None  # no catch trial: nothing to fail
    assert got["ok"].flagged_by == []
    allowed = screen(rows, Screening(rules=["catch"], thresholds="fixed"), catch_failures_allowed=1)
    assert allowed["failed"].flagged_by == []


@pytest.mark.parametrize("name", ["NFLX_dataset_public_raw", "VQEGHD3_dataset_raw"])
def test_bt500_is_sureals_subject_rejection(name):
    x, content = dataset(name)
    rejected, first, second = bt500(x)
    theirs = sureal_run("SubjrejMosModel", x, content)
    assert list(rejected) == list(theirs["observer_rejected"])
    np.testing.assert_allclose(first, theirs["observer_rejected_1st_stats"], atol=1e-12)
    np.testing.assert_allclose(second, theirs["observer_rejected_2nd_stats"], atol=1e-12, equal_nan=True)
    if name == "NFLX_dataset_public_raw":  # sureal's verdict on its main dataset: only subject 2 is rejected
        assert np.flatnonzero(rejected).tolist() == [2]


def test_bt500_rejects_nobody_when_it_would_reject_everybody():
    x = np.array([[[1.0], [5.0]], [[5.0], [1.0]], [[1.0], [5.0]]])  # two subjects, always opposite
    rejected, _, _ = bt500(x, ratio=0.0, balance=1.0)
    assert not rejected.any()


def test_planted_bad_observers_are_flagged_by_their_rule_and_good_ones_are_not():
    """The issue's panel: 36 good observers and 4 planted bad ones (seed 0, the first we tried)."""
    rows, kinds = panel(seed=0)
    got = screen(rows, Screening(rules="all"), catch_failures_allowed=0, playback_ms=PLAYBACK)
    for sid, kind in kinds.items():
        if kind != "good":
            assert MEANT[kind] in got[sid].flagged_by, (kind, got[sid].as_dict())
    good_flagged = [s for s, k in kinds.items() if k == "good" and got[s].flagged_by]
    assert len(good_flagged) <= 1, [got[s].as_dict() for s in good_flagged]


def test_planted_bad_observers_over_twenty_panels():
    """Robustness over seeds 0-19: the bad ones are caught by their rule in (nearly) every panel, and good ones
    are flagged at most once per panel on average (measured over 100 seeds: 0 in 80, 1 in 15, 2 in 4, 3 in 1,
    every false flag by bt500; one random observer of 100 escaped the correlation rule, r = 0.68)."""
    missed, false_flags = Counter(), []
    for seed in range(20):
        rows, kinds = panel(seed)
        # the standards' thresholds (the figures above); the design-calibrated ones: test_screening_design.py
        fixed = Screening(rules=[r for r in RULES if r != "disagreement"], thresholds="fixed")
        got = screen(rows, fixed, catch_failures_allowed=0, playback_ms=PLAYBACK)
        missed.update(k for s, k in kinds.items() if k != "good" and MEANT[k] not in got[s].flagged_by)
        false_flags.append(sum(bool(got[s].flagged_by) for s, k in kinds.items() if k == "good"))
    assert sum(missed.values()) <= 1, missed
    assert np.mean(false_flags) <= 1 and max(false_flags) <= 3, false_flags
