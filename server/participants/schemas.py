from __future__ import annotations

import json
import re
from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    StrictBool,
    StrictFloat,
    StrictInt,
    StrictStr,
    StringConstraints,
    field_validator,
    model_validator,
)

from server.studies.scale import AnyChoice

# Row ids are 32-bit integers in the schema; a larger id is refused as invalid input (422), not sent to the
# database (SQLite cannot even bind integers over 64 bits).
RowId = Annotated[int, Field(ge=1, le=2**31 - 1)]

#: A trial in the API: its public id (32 hex digits, ``Trial.public_id``), or, from a page loaded before migration
#: 0008, its old row id (digits).  Row ids are given out no more.
PUBLIC_TRIAL_ID = re.compile(r"^[0-9a-f]{32}$")


def _trial_key(value: str) -> str:
    if PUBLIC_TRIAL_ID.fullmatch(value) or (value.isascii() and value.isdigit() and 1 <= int(value) <= 2**31 - 1
                                        and len(value) <= 10):
        return value
    raise ValueError("a trial id is the trial_id given by GET .../next (32 hex digits)")


TrialKey = Annotated[str, StringConstraints(max_length=32), AfterValidator(_trial_key)]
PublicTrialId = Annotated[str, StringConstraints(pattern=PUBLIC_TRIAL_ID.pattern)]

MAX_EXTRA_BYTES = 16_384
# Request bodies are strict: JSON true is consent, "true" or 1 is not; a number is a number, not a string of one.
STRICT = ConfigDict(strict=True)


class DeviceReport(BaseModel):
    """What the page's device gate measured when the participant started (docs/researchers/participant-page.md)."""

    model_config = ConfigDict(strict=True, extra="forbid")

    viewport_width: int = Field(ge=1, le=100_000)
    viewport_height: int = Field(ge=1, le=100_000)
    device_pixel_ratio: float = Field(gt=0, le=16)
    video_width: int = Field(ge=1, le=100_000)
    video_height: int = Field(ge=1, le=100_000)
    scale: float = Field(ge=0, le=1)
    scaled: bool
    passed: bool


class SessionCreate(BaseModel):
    model_config = STRICT

    consent: bool
    external: dict[str, str] | None = Field(default=None, description="ids from a recruiting platform, e.g. "
                                            "PROLIFIC_PID, STUDY_ID, SESSION_ID")
    device: DeviceReport | None = None
    preview: str | None = Field(default=None, max_length=2000, description="the token of a researcher's preview "
                                "link: the session is a pilot session (draft or open study)")

    @field_validator("consent")
    @classmethod
    def consent_given(cls, value: bool) -> bool:
        if value is not True:
            raise ValueError("consent is required to take part; nothing is stored without it")
        return value

    @field_validator("external")
    @classmethod
    def small_ids(cls, value: dict[str, str] | None) -> dict[str, str] | None:
        if value is not None and (len(value) > 10 or any(len(k) > 64 or len(v) > 200 for k, v in value.items())):
            raise ValueError("at most 10 external ids, names up to 64 and values up to 200 characters")
        return value


class SessionCreated(BaseModel):
    session_id: str
    token: str
    trials_total: int


Key = Annotated[str, StringConstraints(min_length=1, max_length=32)]
# The answers to the study's questions: question id -> choice id (checked against the study by the endpoint).
# A choice id, a number or a short text, as the question's type asks: checked against the study's questions by
# service.answer_errors, which names the question and what it wants (so a JSON true or null gets there too;
# strict: true is not the number 1).
AnswerValue = StrictBool | StrictInt | StrictFloat | Annotated[StrictStr, StringConstraints(max_length=1000)] | None
Answers = Annotated[dict[Key, AnswerValue], Field(max_length=10)]


class SessionRead(BaseModel):
    state: str
    answered: int
    trials_total: int
    demographics_given: bool
    outcome: str | None = Field(None, description="once completed: completed or screened_out")
    completion_code: str | None = None
    completion_url: str | None = None


class TrialRead(BaseModel):
    trial_id: str = Field(description="the trial's id (opaque)")
    index: int
    total: int
    practice: bool
    video_url: str
    preload_url: str | None


class VoteCreate(BaseModel):
    """The answer; extra fields (e.g. measured playback quality) are kept with the vote."""

    model_config = ConfigDict(extra="allow", strict=True)

    choice: AnyChoice = Field(description="one of the answer ids of the study's format (GET /studies/{slug}: "
                              "scale.choices)")
    rt_ms: int = Field(ge=0, le=24 * 3600 * 1000)
    idempotency_key: str = Field(min_length=1, max_length=200)

    @model_validator(mode="after")
    def small_extra(self) -> VoteCreate:
        if len(json.dumps(self.model_extra or {}, default=str)) > MAX_EXTRA_BYTES:
            raise ValueError(f"extra fields may hold at most {MAX_EXTRA_BYTES} bytes of JSON")
        return self

    def extra(self) -> dict[str, Any]:
        return dict(self.model_extra or {})


class VoteRead(BaseModel):
    trial_id: str
    choice: str
    rt_ms: int
    answered_at: datetime
    answered: int
    trials_total: int
    next: TrialRead | None = Field(None, description="the trial to show now (what GET .../next would answer); "
                                                     "null when every trial is answered")


class WithdrawRead(BaseModel):
    state: str


#: A playback event's whole body, in bytes: beyond it, 413 (the page sends well under 300).
MAX_EVENT_BYTES = 2048


class EventDetail(BaseModel):
    """What the page reports with an event: nothing else is stored (no free-form JSON)."""

    model_config = ConfigDict(strict=True, extra="forbid")

    error: str | None = Field(None, max_length=500, description="the browser's error message, e.g. "
                              "'NotAllowedError: ...' for a refused full screen or a video that did not load")


class EventCreate(BaseModel):
    model_config = STRICT

    kind: Literal["load_failure", "playback_stall", "error", "fullscreen_exit", "fullscreen_refused"]
    trial_id: PublicTrialId | RowId | None = Field(None, description="the trial_id given by GET .../next (an "
                                                   "integer: a trial id of before migration 0008)")
    detail: EventDetail | None = None


class EventRead(BaseModel):
    id: int
    kind: str
