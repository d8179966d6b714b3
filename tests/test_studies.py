"""Studies as data: the thesis from studies/thesis.toml equals the old built-in default; a second study runs beside
it with its own texts, labels, question, export and results; ownership; validation errors; PATCH/DELETE rules;
recruitment (URL parameters, completion URL, screened out); the study CLI."""

from __future__ import annotations

import csv
import io
import json
import random
from itertools import pairwise

import pytest

from server import cli
from server.research.export import export_rows
from server.researchers.service import create_researcher
from server.studies import service
from server.studies.design import Design, trial_order
from server.studies.models import Study
from server.studies.studyfile import THESIS_FILE, StudyFileError, parse_study_text, thesis_study
from tests.server_fixtures import answer_all, fake_media, make_study, start, vote, write_fake_media

# The built-in default of revision 0003 (server/studies/service.py before this change), copied literally.
OLD_TEXTS = {
    "information": (
        "This study compares two ways of animating a human character. You will see two identical characters side "
        "by side and say which animation looks better. It takes about 10 minutes. We store your answers and the "
        "two demographic answers without your name or any other identifying information, and publish them "
        "anonymously for research. Taking part is voluntary: you can stop at any time without giving a reason, "
        "and withdraw to have your answers deleted."
    ),
    "consent": (
        "I have read the information above. I agree to take part and to my anonymous answers being stored and "
        "published for research."
    ),
    "instructions": (
        "Each trial shows two characters moving in sync. Watch them, then choose which animation looks better: "
        "significantly or slightly better on the left, equal, or slightly or significantly better on the right. "
        "Pay attention to how natural the motion looks, including the feet on the floor."
    ),
    "thanks": "Thank you for taking part!",
    "contact": "The researchers of this study (contact details are given by the person who invited you).",
}


def old_trial_order(test: list[int], seed: int) -> list[tuple[int, str]]:
    """Revision 0003's trial order (comparison, hybrid side) for the thesis design, re-typed from its code."""
    rng = random.Random(seed)
    items = [(c, side) for c in test for side in ("left", "right")]
    for _ in range(10_000):
        rng.shuffle(items)
        if all(a[0] != b[0] for a, b in pairwise(items)):
            break
    return items


GAIT = {
    "slug": "gait", "title": "Which walk looks more natural?",
    "texts": {"information": "Gait information text.", "consent": "Gait consent text.", "consent_version": "g-1",
              "contact": "gait@example.org", "instructions": "Gait instructions.", "thanks": "Gait thanks."},
    "scale": {"question": "More natural?", "labels": ["L much", "L bit", "Same", "R bit", "R much"]},
    "questions": [{"id": "animator", "text": "Have you animated characters?",
                   "choices": [{"id": "never", "label": "Never"}, {"id": "work", "label": "For work"}]}],
    "design": {"reference": "keyframe", "conditions": ["hybrid1", "hybrid2"], "animations": ["walk", "run"],
               "catch_trials": 2},
    "recruitment": {"parameters": ["PROLIFIC_PID", "STUDY_ID"], "catch_failures_allowed": 0,
                    "completed": {"code": "GOOD1", "url": "https://app.prolific.com/c?cc={code}&pid={PROLIFIC_PID}"},
                    "screened_out": {"code": "SCREEN1", "url": "https://example.org/out?cc={code}"}},
}


@pytest.fixture
def media_dir(client):
    """The render manifest the API creates studies over (fake, opaque names)."""
    media = client.app.state.settings.media_dir
    write_fake_media(media)
    return media


def login(client, db, email, admin=False):
    create_researcher(db, email, "correct horse battery", admin=admin)
    r = client.post("/api/v1/auth/token", data={"username": email, "password": "correct horse battery"})
    return {"Authorization": f"Bearer {r.json()['access_token']}"}


# --- the thesis study -------------------------------------------------------------------------------------------

