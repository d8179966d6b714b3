"""studies as data: conditions instead of keyframe/hybrid columns, study sections, per-question answers, owners

Revision ID: 0004
Revises: 0003
Create Date: 2026-12-01 18:30:00

Every stored vote and score stays as it is: the old scores are from the hybrid's point of view, the hybrid is the
test condition and the keyframe clip the reference, and new scores are from the test condition's point of view.
Old -> new:
- stimuli.method/increment -> stimuli.condition (``keyframe``; ``hybrid<increment>``)
- comparisons.keyframe_id/hybrid_id -> reference_id/test_id; video_hybrid_left -> video_reference_right and
  video_hybrid_right -> video_reference_left; comparisons.animation/increment dropped (the stimuli's)
- trials.hybrid_side -> reference_side (the other side)
- sessions.gamer/tech_savvy -> sessions.answers {"gamer": ..., "tech_savvy": ...}
- studies.completion_code/url -> studies.recruitment; design {increments, practice, practice_increment, ...} ->
  {reference, conditions, practice (a condition or null), ...}; new scale, questions (the thesis's two), owner_id
- researchers.is_admin (existing researchers become admins: they could see every study before)
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None

THESIS_LABELS = [
    "Left animation is significantly better than the right animation",
    "Left animation is slightly better than the right animation",
    "They look equal in visual quality",
    "Right animation is slightly better than the left animation",
    "Right animation is significantly better than the left animation",
]
_YES_NO = [{"id": "yes", "label": "Yes"}, {"id": "no", "label": "No"}, {"id": "dont_know", "label": "Don't know"}]
THESIS_QUESTIONS = [
    {"id": "gamer", "text": "Do you consider yourself a gamer?", "choices": _YES_NO},
    {"id": "tech_savvy", "text": "Do you consider yourself tech-savvy?", "choices": _YES_NO},
]
THESIS_SCALE = {"question": "Which animation looks better?", "labels": THESIS_LABELS, "left": "Left", "right": "Right"}
OUTCOME = {"code": None, "url": None}


def _studies(*columns: str) -> sa.TableClause:
    types = {"id": sa.Integer(), "design": sa.JSON(), "scale": sa.JSON(), "questions": sa.JSON(),
             "recruitment": sa.JSON(), "completion_code": sa.String(), "completion_url": sa.Text()}
    return sa.table("studies", *(sa.column(c, types[c]) for c in columns))


def upgrade() -> None:
    conn = op.get_bind()
    with op.batch_alter_table("researchers") as batch_op:
        batch_op.add_column(sa.Column("is_admin", sa.Boolean(), nullable=False, server_default=sa.false()))
    op.execute(sa.text("UPDATE researchers SET is_admin = :t").bindparams(t=True))

    with op.batch_alter_table("studies") as batch_op:
        for name in ("scale", "questions", "recruitment"):
            batch_op.add_column(sa.Column(name, sa.JSON(), nullable=True))
        batch_op.add_column(sa.Column("owner_id", sa.Integer(), nullable=True))
    old = _studies("id", "design", "completion_code", "completion_url")
    new = _studies("id", "design", "scale", "questions", "recruitment")
    for sid, design, code, url in conn.execute(sa.select(old)).all():
        converted = {
            "reference": "keyframe",
            "conditions": [f"hybrid{i}" for i in design.get("increments", [0, 1])],
            "animations": design.get("animations", ["walk", "run", "crouch", "idle"]),
            "repeats": design.get("repeats", 1),
            "practice": f"hybrid{design.get('practice_increment', 2)}" if design.get("practice") else None,
            "catch_trials": design.get("catch_trials", 0),
        }
        recruitment = {"parameters": ["PROLIFIC_PID", "STUDY_ID", "SESSION_ID"],
                       "completed": {"code": code, "url": url}, "screened_out": dict(OUTCOME),
                       "catch_failures_allowed": 0}
        conn.execute(new.update().where(new.c.id == sid).values(
            design=converted, scale=THESIS_SCALE, questions=THESIS_QUESTIONS, recruitment=recruitment))
    with op.batch_alter_table("studies") as batch_op:
        for name in ("scale", "questions", "recruitment"):
            batch_op.alter_column(name, existing_type=sa.JSON(), nullable=False)
        batch_op.create_index(batch_op.f("ix_studies_owner_id"), ["owner_id"], unique=False)
        batch_op.create_foreign_key(batch_op.f("fk_studies_owner_id_researchers"), "researchers", ["owner_id"],
                                    ["id"], ondelete="SET NULL")
        batch_op.drop_column("completion_code")
        batch_op.drop_column("completion_url")

    with op.batch_alter_table("stimuli") as batch_op:
        batch_op.add_column(sa.Column("condition", sa.String(length=32), nullable=True))
    op.execute("UPDATE stimuli SET condition = CASE WHEN method = 'keyframe' THEN 'keyframe' "
               "ELSE 'hybrid' || CAST(increment AS VARCHAR) END")
    with op.batch_alter_table("stimuli") as batch_op:
        batch_op.alter_column("condition", existing_type=sa.String(length=32), nullable=False)
        batch_op.drop_column("method")
        batch_op.drop_column("increment")

    with op.batch_alter_table("comparisons") as batch_op:
        batch_op.add_column(sa.Column("reference_id", sa.Integer(), nullable=True))
        batch_op.add_column(sa.Column("test_id", sa.Integer(), nullable=True))
        batch_op.add_column(sa.Column("video_reference_left", sa.String(length=64), nullable=True))
        batch_op.add_column(sa.Column("video_reference_right", sa.String(length=64), nullable=True))
    op.execute("UPDATE comparisons SET reference_id = keyframe_id, test_id = hybrid_id, "
               "video_reference_left = video_hybrid_right, video_reference_right = video_hybrid_left")
    with op.batch_alter_table("comparisons") as batch_op:
        batch_op.drop_constraint("fk_comparisons_keyframe_id_stimuli", type_="foreignkey")
        batch_op.drop_constraint("fk_comparisons_hybrid_id_stimuli", type_="foreignkey")
        for name in ("animation", "increment", "keyframe_id", "hybrid_id", "video_hybrid_left", "video_hybrid_right"):
            batch_op.drop_column(name)
        for name, type_ in (("reference_id", sa.Integer()), ("test_id", sa.Integer()),
                            ("video_reference_left", sa.String(length=64)),
                            ("video_reference_right", sa.String(length=64))):
            batch_op.alter_column(name, existing_type=type_, nullable=False)
        batch_op.create_foreign_key(batch_op.f("fk_comparisons_reference_id_stimuli"), "stimuli", ["reference_id"],
                                    ["id"])
        batch_op.create_foreign_key(batch_op.f("fk_comparisons_test_id_stimuli"), "stimuli", ["test_id"], ["id"])

    with op.batch_alter_table("trials") as batch_op:
        batch_op.add_column(sa.Column("reference_side", sa.String(length=8), nullable=True))
    op.execute("UPDATE trials SET reference_side = CASE WHEN hybrid_side = 'left' THEN 'right' ELSE 'left' END")
    with op.batch_alter_table("trials") as batch_op:
        batch_op.alter_column("reference_side", existing_type=sa.String(length=8), nullable=False)
        batch_op.drop_column("hybrid_side")

    with op.batch_alter_table("sessions") as batch_op:
        batch_op.add_column(sa.Column("answers", sa.JSON(), nullable=True))
    sessions = sa.table("sessions", sa.column("id", sa.String()), sa.column("gamer", sa.String()),
                        sa.column("tech_savvy", sa.String()), sa.column("answers", sa.JSON()))
    for sid, gamer, tech in conn.execute(sa.select(sessions.c.id, sessions.c.gamer, sessions.c.tech_savvy).where(
            sessions.c.gamer.is_not(None) | sessions.c.tech_savvy.is_not(None))).all():
        answers = {k: v for k, v in (("gamer", gamer), ("tech_savvy", tech)) if v is not None}
        conn.execute(sessions.update().where(sessions.c.id == sid).values(answers=answers))
    with op.batch_alter_table("sessions") as batch_op:
        batch_op.drop_column("gamer")
        batch_op.drop_column("tech_savvy")


def _increment(condition: str) -> int | None:
    tail = condition.removeprefix("hybrid")
    return int(tail) if condition.startswith("hybrid") and tail.isdigit() else None


def downgrade() -> None:
    """Back to 0003 for the thesis's conditions (``keyframe``, ``hybrid<n>``); others lose their increment."""
    conn = op.get_bind()
    with op.batch_alter_table("sessions") as batch_op:
        batch_op.add_column(sa.Column("gamer", sa.String(length=16), nullable=True))
        batch_op.add_column(sa.Column("tech_savvy", sa.String(length=16), nullable=True))
    sessions = sa.table("sessions", sa.column("id", sa.String()), sa.column("gamer", sa.String()),
                        sa.column("tech_savvy", sa.String()), sa.column("answers", sa.JSON()))
    for sid, answers in conn.execute(sa.select(sessions.c.id, sessions.c.answers)).all():
        if answers:
            conn.execute(sessions.update().where(sessions.c.id == sid).values(
                gamer=answers.get("gamer"), tech_savvy=answers.get("tech_savvy")))
    with op.batch_alter_table("sessions") as batch_op:
        batch_op.drop_column("answers")

    with op.batch_alter_table("trials") as batch_op:
        batch_op.add_column(sa.Column("hybrid_side", sa.String(length=8), nullable=True))
    op.execute("UPDATE trials SET hybrid_side = CASE WHEN reference_side = 'left' THEN 'right' ELSE 'left' END")
    with op.batch_alter_table("trials") as batch_op:
        batch_op.alter_column("hybrid_side", existing_type=sa.String(length=8), nullable=False)
        batch_op.drop_column("reference_side")

    with op.batch_alter_table("stimuli") as batch_op:
        batch_op.add_column(sa.Column("method", sa.String(length=16), nullable=True))
        batch_op.add_column(sa.Column("increment", sa.Integer(), nullable=True))
    stimuli = sa.table("stimuli", sa.column("id", sa.Integer()), sa.column("condition", sa.String()),
                       sa.column("method", sa.String()), sa.column("increment", sa.Integer()))
    for sid, condition in conn.execute(sa.select(stimuli.c.id, stimuli.c.condition)).all():
        conn.execute(stimuli.update().where(stimuli.c.id == sid).values(
            method="keyframe" if condition == "keyframe" else "hybrid", increment=_increment(condition)))

    with op.batch_alter_table("comparisons") as batch_op:
        batch_op.add_column(sa.Column("animation", sa.String(length=32), nullable=True))
        batch_op.add_column(sa.Column("increment", sa.Integer(), nullable=True))
        batch_op.add_column(sa.Column("keyframe_id", sa.Integer(), nullable=True))
        batch_op.add_column(sa.Column("hybrid_id", sa.Integer(), nullable=True))
        batch_op.add_column(sa.Column("video_hybrid_left", sa.String(length=64), nullable=True))
        batch_op.add_column(sa.Column("video_hybrid_right", sa.String(length=64), nullable=True))
    op.execute("UPDATE comparisons SET keyframe_id = reference_id, hybrid_id = test_id, "
               "video_hybrid_left = video_reference_right, video_hybrid_right = video_reference_left, "
               "animation = (SELECT animation FROM stimuli WHERE stimuli.id = comparisons.test_id), "
               "increment = CASE WHEN kind = 'catch' THEN NULL ELSE "
               "(SELECT increment FROM stimuli WHERE stimuli.id = comparisons.test_id) END")
    with op.batch_alter_table("comparisons") as batch_op:
        batch_op.drop_constraint("fk_comparisons_reference_id_stimuli", type_="foreignkey")
        batch_op.drop_constraint("fk_comparisons_test_id_stimuli", type_="foreignkey")
        batch_op.drop_column("reference_id")
        batch_op.drop_column("test_id")
        batch_op.drop_column("video_reference_left")
        batch_op.drop_column("video_reference_right")
        for name, type_ in (("animation", sa.String(length=32)), ("keyframe_id", sa.Integer()),
                            ("hybrid_id", sa.Integer()), ("video_hybrid_left", sa.String(length=64)),
                            ("video_hybrid_right", sa.String(length=64))):
            batch_op.alter_column(name, existing_type=type_, nullable=False)
        batch_op.create_foreign_key(batch_op.f("fk_comparisons_keyframe_id_stimuli"), "stimuli", ["keyframe_id"],
                                    ["id"])
        batch_op.create_foreign_key(batch_op.f("fk_comparisons_hybrid_id_stimuli"), "stimuli", ["hybrid_id"], ["id"])
    with op.batch_alter_table("stimuli") as batch_op:
        batch_op.alter_column("method", existing_type=sa.String(length=16), nullable=False)
        batch_op.drop_column("condition")

    with op.batch_alter_table("studies") as batch_op:
        batch_op.add_column(sa.Column("completion_code", sa.String(length=64), nullable=True))
        batch_op.add_column(sa.Column("completion_url", sa.Text(), nullable=True))
    new = _studies("id", "design", "recruitment")
    old = _studies("id", "design", "completion_code", "completion_url")
    for sid, design, recruitment in conn.execute(sa.select(new)).all():
        increments = [_increment(c) for c in design["conditions"]]
        practice = _increment(design["practice"]) if design.get("practice") else None
        conn.execute(old.update().where(old.c.id == sid).values(
            design={"animations": design["animations"], "increments": [i for i in increments if i is not None],
                    "repeats": design["repeats"], "practice": practice is not None,
                    "practice_increment": 2 if practice is None else practice,
                    "catch_trials": design["catch_trials"]},
            completion_code=recruitment["completed"]["code"], completion_url=recruitment["completed"]["url"]))
    with op.batch_alter_table("studies") as batch_op:
        batch_op.drop_constraint("fk_studies_owner_id_researchers", type_="foreignkey")
        batch_op.drop_index(batch_op.f("ix_studies_owner_id"))
        for name in ("scale", "questions", "recruitment", "owner_id"):
            batch_op.drop_column(name)
    with op.batch_alter_table("researchers") as batch_op:
        batch_op.drop_column("is_admin")
