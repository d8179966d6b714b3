"""Pilot runs: a researcher tries their own study through a preview link without polluting its data.

The link is the participant link with ``?preview=<token>``; the token (a JWT signed with the server's secret, as
researcher logins are) names the study and expires.  Sessions started with it are marked ``pilot``: they may start
while the study is a draft (as well as open), they are left out of the results, the counts and the exports unless
asked for (``?pilot=true``), and one action deletes them with every row they made (trials, votes, playback
events: :func:`server.participants.service.delete_pilot_sessions`).  Changing a draft's design deletes its pilot
sessions first: their trials show the old comparisons.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timedelta

import jwt
from sqlalchemy import select
from sqlalchemy.orm import Session

from server.db import utcnow
from server.errors import Conflict, Forbidden, NotFound

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


def previewed_study(session: Session, slug: str, token: str, secret: bytes) -> Study:
    """The study ``slug`` for a pilot run with the preview ``token`` (a draft too): 404 for an unknown study, 403
    for a token that is not this study's (the draft's existence is then known to the link's holder only)."""
    study = session.scalar(select(Study).where(Study.slug == slug))
    if study is None:
        raise NotFound(f"no study {slug!r}")
    check_preview(study, token, secret)
    return study
