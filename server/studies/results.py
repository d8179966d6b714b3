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

from server.clipset.manifest import MANIFEST, ManifestError, read_clip_manifest
from server.media.build import MediaError, identical_clips, read_clip_set
from server.participants.models import ParticipantSession, SessionState, Vote

from . import scale
from .models import Study
from .service import export_rows, participant_counts
from .statistics import analyse


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


@lru_cache(maxsize=16)
def _analyse_cached(votes: tuple[tuple[tuple[str, Any], ...], ...], counts: tuple[tuple[str, int], ...],
                    questions: tuple[str, ...]) -> dict[str, Any]:
    return analyse([dict(v) for v in votes], dict(counts), questions)


@lru_cache(maxsize=4)
def _identical(clips_dir: Path, stamp: tuple[int, int]) -> dict[str, str]:
    """Clip id -> the first clip with the same arrays, for the clip set whose manifest has ``stamp`` (mtime, size):
    hashing every clip's arrays on each poll of the dashboard would cost more than the rest of the document."""
    try:
        return identical_clips(read_clip_set(clips_dir))
    except MediaError:
        return {}


def study_results(session: Session, study: Study, clips_dir: Path, benchmark_path: Path) -> dict[str, Any]:
    """Everything the dashboard shows.  The statistics are cached on their input: scipy's exact Wilcoxon for
    up to 13 participants with ties enumerates sign patterns and takes seconds, and a dashboard polls."""
    votes = tuple(tuple(sorted(v.items())) for v in export_rows(session, study))
    counts = tuple(sorted(participant_counts(session, study).items()))
    questions = tuple(q["id"] for q in study.questions)
    results = copy.deepcopy(_analyse_cached(votes, counts, questions))
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
    try:
        clips = read_clip_manifest(clips_dir).clips
    except ManifestError:
        clips = []  # the dashboard says there is no clip set
    shown = {s.clip_id for s in study.stimuli}
    stat = (clips_dir / MANIFEST).stat() if clips else None
    same = _identical(clips_dir, (stat.st_mtime_ns, stat.st_size)) if stat else {}
    results["clips"] = [{"id": c.id, "animation": c.animation, "condition": c.condition, "method": c.method,
                         "params": c.params, "key_count": c.key_count, "metrics": c.metrics, "shown": c.id in shown,
                         "identical_to": same.get(c.id) if same.get(c.id, c.id) != c.id else None}
                        for c in clips]
    results["benchmark"] = _read_json(benchmark_path)
    results["scale"] = scale.describe()
    return results
