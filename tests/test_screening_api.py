"""Screening through the study file, the database, the exports and the results (issue 28)."""

from __future__ import annotations

import csv
import io
import random
from collections import defaultdict

import pytest

from server.participants import service
from server.studies.design import Design
from server.studies.service import EXPORT_COLUMNS
from server.studies.studyfile import StudyFileError, parse_study_text
from tests.server_fixtures import make_study, seeded_sessions

# The standards' fixed thresholds: six participants are too few for design-calibrated ones (then the rules say
# "too little data"; tests/test_screening_design.py).
RULES = {"rules": ["catch", "straight_lining", "fast"], "thresholds": "fixed"}


def run_panel(db, study, kinds: dict[str, str], seeds: list[int] | None = None) -> dict[str, str]:
    """Sessions answering every trial: ``good`` (varied answers, slow enough), ``straight`` (always 'equal'),
    ``fast`` (varied, 200 ms: before the 1.33 s clips end), ``careless`` (always 'left much': fails catch trials).
    Returns session id -> kind.

    Each session's trial order and sides come from its seed (`secrets.randbits` in the service): ``seeds`` in
    order, or drawn from a seeded generator.  Left to chance, the good participants' data made the subject model
    stop short of converging or run off (test_subject_model) in about 1 panel in 370 (a simulation of 3,000)."""
    out = {}
    varied = ["left_slightly", "equal", "right_slightly", "right_much", "left_much", "equal"]
    with seeded_sessions(random.Random("screening/sessions"), seeds or ()):
        for name, kind in kinds.items():
            ps = service.start_session(db, study, None).session
            out[ps.id] = kind
            for trial in ps.trials:
                if trial.comparison.kind == "catch":
                    choice = "left_much" if kind == "careless" else "equal"
                else:
                    choice = {"straight": "equal", "careless": "left_much"}.get(kind,
                                                                              varied[trial.index % len(varied)])
                service.cast_vote(db, ps, trial, choice, 200 if kind == "fast" else 2500, f"{name}-{trial.id}", {})
    return out


def export(client, headers, query: str = "") -> list[dict]:
    r = client.get(f"/api/v1/studies/thesis/export.csv{query}", headers=headers)
    assert r.status_code == 200, r.text
    return list(csv.DictReader(io.StringIO(r.text)))


def test_rules_flag_in_the_export_and_the_results_with_and_without_screening(client, db, researcher_headers):
    study = make_study(db, Design(catch_trials=2), screening=RULES)
    kinds = run_panel(db, study, {"g1": "good", "g2": "good", "g3": "good", "s": "straight", "f": "fast",
                                  "c": "careless"})
    rows = export(client, researcher_headers)
    assert {"screened_by", "pilot"} <= set(rows[0])
    per = defaultdict(set)
    for r in rows:
        per[kinds[r["session_id"]]].add((r["outcome"], r["screened_by"], r["pilot"]))
    assert per["good"] == {("completed", "", "false")}
    assert per["straight"] == {("screened_out", "straight_lining", "false")}
    assert per["fast"] == {("screened_out", "fast", "false")}
    assert per["careless"] == {("screened_out", "catch;straight_lining", "false")}

    results = client.get("/api/v1/studies/thesis/results", headers=researcher_headers).json()
    assert results["participants"]["completed"] == 6 and results["participants"]["screened_out"] == 3
    screening = results["screening"]
    assert screening["rules"] == RULES["rules"] and screening["flagged"] == {"catch": 1, "straight_lining": 2,
                                                                            "fast": 1}
    excluded = {kinds[e["session_id"]]: e for e in screening["excluded"]}
    assert set(excluded) == {"straight", "fast", "careless"}
    assert excluded["fast"]["rules"]["fast"] == {"value": 1.0, "threshold": 0.2, "flagged": True,
                                                   "judged": True}
    assert excluded["straight"]["rules"]["straight_lining"]["value"] == 0
    assert len(screening["participants"]) == 6
    assert [c["n_participants"] for c in results["comparisons"]] == [3] * 8
    assert [c["n_participants"] for c in results["without_screening"]["comparisons"]] == [6] * 8
    assert results["without_screening"]["participants"]["screened_out"] == 0
    model = results["subject_model"]
    assert len(model["participants"]) == 3 and len(model["comparisons"]) == 8
    # The seeded panel has a maximum likelihood fit (others may not: docs/screening.md, test_subject_model).
    assert model["status"] == "ok" and model["note"] is None and model["degenerate"] == []
    assert model["diverged"] == {"session_ids": [], "animations": []}


def test_the_default_is_the_catch_rule_and_a_study_without_catch_rule_keeps_careless_answers(client, db,
                                                                                              researcher_headers):
    study = make_study(db, Design(catch_trials=2))
    assert study.screening == {"rules": ["catch"], **{k: v for k, v in study.screening.items() if k != "rules"}}
    kinds = run_panel(db, study, {"g": "good", "c": "careless"})
    outcomes = {(kinds[r["session_id"]], r["outcome"], r["screened_by"]) for r in export(client, researcher_headers)}
    assert outcomes == {("good", "completed", ""), ("careless", "screened_out", "catch")}
    # rules can change after the study opened (participants never see them) ...
    r = client.patch("/api/v1/studies/thesis", json={"screening": {"rules": ["straight_lining"]}},
                     headers=researcher_headers)
    assert r.status_code == 200, r.text
    outcomes = {(kinds[r["session_id"]], r["outcome"], r["screened_by"]) for r in export(client, researcher_headers)}
    assert outcomes == {("good", "completed", ""), ("careless", "screened_out", "straight_lining")}
    # ... nothing else can, and a bad rule is a 422 naming the field
    assert client.patch("/api/v1/studies/thesis", json={"title": "x"}, headers=researcher_headers).status_code == 409
    r = client.patch("/api/v1/studies/thesis", json={"screening": {"rules": ["psychic"]}}, headers=researcher_headers)
    assert r.status_code == 422 and "screening" in r.text


