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


def test_the_participant_page_spells_no_answer_id():
    """The answers are built from the ids the API serves (``scale.choices``, issue 37), in their order."""
    for name in ("participant.html", "participant.js"):
        text = (STATIC / name).read_text(encoding="utf-8")
        spelled = [c for c in scale.ALL_CHOICES if c not in ("left", "right")  # also plain words of the page
                   and re.search(rf'["\'`]{c}["\'`]', text)]
        assert not spelled, f"{name} spells the answer ids {spelled}"
        assert 'value="left_much"' not in text
    js = (STATIC / "participant.js").read_text(encoding="utf-8")
    assert "scale.choices.forEach" in js


def test_the_dashboard_takes_its_score_bounds_from_the_api():
    js = (STATIC / "dashboard.js").read_text(encoding="utf-8")
    assert not re.search(r"-2,\s*2\b", js), "a chart's score bounds are written in dashboard.js"
    assert not re.search(r'key: "-?[12]"', js), "a legend's scores are written in dashboard.js"
    assert "res.answer_scale.min, res.answer_scale.max" in js
