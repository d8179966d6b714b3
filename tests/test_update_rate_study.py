"""studies/update-rate.toml end to end with the real commands (issue 38): the `pps` ladder of
server/clipset/update-rate.toml built (cut to the reference and that ladder), the study's pairs rendered small,
the study created and opened, planted observers through the service layer; every staircase level is the one the
vote log replays to, and the export's levels are the clip set's own `level` fields."""

from __future__ import annotations

import random
import re
from pathlib import Path

import pytest
from sqlalchemy import select

from server.clipset.manifest import read_clip_manifest
from server.config import Settings
from server.db import make_engine, session_factory
from server.participants import service
from server.participants.models import ParticipantSession
from server.research.export import export_rows
from server.studies.design import Design
from server.studies.models import Study
from tests.test_answer_formats import _replayed, observer
from tests.test_studies16_browser import cli_environment, run

REPO = Path(__file__).resolve().parents[1]
CLIP_SET = REPO / "server" / "clipset" / "update-rate.toml"
STUDY = REPO / "studies" / "update-rate.toml"


def pps_clip_set(folder: Path) -> Path:
    """server/clipset/update-rate.toml with only the reference and the pps ladder (the others are not shown)."""
    sections = re.split(r"(?m)^(?=\[)", CLIP_SET.read_text(encoding="utf-8"))
    kept = [sections[0]]
    for section in sections[1:]:
        header = section.split("\n", 1)[0].strip()
        if header == "[[conditions]]" and 'id = "keyframe"' not in section:
            continue
        if header == "[[ladders]]" and 'id = "pps"' not in section:
            continue
        kept.append(section)
    path = folder / "update-rate-pps.toml"
    path.write_text("".join(kept), encoding="utf-8")
    return path


@pytest.mark.slow  # about a minute: builds 14 clips and renders 38 small videos
def test_update_rate_study_end_to_end(data, tmp_path):
    var = tmp_path / "var"
    with cli_environment(data, var, "update-rate-secret-0123456789abcdef"):
        run("clips", "build", "--config", str(pps_clip_set(tmp_path)))
        run("render", "--width", "160", "--height", "120", "--no-shadows", "--workers", "1", "--study", str(STUDY))
        assert "62 trials per participant" in run("study", "create", str(STUDY), "--open")
        settings = Settings()
    levels = {(c.animation, c.condition): c.level for c in read_clip_manifest(settings.clips_dir).clips
              if c.ladder == "pps"}
    assert len(levels) == 2 * 6
    engine = make_engine(settings.sqlalchemy_url)
    try:
        with session_factory(engine)() as db:
            study = db.scalar(select(Study).where(Study.slug == "update-rate"))
            design = Design.model_validate(study.design)
            sessions = []
            for seed, threshold in ((1, 8.0), (2, 16.0)):
                ps = service.start_session(db, study, None).session
                service.set_answers(db, ps, {"gamer": "no", "tech_savvy": "yes"})
                answer = observer(threshold, random.Random(seed))
                for trial in sorted(ps.trials, key=lambda t: t.index):
                    db.refresh(trial)  # its level was chosen when the one before it was answered
                    service.cast_vote(db, ps, trial, answer(trial), 900, f"k{trial.id}", {})
                sessions.append(ps.id)
            for sid in sessions:
                ps = db.get(ParticipantSession, sid)
                assert ps.state == "completed" and ps.trials_total == 62
                stored, replayed = _replayed(db, ps, design)
                assert stored == replayed and sum(s is not None for s in stored) == 60
            rows = list(export_rows(db, study))
            assert len(rows) == 2 * 62
            assert all(r["level"] == levels[(r["animation"], r["test_condition"])] for r in rows)
            assert {r["test_condition"] for r in rows if r["catch"]} == {"pps4"}
    finally:
        engine.dispose()
