"""The columns of the vote exports, each with its type and meaning: the one list that the export
(:func:`server.studies.service.export_columns`), the study file's reserved ids (a question id or URL parameter must
not shadow a column) and the data dictionary (``GET /api/v1/data-dictionary`` and the docs site's page, both from
:func:`data_dictionary_markdown`) are made from.

A new column is one more :class:`ExportColumn` appended to :data:`COLUMNS` (existing names never change: analysis
scripts read them), and the row :func:`server.research.export.export_rows` writes gets the value.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ExportColumn:
    """One export column: ``name`` (CSV header and JSON key), ``type`` (its values, Markdown) and ``meaning``."""

    name: str
    type: str
    meaning: str


COLUMNS: tuple[ExportColumn, ...] = (
    ExportColumn("session_id", "string (32 hex)", "anonymous participant session"),
    ExportColumn("trial_index", "integer ≥ 0",
                 "position of the trial in the session, from 0 (the practice trial, if any, is 0)"),
    ExportColumn("practice", "boolean", "the practice trial: not to be analysed"),
    ExportColumn("catch", "boolean", "a catch trial: the reference clip on both sides (checks attention; "
                 "`test_condition` equals `reference_condition`)"),
    ExportColumn("animation", "a clip-set animation, e.g. `walk`, `run`, `crouch`, `idle`", "the animation shown"),
    ExportColumn("reference_condition", "condition id, e.g. `keyframe`", "the reference condition of the study"),
    ExportColumn("test_condition", "condition id, e.g. `hybrid0`, `hybrid1`",
                 "the condition compared with the reference"),
    ExportColumn("reference_side", "`left`, `right`", "where the reference was shown"),
    ExportColumn("test_side", "`left`, `right`",
                 "where the test was shown (the other side; for a catch trial: `left`)"),
    ExportColumn("choice", "`left_much`, `left_slightly`, `equal`, `right_slightly`, `right_much` (rating5); "
                 "`left`, `right` (2afc); `same`, `different` (same_different)",
                 "the answer as given, one of the ids of the study's answer format (`answer_format`)"),
    ExportColumn("score", "−2 … +2", "the answer from the test condition's point of view: +2 test significantly "
                 "better, +1 slightly better, 0 equal, −1 reference slightly better, −2 reference significantly "
                 "better (`left_much` with the test on the left is +2)"),
    ExportColumn("rt_ms", "integer ≥ 0",
                 "time from the trial being shown to the vote, milliseconds, as measured by the browser"),
    ExportColumn("answered_at", "ISO 8601 time with offset", "when the server stored the vote"),
    ExportColumn("consent_version", "string", "version of the consent text the participant agreed to"),
    ExportColumn("session_state", "`active`, `completed`", "whether the participant finished all trials"),
    ExportColumn("outcome", "`completed`, `screened_out`, or empty", "for a finished session: `screened_out` when "
                 "one of the study's screening rules (`[screening] rules`, see `screened_by`; the default: more "
                 "failed catch trials — a 'significantly better' answer with the same clip on both sides — than "
                 "`[recruitment] catch_failures_allowed`) flagged the participant; the statistics leave every vote "
                 "of a screened-out participant out; empty while the session is active"),
    ExportColumn("viewport_width", "integer (CSS px)", "width of the browser window when the participant started "
                 "(empty for sessions before migration 0005)"),
    ExportColumn("viewport_height", "integer (CSS px)", "its height"),
    ExportColumn("device_pixel_ratio", "number", "device pixels per CSS pixel at the start"),
    ExportColumn("video_scale", "number 0–1",
                 "the scale at which the pair video would be shown at the start (1: its rendered size)"),
    ExportColumn("video_scaled", "`true`, `false`", "whether the video had to be shown below its rendered size"),
    ExportColumn("unfaithful", "`true`, `false`", "whether a clip of the pair was built although it failed the "
                 "fidelity gate (`accept_unfaithful = true`; see the motion guide): what it shows is not faithful "
                 "to its motion file"),
    ExportColumn("left_video", "string (64 hex) or empty", "sha256 of the video of the clip shown on the left (the "
                 "clip's own video in the study's stimulus set; the side-by-side video shows the same frames); empty "
                 "when the set did not record it (a file missing when migration 0007 pinned an older study)"),
    ExportColumn("right_video", "string (64 hex) or empty", "the same for the clip shown on the right"),
    ExportColumn("pair_video", "string (64 hex) or empty",
                 "sha256 of the side-by-side video file the participant was played"),
    ExportColumn("stimulus_set", "string (64 hex) or empty", "digest of the study's stimulus set (sha256 of its "
                 "canonical JSON: clips, metrics, character, render settings, every file's sha256); the same for "
                 "every row of a study once it has opened"),
    ExportColumn("design_mode", "`reference`, `all-pairs`, `incomplete`, `adaptive`, `constant-stimuli`, "
                 "`staircase`", "the study's `[design] mode` "
                 "(see the designs page); in the modes other than `reference`, `reference_condition` and "
                 "`test_condition` are the first and second condition of the pair (in `[design]` order, the "
                 "reference first), not necessarily the study's reference"),
    ExportColumn("left_condition", "condition id", "the condition shown on the left"),
    ExportColumn("right_condition", "condition id", "the condition shown on the right"),
    ExportColumn("screened_by", "rule names, `;`-separated, or empty", "the screening rules that flagged this "
                 "participant (`catch`, `straight_lining`, `z_outlier`, `bt500`, `correlation`, `fast`; see the "
                 "screening page), among the study's chosen ones; empty for a participant no rule flagged and while "
                 "the session is active. The panel-relative rules (`z_outlier`, `bt500`, `correlation`) can change "
                 "as participants are added"),
    ExportColumn("pilot", "`true`, `false`", "a researcher's pilot run (preview link); pilot sessions are in an "
                 "export only when asked for (`?pilot=true`)"),
    ExportColumn("answer_format", "`rating5`, `2afc`, `same_different`", "the study's `[scale] format`: the "
                 "five-point scale (`choice` one of its five answers), two-alternative forced choice (`choice` "
                 "`left` or `right`: the side taken for the original) or same/different (`choice` `same` or "
                 "`different`); `score` is then +1 test side chosen / −1 reference side chosen (2afc), 0 same / "
                 "−1 different (same_different)"),
    ExportColumn("ladder", "ladder id, e.g. `pps`, or empty", "threshold designs (`[design] mode = "
                 "\"constant-stimuli\"` or `\"staircase\"`): the ladder whose levels the conditions are; empty "
                 "otherwise"),
    ExportColumn("level", "number or empty", "the test condition's level on `ladder` (e.g. 12 for `pps12`, poses "
                 "per second), as the clip set's manifest gives it (the study's `design.levels`); empty outside "
                 "threshold designs"),
    ExportColumn("correct", "`true`, `false`, or empty", "derived from `choice`, never stored: 2afc — the "
                 "reference's side was chosen (empty when both sides show one clip); same_different — `same` "
                 "exactly when both sides show one clip; empty for `rating5`"),
)

EXPORT_COLUMNS: tuple[str, ...] = tuple(c.name for c in COLUMNS)
# The study's question columns go in front of this one, its URL-parameter columns at the end.
QUESTIONS_BEFORE = "answered_at"

_QUESTION_ROW = ("*question id*", "by the question's `type`: `choice` (the default): a choice id; `number`: a "
                 "number (in the question's `unit`, within its `min`/`max`); `text`: the participant's text (at most "
                 "`max_length` characters); `likert`: the position of the chosen label, 1 (the first) … n (the "
                 "last); empty if unanswered", "one column per question of the study (`[[questions]]`), named by its "
                 "`id`; the study's `questions` (in the JSON export's `study`) hold each one's type, text, choices, "
                 "unit and labels; the thesis: `gamer` (\"Do you consider yourself a gamer?\") and `tech_savvy` "
                 "(\"Do you consider yourself tech-savvy?\"), each `yes`, `no` or `dont_know`")
_PARAMETER_ROW = ("*URL parameter*", "string or empty", "one column per accepted URL parameter of the study "
                  "(`[recruitment] parameters`, e.g. `PROLIFIC_PID`, `STUDY_ID`, `SESSION_ID`; MTurk `workerId`, "
                  "`assignmentId`, `hitId`), as given in the participant link (supplied by the participant's "
                  "browser, not checked against the platform; for approval and payment); deleted on withdrawal")

_INTRO = """\
# Data dictionary of the vote exports

