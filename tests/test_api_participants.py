"""The participant API contract, on SQLite and (with TEST_DATABASE_URL) PostgreSQL."""

import re

from sqlalchemy import func, select

from server.participants.models import ParticipantSession, Vote
from server.studies.design import Design
from server.studies.models import StudyState
from tests.server_fixtures import answer_all, make_study, start, vote

OPAQUE_VIDEO = re.compile(r"^/media/[0-9a-f]{24}\.mp4$")


def test_public_study_info(client, study):
    r = client.get("/api/v1/studies/thesis")
    assert r.status_code == 200
    body = r.json()
    assert body["trials_total"] == 16 and body["state"] == "open"
    assert {"information", "consent", "instructions", "thanks"} <= set(body["texts"])
    assert body["consent_version"]
    assert "design" not in body  # nothing that says which side is which
    assert client.get("/api/v1/studies/nope").status_code == 404


def test_consent_is_required_and_nothing_is_stored_without_it(client, study, db):
    for body in ({"consent": False}, {}, {"consent": "maybe"}):
        r = client.post("/api/v1/studies/thesis/sessions", json=body)
        assert r.status_code == 422
        assert "consent" in r.text
    assert db.scalar(select(func.count(ParticipantSession.id))) == 0
    r = client.post("/api/v1/studies/thesis/sessions",
                    json={"consent": True, "external": {"PROLIFIC_PID": "p1", "STUDY_ID": "s", "SESSION_ID": "x"}})
    assert r.status_code == 201
    body = r.json()
    assert set(body) == {"session_id", "token", "trials_total"} and body["trials_total"] == 16
    ps = db.get(ParticipantSession, body["session_id"])
    assert ps.external == {"PROLIFIC_PID": "p1", "STUDY_ID": "s", "SESSION_ID": "x"}
    assert ps.consent_at is not None and ps.consent_version == study.consent_version
    assert ps.token_hash != body["token"]  # stored hashed


def test_sessions_only_while_open(client, db):
    make_study(db, slug="draft", state=StudyState.draft)
    make_study(db, slug="closed", state=StudyState.closed)
    for slug, code in (("draft", 404), ("closed", 409)):  # a draft is not public (issue 26)
        r = client.post(f"/api/v1/studies/{slug}/sessions", json={"consent": True})
        assert r.status_code == code, r.text


def test_token_rules(client, study):
    sid, headers = start(client)
    _, other_headers = start(client)
    url = f"/api/v1/sessions/{sid}"
    assert client.get(url, headers=headers).status_code == 200
    assert client.get(url).status_code == 401
    assert client.get(url, headers={"Authorization": "Bearer wrong"}).status_code == 401
    assert client.get(url, headers=other_headers).status_code in (403, 404)
    assert client.get("/api/v1/sessions/0123456789abcdef", headers=headers).status_code == 404
    assert client.get(f"{url}/next", headers=other_headers).status_code in (403, 404)


def test_demographics(client, study, db):
    sid, headers = start(client)
    url = f"/api/v1/sessions/{sid}/demographics"
    r = client.put(url, json={"gamer": "yes", "tech_savvy": "dont_know"}, headers=headers)
    assert r.status_code == 200
    ps = db.get(ParticipantSession, sid)
    assert ps.answers == {"gamer": "yes", "tech_savvy": "dont_know"}
    r = client.put(url, json={"gamer": "sometimes", "tech_savvy": "no"}, headers=headers)
    assert r.status_code == 422
    assert any(e["loc"][-1] == "gamer" for e in r.json()["detail"])
    r = client.put(url, json={"gamer": "no"}, headers=headers)
    assert r.status_code == 422 and "tech_savvy" in r.text
    assert client.put(url, json={"gamer": "no", "tech_savvy": "no"}).status_code == 401


def test_next_trial_is_stable_until_answered_and_ends_with_204(client, study):
    sid, headers = start(client)
    first = client.get(f"/api/v1/sessions/{sid}/next", headers=headers).json()
    again = client.get(f"/api/v1/sessions/{sid}/next", headers=headers).json()  # e.g. after a reload
    assert first == again
    assert (first["index"], first["total"], first["practice"]) == (0, 16, False)
    assert OPAQUE_VIDEO.match(first["video_url"]) and OPAQUE_VIDEO.match(first["preload_url"])
    assert vote(client, sid, headers, first["trial_id"]).status_code == 201
    second = client.get(f"/api/v1/sessions/{sid}/next", headers=headers).json()
    assert second["index"] == 1 and second["video_url"] == first["preload_url"]
    trials = [first, *answer_all(client, sid, headers)]
    assert [t["index"] for t in trials] == list(range(16))
    assert trials[-1]["preload_url"] is None
    state = client.get(f"/api/v1/sessions/{sid}", headers=headers).json()
    assert state == {"state": "completed", "answered": 16, "trials_total": 16, "demographics_given": False,
                     "outcome": "completed"}


