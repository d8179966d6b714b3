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


# --- 4: playback events ------------------------------------------------------------------------------------------

def event(client, sid, headers, **body):
    return client.post(f"/api/v1/sessions/{sid}/events", json={"kind": "load_failure", **body}, headers=headers)


def test_playback_events_are_capped_per_trial_and_session_and_kept_to_a_known_schema(client, db, study):
    from server.participants.models import PlaybackEvent

    sid, headers = start(client)
    trial = client.get(f"/api/v1/sessions/{sid}/next", headers=headers).json()["trial_id"]
    big = event(client, sid, headers, trial_id=trial, detail={"error": "x" * 16_000})
    assert big.status_code == 413, big.text[:200]
    unknown = event(client, sid, headers, detail={"url": "https://evil.example/?" + "q" * 100})
    assert unknown.status_code == 422
    codes = [event(client, sid, headers, trial_id=trial, detail={"error": f"NetworkError {k}"}).status_code
             for k in range(12)]
    assert codes == [201] * 10 + [429] * 2
    codes = [event(client, sid, headers, kind="fullscreen_exit").status_code for _ in range(95)]
    assert codes == [201] * 90 + [429] * 5
    stored = db.query(PlaybackEvent).filter_by(session_id=sid).all()
    assert len(stored) == 100
    assert {tuple(sorted((e.detail or {}).keys())) for e in stored} <= {(), ("error",)}


# --- 5: withdrawal -----------------------------------------------------------------------------------------------

def test_withdrawal_removes_the_device_record_and_every_playback_event(client, db, study):
    from server.participants.models import ParticipantSession, PlaybackEvent, Vote

    device = {"viewport_width": 1280, "viewport_height": 720, "device_pixel_ratio": 1.0, "video_width": 1280,
              "video_height": 360, "scale": 1.0, "scaled": False, "passed": True}
    r = client.post("/api/v1/studies/thesis/sessions", json={"consent": True, "device": device,
                                                             "external": {"PROLIFIC_PID": "p1"}})
    sid, headers = r.json()["session_id"], {"Authorization": f"Bearer {r.json()['token']}"}
    trial = client.get(f"/api/v1/sessions/{sid}/next", headers=headers).json()["trial_id"]
    assert event(client, sid, headers, trial_id=trial, detail={"error": "see https://me.example/p1"}).status_code \
        == 201
    assert client.post(f"/api/v1/sessions/{sid}/trials/{trial}/vote", headers=headers,
                       json={"choice": "equal", "rt_ms": 900, "idempotency_key": "k"}).status_code == 201
    assert client.post(f"/api/v1/sessions/{sid}/withdraw", headers=headers).status_code == 200
    db.expire_all()
    ps = db.get(ParticipantSession, sid)
    assert ps.state == "withdrawn" and ps.device is None and ps.answers is None and ps.external is None
    assert ps.token_hash is None
    assert db.query(PlaybackEvent).filter_by(session_id=sid).count() == 0
    assert db.query(Vote).filter_by(session_id=sid).count() == 0
    # kept: the anonymous row for the count, with the consent it was given under
    assert ps.consent_version == study.consent_version and ps.withdrawn_at is not None


# --- 7: smaller --------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("start_char", [" ", "\n", "\uff1d", "\uff0b", "\uff0d", "\uff20"])
def test_csv_cells_beginning_with_a_space_a_newline_or_a_full_width_sign_are_escaped(client, study,
                                                                                    researcher_headers, start_char):
    import csv
    import io

    pid = f"{start_char}=HYPERLINK(\"http://evil.example\",\"x\")"
    sid, headers = start(client, PROLIFIC_PID=pid)
    trial = client.get(f"/api/v1/sessions/{sid}/next", headers=headers).json()["trial_id"]
    assert client.post(f"/api/v1/sessions/{sid}/trials/{trial}/vote", headers=headers,
                       json={"choice": "equal", "rt_ms": 900, "idempotency_key": "k"}).status_code == 201
    text = client.get("/api/v1/studies/thesis/export.csv", headers=researcher_headers).text
    row = next(csv.DictReader(io.StringIO(text, newline="")))
    assert row["PROLIFIC_PID"] == "'" + pid


def test_a_draft_study_is_not_public(client, db):
    from server.studies.models import StudyState
    from tests.server_fixtures import make_study

    make_study(db, slug="secret-draft", state=StudyState.draft)
    unknown = client.get("/api/v1/studies/no-such-study")
    r = client.get("/api/v1/studies/secret-draft")
    assert r.status_code == 404 and "Information" not in r.text
    assert r.json()["detail"] == unknown.json()["detail"].replace("no-such-study", "secret-draft")
    s = client.post("/api/v1/studies/secret-draft/sessions", json={"consent": True})
    assert s.status_code == 404