`GET /api/v1/studies/{slug}/export.csv` and `export.json` (researcher login required; the study's owner or an
admin), or `animstudy study export SLUG --format csv|json`, hold **one row per vote** of that study only. Votes of
participants who withdrew are deleted and never exported. The CSV is RFC 4180 (UTF-8, comma-separated, CRLF line
ends, values holding commas, quotes or line breaks in double quotes); booleans are `true`/`false`, missing values
are empty, and a text value that a spreadsheet would take for a formula (beginning with `=`, `+`, `-`, `@`, a tab
or a carriage return) is prefixed with `'` (spreadsheets show it as text; drop the `'` to get the value as given).
In the JSON (`{"study": {...}, "columns": [...], "votes": [...]}`) booleans are JSON booleans, missing values
`null`, and text is exactly as given.

A trial shows a **reference** stimulus and a **test** stimulus side by side: one animation in the study's
reference condition (`[design] reference`, the thesis: `keyframe`) and in one compared condition (`[design]
conditions`, the thesis: `hybrid0`, `hybrid1`). Scores are from the test condition's point of view.

The columns, in export order (generated from `server/studies/columns.py`):
"""

# Exports before December 2026 (database revision 0003), of the thesis design only: (old column, meaning, now).
OLD_COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("`increment`", "0, 1, 2: the hybrid increment compared with the keyframe clip; empty for a catch trial",
     "`test_condition` `hybrid<increment>` (`keyframe` for a catch trial)"),
    ("`hybrid_side`", "where the hybrid clip was shown", "`test_side` (same values)"),
    ("`score`", "from the hybrid's point of view", "`score` (the hybrid is the test condition: the same numbers)"),
    ("`gamer`, `tech_savvy`", "the two demographic answers", "the question columns `gamer`, `tech_savvy`"),
)

_OLD_INTRO = """\
## Columns of exports before December 2026 (database revision 0003)