def test_a_vote_answers_with_the_next_trial(client, study):
    """The page moves on with the vote's answer; it must be exactly what GET .../next says, to the end."""
    sid, headers = start(client)
    trial = client.get(f"/api/v1/sessions/{sid}/next", headers=headers).json()
    for number in range(1, 17):
        body = {"choice": "equal", "rt_ms": 900, "idempotency_key": f"k{number}"}
        r = client.post(f"/api/v1/sessions/{sid}/trials/{trial['trial_id']}/vote", headers=headers, json=body)
        assert r.status_code == 201 and r.json()["answered"] == number
        asked = client.get(f"/api/v1/sessions/{sid}/next", headers=headers)
        if number < 16:
            assert r.json()["next"] == asked.json() and r.json()["next"]["index"] == number
        else:
            assert r.json()["next"] is None and asked.status_code == 204
        # A retry of the same vote (its answer was lost) is answered alike.
        again = client.post(f"/api/v1/sessions/{sid}/trials/{trial['trial_id']}/vote", headers=headers, json=body)
        assert again.status_code == 200 and again.json()["next"] == r.json()["next"]
        trial = r.json()["next"]


def test_each_comparison_once_per_side_in_a_session(client, study, db):
    sid, headers = start(client)
    ps = db.get(ParticipantSession, sid)
    shown = sorted((t.comparison_id, t.reference_side) for t in ps.trials)
    assert shown == sorted((c.id, side) for c in study.comparisons for side in ("left", "right"))
    assert all(a.comparison_id != b.comparison_id for a, b in zip(ps.trials, ps.trials[1:], strict=False))
    # The trial's video is the pair video of its comparison in its side order.
    first = client.get(f"/api/v1/sessions/{sid}/next", headers=headers).json()
    trial = ps.trials[0]
    assert first["video_url"] == f"/media/{trial.comparison.video(trial.reference_side)}"


def test_votes_are_stored_exactly_once(client, study, db):
    sid, headers = start(client)
    trial = client.get(f"/api/v1/sessions/{sid}/next", headers=headers).json()["trial_id"]
    r1 = vote(client, sid, headers, trial, "left_slightly", key="abc", frame_drops=2)
    assert r1.status_code == 201
    r2 = vote(client, sid, headers, trial, "left_slightly", key="abc", frame_drops=2)
    assert r2.status_code == 200 and r2.json() == r1.json()
    assert db.scalar(select(func.count(Vote.id)).where(Vote.session_id == sid)) == 1
    stored = db.scalar(select(Vote).where(Vote.session_id == sid))
    assert stored.extra == {"frame_drops": 2}
    # A different vote for the answered trial, or the same key with another body: conflict.
    assert vote(client, sid, headers, trial, "right_much", key="other").status_code == 409
    assert vote(client, sid, headers, trial, "left_slightly", key="abc", rt_ms=9).status_code == 409
    assert db.scalar(select(func.count(Vote.id)).where(Vote.session_id == sid)) == 1
    # Reusing the key for the next trial is a conflict too; a fresh key works.
    nxt = client.get(f"/api/v1/sessions/{sid}/next", headers=headers).json()["trial_id"]
    assert vote(client, sid, headers, nxt, "equal", key="abc").status_code == 409
    assert vote(client, sid, headers, nxt, "equal", key="def").status_code == 201


def test_vote_rules(client, study, db):
    sid, headers = start(client)
    other_sid, _ = start(client)
    current = client.get(f"/api/v1/sessions/{sid}/next", headers=headers).json()["trial_id"]
    ps = db.get(ParticipantSession, sid)
    later = ps.trials[3].id
    assert vote(client, sid, headers, later).status_code == 409  # not the current trial
    other_trial = db.get(ParticipantSession, other_sid).trials[0].id
    assert vote(client, sid, headers, other_trial).status_code == 404  # not in this session
    assert vote(client, sid, headers, 10**9).status_code == 404
    for absurd in (0, 2**31, 2**63):  # ids no row can have: invalid input, never sent to the database
        r = vote(client, sid, headers, absurd)
        assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["path", "trial_id"], r.text
    r = vote(client, sid, headers, current, choice="left_very_much")
    assert r.status_code == 422 and any(e["loc"][-1] == "choice" for e in r.json()["detail"])
    r = vote(client, sid, headers, current, rt_ms=-5)
    assert r.status_code == 422 and any(e["loc"][-1] == "rt_ms" for e in r.json()["detail"])
    r = client.post(f"/api/v1/sessions/{sid}/trials/{current}/vote", json={"choice": "equal", "rt_ms": 1},
                    headers=headers)
    assert r.status_code == 422 and "idempotency_key" in r.text
    assert vote(client, sid, {}, current).status_code == 401
    assert db.scalar(select(func.count(Vote.id))) == 0


