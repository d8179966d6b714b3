"""The study file: one TOML file (or the same content as JSON) that defines a study.  Read and checked here only.

``StudyFile`` is the schema (``animstudy study schema`` prints it as JSON Schema); :func:`load_study_file` reads a
file and reports every error with its field path and, where it can be found, its line.
"""

from __future__ import annotations

import re
import string
import tomllib
from pathlib import Path
from typing import Annotated, Any, Self
from urllib.parse import quote, urlsplit

from pydantic import BaseModel, ConfigDict, Field, StringConstraints, ValidationError, field_validator, model_validator

from .design import Design
from .page import Page
from .scale import DEFAULT_LABELS, DEFAULT_QUESTION

REPO_STUDIES = Path(__file__).resolve().parents[2] / "studies"
THESIS_FILE = REPO_STUDIES / "thesis.toml"
# Export columns a question id must not shadow (see service.EXPORT_COLUMNS).
RESERVED_IDS = frozenset({
    "session_id", "trial_index", "practice", "catch", "animation", "reference_condition", "test_condition",
    "reference_side", "test_side", "choice", "score", "rt_ms", "answered_at", "consent_version", "session_state",
    "outcome", "viewport_width", "viewport_height", "device_pixel_ratio", "video_scale", "video_scaled"})
# A URL parameter must not shadow an export column either (question ids are lower case, so they never meet).

Slug = Annotated[str, StringConstraints(pattern=r"^[a-z0-9][a-z0-9-]{0,63}$")]
Key = Annotated[str, StringConstraints(pattern=r"^[a-z][a-z0-9_]{0,31}$")]
Param = Annotated[str, StringConstraints(pattern=r"^[A-Za-z][A-Za-z0-9_]{0,63}$")]


def _text(max_length: int, description: str) -> Any:
    return Field(min_length=1, max_length=max_length, description=description)


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", str_strip_whitespace=True)


class Texts(_Strict):
    """What the participant page says.  Blank lines separate paragraphs."""

    information: str = _text(5000, "the study information shown first")
    consent: str = _text(2000, "the consent statement the participant agrees to")
    consent_version: str = Field(min_length=1, max_length=40, pattern=r"^[A-Za-z0-9._-]+$",
                                 description="stored with every session; change it when the consent text changes")
    contact: str = _text(500, "who to contact about the study")
    instructions: str = _text(3000, "shown before the first trial")
    thanks: str = _text(1000, "shown after the last trial")


class Scale(_Strict):
    """The five answers, from 'left much better' to 'right much better' (the scoring is fixed, see scale.py)."""

    question: str = Field(DEFAULT_QUESTION, min_length=1, max_length=200)
    labels: list[Annotated[str, StringConstraints(min_length=1, max_length=120)]] = Field(
        default_factory=lambda: list(DEFAULT_LABELS), min_length=5, max_length=5)
    left: str = Field("Left", min_length=1, max_length=40, description="what the left side is called")
    right: str = Field("Right", min_length=1, max_length=40, description="what the right side is called")


class Choice(_Strict):
    id: Key
    label: str = Field(min_length=1, max_length=120)


class Question(_Strict):
    """A demographic or screening question: one answer from ``choices``; an export column named ``id``."""

    id: Key
    text: str = Field(min_length=1, max_length=300)
    choices: list[Choice] = Field(min_length=2, max_length=12)

    @field_validator("id")
    @classmethod
    def not_reserved(cls, value: str) -> str:
        if value in RESERVED_IDS:
            raise ValueError(f"{value!r} is an export column; choose another question id")
        return value

    @model_validator(mode="after")
    def unique_choices(self) -> Self:
        ids = [c.id for c in self.choices]
        if len(set(ids)) != len(ids):
            raise ValueError(f"question {self.id!r} lists a choice id more than once")
        return self


_YES_NO = [Choice(id="yes", label="Yes"), Choice(id="no", label="No"), Choice(id="dont_know", label="Don't know")]
THESIS_QUESTIONS = (
    Question(id="gamer", text="Do you consider yourself a gamer?", choices=_YES_NO),
    Question(id="tech_savvy", text="Do you consider yourself tech-savvy?", choices=_YES_NO),
)


