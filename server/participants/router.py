from __future__ import annotations

from fastapi import APIRouter, Response, status

from server.deps import ParticipantDep, SessionDep
from server.participants import service
from server.studies.service import get_study, trials_total

from .models import SessionState
from .schemas import (
    DemographicsRead,
    DemographicsUpdate,
    EventCreate,
    EventRead,
    SessionCreate,
    SessionCreated,
    SessionRead,
    TrialRead,
    VoteCreate,
    VoteRead,
    WithdrawRead,
)

router = APIRouter(prefix="/api/v1", tags=["participants"])


def media_url(name: str) -> str:
    return f"/media/{name}"


@router.post("/studies/{slug}/sessions", status_code=status.HTTP_201_CREATED, response_model=SessionCreated)
def create_session(slug: str, body: SessionCreate, session: SessionDep) -> SessionCreated:
    study = get_study(session, slug)
    new = service.start_session(session, study, body.external)
    return SessionCreated(session_id=new.session.id, token=new.token, trials_total=len(new.session.trials))


@router.put("/sessions/{session_id}/demographics", response_model=DemographicsRead)
def put_demographics(body: DemographicsUpdate, ps: ParticipantDep, session: SessionDep) -> DemographicsRead:
    service.set_demographics(session, ps, body.gamer, body.tech_savvy)
    return DemographicsRead(gamer=body.gamer, tech_savvy=body.tech_savvy)


@router.get("/sessions/{session_id}", response_model=SessionRead, response_model_exclude_none=True)
def get_session_state(ps: ParticipantDep, session: SessionDep) -> SessionRead:
    completed = ps.state == SessionState.completed
    return SessionRead(state=ps.state, answered=service.answered(session, ps), trials_total=trials_total(ps.study),
                       demographics_given=ps.gamer is not None and ps.tech_savvy is not None,
                       completion_code=ps.study.completion_code if completed else None,
                       completion_url=ps.study.completion_url if completed else None)


@router.get("/sessions/{session_id}/next", response_model=TrialRead,
            responses={204: {"description": "every trial is answered"}})
def next_trial(ps: ParticipantDep, session: SessionDep) -> TrialRead | Response:
    upcoming = service.upcoming(session, ps)
    if not upcoming:
        return Response(status_code=status.HTTP_204_NO_CONTENT)
    trial, following = upcoming[0], (upcoming[1] if len(upcoming) > 1 else None)
    return TrialRead(trial_id=trial.id, index=trial.index, total=service.trials_count(session, ps),
                     practice=trial.practice, video_url=media_url(trial.comparison.video(trial.hybrid_side)),
                     preload_url=media_url(following.comparison.video(following.hybrid_side)) if following else None)


@router.post("/sessions/{session_id}/trials/{trial_id}/vote", response_model=VoteRead,
             status_code=status.HTTP_201_CREATED, responses={200: {"description": "the same vote, already stored"}})
def vote(trial_id: int, body: VoteCreate, ps: ParticipantDep, session: SessionDep, response: Response) -> VoteRead:
    result = service.cast_vote(session, ps, trial_id, body.choice, body.rt_ms, body.idempotency_key, body.extra())
    if not result.created:
        response.status_code = status.HTTP_200_OK
    v = result.vote
    return VoteRead(trial_id=v.trial_id, choice=v.choice, rt_ms=v.rt_ms, answered_at=v.answered_at,
                    answered=service.answered(session, ps), trials_total=service.trials_count(session, ps))


@router.post("/sessions/{session_id}/withdraw", response_model=WithdrawRead)
def withdraw(ps: ParticipantDep, session: SessionDep) -> WithdrawRead:
    return WithdrawRead(state=service.withdraw(session, ps).state)


@router.post("/sessions/{session_id}/events", response_model=EventRead, status_code=status.HTTP_201_CREATED)
def report_event(body: EventCreate, ps: ParticipantDep, session: SessionDep) -> EventRead:
    event = service.record_event(session, ps, body.kind, body.trial_id, body.detail)
    return EventRead(id=event.id, kind=event.kind)
