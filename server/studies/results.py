"""The results document of a study: progress, statistics, and the objective metrics of its clips."""

from __future__ import annotations

import copy
import json
import statistics as pystats
from functools import lru_cache
from pathlib import Path
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from server.participants.models import ParticipantSession, SessionState, Vote
from server.stimuli import service as stimulus_sets

from .assign import session_batches
from .interval_scale import study_scales
from .models import Study
from .service import export_rows, failed_catch_trials, session_outcome
from .statistics import analyse


def participant_counts(session: Session, study: Study) -> dict[str, int]:
    """``started``: every session created (withdrawn included); ``completed``: finished and not withdrawn;
    ``screened_out``: of those, the ones whose votes are not analysed (too many failed catch trials)."""
    rows = session.execute(select(ParticipantSession.state, func.count()).where(
        ParticipantSession.study_id == study.id).group_by(ParticipantSession.state)).all()
    by_state = {state: n for state, n in rows}
    failed = failed_catch_trials(session, study)
    completed = session.scalars(select(ParticipantSession.id).where(
        ParticipantSession.study_id == study.id, ParticipantSession.state == SessionState.completed,
        ParticipantSession.id.in_(failed))) if failed else []
    screened = sum(session_outcome(study, SessionState.completed, failed[sid]) == "screened_out" for sid in completed)
    return {"started": sum(by_state.values()), "completed": by_state.get(SessionState.completed, 0),
            "screened_out": screened, "withdrawn": by_state.get(SessionState.withdrawn, 0),
            "active": by_state.get(SessionState.active, 0)}


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


@lru_cache(maxsize=16)
def _analyse_cached(votes: tuple[tuple[tuple[str, Any], ...], ...], counts: tuple[tuple[str, int], ...],
                    questions: tuple[str, ...], anchor: str | None = None) -> dict[str, Any]:
    return analyse([dict(v) for v in votes], dict(counts), questions, anchor)


@lru_cache(maxsize=16)
def _scales_cached(votes: tuple[tuple[tuple[str, Any], ...], ...], conditions: tuple[str, ...]) -> list[dict]:
    return study_scales([dict(v) for v in votes], conditions)


# (study id, sessions, votes) -> the adaptive rounds: replaying every round refits the model once per session.
_ROUNDS: dict[tuple[int, int, int], list[dict[str, Any]]] = {}


def adaptive_rounds(session: Session, study: Study, n_votes: int) -> list[dict[str, Any]]:
    """Per session of an adaptive study, in order: the votes before it and the information its batch promised."""
    sessions = session.scalar(select(func.count()).select_from(ParticipantSession).where(
        ParticipantSession.study_id == study.id)) or 0
    key = (study.id, sessions, n_votes)
    if key not in _ROUNDS:
        if len(_ROUNDS) > 16:
            _ROUNDS.clear()
        _ROUNDS[key] = [{"round": i + 1, "votes_before": r.votes_before, "information": r.information,
                         "pairs": r.pairs} for i, r in enumerate(session_batches(session, study))]
    return copy.deepcopy(_ROUNDS[key])


def study_results(session: Session, study: Study, benchmark_path: Path) -> dict[str, Any]:
    """Everything the dashboard shows.  The statistics are cached on their input: scipy's exact Wilcoxon for
    up to 13 participants with ties enumerates sign patterns and takes seconds, and a dashboard polls."""
    votes = tuple(tuple(sorted(v.items())) for v in export_rows(session, study))
    counts = tuple(sorted(participant_counts(session, study).items()))
    questions = tuple(q["id"] for q in study.questions)
    results = copy.deepcopy(_analyse_cached(votes, counts, questions, study.design["reference"]))
    durations = [(ps.completed_at - ps.created_at).total_seconds() for ps in session.scalars(
        select(ParticipantSession).where(ParticipantSession.study_id == study.id,
                                         ParticipantSession.state == SessionState.completed))]
    results["overview"] = {
        "slug": study.slug, "title": study.title, "state": study.state,
        "reference": study.design["reference"], "conditions": study.design["conditions"],
        "questions": [{"id": q["id"], "text": q["text"]} for q in study.questions],
        "votes": session.scalar(select(func.count(Vote.id)).join(ParticipantSession).where(
            ParticipantSession.study_id == study.id)) or 0,
        "median_completion_s": pystats.median(durations) if durations else None,
    }
    # The clips of the study's stimulus set, as they were when the set was made: not the clip set on disk, which
    # may have been rebuilt since (and holds other researchers' clips).
    content = stimulus_sets.content_of(study.stimulus_set) if study.stimulus_set is not None else None
    results["stimulus_set"] = study.stimulus_set.digest if study.stimulus_set is not None else None
    results["clips"] = [{"id": c.id, "animation": c.animation, "condition": c.condition, "method": c.method,
                         "params": c.params, "key_count": c.key_count, "metrics": c.metrics, "shown": True,
                         "identical_to": c.identical_to} for c in (content.clips if content else [])]
    results["benchmark"] = _read_json(benchmark_path)
    mode = study.design.get("mode", "reference")
    results["overview"]["design_mode"] = mode
    results["scale"] = copy.deepcopy(_scales_cached(votes, (study.design["reference"], *study.design["conditions"])))
    results["adaptive_rounds"] = (adaptive_rounds(session, study, results["overview"]["votes"]) if mode == "adaptive"
                                  else None)
    return results
