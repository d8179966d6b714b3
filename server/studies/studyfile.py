"""The study file: one TOML file (or the same content as JSON) that defines a study.  Read and checked here only.

``StudyFile`` is the schema (``animstudy study schema`` prints it as JSON Schema); :func:`load_study_file` reads a
file and reports every error with its field path and, where it can be found, its line.
"""

from __future__ import annotations

import math
import re
import string
import tomllib
import unicodedata
from pathlib import Path
from typing import Annotated, Any, Literal, Self
from urllib.parse import quote, urlsplit

from pydantic import (
    ConfigDict,
    Field,
    StringConstraints,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from .columns import EXPORT_COLUMNS
from .design import LADDER_MODES, Design
from .page import Page, Strict
from .scale import DEFAULT_LABELS, DEFAULT_QUESTION, FORMAT_DEFAULTS, AnswerFormat, format_choices
from .screening import Screening

# Package data (pyproject.toml), so an installed animstudy has its default study: in the checkout a link to
# studies/thesis.toml, in a built wheel a copy of it.
THESIS_FILE = Path(__file__).with_name("thesis.toml")
#: The largest whole number a number question accepts: every integer up to it is exact as a float (statistics,
#: export).
MAX_WHOLE_ANSWER = 2**53 - 1
# Export columns a question id must not shadow.
RESERVED_IDS = frozenset(EXPORT_COLUMNS)
# A URL parameter must not shadow an export column either (question ids are lower case, so they never meet).

Slug = Annotated[str, StringConstraints(pattern=r"^[a-z0-9][a-z0-9-]{0,63}$")]
Key = Annotated[str, StringConstraints(pattern=r"^[a-z][a-z0-9_]{0,31}$")]
Param = Annotated[str, StringConstraints(pattern=r"^[A-Za-z][A-Za-z0-9_]{0,63}$")]


def _text(max_length: int, description: str) -> Any:
    return Field(min_length=1, max_length=max_length, description=description)


class Texts(Strict):
    """What the participant page says.  Blank lines separate paragraphs."""

    information: str = _text(5000, "the study information shown first")
    consent: str = _text(2000, "the consent statement the participant agrees to")
    consent_version: str = Field(min_length=1, max_length=40, pattern=r"^[A-Za-z0-9._-]+$",
                                 description="stored with every session; change it when the consent text changes")
    contact: str = _text(500, "who to contact about the study")
    instructions: str = _text(3000, "shown before the first trial")
    thanks: str = _text(1000, "shown after the last trial")


class Scale(Strict):
    """The answer format and its wording.  ``rating5`` (the default): five answers, from 'left much better' to
    'right much better' (the scoring is fixed, see scale.py); ``2afc``: two, "the left one" / "the right one"
    (which is the original, or which moves more smoothly); ``same_different``: "same" / "different".  The answer
    ids are the format's (``scale.FORMAT_CHOICES``); ``labels`` word them, one per answer, in their order."""

    format: AnswerFormat = Field("rating5", description="rating5: the five-point scale; 2afc: two-alternative "
                                 "forced choice (which side is the original); same_different: same or different")
    question: str = Field(DEFAULT_QUESTION, min_length=1, max_length=200)
    labels: list[Annotated[str, StringConstraints(min_length=1, max_length=120)]] = Field(
        default_factory=lambda: list(DEFAULT_LABELS), min_length=2, max_length=5,
        description="one per answer of the format (5 for rating5, 2 for 2afc and same_different)")
    left: str = Field("Left", min_length=1, max_length=40, description="what the left side is called")
    right: str = Field("Right", min_length=1, max_length=40, description="what the right side is called")

    @model_validator(mode="before")
    @classmethod
    def format_defaults(cls, data: Any) -> Any:
        """The question and labels a format gets when the file does not word them."""
        if isinstance(data, dict) and data.get("format") in FORMAT_DEFAULTS:
            question, labels = FORMAT_DEFAULTS[data["format"]]
            data = {"question": question, "labels": list(labels), **data}
        return data

    @field_validator("labels")
    @classmethod
    def one_label_per_answer(cls, labels: list[str], info: ValidationInfo) -> list[str]:
        answer_format = info.data.get("format")
        if answer_format is None:  # the format itself was refused
            return labels
        ids = format_choices(answer_format)
        if len(labels) != len(ids):
            raise ValueError(f"format {answer_format!r} has {len(ids)} answers ({', '.join(ids)}), so it takes "
                             f"{len(ids)} labels, not {len(labels)}")
        return labels

    def choices(self) -> list[str]:
        return list(format_choices(self.format))


class Choice(Strict):
    id: Key
    label: str = Field(min_length=1, max_length=120)


QuestionType = Literal["choice", "number", "text", "likert"]
Label = Annotated[str, StringConstraints(min_length=1, max_length=120)]


class Question(Strict):
    """A demographic or screening question; an export column named ``id``.  ``type``:

    - ``choice`` (the default): one answer from ``choices``, exported as the choice's id;
    - ``number``: a number between ``min`` and ``max`` (whole if ``integer``), e.g. an age, in ``unit``;
    - ``text``: a short free text of at most ``max_length`` characters;
    - ``likert``: one point of a scale with 3 to 11 ``labels`` (first to last), exported as its position 1..n.
    """

    id: Key
    text: str = Field(min_length=1, max_length=300)
    type: QuestionType = "choice"
    choices: list[Choice] | None = Field(None, min_length=2, max_length=12, description="choice: the answers")
    min: float | None = Field(None, description="number: the least accepted answer")
    max: float | None = Field(None, description="number: the largest accepted answer")
    integer: bool = Field(False, description="number: whole numbers only")
    unit: str | None = Field(None, min_length=1, max_length=20, description="number: shown beside the field, "
                             "e.g. years")
    max_length: int = Field(200, ge=1, le=1000, description="text: the most characters")
    labels: list[Label] | None = Field(None, min_length=3, max_length=11, description="likert: the points' labels")

    @field_validator("id")
    @classmethod
    def not_reserved(cls, value: str) -> str:
        if value in RESERVED_IDS:
            raise ValueError(f"{value!r} is an export column; choose another question id")
        return value

    @model_validator(mode="after")
    def fits_its_type(self) -> Self:
        if (self.type == "choice") != (self.choices is not None):
            raise ValueError(f"question {self.id!r}: choices are required for type 'choice' and only for it")
        if (self.type == "likert") != (self.labels is not None):
            raise ValueError(f"question {self.id!r}: labels are required for type 'likert' and only for it")
        if self.type != "number" and (self.min is not None or self.max is not None or self.unit or self.integer):
            raise ValueError(f"question {self.id!r}: min, max, integer and unit are for type 'number' only")
        for bound in (self.min, self.max):
            if bound is not None and not math.isfinite(bound):
                raise ValueError(f"question {self.id!r}: min and max must be finite numbers")
        if self.min is not None and self.max is not None and self.min >= self.max:
            raise ValueError(f"question {self.id!r}: min must be less than max")
        if self.choices is not None:
            ids = [c.id for c in self.choices]
            if len(set(ids)) != len(ids):
                raise ValueError(f"question {self.id!r} lists a choice id more than once")
        return self

    def answer_error(self, value: object) -> str | None:
        """Why ``value`` (as JSON decoded it) is not an answer to this question; None if it is."""
        if self.type == "choice":
            ids = [c.id for c in self.choices or []]
            return None if isinstance(value, str) and value in ids else f"Input should be {', '.join(map(repr, ids))}"
        if self.type == "likert":
            n = len(self.labels or [])
            ok = isinstance(value, int) and not isinstance(value, bool) and 1 <= value <= n
            return None if ok else f"Input should be a whole number from 1 to {n}"
        if self.type == "text":
            if not isinstance(value, str) or not value.strip():
                return "Input should be a non-empty text"
            if len(value) > self.max_length:
                return f"Input should have at most {self.max_length} characters"
            if any(unicodedata.category(ch) == "Cc" and ch not in "\n\t" for ch in value):
                return "Input should not contain control characters"
            return None
        if isinstance(value, bool) or not isinstance(value, int | float):
            return "Input should be a number"
        # JSON integers have no size limit: one of 309 digits made math.isfinite (a float conversion) raise
        # OverflowError, a 500.  Compared as ints, never converted; whole numbers up to 2**53 are exact as floats.
        if isinstance(value, int) and abs(value) > MAX_WHOLE_ANSWER:
            return f"Input should be a number between -{MAX_WHOLE_ANSWER} and {MAX_WHOLE_ANSWER}"
        if not math.isfinite(value):
            return "Input should be a number"
        if self.integer and value != int(value):
            return "Input should be a whole number"
        if (self.min is not None and value < self.min) or (self.max is not None and value > self.max):
            low = "" if self.min is None else f" from {self.min:g}"
            high = "" if self.max is None else f" to {self.max:g}"
            return f"Input should be a number{low}{high}"
        return None


_YES_NO = [Choice(id="yes", label="Yes"), Choice(id="no", label="No"), Choice(id="dont_know", label="Don't know")]
THESIS_QUESTIONS = (
    Question(id="gamer", text="Do you consider yourself a gamer?", choices=_YES_NO),
    Question(id="tech_savvy", text="Do you consider yourself tech-savvy?", choices=_YES_NO),
)


class Outcome(Strict):
    """What a participant gets at the end: a code to paste and/or a link back to the recruiting platform."""

    code: str | None = Field(None, min_length=1, max_length=64)
    url: str | None = Field(None, max_length=2000, description="an https://host/ URL; its path and query may use "
                            "plain {code} and {<accepted URL parameter>} placeholders, e.g. {PROLIFIC_PID}")


class Recruitment(Strict):
    parameters: list[Param] = Field(default_factory=list, max_length=10, description="URL parameters of the "
                                    "participant link kept with the session and exported, e.g. PROLIFIC_PID, "
                                    "STUDY_ID, SESSION_ID; MTurk workerId, assignmentId, hitId; SONA id")
    completed: Outcome = Field(default_factory=Outcome)
    screened_out: Outcome = Field(default_factory=Outcome, description="for a participant who failed the "
                                  "attention checks (catch trials)")
    catch_failures_allowed: int = Field(0, ge=0, le=16, description="failed catch trials (a 'significantly "
                                        "better' answer when both sides show the same clip) before screening out")

    @field_validator("parameters")
    @classmethod
    def distinct_parameters(cls, value: list[str]) -> list[str]:
        clash = sorted(set(value) & RESERVED_IDS)
        if clash or len(set(value)) != len(value):
            raise ValueError(f"parameters must be distinct and not export columns ({', '.join(clash) or 'repeated'})")
        return value

    @model_validator(mode="after")
    def urls(self, info: ValidationInfo) -> Self:
        if (info.context or {}).get("stored"):  # as stored before these rules: completion_url() gives no URL
            return self
        fields = {"code", *self.parameters}
        for name in ("completed", "screened_out"):
            url = getattr(self, name).url
            if url is not None:
                problem = template_problem(url, fields)
                if problem:
                    raise ValueError(f"{name}.url {problem}")
        return self

    def completion_url(self, outcome: str, code: str | None, external: dict[str, str] | None) -> str | None:
        """The outcome's URL with ``{code}`` and the session's parameters filled in (URL-quoted, each at most
        :data:`MAX_URL_VALUE` characters; missing: empty).  A template stored before the rules of
        :func:`template_problem` that breaks them gives no URL rather than a redirect anywhere."""
        url = getattr(self, outcome).url
        if url is None:
            return None
        fields = {"code", *self.parameters}
        if template_problem(url, fields):
            return None
        values = {p: (external or {}).get(p, "") for p in self.parameters} | {"code": code or ""}
        out = []
        for literal, field, _, _ in string.Formatter().parse(url):
            out.append(literal)
            if field is not None:
                out.append(quote(values[field][:MAX_URL_VALUE], safe=""))
        return "".join(out)


#: Characters of one value filled into a completion URL (before URL-encoding).
MAX_URL_VALUE = 200


def template_problem(url: str, fields: set[str]) -> str | None:
    """What is wrong with a completion-URL template, or None.  Allowed: an ``https://host/`` written out, then
    path and query with plain ``{name}`` placeholders of ``fields`` (no format spec, conversion, index or
    attribute: ``{code:>300000000}`` would make a 300 MB answer, ``{code:{PROLIFIC_PID}}`` let the participant
    choose one, and ``https://{PROLIFIC_PID}/`` send them anywhere)."""
    try:
        parts = list(string.Formatter().parse(url))
    except ValueError as exc:
        return f"is not a valid template: {exc}"
    for _, field, spec, conversion in parts:
        if field is None:
            continue
        if spec or conversion or field not in fields:
            shown = "{" + field + (f"!{conversion}" if conversion else "") + (f":{spec}" if spec else "") + "}"
            if field not in fields:
                return (f"uses {shown}, which is neither {{code}} nor an accepted parameter "
                        f"({', '.join(sorted(fields))})")
            return f"uses {shown}; only plain {{name}} placeholders are allowed (no format spec or conversion)"
    fixed = parts[0][0] if parts else url  # the text before the first placeholder
    split = urlsplit(fixed)
    if split.scheme != "https" or not split.netloc or not fixed[len(f"https://{split.netloc}"):].startswith("/"):
        return (f"must start with a fixed https://host/ before any placeholder (placeholders only in the path or "
                f"query), got {url!r}")
    return None


class Clips(Strict):
    """The clip set a study's clips come from (``[clips]``): ``set``, a clip-set file (README "Clip-set file")
    relative to the study file; or inline ``conditions`` (``[[clips.conditions]]``, as a clip-set file's
    ``[[conditions]]``), ``ladders`` (``[[clips.ladders]]``, as its ``[[ladders]]``, checked alike:
    :func:`server.clipset.config.inline_config`) and/or ``animations`` (``[clips.animations.<name>]``, sources
    under the data directory), the rest from the default clip-set file.  `animstudy study create` builds the
    clips of it the study needs and renders their videos; without ``[clips]`` the study uses the server's clip
    set."""

    set: str | None = Field(None, min_length=1, max_length=500, pattern=r"\.toml$",
                            description="clip-set file (TOML), relative to the study file")
    conditions: list[dict[str, Any]] | None = Field(None, min_length=1, max_length=64,
                                                    description="conditions, as a clip-set file's [[conditions]]")
    animations: dict[str, dict[str, Any]] | None = Field(None, min_length=1, max_length=64,
                                                         description="animations, as a clip-set file's "
                                                                     "[animations.<name>]")
    ladders: list[dict[str, Any]] | None = Field(None, min_length=1, max_length=16,
                                                 description="ladders, as a clip-set file's [[ladders]]: one "
                                                             "condition per level, added to the conditions")

    @model_validator(mode="after")
    def one_source(self) -> Self:
        inline = (self.conditions, self.animations, self.ladders)
        if self.set is None and all(v is None for v in inline):
            raise ValueError("[clips] needs set, or conditions, ladders and/or animations")
        if self.set is not None and any(v is not None for v in inline):
            raise ValueError("[clips] takes either set (a clip-set file) or conditions/ladders/animations inline, "
                             "not both")
        return self


class StudyFile(Strict):
    """A study: what it shows, what it says, what it asks and where participants go at the end."""

    model_config = ConfigDict(title="animstudy study file", json_schema_extra={"$schema":
                                                                               "https://json-schema.org/draft/2020-12/schema"})

    slug: Slug = Field(description="the study's address: /s/<slug>")
    title: str = Field(min_length=1, max_length=200)
    texts: Texts
    scale: Scale = Field(default_factory=Scale)
    questions: list[Question] = Field(default_factory=lambda: list(THESIS_QUESTIONS), max_length=10)
    design: Design = Field(default_factory=Design)
    recruitment: Recruitment = Field(default_factory=Recruitment)
    page: Page = Field(default_factory=Page, description="the page's language, its own wording and the device gate")
    clips: Clips | None = Field(None, description="the clip set its clips come from (default: the server's)")
    screening: Screening = Field(default_factory=Screening, description="the observer-screening rules the results "
                                 "and exports apply (docs/screening.md); the default: failed catch trials")

    @model_validator(mode="after")
    def unique_questions(self) -> Self:
        ids = [q.id for q in self.questions]
        if len(set(ids)) != len(ids):
            raise ValueError("two questions have the same id")
        return self

    @model_validator(mode="after")
    def format_fits_design(self) -> Self:
        """A threshold design asks who tells the test from the reference: 2AFC or same/different, never the
        five-point scale; 2AFC needs a reference to be the original (the design always has one)."""
        if self.design.mode in LADDER_MODES and self.scale.format == "rating5":
            raise ValueError(f"scale.format: design.mode = {self.design.mode!r} needs an answer format that "
                             f"detects (\"2afc\" or \"same_different\"), not \"rating5\"")
        return self


class StudyFileError(ValueError):
    """A study file that cannot be used; ``errors`` holds one line per problem."""

    def __init__(self, source: str, errors: list[str]) -> None:
        super().__init__(f"{source}: " + "; ".join(errors))
        self.source = source
        self.errors = errors


def field_path(loc: tuple[int | str, ...]) -> str:
    """``("design", "conditions", 1)`` -> ``design.conditions[1]``."""
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


_HEADER = re.compile(r"^\s*(\[\[?)\s*([A-Za-z0-9_.\-]+)\s*\]\]?")
_KEY = re.compile(r"^\s*([A-Za-z0-9_\-]+)\s*=")


def _line_of(text: str, loc: tuple[int | str, ...]) -> int | None:
    """The line that sets (or, failing that, the table that holds) the field at ``loc``; TOML parsers keep no
    positions, so this follows table headers and keys the way study files are written."""
    names = [p for p in loc if isinstance(p, str)]
    table: list[str] = []
    counts: dict[str, int] = {}
    best: tuple[int, int] | None = None  # (matched depth, line)
    for number, line in enumerate(text.splitlines(), 1):
        header = _HEADER.match(line)
        if header:
            table = header.group(2).split(".")
            if header.group(1) == "[[":
                counts[header.group(2)] = counts.get(header.group(2), -1) + 1
            path: list[int | str] = []
            for i, t in enumerate(table):
                path.append(t)
                key = ".".join(table[: i + 1])
                if key in counts and i == len(table) - 1:
                    path.append(counts[key])
            if tuple(path) == tuple(loc[: len(path)]):
                depth = len(path)
                if best is None or depth > best[0]:
                    best = (depth, number)
            continue
        key = _KEY.match(line)
        if key and [*table, key.group(1)] == names[: len(table) + 1]:
            depth = len(table) + 1 + sum(isinstance(p, int) for p in loc[: len(table) + 1])
            if best is None or depth >= best[0]:
                best = (depth, number)
    return best[1] if best else None


def errors_of(exc: ValidationError, text: str | None = None) -> list[str]:
    """One line per error: ``field.path (line N): message``."""
    out = []
    for error in exc.errors():
        loc = tuple(p for p in error["loc"] if p not in ("body",))
        where = field_path(loc) or "(the file)"
        line = _line_of(text, loc) if text is not None and loc else None
        out.append(f"{where}{f' (line {line})' if line else ''}: {error['msg']}")
    return out


NESTED_TOO_DEEPLY = "not a study file: its arrays or tables are nested too deeply"


def parse_study_text(text: str, source: str = "study file") -> StudyFile:
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise StudyFileError(source, [f"not valid TOML: {exc}"]) from None
    except RecursionError:  # tomllib recurses per level of [ or {: a few hundred levels exhaust the stack
        raise StudyFileError(source, [NESTED_TOO_DEEPLY]) from None
    try:
        return StudyFile.model_validate(raw)
    except ValidationError as exc:
        raise StudyFileError(source, errors_of(exc, text)) from None
    except RecursionError:
        raise StudyFileError(source, [NESTED_TOO_DEEPLY]) from None


def load_study_file(path: Path) -> StudyFile:
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise StudyFileError(str(path), [f"cannot read it: {exc}"]) from None
    return parse_study_text(text, str(path))


def thesis_study() -> StudyFile:
    """The thesis study as ``studies/thesis.toml`` defines it (the default study)."""
    return load_study_file(THESIS_FILE)