def test_thesis_file_equals_the_old_default(db):
    definition = thesis_study()
    assert definition.slug == "thesis" and definition.title == "How good does this character animation look?"
    assert {k: getattr(definition.texts, k) for k in OLD_TEXTS} == OLD_TEXTS
    assert definition.texts.consent_version == "2026-11-1"
    assert [(q.id, q.text, [c.id for c in q.choices]) for q in definition.questions] == [
        ("gamer", "Do you consider yourself a gamer?", ["yes", "no", "dont_know"]),
        ("tech_savvy", "Do you consider yourself tech-savvy?", ["yes", "no", "dont_know"])]
    study = make_study(db)
    assert service.trials_total(study) == 16 and len(study.comparisons) == 8
    assert sorted((c.reference.animation, c.reference.condition, c.test.condition) for c in study.comparisons) == \
        sorted((a, "keyframe", f"hybrid{i}") for a in ("walk", "run", "crouch", "idle") for i in (0, 1))
    # The same seed gives the same order as revision 0003, the hybrid on the side the reference is not.
    ids = service.comparison_ids(study)
    for seed in range(50):
        new = [(t.comparison_id, "left" if t.reference_side == "right" else "right")
               for t in trial_order(ids, 1, seed)]
        assert new == old_trial_order(ids.test, seed)


# --- a second study beside it -------------------------------------------------------------------------------------

def test_second_study_runs_beside_the_thesis(client, db, media_dir, researcher_headers):
    thesis = make_study(db)
    sid, headers = start(client)
    client.put(f"/api/v1/sessions/{sid}/demographics", json={"gamer": "yes", "tech_savvy": "no"}, headers=headers)
    answer_all(client, sid, headers, "left_much")
    thesis_csv = client.get("/api/v1/studies/thesis/export.csv", headers=researcher_headers).text
    thesis_results = client.get("/api/v1/studies/thesis/results", headers=researcher_headers).json()["comparisons"]

    r = client.post("/api/v1/studies", json=GAIT, headers=researcher_headers)
    assert r.status_code == 201, r.text
    assert (r.json()["state"], r.json()["trials_total"], r.json()["participant_url"]) == ("draft", 10, "/s/gait")
    assert client.post("/api/v1/studies/gait/open", headers=researcher_headers).status_code == 200
    public = client.get("/api/v1/studies/gait").json()
    assert public["texts"]["information"] == "Gait information text." and public["scale"]["labels"][2] == "Same"
    assert [q["id"] for q in public["questions"]] == ["animator"] and public["trials_total"] == 10
    assert client.get("/s/gait").status_code == 200

    for choice in ("left_slightly", "right_much"):
        gsid, gheaders = start(client, "gait", PROLIFIC_PID="p1", STUDY_ID="s1", OTHER="dropped")
        url = f"/api/v1/sessions/{gsid}/demographics"
        bad = client.put(url, json={"gamer": "yes"}, headers=gheaders)
        assert bad.status_code == 422 and {tuple(e["loc"]) for e in bad.json()["detail"]} == {
            ("body", "animator"), ("body", "gamer")}
        assert client.put(url, json={"animator": "often"}, headers=gheaders).status_code == 422
        assert client.put(url, json={"animator": "work"}, headers=gheaders).status_code == 200
        state = client.get(f"/api/v1/sessions/{gsid}", headers=gheaders).json()
        assert state["demographics_given"] is True
        trials = answer_all(client, gsid, gheaders, "equal" if choice == "left_slightly" else choice)
        assert len(trials) == 10

    rows = list(csv.DictReader(io.StringIO(client.get("/api/v1/studies/gait/export.csv",
                                                      headers=researcher_headers).text)))
    assert len(rows) == 20 and {r["session_id"] for r in rows}.isdisjoint({sid})
    assert "animator" in rows[0] and "gamer" not in rows[0] and {r["animator"] for r in rows} == {"work"}
    assert {r["animation"] for r in rows} == {"walk", "run"}
    assert {r["test_condition"] for r in rows if r["catch"] == "false"} == {"hybrid1", "hybrid2"}
    assert sum(r["catch"] == "true" for r in rows) == 4
    assert all(r["test_condition"] == r["reference_condition"] == "keyframe" for r in rows if r["catch"] == "true")
    # The thesis study's export and numbers did not move.
    assert client.get("/api/v1/studies/thesis/export.csv", headers=researcher_headers).text == thesis_csv
    assert client.get("/api/v1/studies/thesis/results", headers=researcher_headers).json()["comparisons"] == \
        thesis_results
    gait = client.get("/api/v1/studies/gait/results", headers=researcher_headers).json()
    assert [(c["animation"], c["condition"], c["reference"]) for c in gait["comparisons"]] == [
        ("run", "hybrid1", "keyframe"), ("run", "hybrid2", "keyframe"), ("walk", "hybrid1", "keyframe"),
        ("walk", "hybrid2", "keyframe")]
    # "right_much" on the catch trials failed them: that participant is screened out and not analysed
    assert {r["outcome"] for r in rows if r["choice"] == "right_much"} == {"screened_out"}
    assert gait["participants"]["screened_out"] == 1
    assert all(c["votes"] == 2 for c in gait["comparisons"]) and set(gait["demographics"]) == {"animator"}
    assert thesis.id != db.query(Study).filter_by(slug="gait").one().id


