"""The participant API.

The endpoints are ``async def`` and call the (synchronous) service functions directly, on the event loop, on
purpose: each request is a few sub-millisecond queries on a local database, and handing it to a worker thread
cost more than it saved (thread hand-offs and GIL contention; measured on 2 cores, 2 workers, 100 participants
20 at a time: 190 -> 290 votes/s on PostgreSQL, 240 -> 400 on SQLite, p99 of a vote 190 -> 65 ms and
175 -> 42 ms).  The price: a worker serves one request at a time while the database answers, so the
database waits are bounded (PostgreSQL connect timeout; SQLite writers queue in ``server.db.WriterQueue``).
The researcher endpoints, which can compute for seconds, stay in the thread pool.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Path, Request, Response, status
from fastapi.exceptions import RequestValidationError

from server.deps import ParticipantTokenDep, SessionDep, SettingsDep, limit_new_sessions
from server.errors import PayloadTooLarge
from server.participants import service, staircase
from server.studies import service as studies_service
from server.studies.pilot import previewed_study
from server.studies.service import public_study

from .models import ParticipantSession, SessionState, Trial
from .schemas import (
    MAX_EVENT_BYTES,
    Answers,
    EventCreate,
    EventRead,
    SessionCreate,
    SessionCreated,
    SessionRead,
    TrialKey,
    TrialRead,
    VoteCreate,
    VoteRead,
    WithdrawRead,
)

router = APIRouter(prefix="/api/v1", tags=["participants"])


def media_url(name: str) -> str:
    return f"/media/{name}"


@router.post("/studies/{slug}/sessions", status_code=status.HTTP_201_CREATED, response_model=SessionCreated,
             dependencies=[Depends(limit_new_sessions)])
async def create_session(slug: str, body: SessionCreate, session: SessionDep,
                         settings: SettingsDep) -> SessionCreated:
    study = (previewed_study(session, slug, body.preview, settings.secret) if body.preview is not None
             else public_study(session, slug))  # a researcher's pilot run: draft studies too
    new = service.start_session(session, study, body.external,
                                body.device.model_dump() if body.device else None, pilot=body.preview is not None)
    return SessionCreated(session_id=new.session.id, token=new.token, trials_total=new.session.trials_total)


@router.put("/sessions/{session_id}/demographics", response_model=Answers)
async def put_demographics(session_id: str, body: Answers, token: ParticipantTokenDep,
                           session: SessionDep) -> dict[str, Any]:
    """The answers to the study's questions, ``{question id: answer}`` (every question, once): a choice id, a
    number, a text or a Likert point 1..n, as the question's type asks."""
    ps = service.authorize(session, session_id, token, lock="update")
    errors = service.answer_errors(ps.study, body)
    if errors:
        raise RequestValidationError([{"loc": ("body", q), "msg": m, "type": "value_error"} for q, m in errors])
    service.set_answers(session, ps, body)
    return body


@router.get("/sessions/{session_id}", response_model=SessionRead, response_model_exclude_none=True)
async def get_session_state(session_id: str, token: ParticipantTokenDep, session: SessionDep) -> SessionRead:
    ps = service.authorize(session, session_id, token)
    read = SessionRead(state=ps.state, answered=service.answered(session, ps), trials_total=ps.trials_total,
                       demographics_given=service.questions_answered(ps))
    if ps.state == SessionState.completed:
        outcome = service.outcome(session, ps)
        recruitment = studies_service.recruitment(ps.study)
        code = getattr(recruitment, outcome).code
        read.outcome, read.completion_code = outcome, code
        read.completion_url = recruitment.completion_url(outcome, code, ps.external)
    return read


def public_trial_id(trial: Trial) -> str:
    # A trial of before migration 0008 that it did not reach has no public id: its row id stands in.
    return trial.public_id or str(trial.id)


def trial_read(ps: ParticipantSession, upcoming: list[Trial]) -> TrialRead | None:
    """The first of ``upcoming`` as the page shows it, with the video of the one after it to preload."""
    if not upcoming:
        return None
    trial, following = upcoming[0], (upcoming[1] if len(upcoming) > 1 else None)
    if following is not None and staircase.undecided(ps, following):
        following = None  # its level waits for this trial's answer: nothing to preload, nothing to give away
    return TrialRead(trial_id=public_trial_id(trial), index=trial.index, total=ps.trials_total,
                     practice=trial.practice, video_url=media_url(trial.comparison.video(trial.reference_side)),
                     preload_url=media_url(following.comparison.video(following.reference_side)) if following else None)


@router.get("/sessions/{session_id}/next", response_model=TrialRead,
            responses={204: {"description": "every trial is answered"}})
async def next_trial(session_id: str, token: ParticipantTokenDep, session: SessionDep) -> TrialRead | Response:
    ps = service.authorize(session, session_id, token)
    trial = trial_read(ps, service.upcoming(session, ps))
    return trial if trial is not None else Response(status_code=status.HTTP_204_NO_CONTENT)


@router.post("/sessions/{session_id}/trials/{trial_id}/vote", response_model=VoteRead,
             status_code=status.HTTP_201_CREATED, responses={200: {"description": "the same vote, already stored"}})
async def vote(session_id: str, trial_id: Annotated[TrialKey, Path()], body: VoteCreate, token: ParticipantTokenDep,
               session: SessionDep, response: Response) -> VoteRead:
    """Store the vote (exactly once, see ``cast_vote``) and answer with the next trial, which saves the page a
    request per trial."""
    ps, trial = service.authorize_answer(session, session_id, token, trial_id)
    if (error := service.choice_error(ps.study, body.choice)) is not None:
        raise RequestValidationError([{"loc": ("body", "choice"), "msg": error, "type": "value_error"}])
    result = service.cast_vote(session, ps, trial, body.choice, body.rt_ms, body.idempotency_key, body.extra())
    if not result.created:
        response.status_code = status.HTTP_200_OK
    return VoteRead(trial_id=public_trial_id(trial), choice=result.choice, rt_ms=result.rt_ms,
                    answered_at=result.answered_at, answered=result.answered, trials_total=ps.trials_total,
                    next=trial_read(ps, result.upcoming))


@router.post("/sessions/{session_id}/withdraw", response_model=WithdrawRead)
async def withdraw(session_id: str, token: ParticipantTokenDep, session: SessionDep) -> WithdrawRead:
    ps = service.authorize(session, session_id, token, lock="update")
    return WithdrawRead(state=service.withdraw(session, ps).state)


async def small_event(request: Request) -> None:
    """413 for an event body over :data:`~.schemas.MAX_EVENT_BYTES` (before it is validated)."""
    if len(await request.body()) > MAX_EVENT_BYTES:
        raise PayloadTooLarge(f"an event may hold at most {MAX_EVENT_BYTES} bytes")


@router.post("/sessions/{session_id}/events", response_model=EventRead, status_code=status.HTTP_201_CREATED,
             dependencies=[Depends(small_event)],
             responses={413: {"description": "the event is too large"},
                        429: {"description": "the session or trial has reported enough events"}})
async def report_event(session_id: str, body: EventCreate, token: ParticipantTokenDep,
                       session: SessionDep) -> EventRead:
    """A playback problem (``detail``: only the known fields of ``EventDetail``), at most 100 per session and
    10 per trial."""
    ps = service.authorize(session, session_id, token, lock="update")
    detail = body.detail.model_dump(exclude_none=True) if body.detail else None
    event = service.record_event(session, ps, body.kind, None if body.trial_id is None else str(body.trial_id),
                                 detail)
    return EventRead(id=event.id, kind=event.kind)
