"""The participant's journey: consent, demographics, trials, exactly-once votes, withdrawal."""

from __future__ import annotations

import hashlib
import json
import secrets
import uuid
from dataclasses import dataclass
from typing import Any

from sqlalchemy import delete, func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, joinedload

from server.db import utcnow
from server.errors import Conflict, Forbidden, NotFound, Unauthorized
from server.studies.design import Design, trial_order
from server.studies.models import Study, StudyState
from server.studies.service import comparison_ids, score

from .models import ParticipantSession, PlaybackEvent, SessionState, Trial, Vote


def _hash(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


@dataclass(frozen=True)
class NewSession:
    session: ParticipantSession
    token: str


def start_session(session: Session, study: Study, external: dict[str, str] | None) -> NewSession:
    """A session with its trials drawn in a seeded random order; the token is returned once, stored hashed."""
    if study.state != StudyState.open:
        raise Conflict(f"study {study.slug!r} is not open for participants")
    token = secrets.token_urlsafe(32)
    seed = secrets.randbits(63)
    ps = ParticipantSession(id=uuid.uuid4().hex, study=study, token_hash=_hash(token), seed=seed,
                            state=SessionState.active, consent_at=utcnow(), consent_version=study.consent_version,
                            external=external or None)
    design = Design.model_validate(study.design)
    for index, planned in enumerate(trial_order(comparison_ids(study), design.repeats, seed)):
        ps.trials.append(Trial(index=index, comparison_id=planned.comparison_id, hybrid_side=planned.hybrid_side,
                               practice=planned.practice))
    session.add(ps)
    session.commit()
    return NewSession(ps, token)


def authorize(session: Session, session_id: str, token: str | None) -> ParticipantSession:
    """The session ``session_id`` if ``token`` is its token: 401 without a valid token, 403 with another
    session's, 404 for an unknown session."""
    ps = session.get(ParticipantSession, session_id)
    if ps is None:
        raise NotFound("no such session")
    if not token:
        raise Unauthorized("missing bearer token")
    token_hash = _hash(token)
    if ps.token_hash is not None and secrets.compare_digest(ps.token_hash, token_hash):
        return ps
    if session.scalar(select(ParticipantSession.id).where(ParticipantSession.token_hash == token_hash)):
        raise Forbidden("this token belongs to another session")
    raise Unauthorized("invalid or withdrawn token")


def set_demographics(session: Session, ps: ParticipantSession, gamer: str, tech_savvy: str) -> ParticipantSession:
    ps.gamer, ps.tech_savvy = gamer, tech_savvy
    session.commit()
    return ps


def answered(session: Session, ps: ParticipantSession) -> int:
    return session.scalar(select(func.count(Vote.id)).where(Vote.session_id == ps.id)) or 0


def upcoming(session: Session, ps: ParticipantSession, limit: int = 2) -> list[Trial]:
    """The first unanswered trials, in order: the current one (the same on every call until it is answered)
    and the one after it.  Trials are answered in order, so they are the session's lowest unanswered indices."""
    return list(session.scalars(
        select(Trial).outerjoin(Vote, Vote.trial_id == Trial.id)
        .where(Trial.session_id == ps.id, Vote.id.is_(None)).order_by(Trial.index).limit(limit)
        .options(joinedload(Trial.comparison))))


def current_trial(session: Session, ps: ParticipantSession) -> Trial | None:
    trials = upcoming(session, ps, limit=1)
    return trials[0] if trials else None


def trials_count(session: Session, ps: ParticipantSession) -> int:
    return session.scalar(select(func.count(Trial.id)).where(Trial.session_id == ps.id)) or 0


def request_hash(body: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


@dataclass(frozen=True)
class VoteResult:
    vote: Vote
    created: bool


def cast_vote(session: Session, ps: ParticipantSession, trial_id: int, choice: str, rt_ms: int,
              idempotency_key: str, extra: dict[str, Any]) -> VoteResult:
    """Store the vote once.  Repeating the same request returns the stored vote; anything else that would change
    or duplicate an answer is a conflict."""
    if ps.state == SessionState.withdrawn:
        raise Unauthorized("this session was withdrawn")
    trial = session.get(Trial, trial_id)
    if trial is None or trial.session_id != ps.id:
        raise NotFound("no such trial in this session")
    body_hash = request_hash({"choice": choice, "rt_ms": rt_ms, "idempotency_key": idempotency_key, **extra})

    def replay(existing: Vote) -> VoteResult:
        if existing.trial_id == trial.id and existing.request_hash == body_hash:
            return VoteResult(existing, created=False)
        if existing.trial_id == trial.id:
            raise Conflict("this trial is answered already, with a different vote")
        raise Conflict("this idempotency key was used for another vote")

    def stored() -> Vote | None:
        return session.scalar(select(Vote).where(
            (Vote.trial_id == trial.id) | ((Vote.session_id == ps.id) & (Vote.idempotency_key == idempotency_key))))

    existing = stored()
    if existing is not None:
        return replay(existing)
    current = current_trial(session, ps)
    if current is None or current.id != trial.id:
        existing = stored()  # a simultaneous request may have answered this trial in between
        if existing is not None:
            return replay(existing)
        raise Conflict("this is not the current trial")
    # Counted before add(): a query after it would autoflush the INSERT outside the IntegrityError guard below.
    last = trial.index == trials_count(session, ps) - 1  # trials are answered in order
    vote = Vote(trial_id=trial.id, session_id=ps.id, choice=choice, score=score(choice, trial.hybrid_side),
                rt_ms=rt_ms, idempotency_key=idempotency_key, request_hash=body_hash, extra=extra or None)
    session.add(vote)
    if last:
        ps.state = SessionState.completed
        ps.completed_at = utcnow()
    try:
        session.commit()
    except IntegrityError:  # a simultaneous request stored this vote (or used this key) first: nothing was written
        session.rollback()
        existing = stored()
        if existing is None:
            raise
        return replay(existing)
    return VoteResult(vote, created=True)


def withdraw(session: Session, ps: ParticipantSession) -> ParticipantSession:
    """Delete the session's votes, demographics and external ids; keep an anonymous row for the count."""
    session.execute(delete(Vote).where(Vote.session_id == ps.id))
    ps.gamer = ps.tech_savvy = None
    ps.external = None
    ps.token_hash = None
    ps.state = SessionState.withdrawn
    ps.withdrawn_at = utcnow()
    session.commit()
    return ps


def record_event(session: Session, ps: ParticipantSession, kind: str, trial_id: int | None,
                 detail: dict[str, Any] | None) -> PlaybackEvent:
    """Keep what the browser reports (e.g. a video that failed to load after its retries)."""
    if trial_id is not None:
        trial = session.get(Trial, trial_id)
        if trial is None or trial.session_id != ps.id:
            raise NotFound("no such trial in this session")
    event = PlaybackEvent(session_id=ps.id, trial_id=trial_id, kind=kind, detail=detail or None)
    session.add(event)
    session.commit()
    return event