def test_recruitment_parameters_completion_url_and_screening(client, db, researcher_headers):
    make_study(db, Design(conditions=["hybrid1", "hybrid2"], animations=["walk", "run"], catch_trials=2),
               slug="gait", **{k: GAIT[k] for k in ("texts", "scale", "questions", "recruitment")})
    outcomes = {}
    for catch_choice in ("equal", "left_much"):
        gsid, gheaders = start(client, "gait", PROLIFIC_PID="pid/1 x", STUDY_ID="s1", OTHER="dropped")
        while (r := client.get(f"/api/v1/sessions/{gsid}/next", headers=gheaders)).status_code == 200:
            trial = r.json()
            is_catch = _is_catch(db, trial["trial_id"])
            vote(client, gsid, gheaders, trial["trial_id"], catch_choice if is_catch else "equal")
        outcomes[catch_choice] = client.get(f"/api/v1/sessions/{gsid}", headers=gheaders).json()
    assert outcomes["equal"]["outcome"] == "completed" and outcomes["equal"]["completion_code"] == "GOOD1"
    assert outcomes["equal"]["completion_url"] == "https://app.prolific.com/c?cc=GOOD1&pid=pid%2F1%20x"
    assert outcomes["left_much"]["outcome"] == "screened_out"
    assert outcomes["left_much"]["completion_code"] == "SCREEN1"
    assert outcomes["left_much"]["completion_url"] == "https://example.org/out?cc=SCREEN1"
    from server.participants.models import ParticipantSession

    kept = {ps.id: ps.external for ps in db.query(ParticipantSession)}
    assert set(map(json.dumps, kept.values())) == {json.dumps({"PROLIFIC_PID": "pid/1 x", "STUDY_ID": "s1"})}
    rows = list(export_rows(db, service.get_study(db, "gait")))
    assert service.export_columns(service.get_study(db, "gait"))[-2:] == ["PROLIFIC_PID", "STUDY_ID"]
    assert len(rows) == 20 and {(r["PROLIFIC_PID"], r["STUDY_ID"]) for r in rows} == {("pid/1 x", "s1")}
    assert "OTHER" not in rows[0]


def _is_catch(db, trial_id):
    from server.participants.models import Trial

    return db.query(Trial).filter_by(public_id=trial_id).one().comparison.kind == "catch"


# --- ownership -----------------------------------------------------------------------------------------------------