Older exports, of the thesis design only, had these columns instead; the values carry over exactly (migration 0004
converted the database without changing any vote or score):
"""


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def data_dictionary_markdown() -> str:
    """The data dictionary as one Markdown page: how the files are written, then a table of every column in export
    order (the question and URL-parameter columns where :func:`~server.studies.service.export_columns` puts them),
    then the columns of old exports."""
    rows = []
    for column in COLUMNS:
        if column.name == QUESTIONS_BEFORE:
            rows.append(_QUESTION_ROW)
        rows.append((f"`{column.name}`", column.type, column.meaning))
    rows.append(_PARAMETER_ROW)
    return (f"{_INTRO}\n{_table(('column', 'type', 'meaning'), rows)}\n\n"
            f"{_OLD_INTRO}\n{_table(('old column', 'meaning', 'now'), OLD_COLUMNS)}\n")


def data_dictionary_json() -> dict[str, list[dict[str, str]]]:
    """The same dictionary as data, for programs (``GET /api/v1/data-dictionary.json``): the columns in export order,
    the question and URL-parameter placeholders where the Markdown puts them (``name`` in italics there, here
    ``"*question id*"``/``"*URL parameter*"`` too: both show the same rows); then the old columns."""
    columns = []
    for column in COLUMNS:
        if column.name == QUESTIONS_BEFORE:
            columns.append(dict(zip(("name", "type", "meaning"), _QUESTION_ROW, strict=True)))
        columns.append({"name": column.name, "type": column.type, "meaning": column.meaning})
    columns.append(dict(zip(("name", "type", "meaning"), _PARAMETER_ROW, strict=True)))
    old = [dict(zip(("name", "meaning", "now"), row, strict=True)) for row in OLD_COLUMNS]
    return {"columns": columns, "old_columns": old}


def _table(header: tuple[str, str, str], rows: list[tuple[str, str, str]] | tuple[tuple[str, str, str], ...]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|---|---|---|"]
    lines += ["| " + " | ".join(_cell(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)
