"""The exports of a study's votes: CSV and JSON rows (one per vote, with every participant's screening outcome),
and the analysed test votes for sureal and pwcmp.  The columns are :mod:`server.studies.columns`'s."""

from __future__ import annotations

import csv
import io
import unicodedata
from collections.abc import Iterator
from typing import Any

from sqlalchemy.orm import Session

from server.participants.rows import screened_rows
from server.studies.models import Study
from server.studies.scale import RAW_SCORES
from server.studies.service import export_columns

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
        raw = RAW_SCORES[r["choice"]]
        if raw:
            writer.writerow([csv_cell(v) for v in (r["session_id"], 1, r["animation"], left, right,
                                                   1 if raw > 0 else 2)])
    return buffer.getvalue()