def test_study_file_screening_section():
    from server.studies.studyfile import THESIS_FILE

    text = THESIS_FILE.read_text(encoding="utf-8")
    study = parse_study_text(text + '\n[screening]\nrules = "all"\nmin_variance = 0.2\n')
    assert study.screening.rules == ["catch", "straight_lining", "z_outlier", "bt500", "correlation",
                                     "disagreement", "fast"]
    assert study.screening.min_variance == 0.2
    with pytest.raises(StudyFileError) as err:
        parse_study_text(text + '\n[screening]\nrules = ["catch", "psychic"]\n')
    assert any(e.startswith("screening.rules[1] (line") for e in err.value.errors), err.value.errors
    assert {"screened_by", "pilot"} <= set(EXPORT_COLUMNS)


def test_sureal_export_reads_into_sureal_and_gives_the_dashboards_subject_model(client, db, researcher_headers,
                                                                                 tmp_path):
    """The sureal dataset, read by sureal's own JSON reader and fitted by sureal's MLE, gives the numbers of the
    results' subject model; the pwcmp table has one row per non-equal analysed vote, left/right conditions."""
    import contextlib
    import json
    import warnings

    import numpy as np
    from sureal.dataset_reader import RawDatasetReader
    from sureal.subjective_model import MaximumLikelihoodEstimationModel
    from sureal.tools.misc import import_json_file

    study = make_study(db, Design(catch_trials=2), screening=RULES)
    run_panel(db, study, {"g1": "good", "g2": "good", "g3": "good", "s": "straight"})
    r = client.get("/api/v1/studies/thesis/export.sureal.json", headers=researcher_headers)
    assert r.status_code == 200 and "attachment" in r.headers["content-disposition"]
    path = tmp_path / "thesis.json"
    path.write_text(r.text)
    with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        theirs = MaximumLikelihoodEstimationModel(RawDatasetReader(import_json_file(str(path)))).run_modeling()
    ours = client.get("/api/v1/studies/thesis/results", headers=researcher_headers).json()["subject_model"]
    dataset = json.loads(r.text)
    assert len(dataset["dis_videos"]) == 8 and all(len(v["os"]) == 3 for v in dataset["dis_videos"])  # 3 kept
    by_key = {(c["animation"], c["condition"]): c["score"] for c in ours["comparisons"]}
    # A fit with a maximum (run_panel's seeded panel) equals sureal's.  Left to chance, the panel's fit had none
    # or the solver ran off about once in 370 panels, and this failed once in CI by 0.24 (981cdd7): those report
    # where the solver stopped, not estimates (test_a_subject_model_that_ran_off_is_not_called_ok).
    assert ours["status"] == "ok", ours["note"]
    np.testing.assert_allclose([by_key[(v["animation"], v["test_condition"])] for v in dataset["dis_videos"]],
                               theirs["quality_scores"], atol=1e-9, err_msg=f"{ours['iterations']} iterations")

    rows = list(csv.reader(io.StringIO(client.get("/api/v1/studies/thesis/export.pwcmp.csv",
                                                  headers=researcher_headers).text)))
    assert rows[0] == ["observer", "session", "scene", "cond1", "cond2", "selection"]
    votes = [v for v in export(client, researcher_headers)
             if v["outcome"] == "completed" and v["catch"] == "false" and v["choice"] != "equal"]
    assert len(rows) - 1 == len(votes)
    for row, v in zip(rows[1:], votes, strict=True):
        left = v["reference_condition"] if v["reference_side"] == "left" else v["test_condition"]
        right = v["test_condition"] if v["reference_side"] == "left" else v["reference_condition"]
        selection = "1" if v["choice"].startswith("left") else "2"
        assert row == [v["session_id"], "1", v["animation"], left, right, selection]


def test_a_subject_model_that_ran_off_is_not_called_ok(client, db, researcher_headers):
    """Session seeds that made sureal's solver run off with a participant's inconsistency (1e18, "converged"):
    the results say not_converged, name the participant and say why, instead of reporting the numbers as a fit."""
    study = make_study(db, Design(catch_trials=2), screening=RULES)
    kinds = run_panel(db, study, {"g1": "good", "g2": "good", "g3": "good"},
                      seeds=[105965761475679314, 8217689449242577302, 4522096967830459489])
    model = client.get("/api/v1/studies/thesis/results", headers=researcher_headers).json()["subject_model"]
    assert model["status"] == "not_converged" and model["degenerate"] == []
    (ran_off,) = model["diverged"]["session_ids"]
    assert kinds[ran_off] == "good" and model["diverged"]["animations"] == []
    assert f"participant {ran_off[:8]}'s inconsistency" in model["note"] and "not estimates" in model["note"]
    inconsistency = {p["session_id"]: p["inconsistency"] for p in model["participants"]}
    assert inconsistency[ran_off] > 1e6
