"""Hostile input, round two (issue 26): completion-URL templates, nesting depth, bidirectional controls, playback
events, withdrawal, CSV cells, draft texts, 404 alike, opaque trial ids, X-Forwarded-For.  Uploads:
tests/test_hostile_uploads.py."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from server.studies.models import Study
from server.studies.studyfile import Recruitment, StudyFileError, parse_study_text, thesis_study
from tests.server_fixtures import answer_all, start

RECRUITMENT = {"parameters": ["PROLIFIC_PID"], "completed": {"code": "GOOD1"}}


def recruitment(url: str) -> Recruitment:
    return Recruitment.model_validate({**RECRUITMENT, "completed": {"code": "GOOD1", "url": url}})


@pytest.mark.parametrize("url, says", [
    ("https://example.org/c?cc={code:>300000000}", "only plain {name} placeholders"),
    ("https://example.org/c?cc={code:{PROLIFIC_PID}}", "only plain {name} placeholders"),
    ("https://example.org/c?cc={code!r}", "only plain {name} placeholders"),
    ("https://example.org/c?cc={code.real}", "neither {code} nor an accepted parameter"),
    ("https://example.org/c?cc={code[0]}", "neither {code} nor an accepted parameter"),
    ("https://{PROLIFIC_PID}/done", "fixed https://host/"),
    ("https://example.org{PROLIFIC_PID}/done", "fixed https://host/"),
    ("https://{PROLIFIC_PID}.example.org/done", "fixed https://host/"),
    ("http://example.org/c?cc={code}", "fixed https://host/"),
    ("{PROLIFIC_PID}", "fixed https://host/"),
])
def test_completion_url_templates_allow_only_plain_placeholders_after_a_fixed_host(url, says):
    with pytest.raises(ValidationError) as error:
        recruitment(url)
    assert says in str(error.value)


def test_completion_url_values_are_encoded_and_capped():
    r = recruitment("https://app.prolific.com/c/{PROLIFIC_PID}?cc={code}&pid={PROLIFIC_PID}")
    url = r.completion_url("completed", "GOOD1", {"PROLIFIC_PID": "../x?y=1&z#" + "a" * 500})
    assert url is not None and url.startswith("https://app.prolific.com/c/..%2Fx%3Fy%3D1%26z%23aaa")
    assert "a" * 200 not in url and url.count("a" * 189) == 2  # each value cut to 200 characters


def test_a_stored_template_of_before_the_rules_gives_no_url_and_no_huge_answer(client, db, study):
    """A study stored before these rules (its template now refused) must not make every read 300 MB, nor
    redirect anywhere: it gets no completion URL."""
    study.recruitment = {**study.recruitment, "parameters": ["PROLIFIC_PID"],
                         "completed": {"code": "GOOD1", "url": "https://example.org/c?cc={code:>3000000}"},
                         "screened_out": {"code": None, "url": "https://{PROLIFIC_PID}/done"}}
    db.commit()
    sid, headers = start(client, PROLIFIC_PID="evil.example")
    answer_all(client, sid, headers)
    r = client.get(f"/api/v1/sessions/{sid}", headers=headers)
    assert r.status_code == 200 and len(r.content) < 2000, len(r.content)
    assert r.json()["completion_code"] == "GOOD1" and "completion_url" not in r.json()


def test_toml_nested_20000_deep_is_a_clear_error(client, db, researcher_headers):
    text = "a = " + "[" * 20000 + "]" * 20000 + "\n"
    with pytest.raises(StudyFileError, match="nested too deeply"):
        parse_study_text(text)
    r = client.post("/api/v1/studies/file", content=text.encode(),
                    headers={**researcher_headers, "Content-Type": "text/plain"})
    assert r.status_code == 422 and "nested too deeply" in r.text, r.text[:300]
    assert db.query(Study).count() == 0


def test_clip_set_file_nested_deeply_is_a_config_error(tmp_path):
    from server.clipset.config import ConfigError, load_config

    path = tmp_path / "deep.toml"
    path.write_text("fps = " + "{a = " * 5000 + "1" + "}" * 5000 + "\n")
    with pytest.raises(ConfigError, match="nested too deeply"):
        load_config(path)


@pytest.mark.parametrize("path, value", [
    (("title",), "Animation \u202egnp.exe"),
    (("texts", "consent"), "I agree \u2066to everything\u2069"),
    (("scale", "labels", 0), "Left \u202dmuch better"),
    (("questions", 0, "choices", 0, "label"), "Yes\u202b"),
    (("page", "chrome", "start"), "Start \u202e"),
])
def test_bidirectional_controls_are_refused_in_titles_labels_and_texts(client, db, researcher_headers, path, value):
    body = thesis_study().model_dump(mode="json")
    body["slug"] = "bidi"
    target = body
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    r = client.post("/api/v1/studies", json=body, headers=researcher_headers)
    assert r.status_code == 422, r.text[:300]
    assert "bidirectional control character" in r.text
    assert db.query(Study).count() == 0


def test_right_to_left_marks_stay_allowed():
    body = thesis_study().model_dump(mode="json")
    body["title"] = "\u05de\u05d7\u05e7\u05e8 \u200f(2026)"
    body["page"] = {"lang": "he"}
    from server.studies.studyfile import StudyFile

    assert StudyFile.model_validate(body).title.endswith("(2026)")