def test_researchers_manage_their_own_studies_and_admins_all(client, db, media_dir):
    make_study(db)  # the thesis study: no owner
    alice, bob = login(client, db, "alice@example.org"), login(client, db, "bob@example.org")
    admin = login(client, db, "admin@example.org", admin=True)
    assert client.post("/api/v1/studies", json=GAIT, headers=alice).status_code == 201
    assert [s["slug"] for s in client.get("/api/v1/studies", headers=alice).json()] == ["gait"]
    assert client.get("/api/v1/studies", headers=bob).json() == []
    assert [s["slug"] for s in client.get("/api/v1/studies", headers=admin).json()] == ["thesis", "gait"]
    owner = client.get("/api/v1/studies", headers=admin).json()[1]["owner"]
    assert owner == "alice@example.org"
    for path in ("/export.csv", "/export.json", "/results", "/definition"):
        assert client.get(f"/api/v1/studies/gait{path}", headers=bob).status_code == 404, path
        assert client.get(f"/api/v1/studies/thesis{path}", headers=alice).status_code == 404, path
        assert client.get(f"/api/v1/studies/gait{path}", headers=alice).status_code == 200, path
        assert client.get(f"/api/v1/studies/gait{path}", headers=admin).status_code == 200, path
    assert client.post("/api/v1/studies/gait/open", headers=bob).status_code == 404
    assert client.patch("/api/v1/studies/gait", json={"title": "x"}, headers=bob).status_code == 404
    assert client.delete("/api/v1/studies/gait", headers=bob).status_code == 404
    assert client.post("/api/v1/studies/thesis/close", headers=alice).status_code == 404
    assert client.post("/api/v1/studies/thesis/close", headers=admin).status_code == 200
    assert client.get("/api/v1/studies").status_code == 401


# --- bad input ----------------------------------------------------------------------------------------------------

def _with(**changes):
    body = json.loads(json.dumps(GAIT))
    for path, value in changes.items():
        target = body
        *parents, last = path.split("__")
        for p in parents:
            target = target[p]
        if value is None:
            target.pop(last)
        else:
            target[last] = value
    return body


@pytest.mark.parametrize(("changes", "field"), [
    ({"texts__consent": None}, ["body", "texts", "consent"]),
    ({"design__repeats": "often"}, ["body", "design", "repeats"]),
    ({"texts__information": "x" * 5001}, ["body", "texts", "information"]),
    ({"recruitment__completed__url": "javascript:alert(1)"}, ["body", "recruitment"]),
    ({"recruitment__completed__url": "https://x.org/?id={workerId}"}, ["body", "recruitment"]),
    ({"design__conditions": ["hybrid1"], "design__animations": ["walk"], "design__catch_trials": 0},
     ["body", "design"]),
    ({"questions": [{"id": "score", "text": "t", "choices": [{"id": "a", "label": "A"}, {"id": "b", "label": "B"}]}]},
     ["body", "questions", 0, "id"]),
    ({"slug": "Not A Slug"}, ["body", "slug"]),
    ({"scale__labels": ["a", "b"]}, ["body", "scale", "labels"]),
    ({"surprise": 1}, ["body", "surprise"]),
])
def test_invalid_study_bodies_name_the_field_and_create_nothing(client, db, media_dir, researcher_headers,
                                                                 changes, field):
    r = client.post("/api/v1/studies", json=_with(**changes), headers=researcher_headers)
    assert r.status_code == 422, r.text
    assert field in [e["loc"] for e in r.json()["detail"]], r.json()
    assert db.query(Study).count() == 0


def test_unknown_condition_or_animation_and_taken_slug(client, db, media_dir, researcher_headers):
    r = client.post("/api/v1/studies", json=_with(design__conditions=["hybrid1", "footik"]),
                    headers=researcher_headers)
    assert r.status_code == 422 and "footik" in r.json()["detail"] and "hybrid2" in r.json()["detail"]
    r = client.post("/api/v1/studies", json=_with(design__animations=["walk", "moonwalk"]),
                    headers=researcher_headers)
    assert r.status_code == 422 and "moonwalk" in r.json()["detail"]
    assert db.query(Study).count() == 0
    assert client.post("/api/v1/studies", json=GAIT, headers=researcher_headers).status_code == 201
    assert client.post("/api/v1/studies", json=GAIT, headers=researcher_headers).status_code == 409
    assert db.query(Study).count() == 1


