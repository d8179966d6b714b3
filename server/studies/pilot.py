"""Pilot runs: a researcher tries their own study through a preview link without polluting its data.

The link is the participant link with ``?preview=<token>``; the token (a JWT signed with the server's secret, as
researcher logins are) names the study and expires.  Sessions started with it are marked ``pilot``: they may start
while the study is a draft (as well as open), they are left out of the results, the counts and the exports unless
asked for (``?pilot=true``), and one action deletes them with every row they made (trials, votes, playback
events).  Changing a draft's design deletes its pilot sessions first: their trials show the old comparisons.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timedelta

import jwt
from sqlalchemy import delete, func, select
from sqlalchemy.orm import Session

from server.db import utcnow
from server.errors import Conflict, Forbidden, NotFound
from server.participants.models import ParticipantSession, PlaybackEvent, Trial, Vote

from .models import Study, StudyState

ALGORITHM = "HS256"
PREVIEW_DAYS = 14
PREVIEW_STATES = (StudyState.draft, StudyState.open)


@dataclass(frozen=True)
class Preview:
    url: str
    token: str
    expires_at: datetime


def preview_link(study: Study, secret: bytes, days: float = PREVIEW_DAYS) -> Preview:
    """The study's preview link (valid ``days``)."""
    expires = utcnow() + timedelta(days=days)
    token = jwt.encode({"typ": "preview", "study": study.id, "slug": study.slug, "exp": expires}, secret,
                       algorithm=ALGORITHM)
    return Preview(url=f"/s/{study.slug}?preview={token}", token=token, expires_at=expires)


def check_preview(study: Study, token: str, secret: bytes) -> None:
    """403 unless ``token`` is a valid, unexpired preview token of ``study``; 409 when the study is closed."""
    try:
        claims = jwt.decode(token, secret, algorithms=[ALGORITHM])
    except jwt.ExpiredSignatureError:
        raise Forbidden("this preview link has expired; get a new one from the study's page") from None
    except jwt.PyJWTError:
        raise Forbidden("invalid preview link") from None
    if claims.get("typ") != "preview" or claims.get("study") != study.id:
        raise Forbidden("this preview link belongs to another study")
    if study.state not in PREVIEW_STATES:
        raise Conflict(f"study {study.slug!r} is {study.state}: pilot sessions start only while it is a draft or open")


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


def previewed_study(session: Session, slug: str, token: str, secret: bytes) -> Study:
    """The study ``slug`` for a pilot run with the preview ``token`` (a draft too): 404 for an unknown study, 403
    for a token that is not this study's (the draft's existence is then known to the link's holder only)."""
    study = session.scalar(select(Study).where(Study.slug == slug))
    if study is None:
        raise NotFound(f"no study {slug!r}")
    check_preview(study, token, secret)
    return study
