"""Migration 0004 (studies as data) on a database populated at revision 0003: every vote, score, shown video and
export row comes through unchanged (old export columns mapped to the new ones)."""

from __future__ import annotations

import random
from datetime import UTC, datetime, timedelta

import pytest
import sqlalchemy as sa
from sqlalchemy.orm import Session

from server.db import migrate
from server.participants import service as participants
from server.participants.models import ParticipantSession
from server.research.export import export_rows
from server.studies import service
from server.studies.models import Study
from tests.conftest import DATABASES, _fresh_engine

VALUES = {"left_much": 2, "left_slightly": 1, "equal": 0, "right_slightly": -1, "right_much": -2}
OLD_DESIGN = {"animations": ["walk", "run", "crouch", "idle"], "increments": [0, 1], "repeats": 1,
              "practice": True, "practice_increment": 2, "catch_trials": 1}
# The export of revision 0003 (server/studies/service.py at 0003), as SQL.
OLD_EXPORT = """
SELECT s.id AS session_id, t."index" AS trial_index, t.practice, c.kind = 'catch' AS is_catch, c.animation,
       c.increment, t.hybrid_side, v.choice, v.score, v.rt_ms, s.gamer, s.tech_savvy, v.answered_at,
       s.consent_version, s.state AS session_state,
       CASE WHEN t.hybrid_side = 'left' THEN c.video_hybrid_left ELSE c.video_hybrid_right END AS video
FROM votes v JOIN trials t ON v.trial_id = t.id JOIN sessions s ON t.session_id = s.id
JOIN comparisons c ON t.comparison_id = c.id
WHERE s.study_id = :study ORDER BY s.created_at, s.id, t."index"
"""


def populate_0003(conn: sa.Connection, rng: random.Random) -> int:
    """A thesis study (with a practice and a catch trial) as revision 0003 stored it, with completed, unfinished
    and withdrawn sessions; returns the study id."""
    now = datetime(2026, 11, 25, 12, tzinfo=UTC)
    conn.execute(sa.text("INSERT INTO researchers (email, password_hash, created_at) VALUES "
                         "('old@example.org', 'x', :t)"), {"t": now})
    study_table = sa.table("studies", *(sa.column(c) for c in (
        "slug", "title", "consent_version", "state", "completion_code", "completion_url",
        "created_at", "opened_at")), sa.column("design", sa.JSON()), sa.column("texts", sa.JSON()))
    conn.execute(study_table.insert().values(
        slug="thesis", title="How good does this character animation look?", design=OLD_DESIGN,
        texts={"information": "i", "consent": "c", "instructions": "n", "thanks": "t", "contact": "o"},
        consent_version="2026-11-1", state="open", completion_code="OLD42",
        completion_url="https://example.org/done?cc=OLD42", created_at=now, opened_at=now))
    study_id = conn.scalar(sa.text("SELECT id FROM studies"))
    stimulus = {}
    for a in OLD_DESIGN["animations"]:
        for method, inc in (("keyframe", None), ("hybrid", 0), ("hybrid", 1), ("hybrid", 2)):
            cid = f"{a}-{method if inc is None else f'hybrid{inc}'}"
            stimulus[cid] = conn.scalar(sa.text(
                "INSERT INTO stimuli (study_id, clip_id, animation, method, increment, video, poster, frames, fps) "
                "VALUES (:s, :c, :a, :m, :i, :v, :p, 40, 30) RETURNING id"),
                {"s": study_id, "c": cid, "a": a, "m": method, "i": inc, "v": f"v-{cid}.mp4", "p": f"p-{cid}.jpg"})
    comparisons = []  # (id, kind)

    def comparison(kind: str, animation: str, inc: int | None, keyframe: str, hybrid: str) -> None:
        cid = conn.scalar(sa.text(
            "INSERT INTO comparisons (study_id, kind, animation, increment, keyframe_id, hybrid_id, "
            "video_hybrid_left, video_hybrid_right) VALUES (:s, :k, :a, :i, :kf, :h, :l, :r) RETURNING id"),
            {"s": study_id, "k": kind, "a": animation, "i": inc, "kf": stimulus[keyframe], "h": stimulus[hybrid],
             "l": f"pair-{hybrid}|{keyframe}.mp4", "r": f"pair-{keyframe}|{hybrid}.mp4"})
        comparisons.append((cid, kind))

    for a in OLD_DESIGN["animations"]:
        for inc in (0, 1):
            comparison("test", a, inc, f"{a}-keyframe", f"{a}-hybrid{inc}")
    comparison("catch", "walk", None, "walk-keyframe", "walk-keyframe")
    comparison("practice", "walk", 2, "walk-keyframe", "walk-hybrid2")

    for p in range(7):
        sid = f"{p:032x}"
        state = "withdrawn" if p == 6 else ("active" if p == 5 else "completed")
        answers = [(None, None), ("yes", "no"), ("dont_know", None)][p % 3] if state != "withdrawn" else (None, None)
        conn.execute(sa.text(
            "INSERT INTO sessions (id, study_id, token_hash, seed, trials_total, state, consent_at, consent_version, "
            "gamer, tech_savvy, external, created_at) VALUES (:id, :s, :h, :seed, 18, :st, :t, '2026-11-1', :g, "
            ":ts, NULL, :t)"),
            {"id": sid, "s": study_id, "h": None if state == "withdrawn" else f"{p:064x}", "seed": p, "st": state,
             "t": now + timedelta(minutes=p), "g": answers[0], "ts": answers[1]})
        practice = [c for c in comparisons if c[1] == "practice"]
        body = [(c, side) for c in comparisons if c[1] == "test" for side in ("left", "right")]
        body += [(c, "left") for c in comparisons if c[1] == "catch"]
        rng.shuffle(body)
        order = [(practice[0], rng.choice(("left", "right"))), *body]
        answered = {5: 7, 6: 0}.get(p, len(order))
        for index, ((cid, _kind), side) in enumerate(order):
            tid = conn.scalar(sa.text(
                "INSERT INTO trials (session_id, \"index\", comparison_id, hybrid_side, practice) "
                "VALUES (:s, :i, :c, :h, :p) RETURNING id"), {"s": sid, "i": index, "c": cid, "h": side,
                                                               "p": index == 0})
            if index < answered:
                choice = rng.choice(list(VALUES))
                score = VALUES[choice] if side == "left" else -VALUES[choice]
                conn.execute(sa.text(
                    "INSERT INTO votes (trial_id, session_id, choice, score, rt_ms, idempotency_key, request_hash, "
                    "extra, answered_at) VALUES (:t, :s, :c, :sc, :rt, :k, 'h', NULL, :at)"),
                    {"t": tid, "s": sid, "c": choice, "sc": score, "rt": rng.randint(300, 9000), "k": f"k{tid}",
                     "at": now + timedelta(minutes=p, seconds=index)})
    return study_id


