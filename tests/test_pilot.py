"""Pilot runs: a researcher's preview link works on draft and open studies, its sessions stay out of results and
exports unless asked for, and one action deletes them with every row they made (issue 28)."""

from __future__ import annotations

import csv
import io

import sqlalchemy as sa

from server.participants.models import ParticipantSession, PlaybackEvent, Trial, Vote
from server.studies.models import StudyState
from tests.server_fixtures import answer_all, make_study, start


def preview(client, headers, slug="thesis") -> str:
    r = client.post(f"/api/v1/studies/{slug}/preview", headers=headers)
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["url"].startswith(f"/s/{slug}?preview=")
    return body["url"].split("preview=", 1)[1]


def start_pilot(client, token, slug="thesis"):
    return client.post(f"/api/v1/studies/{slug}/sessions", json={"consent": True, "preview": token})


def rows_of(db, model, column, ids) -> int:
    return db.scalar(sa.select(sa.func.count()).select_from(model).where(column.in_(ids)))


def test_preview_link_starts_pilot_sessions_on_a_draft_and_only_with_a_valid_token(client, db, researcher_headers):
    make_study(db, state=StudyState.draft)
    make_study(db, slug="other", state=StudyState.open)
    assert start_pilot(client, None).status_code == 404  # no token: a draft is unknown to participants
    token = preview(client, researcher_headers)
    r = start_pilot(client, token)
    assert r.status_code == 201, r.text
    assert db.get(ParticipantSession, r.json()["session_id"]).pilot is True
    # another study's link, a forged one: as for a study that does not exist (issue 36)
    assert start_pilot(client, token, "other").status_code == 404
    assert start_pilot(client, token[:-4] + "AAAA").status_code == 404
    assert client.post("/api/v1/studies/thesis/preview").status_code == 401  # researchers only
    client.post("/api/v1/studies/thesis/close", headers=researcher_headers)
    assert start_pilot(client, token).status_code == 409
    assert client.post("/api/v1/studies/thesis/preview", headers=researcher_headers).status_code == 409


def test_pilot_sessions_stay_out_of_results_and_exports_unless_asked_and_are_deleted_with_every_row(
        client, db, researcher_headers):
    make_study(db)
    real_sid, real_headers = start(client)
    answer_all(client, real_sid, real_headers, "left_slightly")
    token = preview(client, researcher_headers)
    pilots = []
    for choice in ("right_much", "equal"):
        r = start_pilot(client, token)
        sid, headers = r.json()["session_id"], {"Authorization": f"Bearer {r.json()['token']}"}
        answer_all(client, sid, headers, choice)
        assert client.post(f"/api/v1/sessions/{sid}/events", headers=headers,
                           json={"kind": "load_failure", "detail": {"error": "test"}}).status_code == 201
        pilots.append(sid)
    unfinished = start_pilot(client, token).json()["session_id"]
    pilots.append(unfinished)

    def export(query=""):
        text = client.get(f"/api/v1/studies/thesis/export.csv{query}", headers=researcher_headers).text
        return list(csv.DictReader(io.StringIO(text)))

    assert {r["session_id"] for r in export()} == {real_sid}
    with_pilot = export("?pilot=true")
    assert {r["session_id"] for r in with_pilot} == {real_sid, *pilots[:2]}
    assert {(r["session_id"] in pilots, r["pilot"]) for r in with_pilot} == {(False, "false"), (True, "true")}
    doc = client.get("/api/v1/studies/thesis/export.json", headers=researcher_headers).json()
    assert {v["session_id"] for v in doc["votes"]} == {real_sid}
    results = client.get("/api/v1/studies/thesis/results", headers=researcher_headers).json()
    assert results["participants"]["completed"] == 1 and results["participants"]["started"] == 1
    assert results["participants"]["pilot"] == 3
    assert all(c["n_participants"] == 1 for c in results["comparisons"])
    shown = client.get("/api/v1/studies/thesis/results?pilot=true", headers=researcher_headers).json()
    assert shown["participants"]["completed"] == 3 and shown["pilot_included"] is True
    listed = client.get("/api/v1/studies", headers=researcher_headers).json()[0]
    assert (listed["started"], listed["completed"], listed["votes"]) == (1, 1, 16)

    before = {name: rows_of(db, m, c, pilots) for name, m, c in (
        ("sessions", ParticipantSession, ParticipantSession.id), ("trials", Trial, Trial.session_id),
        ("votes", Vote, Vote.session_id), ("events", PlaybackEvent, PlaybackEvent.session_id))}
    assert before == {"sessions": 3, "trials": 48, "votes": 32, "events": 2}
    r = client.delete("/api/v1/studies/thesis/pilot-sessions", headers=researcher_headers)
    assert r.status_code == 200 and r.json() == before
    assert {name: rows_of(db, m, c, pilots) for name, m, c in (
        ("sessions", ParticipantSession, ParticipantSession.id), ("trials", Trial, Trial.session_id),
        ("votes", Vote, Vote.session_id), ("events", PlaybackEvent, PlaybackEvent.session_id))} == dict.fromkeys(
        before, 0)
    assert {r["session_id"] for r in export("?pilot=true")} == {real_sid}
    assert len(export()) == 16  # the real participant's votes are untouched


def test_a_drafts_design_change_and_deletion_take_its_pilot_sessions_along(client, db, researcher_headers):
    make_study(db, state=StudyState.draft)
    token = preview(client, researcher_headers)
    r = start_pilot(client, token)
    sid, headers = r.json()["session_id"], {"Authorization": f"Bearer {r.json()['token']}"}
    answer_all(client, sid, headers)
    from server.participants.service import update_study
    from server.studies import service
    from tests.server_fixtures import fake_media
    study = service.get_study(db, "thesis")
    update_study(db, study, {"design": {"conditions": ["hybrid1"]}}, fake_media())
    assert db.get(ParticipantSession, sid) is None
    sid = start_pilot(client, token).json()["session_id"]
    assert client.delete("/api/v1/studies/thesis", headers=researcher_headers).status_code == 204
    assert db.get(ParticipantSession, sid) is None