class Outcome(_Strict):
    """What a participant gets at the end: a code to paste and/or a link back to the recruiting platform."""

    code: str | None = Field(None, min_length=1, max_length=64)
    url: str | None = Field(None, max_length=2000, description="http(s) URL; may use {code} and the accepted "
                            "URL parameters, e.g. {PROLIFIC_PID}")


class Recruitment(_Strict):
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
    def urls(self) -> Self:
        fields = {"code", *self.parameters}
        for name in ("completed", "screened_out"):
            url = getattr(self, name).url
            if url is None:
                continue
            try:
                names = [f for _, f, _, _ in string.Formatter().parse(url) if f is not None]
            except ValueError as exc:
                raise ValueError(f"{name}.url is not a valid template: {exc}") from None
            unknown = sorted(set(names) - fields)
            if unknown:
                raise ValueError(f"{name}.url uses {', '.join(unknown)}, which is neither {{code}} nor an "
                                 f"accepted parameter")
            parts = urlsplit(url)
            if parts.scheme not in ("http", "https") or not parts.netloc:
                raise ValueError(f"{name}.url must be an http(s) URL, got {url!r}")
        return self

    def completion_url(self, outcome: str, code: str | None, external: dict[str, str] | None) -> str | None:
        """The outcome's URL with ``{code}`` and the session's parameters filled in (URL-quoted; missing: empty)."""
        url = getattr(self, outcome).url
        if url is None:
            return None
        values = {p: quote((external or {}).get(p, ""), safe="") for p in self.parameters}
        return url.format(code=quote(code or "", safe=""), **values)


class Clips(_Strict):
    """The clip set a study's clips come from (``[clips]``): ``set``, a clip-set file (README "Clip-set file")
    relative to the study file; or inline ``conditions`` (``[[clips.conditions]]``, as a clip-set file's
    ``[[conditions]]``) and/or ``animations`` (``[clips.animations.<name>]``, sources under the data directory),
    the rest from the default clip-set file.  `animstudy study create` builds the clips of it the study needs and
    renders their videos; without ``[clips]`` the study uses the server's clip set."""

    set: str | None = Field(None, min_length=1, max_length=500, pattern=r"\.toml$",
                            description="clip-set file (TOML), relative to the study file")
    conditions: list[dict[str, Any]] | None = Field(None, min_length=1, max_length=64,
                                                    description="conditions, as a clip-set file's [[conditions]]")
    animations: dict[str, dict[str, Any]] | None = Field(None, min_length=1, max_length=64,
                                                         description="animations, as a clip-set file's "
                                                                     "[animations.<name>]")

    @model_validator(mode="after")
    def one_source(self) -> Self:
        if self.set is None and self.conditions is None and self.animations is None:
            raise ValueError("[clips] needs set, or conditions and/or animations")
        if self.set is not None and (self.conditions is not None or self.animations is not None):
            raise ValueError("[clips] takes either set (a clip-set file) or conditions/animations inline, not both")
        return self


class StudyFile(_Strict):
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

    @model_validator(mode="after")
    def unique_questions(self) -> Self:
        ids = [q.id for q in self.questions]
        if len(set(ids)) != len(ids):
            raise ValueError("two questions have the same id")
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


def parse_study_text(text: str, source: str = "study file") -> StudyFile:
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise StudyFileError(source, [f"not valid TOML: {exc}"]) from None
    try:
        return StudyFile.model_validate(raw)
    except ValidationError as exc:
        raise StudyFileError(source, errors_of(exc, text)) from None


def load_study_file(path: Path) -> StudyFile:
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise StudyFileError(str(path), [f"cannot read it: {exc}"]) from None
    return parse_study_text(text, str(path))


def thesis_study() -> StudyFile:
    """The thesis study as ``studies/thesis.toml`` defines it (the default study)."""
    return load_study_file(THESIS_FILE)