def _old_to_new(row: sa.Row) -> dict:
    r = row._asdict()
    return {
        "session_id": r["session_id"], "trial_index": r["trial_index"], "practice": bool(r["practice"]),
        "catch": bool(r["is_catch"]), "animation": r["animation"], "reference_condition": "keyframe",
        "test_condition": "keyframe" if r["increment"] is None else f"hybrid{r['increment']}",
        "test_side": r["hybrid_side"], "choice": r["choice"], "score": r["score"], "rt_ms": r["rt_ms"],
        "gamer": r["gamer"], "tech_savvy": r["tech_savvy"], "consent_version": r["consent_version"],
        "session_state": r["session_state"],
    }


@pytest.mark.parametrize("kind", DATABASES)
def test_0004_keeps_every_vote_score_video_and_export_row(kind, tmp_path_factory):
    engine = _fresh_engine(kind, tmp_path_factory, database="test_animstudy_migration_0004")
    try:
        migrate(engine, "0003")
        with engine.begin() as conn:
            study_id = populate_0003(conn, random.Random(4))
        with engine.connect() as conn:
            old_rows = conn.execute(sa.text(OLD_EXPORT), {"study": study_id}).all()
            old_votes = conn.execute(sa.text("SELECT id, trial_id, session_id, choice, score, rt_ms, answered_at "
                                             "FROM votes ORDER BY id")).all()
        assert len(old_rows) == 5 * 18 + 7 and {r.increment for r in old_rows} == {0, 1, 2, None}

        migrate(engine)

        with engine.connect() as conn:
            assert conn.execute(sa.text("SELECT id, trial_id, session_id, choice, score, rt_ms, answered_at "
                                        "FROM votes ORDER BY id")).all() == old_votes
        with Session(engine) as db:
            study = db.get(Study, study_id)
            new_rows = list(export_rows(db, study))
            assert len(new_rows) == len(old_rows)
            for old, new in zip(old_rows, new_rows, strict=True):
                expected = _old_to_new(old)
                assert {k: new[k] for k in expected} == expected
                assert new["reference_side"] == ("right" if old.hybrid_side == "left" else "left")
                answered = old.answered_at if isinstance(old.answered_at, datetime) else \
                    datetime.fromisoformat(old.answered_at)
                assert new["answered_at"] == answered.astimezone(UTC).isoformat()
            # The video each trial showed is the video it shows now.
            trials = {(ps.id, t.index): t for ps in db.query(ParticipantSession) for t in ps.trials}
            for old in old_rows:
                trial = trials[(old.session_id, old.trial_index)]
                assert trial.comparison.video(trial.reference_side) == old.video
            # The study as data: the old design, texts, completion code and URL, the thesis questions.
            definition = service.definition(study)
            assert definition.design.conditions == ["hybrid0", "hybrid1"]
            assert (definition.design.practice, definition.design.catch_trials) == ("hybrid2", 1)
            assert definition.recruitment.completed.code == "OLD42"
            assert [q.id for q in definition.questions] == ["gamer", "tech_savvy"]
            assert service.trials_total(study) == 18
            # The unfinished session goes on: its next vote is scored as revision 0003 scored it.
            ps = db.get(ParticipantSession, f"{5:032x}")
            trial = participants.upcoming(db, ps)[0]
            hybrid_side = "left" if trial.reference_side == "right" else "right"
            result = participants.cast_vote(db, ps, trial, "left_much", 1000, "after-upgrade", {})
            assert result.created
            stored = db.execute(sa.text("SELECT score FROM votes WHERE idempotency_key = 'after-upgrade'")).scalar()
            assert stored == (2 if hybrid_side == "left" else -2)
    finally:
        engine.dispose()