def test_an_old_render_manifest_is_a_clear_conflict(client, db, media_dir, researcher_headers):
    old = fake_media().model_dump()
    for entry in old["clips"].values():
        del entry["condition"]
    (media_dir / "manifest.json").write_text(json.dumps(old))
    r = client.post("/api/v1/studies", json=GAIT, headers=researcher_headers)
    assert r.status_code == 409 and "animstudy render" in r.json()["detail"]


def test_study_file_upload_reports_lines(client, db, media_dir, researcher_headers):
    text = THESIS_FILE.read_text().replace('slug = "thesis"', 'slug = "upload"').replace("repeats = 1", "repeats = 0")
    r = client.post("/api/v1/studies/file", content=text.encode(), headers={**researcher_headers,
                                                                           "Content-Type": "application/toml"})
    line = text.splitlines().index("repeats = 0") + 1
    assert r.status_code == 422 and r.json()["detail"][0]["msg"].startswith(f"design.repeats (line {line}):")
    r = client.post("/api/v1/studies/file", content=text.replace("repeats = 0", "repeats = 1").encode(),
                    headers={**researcher_headers, "Content-Type": "application/toml"})
    assert r.status_code == 201 and r.json()["slug"] == "upload"
    assert client.post("/api/v1/studies/file", content=b"slug = ", headers=researcher_headers).status_code == 422


def test_study_file_errors_name_path_and_line():
    text = THESIS_FILE.read_text()
    bad = text.replace('conditions = ["hybrid0", "hybrid1"]', 'conditions = ["hybrid0", 7]').replace(
        'id = "tech_savvy"', 'id = "Tech Savvy"')
    with pytest.raises(StudyFileError) as info:
        parse_study_text(bad, "bad.toml")
    lines = bad.splitlines()
    conditions_line = lines.index('conditions = ["hybrid0", 7]') + 1
    id_line = lines.index('id = "Tech Savvy"') + 1
    assert info.value.errors[0].startswith(f"questions[1].id (line {id_line}):"), info.value.errors
    assert info.value.errors[1].startswith(f"design.conditions[1] (line {conditions_line}):"), info.value.errors


# --- editing ------------------------------------------------------------------------------------------------------

def test_patch_and_delete_rules(client, db, media_dir, researcher_headers):
    assert client.post("/api/v1/studies", json=GAIT, headers=researcher_headers).status_code == 201
    r = client.patch("/api/v1/studies/gait", json={"texts": {"thanks": "Merci!"}, "recruitment": {
        "parameters": ["workerId"], "completed": {"code": "M1", "url": "https://mturk.example/?w={workerId}"}}},
        headers=researcher_headers)
    assert r.status_code == 200, r.text
    definition = client.get("/api/v1/studies/gait/definition", headers=researcher_headers).json()
    assert definition["texts"]["thanks"] == "Merci!" and definition["texts"]["contact"] == "gait@example.org"
    assert definition["recruitment"]["parameters"] == ["workerId"]
    r = client.patch("/api/v1/studies/gait", json={"texts": {"thanks": "x" * 1001}}, headers=researcher_headers)
    assert r.status_code == 422 and ["body", "texts", "thanks"] in [e["loc"] for e in r.json()["detail"]]
    r = client.patch("/api/v1/studies/gait", json={"design": {**GAIT["design"], "repeats": 2, "catch_trials": 1}},
                     headers=researcher_headers)
    assert r.status_code == 200 and r.json()["trials_total"] == 4 * 2 * 2 + 1
    study = db.query(Study).filter_by(slug="gait").one()
    assert sorted(c.kind for c in study.comparisons) == ["catch"] + ["test"] * 4
    r = client.patch("/api/v1/studies/gait", json={"design": {**GAIT["design"], "conditions": ["hybrid9"]}},
                     headers=researcher_headers)
    assert r.status_code == 422 and "hybrid9" in r.json()["detail"]
    client.post("/api/v1/studies/gait/open", headers=researcher_headers)
    r = client.patch("/api/v1/studies/gait", json={"design": GAIT["design"]}, headers=researcher_headers)
    assert r.status_code == 409
    client.post("/api/v1/studies/gait/close", headers=researcher_headers)
    r = client.patch("/api/v1/studies/gait", json={"texts": {"thanks": "Later"}}, headers=researcher_headers)
    assert r.status_code == 409
    assert client.delete("/api/v1/studies/gait", headers=researcher_headers).status_code == 409
    assert client.post("/api/v1/studies", json=_with(slug="draft2"), headers=researcher_headers).status_code == 201
    assert client.delete("/api/v1/studies/draft2", headers=researcher_headers).status_code == 204
    assert client.get("/api/v1/studies/draft2").status_code == 404