def test_unknown_and_another_researchers_studies_answer_alike(client, db, researcher_headers):
    from server.researchers.service import create_researcher
    from tests.server_fixtures import make_study

    make_study(db, slug="theirs")
    create_researcher(db, "mallory@example.org", "correct horse battery")
    r = client.post("/api/v1/auth/token", data={"username": "mallory@example.org", "password": "correct horse battery"})
    mallory = {"Authorization": f"Bearer {r.json()['access_token']}"}
    for method, path in (("GET", "/results"), ("GET", "/export.csv"), ("GET", "/definition"), ("POST", "/open"),
                         ("GET", "/assets"), ("DELETE", "")):
        theirs = client.request(method, f"/api/v1/studies/theirs{path}", headers=mallory)
        unknown = client.request(method, f"/api/v1/studies/nothere{path}", headers=mallory)
        assert (theirs.status_code, unknown.status_code) == (404, 404), path
        assert theirs.json()["detail"] == unknown.json()["detail"].replace("nothere", "theirs"), path


def test_x_forwarded_for_is_trusted_only_from_configured_proxies(db, engine, tmp_path, study):
    from fastapi.testclient import TestClient

    from server.app import create_app
    from server.config import Settings
    from server.deps import get_session
    from server.security import RateLimiter

    def client_for(trusted: str, address: str) -> TestClient:
        settings = Settings(var_dir=tmp_path / "var", secret_key="test-secret-0123456789abcdef0123456789",
                            trusted_proxies=trusted)
        app = create_app(settings, engine, run_migrations=False)
        app.dependency_overrides[get_session] = lambda: db
        app.state.session_limiter = RateLimiter(2)
        return TestClient(app, client=(address, 50000))

    assert Settings(_env_file=None).trusted_proxies == []
    # No trusted proxy (the default): a client cannot choose its address to escape the limit.
    with client_for("", "127.0.0.1") as c:
        codes = [c.post("/api/v1/studies/thesis/sessions", json={"consent": True},
                        headers={"X-Forwarded-For": f"203.0.113.{k}"}).status_code for k in range(3)]
        assert codes == [201, 201, 429]
    # Behind a trusted proxy each forwarded client counts on its own; what the client wrote before is ignored.
    with client_for("127.0.0.1", "127.0.0.1") as c:
        codes = [c.post("/api/v1/studies/thesis/sessions", json={"consent": True},
                        headers={"X-Forwarded-For": f"198.51.100.{k % 2}, 203.0.113.9"}).status_code
                 for k in range(3)]
        assert codes == [201, 201, 429]  # the proxy appended 203.0.113.9: that is the client
        other = c.post("/api/v1/studies/thesis/sessions", json={"consent": True},
                       headers={"X-Forwarded-For": "203.0.113.10"})
        assert other.status_code == 201
    # From an address that is not a trusted proxy, the header is ignored.
    with client_for("10.0.0.0/8", "192.0.2.7") as c:
        codes = [c.post("/api/v1/studies/thesis/sessions", json={"consent": True},
                        headers={"X-Forwarded-For": f"10.0.0.{k}"}).status_code for k in range(3)]
        assert codes == [201, 201, 429]


def test_trial_ids_are_opaque_and_old_row_ids_still_answer(client, db, study):
    import re

    from server.participants.models import ParticipantSession

    seen = []
    for _ in range(3):
        sid, headers = start(client)
        trial = client.get(f"/api/v1/sessions/{sid}/next", headers=headers).json()
        assert re.fullmatch(r"[0-9a-f]{32}", trial["trial_id"]), trial["trial_id"]
        seen.append(trial["trial_id"])
    assert len(set(seen)) == 3
    # a page loaded before migration 0008 holds the trial's row id: its vote still counts
    row_id = db.get(ParticipantSession, sid).trials[0].id
    r = client.post(f"/api/v1/sessions/{sid}/trials/{row_id}/vote", headers=headers,
                    json={"choice": "equal", "rt_ms": 900, "idempotency_key": "k"})
    assert r.status_code == 201 and r.json()["trial_id"] == seen[-1]
    assert r.json()["next"]["trial_id"] != seen[-1] and re.fullmatch(r"[0-9a-f]{32}", r.json()["next"]["trial_id"])
    assert event(client, sid, headers, trial_id=r.json()["next"]["trial_id"]).status_code == 201
    assert event(client, sid, headers, trial_id=seen[0]).status_code == 404  # another session's trial
