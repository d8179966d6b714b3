"""The answer scale is defined once (server/studies/scale.py): the API gives it, the pages use it (issue 23)."""

import re
from pathlib import Path

from server.studies import scale

STATIC = Path(__file__).resolve().parents[1] / "static"


def test_the_results_give_the_scale(client, study, researcher_headers):
    r = client.get(f"/api/v1/studies/{study.slug}/results", headers=researcher_headers)
    assert r.status_code == 200
    assert r.json()["answer_scale"] == {
        "choices": ["left_much", "left_slightly", "equal", "right_slightly", "right_much"],
        "scores": [-2, -1, 0, 1, 2], "min": -2, "max": 2,
        "choice_scores": {"left_much": 2, "left_slightly": 1, "equal": 0, "right_slightly": -1, "right_much": -2}}


def test_the_participant_form_sends_the_scale_ids_in_order():
    html = (STATIC / "participant.html").read_text(encoding="utf-8")
    assert tuple(re.findall(r'name="choice" value="([a-z_]+)"', html)) == scale.CHOICES


def test_the_dashboard_takes_its_score_bounds_from_the_api():
    js = (STATIC / "dashboard.js").read_text(encoding="utf-8")
    assert not re.search(r"-2,\s*2\b", js), "a chart's score bounds are written in dashboard.js"
    assert not re.search(r'key: "-?[12]"', js), "a legend's scores are written in dashboard.js"
    assert "res.answer_scale.min, res.answer_scale.max" in js
