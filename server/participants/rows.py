"""The vote rows every reader of a study's votes shares (the export, the results, the adaptive design): one row
per vote with its session, trial, pair and answers, and each finished participant's screening record by the study's
rules.  Here, below both ``server.research`` (the export, the results) and the design's sampler
(:mod:`server.participants.assign`), so that one definition serves them all."""

from __future__ import annotations

from collections.abc import Collection, Iterable
from typing import Any

from sqlalchemy.orm import Session

from server.analysis.screening import ParticipantScreening, screen
from server.stimuli import service as stimulus_sets
from server.studies.models import ComparisonKind, Study
from server.studies.scale import correct, other_side
from server.studies.service import recruitment, screening_rules

from .service import vote_records


def screened_rows(session: Session, study: Study, include_pilot: bool = False
                  ) -> tuple[list[dict[str, Any]], dict[str, ParticipantScreening]]:
    """The export rows (see :func:`export_rows`) and every completed participant's screening record, by the
    study's ``[screening]`` rules (``screening.screen``).  Pilot sessions only with ``include_pilot``."""
    rows, playback = vote_rows(session, study, include_pilot)
    records = screen_rows(study, rows, playback)
    for row in rows:
        record = records.get(row["session_id"])
        if record is not None:  # a completed session
            row["outcome"] = "screened_out" if record.screened_out else "completed"
            row["screened_by"] = ";".join(record.flagged_by) or None
    return rows, records


Playback = dict[tuple[str, str, str], float]


def screen_rows(study: Study, rows: Iterable[dict[str, Any]], playback: Playback
                ) -> dict[str, ParticipantScreening]:
    """The screening record of every completed participant of ``rows`` (:func:`vote_rows`) by the study's rules."""
    return screen(rows, screening_rules(study), recruitment(study).catch_failures_allowed, playback)


def vote_rows(session: Session, study: Study, include_pilot: bool = False, sessions: Collection[str] | None = None
              ) -> tuple[list[dict[str, Any]], Playback]:
    """The export rows before screening (``outcome`` and ``screened_by`` empty), of the given ``sessions`` only if
    given, and the duration of one playback of each comparison's pair video (ms, the ``fast`` rule's)."""
    questions = [q["id"] for q in study.questions]
    parameters = list(study.recruitment["parameters"])
    pinned = study.stimulus_set
    content = stimulus_sets.content_of(pinned) if pinned is not None else None
    hashes = content.hashes() if content is not None else {}
    # clips built in spite of the fidelity gate (accept_unfaithful) mark every vote on them
    unfaithful = {c.id for c in content.clips if c.metrics.get("unfaithful")} if content is not None else set()
    mode = study.design.get("mode", "reference")  # designs stored before issue 27 have no mode
    answer_format = study.scale.get("format", "rating5")  # scales stored before issue 38 are five-point
    ladder = study.design.get("ladder")
    levels = study.design.get("levels") or {}  # filled in from the clip set when the study was created
    rows: list[dict[str, Any]] = []
    playback: Playback = {}
    for (vote, trial, ps, kind, animation, ref_condition, test_condition, ref_clip, test_clip, ref_video, test_video,
         pair_ref_left, pair_ref_right, ref_frames, ref_fps, test_frames, test_fps) in vote_records(session, study,
                                                                                         include_pilot, sessions):
        # one playback of the pair video: until the longer of its two clips has ended
        playback[(animation, ref_condition, test_condition)] = 1000 * max(ref_frames / ref_fps,
                                                                          test_frames / test_fps)
        left, right = (ref_video, test_video) if trial.reference_side == "left" else (test_video, ref_video)
        left_condition, right_condition = ((ref_condition, test_condition) if trial.reference_side == "left"
                                           else (test_condition, ref_condition))
        pair = pair_ref_left if trial.reference_side == "left" else pair_ref_right
        answers, external, device = ps.answers or {}, ps.external or {}, ps.device or {}
        is_correct = correct(answer_format, vote.choice, trial.reference_side, ref_clip == test_clip)
        rows.append({
            "session_id": ps.id, "trial_index": trial.index, "practice": trial.practice,
            "catch": kind == ComparisonKind.catch, "animation": animation, "reference_condition": ref_condition,
            "test_condition": test_condition, "reference_side": trial.reference_side,
            "test_side": other_side(trial.reference_side), "choice": vote.choice, "score": vote.score,
            "rt_ms": vote.rt_ms, **{q: answers.get(q) for q in questions},
            "answered_at": vote.answered_at.isoformat(), "consent_version": ps.consent_version,
            "session_state": ps.state, "outcome": None,
            "viewport_width": device.get("viewport_width"),
            "viewport_height": device.get("viewport_height"), "device_pixel_ratio": device.get("device_pixel_ratio"),
            "video_scale": device.get("scale"), "video_scaled": device.get("scaled"),
            "unfaithful": ref_clip in unfaithful or test_clip in unfaithful,
            "left_video": hashes.get(left), "right_video": hashes.get(right), "pair_video": hashes.get(pair),
            "stimulus_set": pinned.digest if pinned is not None else None,
            "design_mode": mode, "left_condition": left_condition,
            "right_condition": right_condition,
            "screened_by": None, "pilot": ps.pilot, "answer_format": answer_format, "ladder": ladder,
            "level": levels.get(test_condition) if ladder else None, "correct": is_correct,
            **{p: external.get(p) for p in parameters},
        })
    return rows, playback