# --- the CLI ------------------------------------------------------------------------------------------------------

def test_study_cli(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("ANIMSTUDY_VAR_DIR", str(tmp_path / "var"))
    monkeypatch.setenv("ANIMSTUDY_SECRET_KEY", "cli-test-secret-0123456789abcdef0123")
    monkeypatch.delenv("ANIMSTUDY_DATABASE_URL", raising=False)
    monkeypatch.delenv("DATABASE_URL", raising=False)
    assert cli.main(["study", "schema"]) == 0
    schema = json.loads(capsys.readouterr().out)
    assert {"slug", "title", "texts", "scale", "questions", "design", "recruitment"} <= set(schema["properties"])
    assert cli.main(["study", "validate", str(THESIS_FILE)]) == 0
    assert "16 trials per participant" in capsys.readouterr().out
    bad = tmp_path / "bad.toml"
    bad.write_text(THESIS_FILE.read_text().replace("repeats = 1", "repeats = 9"))
    assert cli.main(["study", "validate", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "design.repeats (line" in err and "less than or equal to 5" in err
    # The first account `serve` makes is an admin (it must manage the default study, which has no owner).
    from server.config import Settings
    from server.db import make_engine, migrate, session_factory
    from server.researchers.models import Researcher

    settings = Settings.from_env()
    engine = make_engine(settings.sqlalchemy_url)
    migrate(engine)
    cli.ensure_researcher(settings, session_factory(engine))
    assert cli.main(["researcher", "create", "--email", "boss@example.org", "--password", "0123456789ab",
                     "--admin"]) == 0
    assert cli.main(["researcher", "create", "--email", "staff@example.org", "--password", "0123456789ab"]) == 0
    with session_factory(engine)() as db:
        assert [(r.email, r.is_admin) for r in db.query(Researcher).order_by(Researcher.id)] == [
            ("admin@localhost", True), ("boss@example.org", True), ("staff@example.org", False)]
    assert "(admin" in capsys.readouterr().out
    # A study in the CLI's database (the videos are fake: create needs the renderer, tested in the browser tests).
    with session_factory(engine)() as db:
        service.create_study(db, write_fake_media(settings.media_dir), thesis_study(), media_dir=settings.media_dir)
    engine.dispose()
    assert cli.main(["study", "list"]) == 0
    listed = capsys.readouterr().out
    assert "thesis" in listed and "draft" in listed
    assert cli.main(["study", "open", "thesis"]) == 0 and "is open" in capsys.readouterr().out
    assert cli.main(["study", "close", "nope"]) == 2
    out = tmp_path / "votes.csv"
    assert cli.main(["study", "export", "thesis", "--format", "csv", "--out", str(out)]) == 0
    assert out.read_text().splitlines()[0].startswith("session_id,trial_index,practice,catch,animation")
    assert cli.main(["study", "export", "thesis", "--format", "json"]) == 0
    assert json.loads(capsys.readouterr().out)["columns"][-26:] == [
        "answered_at", "consent_version", "session_state", "outcome", "viewport_width", "viewport_height",
        "device_pixel_ratio", "video_scale", "video_scaled", "unfaithful", "left_video", "right_video", "pair_video",
        "stimulus_set", "design_mode", "left_condition", "right_condition", "screened_by", "pilot", "answer_format",
        "ladder", "level", "correct", "PROLIFIC_PID", "STUDY_ID", "SESSION_ID"]
