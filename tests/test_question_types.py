"""Question types (choice, number, text, likert): the study file, the API's checks, the export and the results'
breakdown (issue 28)."""

from __future__ import annotations

import csv
import io
import json

import pytest
from pydantic import ValidationError

from server.studies.studyfile import Question
from tests.server_fixtures import answer_all, make_study, start

QUESTIONS = [
    {"id": "gamer", "text": "Do you play games?",
     "choices": [{"id": "yes", "label": "Yes"}, {"id": "no", "label": "No"}]},
    {"id": "age", "text": "Your age?", "type": "number", "min": 18, "max": 99, "integer": True, "unit": "years"},
    {"id": "remarks", "text": "Anything to add?", "type": "text", "max_length": 40},
    {"id": "experience", "text": "Animation experience", "type": "likert",
     "labels": ["None", "Some", "Moderate", "Much", "Expert"]},
]
GOOD = {"gamer": "yes", "age": 34, "remarks": "=cmd|' /C calc'!A0", "experience": 4}


def put(client, sid, headers, answers):
    return client.put(f"/api/v1/sessions/{sid}/demographics", json=answers, headers=headers)


@pytest.mark.parametrize(("question", "value", "message"), [
    ("gamer", "maybe", "Input should be 'yes', 'no'"),
    ("gamer", 1, "Input should be 'yes', 'no'"),
    ("age", 17, "Input should be a number from 18 to 99"),
    ("age", 100, "Input should be a number from 18 to 99"),
    ("age", 34.5, "Input should be a whole number"),
    ("age", "34", "Input should be a number"),
    ("age", True, "Input should be a number"),
    ("age", None, "Input should be a number"),
    ("remarks", "x" * 41, "Input should have at most 40 characters"),
    ("remarks", "   ", "Input should be a non-empty text"),
    ("remarks", "a\u0000b", "Input should not contain control characters"),
    ("remarks", 5, "Input should be a non-empty text"),
    ("experience", 0, "Input should be a whole number from 1 to 5"),
    ("experience", 6, "Input should be a whole number from 1 to 5"),
    ("experience", "4", "Input should be a whole number from 1 to 5"),
])
def test_invalid_answers_are_refused_by_the_api_with_the_field_named(client, db, question, value, message):
    make_study(db, questions=QUESTIONS)
    sid, headers = start(client)
    r = put(client, sid, headers, {**GOOD, question: value})
    assert r.status_code == 422, r.text
    errors = r.json()["detail"]
    assert any(e["loc"][-1] == question and message in e["msg"] for e in errors), errors
    assert client.get(f"/api/v1/sessions/{sid}", headers=headers).json()["demographics_given"] is False


def test_valid_answers_are_stored_and_exported_with_their_types(client, db, researcher_headers):
    make_study(db, questions=QUESTIONS)
    sid, headers = start(client)
    r = put(client, sid, headers, GOOD)
    assert r.status_code == 200 and r.json() == GOOD
    answer_all(client, sid, headers)
    doc = client.get("/api/v1/studies/thesis/export.json", headers=researcher_headers).json()
    row = doc["votes"][0]
    assert {k: row[k] for k in GOOD} == GOOD  # a number stays a number, a Likert point an integer
    assert [q["type"] for q in doc["study"]["questions"]] == ["choice", "number", "text", "likert"]
    text = client.get("/api/v1/studies/thesis/export.csv", headers=researcher_headers).text
    first = next(csv.DictReader(io.StringIO(text)))
    assert (first["age"], first["experience"], first["remarks"]) == ("34", "4", "'=cmd|' /C calc'!A0")
    dictionary = client.get("/api/v1/data-dictionary").text
    assert "likert" in dictionary and "number" in dictionary


def test_results_break_down_by_number_bins_and_skip_free_text(client, db, researcher_headers):
    make_study(db, questions=QUESTIONS)
    for age in (18, 25, 40, 70):
        sid, headers = start(client)
        assert put(client, sid, headers, {**GOOD, "age": age, "remarks": f"r{age}"}).status_code == 200
        answer_all(client, sid, headers)
    results = client.get("/api/v1/studies/thesis/results", headers=researcher_headers).json()
    demographics = results["demographics"]
    assert set(demographics) == {"gamer", "age", "experience"}
    assert sum(b["participants"] for b in demographics["age"].values()) == 4
    assert all(label.endswith(" years") for label in demographics["age"])
    assert "18–" in json.dumps(demographics["age"], ensure_ascii=False)


def test_the_study_file_checks_each_type():
    assert Question.model_validate(QUESTIONS[1]).type == "number"
    assert Question.model_validate({"id": "g", "text": "t", "choices": QUESTIONS[0]["choices"]}).type == "choice"
    for bad in ({"id": "a", "text": "t", "type": "number", "min": 5, "max": 5},
                {"id": "a", "text": "t", "type": "likert", "labels": ["a", "b"]},
                {"id": "a", "text": "t", "type": "likert", "labels": [str(i) for i in range(12)]},
                {"id": "a", "text": "t", "type": "text", "choices": QUESTIONS[0]["choices"]},
                {"id": "a", "text": "t", "type": "choice"},
                {"id": "a", "text": "t", "type": "text", "unit": "cm"},
                {"id": "a", "text": "t", "type": "text", "max_length": 5000},
                {"id": "a", "text": "t", "type": "slider"}):
        with pytest.raises(ValidationError):
            Question.model_validate(bad)
