"""The exports of a study's votes: CSV and JSON rows (one per vote, with every participant's screening outcome),
and the analysed test votes for sureal and pwcmp.  The columns are :mod:`server.studies.columns`'s."""

from __future__ import annotations

import csv
import io
import unicodedata
from collections.abc import Collection, Iterable, Iterator
from typing import Any

from sqlalchemy.orm import Session

from server.participants.service import vote_records
from server.stimuli import service as stimulus_sets
from server.studies.models import ComparisonKind, Study
from server.studies.scale import CHOICE_SCORES, other_side
from server.studies.screening import ParticipantScreening, screen
from server.studies.service import export_columns, recruitment, screening_rules

# A text cell beginning with one of these is a formula (or becomes one) in Excel, LibreOffice and Google Sheets:
# leading spaces and line breaks are skipped by some of them, and the full-width forms (U+FF1D ＝ and its
# neighbours) are read as the ASCII ones by others.
FORMULA_STARTS = ("=", "+", "-", "@", "\t", "\r", "\n", " ", "\uff1d", "\uff0b", "\uff0d", "\uff20")


def csv_cell(value: object) -> object:
    """A value as a CSV cell: booleans ``true``/``false``, None empty, and text that a spreadsheet would evaluate
    (participant-supplied ids could be ``=HYPERLINK(...)``) prefixed with ``'``, which spreadsheets show as text.
    Numbers stay numbers: a score of -2 is not text."""
    if isinstance(value, bool):
        return str(value).lower()
    if value is None:
        return ""
    if isinstance(value, str) and is_formula(value):
        return "'" + value
    return value


def is_formula(text: str) -> bool:
    """Whether a spreadsheet could read ``text`` as a formula: it begins with one of :data:`FORMULA_STARTS`, or
    does so after leading invisible characters (zero-width, bidirectional marks and other format characters,
    Unicode category Cf, or white space), which some spreadsheets drop and a reader does not see."""
    if text.startswith(FORMULA_STARTS):
        return True
    visible = next((i for i, ch in enumerate(text) if not (ch.isspace() or unicodedata.category(ch) == "Cf")),
                   len(text))
    return visible > 0 and text[visible:].startswith(FORMULA_STARTS)


def export_csv(session: Session, study: Study, include_pilot: bool = False) -> str:
    """The export as CSV (cells as :func:`csv_cell` writes them)."""
    buffer = io.StringIO()
    # RFC 4180 line ends: with "\n" alone the csv module would not quote a value holding a bare "\r", and every
    # reader would split the row there.
    writer = csv.DictWriter(buffer, fieldnames=export_columns(study), lineterminator="\r\n")
    writer.writeheader()
    for row in export_rows(session, study, include_pilot):
        writer.writerow({k: csv_cell(v) for k, v in row.items()})
    return buffer.getvalue()


def export_document(session: Session, study: Study, include_pilot: bool = False) -> dict[str, Any]:
    """The export as one JSON document: the study, the columns, the rows."""
    return {"study": {"slug": study.slug, "title": study.title, "state": study.state, "design": study.design,
                      "consent_version": study.consent_version, "questions": study.questions},
            "columns": export_columns(study), "votes": list(export_rows(session, study, include_pilot))}


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
            "screened_by": None, "pilot": ps.pilot,
            **{p: external.get(p) for p in parameters},
        })
    return rows, playback


def export_rows(session: Session, study: Study, include_pilot: bool = False) -> Iterator[dict[str, Any]]:
    """One row per vote (withdrawn participants' votes no longer exist), in session and trial order; ``outcome``
    and ``screened_by`` by the study's screening rules; pilot sessions only with ``include_pilot``."""
    yield from screened_rows(session, study, include_pilot)[0]


def _analysed_test_rows(session: Session, study: Study, include_pilot: bool) -> list[dict[str, Any]]:
    """Test trials of the participants who finished and were not screened out (the subject model's input)."""
    rows, _ = screened_rows(session, study, include_pilot)
    return [r for r in rows if not r["practice"] and not r["catch"] and r["outcome"] == "completed"]


def export_sureal(session: Session, study: Study, include_pilot: bool = False) -> dict[str, Any]:
    """The analysed test votes as a ``sureal`` dataset (its JSON form: ``sureal --dataset FILE.json``, or
    ``sureal.tools.misc.import_json_file``): a comparison (animation, reference, test condition) is a distorted
    video, its animation the content, each participant's side-swapped showings the repetitions of their score;
    scores -2..+2 from the test condition's point of view."""
    rows = _analysed_test_rows(session, study, include_pilot)
    comparisons = sorted({(r["animation"], r["reference_condition"], r["test_condition"]) for r in rows})
    animations = sorted({a for a, _, _ in comparisons})
    scores: dict[tuple[str, str, str], dict[str, list[int]]] = {c: {} for c in comparisons}
    for r in rows:
        key = (r["animation"], r["reference_condition"], r["test_condition"])
        scores[key].setdefault(r["session_id"], []).append(r["score"])
    return {
        "dataset_name": study.slug,
        "ref_videos": [{"content_id": i, "content_name": a, "path": a} for i, a in enumerate(animations)],
        "dis_videos": [{"asset_id": i, "content_id": animations.index(a), "path": f"{a}/{test}-vs-{ref}",
                        "animation": a, "reference_condition": ref, "test_condition": test,
                        "os": scores[(a, ref, test)]}
                       for i, (a, ref, test) in enumerate(comparisons)],
    }


PWCMP_COLUMNS = ("observer", "session", "scene", "cond1", "cond2", "selection")


def export_pwcmp_csv(session: Session, study: Study, include_pilot: bool = False) -> str:
    """The analysed test votes as pairwise comparisons in pwcmp's table (observer, session, scene, cond1, cond2,
    selection): cond1 the condition shown left, cond2 the one shown right, selection 1 or 2 for the side the
    participant preferred (slightly or much); "equal" answers are left out, as pwcmp models a forced choice.
    Works for any design: it reads each trial's two conditions."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\r\n")
    writer.writerow(PWCMP_COLUMNS)
    for r in _analysed_test_rows(session, study, include_pilot):
        left, right = ((r["reference_condition"], r["test_condition"]) if r["reference_side"] == "left"
                       else (r["test_condition"], r["reference_condition"]))
        raw = CHOICE_SCORES[r["choice"]]
        if raw:
            writer.writerow([csv_cell(v) for v in (r["session_id"], 1, r["animation"], left, right,
                                                   1 if raw > 0 else 2)])
    return buffer.getvalue()
