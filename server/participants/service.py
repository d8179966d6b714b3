"""The participant's journey (consent, demographics, trials, exactly-once votes, withdrawal) and everything else
that reads or deletes sessions, trials and votes: the counts, the vote log, pilot sessions."""

from __future__ import annotations

import hashlib
import json
import secrets
import uuid
from collections.abc import Collection, Iterator, Mapping
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any, Literal

from sqlalchemy import JSON, bindparam, delete, func, select
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.engine import Row
from sqlalchemy.orm import Session, aliased, joinedload

from server.analysis.screening import ParticipantScreening
from server.config import Settings
from server.db import utcnow
from server.errors import Conflict, Forbidden, NotFound, TooManyRequests, Unauthorized
from server.media.manifest import RenderManifest
from server.studies.design import Design, trial_order
from server.studies.models import Comparison, ComparisonKind, Stimulus, Study, StudyState
from server.studies.scale import MAX_SCORE, format_choices, format_score
from server.studies.service import (
    check_deletable,
    recruitment,
    redesigns,
    remove_study,
    revise_study,
    revision,
    screening_rules,
)
from server.studies.studyfile import Question

from . import staircase
from .assign import session_comparisons
from .models import ParticipantSession, PlaybackEvent, SessionState, Trial, Vote


def _hash(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


@dataclass(frozen=True)
class NewSession:
    session: ParticipantSession
    token: str


def staircase_comparisons(study: Study) -> dict[tuple[str, str], int]:
    """(animation, test condition) -> test comparison id (a staircase design's reference-against-level pairs)."""
    return {(c.reference.animation, c.test.condition): c.id for c in study.comparisons
            if c.kind == ComparisonKind.test}


def choice_error(study: Study, choice: str) -> str | None:
    """Why ``choice`` is not an answer of the study's format (``[scale] format``), or None."""
    ids = format_choices((study.scale or {}).get("format", "rating5"))
    return None if choice in ids else f"Input should be {', '.join(map(repr, ids))} (this study's answer format)"


def start_session(session: Session, study: Study, external: dict[str, str] | None,
                  device: dict[str, Any] | None = None, pilot: bool = False) -> NewSession:
    """A session with its trials drawn in a seeded random order; the token is returned once, stored hashed.
    ``pilot``: a researcher's pilot session (the caller checked the preview link), allowed on a draft too."""
    if not pilot and study.state != StudyState.open:
        raise Conflict(f"study {study.slug!r} is not open for participants")
    token = secrets.token_urlsafe(32)
    seed = secrets.randbits(63)
    accepted = recruitment(study).parameters  # only the study's accepted URL parameters are kept
    kept = {k: v for k, v in (external or {}).items() if k in accepted}
    now = utcnow()
    ps = ParticipantSession(id=uuid.uuid4().hex, study=study, token_hash=_hash(token), seed=seed, created_at=now,
                            state=SessionState.active, consent_at=now, consent_version=study.consent_version,
                            external=kept or None, device=device, pilot=pilot)
    design = Design.model_validate(study.design)
    chosen = session_comparisons(session, study, seed, now)  # by the design's mode
    if design.mode == "staircase":  # one QUEST+ staircase per animation, its levels chosen as answers come
        planned_trials = staircase.plan(design, chosen, staircase_comparisons(study), study.scale.get("format", "2afc"),
                                        seed)
    else:
        planned_trials = trial_order(chosen, design.repeats, seed)
    for index, planned in enumerate(planned_trials):
        ps.trials.append(Trial(index=index, comparison_id=planned.comparison_id,
                               reference_side=planned.reference_side, practice=planned.practice))
    ps.trials_total = len(ps.trials)
    session.add(ps)
    session.commit()
    return NewSession(ps, token)


_by_id = select(ParticipantSession).where(ParticipantSession.id == bindparam("id"))
_SESSION = {None: _by_id, "share": _by_id.with_for_update(read=True), "update": _by_id.with_for_update()}
# A vote's session (locked as by authorize(lock="share")) and its trial, in one round trip: by the trial's public id,
# or by its row id from a page loaded before migration 0008.
_ANSWER = {by: (select(ParticipantSession, Trial)
                .outerjoin(Trial, (column == bindparam("trial_id")) & (Trial.session_id == ParticipantSession.id))
                .where(ParticipantSession.id == bindparam("id")).with_for_update(read=True, of=ParticipantSession))
           for by, column in (("public", Trial.public_id), ("row", Trial.id))}


def _trial_key(trial_id: str | int) -> tuple[str, str | int]:
    """Which column a trial id of the API names (``TrialKey``: 32 hex digits, or an old row id, digits)."""
    trial_id = str(trial_id)
    return ("row", int(trial_id)) if trial_id.isdigit() and len(trial_id) <= 10 else ("public", trial_id)


def authorize(session: Session, session_id: str, token: str | None,
              lock: Literal["share", "update"] | None = None) -> ParticipantSession:
    """The session ``session_id`` if ``token`` is its token: 401 without a valid token, 403 with another
    session's, 404 for an unknown session.

    ``lock``: requests that write lock the session row until they commit ("share" for answers, "update" for
    withdrawal and demographics), so a withdrawal never runs beside a vote of the same session: without it a vote
    could be stored just after the withdrawal deleted the answers.  (SQLite has one writer at a time anyway.)
    """
    return _checked(session, session.scalars(_SESSION[lock], {"id": session_id}).first(), token)


def authorize_answer(session: Session, session_id: str, token: str | None, trial_id: str | int
                     ) -> tuple[ParticipantSession, Trial]:
    """:func:`authorize` with ``lock="share"``, and the session's trial ``trial_id`` (its public id, or its row id
    from a page of before migration 0008; 404 if the session has no such trial)."""
    by, key = _trial_key(trial_id)
    row = session.execute(_ANSWER[by], {"id": session_id, "trial_id": key}).first()
    ps = _checked(session, row[0] if row is not None else None, token)
    trial = row[1]  # type: ignore[index]  # _checked raised if there was no row
    if trial is None:
        raise NotFound("no such trial in this session")
    return ps, trial


def _checked(session: Session, ps: ParticipantSession | None, token: str | None) -> ParticipantSession:
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


def answer_errors(study: Study, answers: dict[str, Any]) -> list[tuple[str, str]]:
    """(question id, message) for every question of ``study`` unanswered or answered with something its type
    does not accept (``studyfile.Question.answer_error``), and every answer to a question the study does not
    ask."""
    errors = []
    for q in study.questions:
        question = Question.model_validate(q)
        if q["id"] not in answers:
            errors.append((q["id"], "Field required"))
        elif (error := question.answer_error(answers[q["id"]])) is not None:
            errors.append((q["id"], error))
    asked = {q["id"] for q in study.questions}
    errors += [(k, "this study asks no such question") for k in answers if k not in asked]
    return errors


def set_answers(session: Session, ps: ParticipantSession, answers: dict[str, Any]) -> ParticipantSession:
    """Store (or correct) the answers to the study's questions (checked with :func:`answer_errors` first) while
    the session is active; a finished session's data is final."""
    if ps.state != SessionState.active:
        raise Conflict(f"this session is {ps.state}; its answers can no longer be changed")
    ps.answers = dict(answers)
    session.commit()
    return ps


def questions_answered(ps: ParticipantSession) -> bool:
    return all(q["id"] in (ps.answers or {}) for q in ps.study.questions)


def outcome(session: Session, ps: ParticipantSession) -> str:
    """``completed`` or ``screened_out`` (:func:`session_outcome`) of a finished session."""
    failed = failed_catch_trials(session, ps.study, ps.id).get(ps.id, 0)
    return session_outcome(ps.study, SessionState.completed, failed) or "completed"


def answered(session: Session, ps: ParticipantSession) -> int:
    return session.scalar(select(func.count(Vote.id)).where(Vote.session_id == ps.id)) or 0


# The statements of the hot path are built once, with bind parameters: building them per request (and their
# cache keys) was a third of the CPU time of a vote.
_UPCOMING = (select(Trial).outerjoin(Vote, Vote.trial_id == Trial.id)
             .where(Trial.session_id == bindparam("session_id"), Vote.id.is_(None)).order_by(Trial.index).limit(2)
             .options(joinedload(Trial.comparison)))


def upcoming(session: Session, ps: ParticipantSession) -> list[Trial]:
    """The first unanswered trials, in order: the current one (the same on every call until it is answered)
    and the one after it.  Trials are answered in order, so they are the session's lowest unanswered indices."""
    return list(session.scalars(_UPCOMING, {"session_id": ps.id}))


def request_hash(body: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


@dataclass(frozen=True)
class VoteResult:
    trial_id: int
    choice: str
    rt_ms: int
    answered_at: datetime
    answered: int  # votes of the session after this one
    created: bool
    upcoming: list[Trial]  # what comes next (see upcoming()), read in the same transaction


def _vote_insert(insert: Any) -> Any:
    """``INSERT INTO votes ... SELECT <the vote> WHERE <every earlier trial is answered> ON CONFLICT DO NOTHING
    RETURNING id`` for one dialect's ``insert`` (both spell ON CONFLICT alike)."""
    earlier_open = (select(Trial.id).outerjoin(Vote, Vote.trial_id == Trial.id)
                    .where(Trial.session_id == bindparam("session_id"), Trial.index < bindparam("index"),
                           Vote.id.is_(None)).exists())
    columns = ["trial_id", "session_id", "choice", "score", "rt_ms", "idempotency_key", "request_hash", "extra",
               "answered_at"]
    types = {c: Vote.__table__.c[c].type for c in columns} | {"extra": JSON(none_as_null=True)}  # None: SQL NULL
    row = select(*(bindparam(c, type_=types[c]) for c in columns)).where(~earlier_open)
    # The table, not the entity: with parameters, an ORM insert would be taken for a bulk insert of objects.
    table = Vote.__table__
    return insert(table).from_select(columns, row).on_conflict_do_nothing().returning(table.c.id)


_VOTE_INSERT = {"postgresql": _vote_insert(postgresql.insert), "sqlite": _vote_insert(sqlite.insert)}


def cast_vote(session: Session, ps: ParticipantSession, trial: Trial, choice: str, rt_ms: int,
              idempotency_key: str, extra: dict[str, Any]) -> VoteResult:
    """Store the vote once.  Repeating the same request returns the stored vote; anything else that would change
    or duplicate an answer is a conflict.

    One statement decides: the INSERT happens only if every earlier trial is answered (trials are answered in
    order) and does nothing if this trial or this idempotency key has a vote already (the unique constraints).
    Simultaneous requests are therefore settled by the database, never by a read-then-write race.
    """
    if ps.state == SessionState.withdrawn:
        raise Unauthorized("this session was withdrawn")
    body_hash = request_hash({"choice": choice, "rt_ms": rt_ms, "idempotency_key": idempotency_key, **extra})
    now = utcnow()
    inserted = session.scalar(_VOTE_INSERT[session.get_bind().dialect.name], {
        "trial_id": trial.id, "session_id": ps.id, "index": trial.index, "choice": choice,
        "score": format_score(ps.study.scale.get("format", "rating5"), choice, trial.reference_side),
        "rt_ms": rt_ms, "idempotency_key": idempotency_key,
        "request_hash": body_hash, "extra": extra or None, "answered_at": now})
    if inserted is not None:
        if trial.index == ps.trials_total - 1:
            ps.state = SessionState.completed
            ps.completed_at = now
        else:
            staircase.advance(session, ps, trial)  # a staircase's next level, from this answer on
        following = upcoming(session, ps)  # before the commit: one transaction (and one SQLite write turn)
        session.commit()
        return VoteResult(trial.id, choice, rt_ms, now, trial.index + 1, created=True, upcoming=following)
    # Nothing was written.  The statements below see what the other request committed (a new snapshot per
    # statement on PostgreSQL; on SQLite this transaction took the write lock after it).
    existing = session.scalar(select(Vote).where(
        (Vote.trial_id == trial.id) | ((Vote.session_id == ps.id) & (Vote.idempotency_key == idempotency_key))))
    if existing is None:
        raise Conflict("this is not the current trial")
    if existing.trial_id != trial.id:
        raise Conflict("this idempotency key was used for another vote")
    if existing.request_hash != body_hash:
        raise Conflict("this trial is answered already, with a different vote")
    return VoteResult(existing.trial_id, existing.choice, existing.rt_ms, existing.answered_at,
                      answered(session, ps), created=False, upcoming=upcoming(session, ps))


def withdraw(session: Session, ps: ParticipantSession) -> ParticipantSession:
    """Delete everything the participant gave or their browser reported: votes, answers, external ids, the device
    report and every playback event.  Kept (docs/security.md, "Withdrawal"): an anonymous row for the withdrawal
    count (state, study, consent version and time, start and withdrawal times) and the trial order the server
    drew (no participant data)."""
    session.execute(delete(Vote).where(Vote.session_id == ps.id))
    session.execute(delete(PlaybackEvent).where(PlaybackEvent.session_id == ps.id))
    ps.answers = None
    ps.external = None
    ps.device = None
    ps.token_hash = None
    ps.state = SessionState.withdrawn
    ps.withdrawn_at = utcnow()
    session.commit()
    return ps


#: Playback events kept per session and per trial; beyond them, 429 (the page reports a failed video once per
#: trial and a left full screen when it happens).
MAX_EVENTS_PER_SESSION = 100
MAX_EVENTS_PER_TRIAL = 10


def record_event(session: Session, ps: ParticipantSession, kind: str, trial_key: str | None,
                 detail: dict[str, Any] | None) -> PlaybackEvent:
    """Keep what the browser reports (e.g. a video that failed to load after its retries), up to
    :data:`MAX_EVENTS_PER_SESSION` per session and :data:`MAX_EVENTS_PER_TRIAL` per trial (429 beyond).  The
    caller holds the session row locked (``authorize(lock="update")``), so concurrent reports count right."""
    trial_id = None
    if trial_key is not None:
        by, key = _trial_key(trial_key)
        trial = session.scalar(select(Trial).where(Trial.session_id == ps.id,
                                                   (Trial.public_id if by == "public" else Trial.id) == key))
        if trial is None:
            raise NotFound("no such trial in this session")
        trial_id = trial.id
    count = select(func.count(PlaybackEvent.id)).where(PlaybackEvent.session_id == ps.id)
    if (session.scalar(count) or 0) >= MAX_EVENTS_PER_SESSION:
        raise TooManyRequests(f"this session has reported {MAX_EVENTS_PER_SESSION} events already; no more are kept")
    if trial_id is not None and (session.scalar(count.where(PlaybackEvent.trial_id == trial_id)) or 0) \
            >= MAX_EVENTS_PER_TRIAL:
        raise TooManyRequests(f"this trial has {MAX_EVENTS_PER_TRIAL} events already; no more are kept")
    event = PlaybackEvent(session_id=ps.id, trial_id=trial_id, kind=kind, detail=detail or None)
    session.add(event)
    session.commit()
    return event


def failed_catch_trials(session: Session, study: Study, session_id: str | None = None) -> dict[str, int]:
    """Failed catch trials per participant session of ``study`` (or of the one session ``session_id``), by the
    study's answer format (``scale.catch_row_failed``): a 'significantly better' answer (rating5) or "different"
    (same_different) when both sides show the same clip; the wrong side (2afc) or "same" on a threshold design's
    catch trial (its easiest level).  Sessions without a failure are absent."""
    answer_format = (study.scale or {}).get("format", "rating5")
    same_clip = Comparison.reference_id == Comparison.test_id
    failed = {"rating5": func.abs(Vote.score) == MAX_SCORE,
              "2afc": ~same_clip & (Vote.score == 1),  # the test side taken for the original
              "same_different": (same_clip & (Vote.score == -1)) | (~same_clip & (Vote.score == 0))}[answer_format]
    query = (select(Trial.session_id, func.count(Vote.id)).join(Vote, Vote.trial_id == Trial.id)
             .join(Comparison, Trial.comparison_id == Comparison.id)
             .where(Comparison.study_id == study.id, Comparison.kind == ComparisonKind.catch, failed)
             .group_by(Trial.session_id))
    if session_id is not None:
        query = query.where(Trial.session_id == session_id)
    return {sid: n for sid, n in session.execute(query).all()}


def session_outcome(study: Study, state: str, failed_catch: int) -> str | None:
    """What a finished session's participant is told (and which completion code or link they get):
    ``completed``, or ``screened_out`` when the study screens by catch trials (``[screening] rules``) and more
    were failed than it allows; None for a session that has not finished.  The other rules are applied to the
    results and exports only: most compare a participant with the panel, which grows after they leave."""
    if state != SessionState.completed:
        return None
    if "catch" not in screening_rules(study).rules:
        return "completed"
    return "screened_out" if failed_catch > recruitment(study).catch_failures_allowed else "completed"


def pilot_counts(session: Session, study: Study) -> dict[str, int]:
    """Sessions, trials, votes and playback events of the study's pilot sessions."""
    ids = select(ParticipantSession.id).where(ParticipantSession.study_id == study.id,
                                              ParticipantSession.pilot.is_(True))
    count = {name: session.scalar(select(func.count()).select_from(model).where(column.in_(ids))) or 0
             for name, model, column in (("sessions", ParticipantSession, ParticipantSession.id),
                                         ("trials", Trial, Trial.session_id), ("votes", Vote, Vote.session_id),
                                         ("events", PlaybackEvent, PlaybackEvent.session_id))}
    return count


def delete_pilot_sessions(session: Session, study: Study, commit: bool = True) -> dict[str, int]:
    """Delete every pilot session of ``study`` and every row it made, in one transaction; what was deleted."""
    deleted = pilot_counts(session, study)
    ids = select(ParticipantSession.id).where(ParticipantSession.study_id == study.id,
                                              ParticipantSession.pilot.is_(True)).scalar_subquery()
    # explicitly, children first: the database's ON DELETE CASCADE would do, but this says what goes
    session.execute(delete(PlaybackEvent).where(PlaybackEvent.session_id.in_(ids)))
    session.execute(delete(Vote).where(Vote.session_id.in_(ids)))
    session.execute(delete(Trial).where(Trial.session_id.in_(ids)))
    session.execute(delete(ParticipantSession).where(ParticipantSession.study_id == study.id,
                                                     ParticipantSession.pilot.is_(True)))
    if commit:
        session.commit()
    return deleted


def update_study(session: Session, study: Study, changes: Mapping[str, Any], media: RenderManifest | None = None,
                 media_dir: Path | None = None, clips_dir: Path | None = None,
                 animations: Collection[str] | None = None) -> Study:
    """Apply a partial study file (:func:`server.studies.service.revision` says what may change when); a new
    design deletes the draft's pilot sessions first: their trials show the old comparisons."""
    updated = revision(study, changes, media)
    if redesigns(study, updated):
        delete_pilot_sessions(session, study, commit=False)
    return revise_study(session, study, updated, media, media_dir, clips_dir, animations)


def delete_study(session: Session, study: Study, settings: Settings) -> None:
    """A draft that never opened (:func:`server.studies.service.remove_study`) with its pilot sessions, a draft's
    only ones: their trials hold its comparisons."""
    check_deletable(study)
    delete_pilot_sessions(session, study, commit=False)
    remove_study(session, study, settings)


def participant_counts(session: Session, study: Study, include_pilot: bool = False,
                       records: Mapping[str, ParticipantScreening] | None = None) -> dict[str, int]:
    """``started``: every session created (withdrawn included); ``completed``: finished and not withdrawn;
    ``screened_out``: of those, the ones whose votes are not analysed, by the screening ``records`` (the caller
    has them: :func:`server.research.service.participant_counts`) or, without them, by catch trials alone;
    ``pilot``: the researcher's preview sessions, which count in the others only with ``include_pilot``."""
    query = select(ParticipantSession.state, ParticipantSession.pilot, func.count()).where(
        ParticipantSession.study_id == study.id).group_by(ParticipantSession.state, ParticipantSession.pilot)
    by_state: dict[str, int] = {}
    pilot = 0
    for state, is_pilot, n in session.execute(query).all():
        pilot += n if is_pilot else 0
        if include_pilot or not is_pilot:
            by_state[state] = by_state.get(state, 0) + n
    if records is not None:
        screened = sum(r.screened_out for r in records.values())
    else:  # the cheap count, without reading every vote
        failed = failed_catch_trials(session, study)
        query = select(ParticipantSession.id).where(
            ParticipantSession.study_id == study.id, ParticipantSession.state == SessionState.completed,
            ParticipantSession.id.in_(failed))
        if not include_pilot:
            query = query.where(ParticipantSession.pilot.is_(False))
        completed = session.scalars(query) if failed else []
        screened = sum(session_outcome(study, SessionState.completed, failed[sid]) == "screened_out"
                       for sid in completed)
    return {"started": sum(by_state.values()), "completed": by_state.get(SessionState.completed, 0),
            "screened_out": screened, "withdrawn": by_state.get(SessionState.withdrawn, 0),
            "active": by_state.get(SessionState.active, 0), "pilot": pilot}


def vote_count(session: Session, study: Study) -> int:
    """The votes of the study's participants (pilot sessions left out)."""
    return session.scalar(select(func.count(Vote.id)).join(ParticipantSession).where(
        ParticipantSession.study_id == study.id, ParticipantSession.pilot.is_(False))) or 0


def completion_times(session: Session, study: Study, include_pilot: bool = False) -> list[float]:
    """Seconds from start to finish of every completed session (pilot sessions only with ``include_pilot``)."""
    return [(ps.completed_at - ps.created_at).total_seconds() for ps in session.scalars(
        select(ParticipantSession).where(ParticipantSession.study_id == study.id,
                                         ParticipantSession.state == SessionState.completed,
                                         *([] if include_pilot else [ParticipantSession.pilot.is_(False)])))]


def vote_records(session: Session, study: Study, include_pilot: bool = False,
                 sessions: Collection[str] | None = None) -> Iterator[Row[Any]]:
    """Every vote of ``study`` (of ``sessions`` only, if given) in session and trial order, with its trial, its
    session and what the comparison showed (kind; reference animation and condition, test condition; both clips,
    videos, frames and fps; the two pair videos): the rows :func:`server.participants.rows.screened_rows` turns into
    the export."""
    reference, test = aliased(Stimulus), aliased(Stimulus)
    query = (
        select(Vote, Trial, ParticipantSession, Comparison.kind, reference.animation, reference.condition,
               test.condition, reference.clip_id, test.clip_id, reference.video, test.video,
               Comparison.video_reference_left, Comparison.video_reference_right, reference.frames,
               reference.fps, test.frames, test.fps)
        .join(Trial, Vote.trial_id == Trial.id)
        .join(ParticipantSession, Trial.session_id == ParticipantSession.id)
        .join(Comparison, Trial.comparison_id == Comparison.id)
        .join(reference, Comparison.reference_id == reference.id)
        .join(test, Comparison.test_id == test.id)
        .where(ParticipantSession.study_id == study.id)
        .order_by(ParticipantSession.created_at, ParticipantSession.id, Trial.index)
    )
    if not include_pilot:
        query = query.where(ParticipantSession.pilot.is_(False))
    if sessions is not None:
        query = query.where(ParticipantSession.id.in_(sessions))
    yield from session.execute(query)