def test_withdrawal_deletes_answers_and_keeps_only_a_count(client, study, db):
    sid, headers = start(client, PROLIFIC_PID="someone")
    client.put(f"/api/v1/sessions/{sid}/demographics", json={"gamer": "yes", "tech_savvy": "yes"}, headers=headers)
    for _ in range(3):
        trial = client.get(f"/api/v1/sessions/{sid}/next", headers=headers).json()["trial_id"]
        assert vote(client, sid, headers, trial).status_code == 201
    r = client.post(f"/api/v1/sessions/{sid}/withdraw", headers=headers)
    assert r.status_code == 200 and r.json() == {"state": "withdrawn"}
    assert db.scalar(select(func.count(Vote.id)).where(Vote.session_id == sid)) == 0
    ps = db.get(ParticipantSession, sid)
    assert (ps.answers, ps.external, ps.token_hash) == (None, None, None)
    assert ps.state == "withdrawn"
    assert client.get(f"/api/v1/sessions/{sid}", headers=headers).status_code == 401
    assert client.post(f"/api/v1/sessions/{sid}/withdraw", headers=headers).status_code == 401


def test_completion_code_and_practice_trial(client, db):
    design = Design(practice="hybrid2", catch_trials=2)
    make_study(db, design, slug="prolific", recruitment={
        "parameters": ["PROLIFIC_PID"], "completed": {
            "code": "C0DE42", "url": "https://app.prolific.com/submissions/complete?cc={code}&p={PROLIFIC_PID}"}})
    info = client.get("/api/v1/studies/prolific").json()
    assert info["trials_total"] == 16 + 2 + 1
    sid, headers = start(client, "prolific", PROLIFIC_PID="pp")
    first = client.get(f"/api/v1/sessions/{sid}/next", headers=headers).json()
    assert first["practice"] is True and first["index"] == 0 and first["total"] == 19
    assert "completion_code" not in client.get(f"/api/v1/sessions/{sid}", headers=headers).json()
    assert vote(client, sid, headers, first["trial_id"]).status_code == 201
    rest = answer_all(client, sid, headers)
    assert not any(t["practice"] for t in rest)
    state = client.get(f"/api/v1/sessions/{sid}", headers=headers).json()
    assert state["completion_code"] == "C0DE42" and state["outcome"] == "completed"
    assert state["completion_url"] == "https://app.prolific.com/submissions/complete?cc=C0DE42&p=pp"


DEVICE = {"viewport_width": 1920, "viewport_height": 1080, "device_pixel_ratio": 1.5, "video_width": 1284,
          "video_height": 480, "scale": 0.983, "scaled": True, "passed": True}


def test_the_device_at_the_start_is_kept_with_the_session(client, study, db):
    for bad in ({**DEVICE, "viewport_width": "1920"}, {**DEVICE, "scale": 2}, {**DEVICE, "extra": 1},
                {k: v for k, v in DEVICE.items() if k != "passed"}):
        r = client.post("/api/v1/studies/thesis/sessions", json={"consent": True, "device": bad})
        assert r.status_code == 422 and "device" in r.text, r.text
    assert db.scalar(select(func.count(ParticipantSession.id))) == 0
    r = client.post("/api/v1/studies/thesis/sessions", json={"consent": True, "device": DEVICE})
    assert r.status_code == 201
    assert db.get(ParticipantSession, r.json()["session_id"]).device == DEVICE
    r = client.post("/api/v1/studies/thesis/sessions", json={"consent": True})  # an older page: no device
    assert r.status_code == 201 and db.get(ParticipantSession, r.json()["session_id"]).device is None


def test_public_study_has_its_page_settings(client, study):
    page = client.get("/api/v1/studies/thesis").json()["page"]
    assert (page["lang"], page["dir"], page["device_gate"]) == ("en", "ltr", {"min_scale": 0.8})
    assert page["chrome"]["submit"] == "Submit vote" and page["chrome"]["progress"] == "Trial {index} of {total}"
    defaults = client.get("/api/v1/page-defaults").json()["chrome"]
    assert defaults == {**page["chrome"], "questions_title": "Questions about you"}  # the thesis words it its way
    assert page["chrome"]["questions_title"] == "Two questions about you"
