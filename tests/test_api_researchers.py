"""Researcher login, study state, exports and the data dictionary; media serving."""

import csv
import io
import json

from fastapi.testclient import TestClient

from server.studies.service import EXPORT_COLUMNS
from tests.server_fixtures import RESEARCHER, make_client, start, vote

FIELDS = {"session_id", "trial_index", "practice", "animation", "reference_condition", "test_condition",
          "reference_side", "test_side", "choice", "score", "rt_ms", "gamer", "tech_savvy", "answered_at"}


def test_login(client, researcher_headers):
    r = client.post("/api/v1/auth/token", data={"username": RESEARCHER[0], "password": "wrong password"})
    assert r.status_code == 401
    r = client.post("/api/v1/auth/token", data={"username": "nobody@example.org", "password": RESEARCHER[1]})
    assert r.status_code == 401
    r = client.post("/api/v1/auth/token", data={"username": RESEARCHER[0].upper(), "password": RESEARCHER[1]})
    assert r.status_code == 200 and r.json()["token_type"] == "bearer"


def test_open_and_close_need_a_researcher(client, study, researcher_headers):
    assert client.post("/api/v1/studies/thesis/close").status_code == 401
    assert client.post("/api/v1/studies/thesis/close", headers={"Authorization": "Bearer junk"}).status_code == 401
    r = client.post("/api/v1/studies/thesis/close", headers=researcher_headers)
    assert r.status_code == 200 and r.json() == {"slug": "thesis", "state": "closed"}
    assert client.post("/api/v1/studies/thesis/sessions", json={"consent": True}).status_code == 409
    assert client.post("/api/v1/studies/thesis/open", headers=researcher_headers).json()["state"] == "open"
    assert client.post("/api/v1/studies/thesis/sessions", json={"consent": True}).status_code == 201


def test_a_participant_token_is_not_a_researcher_token(client, study):
    _, headers = start(client)
    assert client.get("/api/v1/studies/thesis/export.csv", headers=headers).status_code == 401


def test_exports_one_row_per_vote_with_test_condition_scores(client, study, researcher_headers, db):
    sid, headers = start(client)
    client.put(f"/api/v1/sessions/{sid}/demographics", json={"gamer": "no", "tech_savvy": "yes"}, headers=headers)
    answered = []
    for choice in ("left_much", "right_slightly", "equal"):
        trial = client.get(f"/api/v1/sessions/{sid}/next", headers=headers).json()
        assert vote(client, sid, headers, trial["trial_id"], choice, rt_ms=1234).status_code == 201
        answered.append((trial, choice))
    withdrawn_sid, withdrawn_headers = start(client)
    first = client.get(f"/api/v1/sessions/{withdrawn_sid}/next", headers=withdrawn_headers).json()
    vote(client, withdrawn_sid, withdrawn_headers, first["trial_id"])
    client.post(f"/api/v1/sessions/{withdrawn_sid}/withdraw", headers=withdrawn_headers)

    assert client.get("/api/v1/studies/thesis/export.csv").status_code == 401
    assert client.get("/api/v1/studies/thesis/export.json").status_code == 401
    r = client.get("/api/v1/studies/thesis/export.csv", headers=researcher_headers)
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/csv")
    rows = list(csv.DictReader(io.StringIO(r.text)))
    assert len(rows) == 3 and FIELDS <= set(rows[0])
    data = client.get("/api/v1/studies/thesis/export.json", headers=researcher_headers).json()
    assert data["study"]["slug"] == "thesis" and len(data["votes"]) == 3

    from server.participants.models import ParticipantSession

    trials = {t.index: t for t in db.get(ParticipantSession, sid).trials}
    values = {"left_much": 2, "left_slightly": 1, "equal": 0, "right_slightly": -1, "right_much": -2}
    for row, obj, (trial, choice) in zip(rows, data["votes"], answered, strict=True):
        side = "left" if trials[trial["index"]].reference_side == "right" else "right"  # the test's
        expected = values[choice] if side == "left" else -values[choice]
        assert (row["session_id"], int(row["trial_index"]), row["choice"]) == (sid, trial["index"], choice)
        assert (row["test_side"], int(row["score"]), row["practice"]) == (side, expected, "false")
        assert row["reference_side"] == trials[trial["index"]].reference_side
        assert (row["gamer"], row["tech_savvy"], row["rt_ms"]) == ("no", "yes", "1234")
        assert row["animation"] in ("walk", "run", "crouch", "idle") and row["reference_condition"] == "keyframe"
        assert row["test_condition"] in ("hybrid0", "hybrid1")
        assert obj["score"] == expected and obj["practice"] is False and obj["test_condition"] in ("hybrid0", "hybrid1")


def test_data_dictionary_documents_every_column(client):
    r = client.get("/api/v1/data-dictionary")
    assert r.status_code == 200
    for column in EXPORT_COLUMNS:
        assert f"| `{column}` |" in r.text


def test_data_dictionary_as_json_has_the_same_columns(client):
    r = client.get("/api/v1/data-dictionary.json")
    assert r.status_code == 200
    names = [c["name"] for c in r.json()["columns"]]
    # Every export column, in export order, and each row says what its values are.
    assert [n for n in names if not n.startswith("*")] == list(EXPORT_COLUMNS)
    assert all(c["type"] and c["meaning"] for c in r.json()["columns"])
    assert r.json()["old_columns"]


def test_the_name_rule_is_served_and_the_pages_do_not_spell_it(client):
    """Issue 37: the rule for animation and condition names is defined once (the clip-set reader's); the studies
    page takes it from the API, and no page copies it."""
    import re
    from pathlib import Path

    from server.clipset.config import NAME, NAME_PATTERN

    r = client.get("/api/v1/constants")
    assert r.status_code == 200
    pattern = r.json()["name_pattern"]
    assert f"^{pattern}$" == NAME_PATTERN
    for name in ("walk", "hybrid_ik0", "a" * 32, "Walk", "walk-1", "a" * 33, "_x"):
        assert bool(re.fullmatch(pattern, name)) == bool(NAME.fullmatch(name)), name
    static = Path(__file__).resolve().parents[1] / "static"
    for page in static.glob("*.html"):
        assert "a-z0-9_]{0,31}" not in page.read_text(), page.name


def test_media_serving(db, engine, tmp_path):
    clients = make_client(db, engine, tmp_path)
    client: TestClient = next(clients)
    media = tmp_path / "var" / "media"
    media.mkdir(parents=True)
    name = "0123456789abcdef01234567.mp4"
    payload = bytes(range(256)) * 40
    (media / name).write_bytes(payload)
    (media / "manifest.json").write_text(json.dumps({"clips": {}}))
    r = client.get(f"/media/{name}")
    assert r.status_code == 200 and r.content == payload
    assert r.headers["content-type"] == "video/mp4" and "immutable" in r.headers["cache-control"]
    assert r.headers["accept-ranges"] == "bytes"
    r = client.get(f"/media/{name}", headers={"Range": "bytes=100-199"})
    assert r.status_code == 206 and r.content == payload[100:200]
    assert r.headers["content-range"] == f"bytes 100-199/{len(payload)}"
    for bad in ("manifest.json", "..%2Fsecret.key", "walk-keyframe.mp4", "0123456789abcdef0123456.mp4",
                "ffffffffffffffffffffffff.mp4"):
        assert client.get(f"/media/{bad}").status_code == 404
