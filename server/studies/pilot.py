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
from datetime import UTC, datetime, timedelta

import jwt
from sqlalchemy import select
from sqlalchemy.orm import Session

from server.db import utcnow
from server.errors import Conflict, NotFound

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
    token = jwt.encode({"typ": "preview", "study": study.id, "nonce": nonce(study), "slug": study.slug,
                        "exp": expires}, secret, algorithm=ALGORITHM)
    return Preview(url=f"/s/{study.slug}?preview={token}", token=token, expires_at=expires)


def nonce(study: Study) -> str:
    """What binds a token to this study and no later one: its id alone could name another study once the first is
    deleted (SQLite reused ids before migration 0012, and a restored database may too); its creation time, to the
    microsecond, does not recur."""
    return study.created_at.astimezone(UTC).isoformat()


def check_preview(study: Study, token: str, secret: bytes) -> None:
    """404 unless ``token`` is a valid, unexpired preview token of ``study``, the same answer as for a study that
    does not exist (:func:`unknown`); 409 when the study is closed."""
    try:
        claims = jwt.decode(token, secret, algorithms=[ALGORITHM])
    except jwt.PyJWTError:  # expired, forged or not a token: nothing is said of the study
        raise unknown(study.slug) from None
    if claims.get("typ") != "preview" or claims.get("study") != study.id or claims.get("nonce") != nonce(study):
        raise unknown(study.slug)
    if study.state not in PREVIEW_STATES:
        raise Conflict(f"study {study.slug!r} is {study.state}: pilot sessions start only while it is a draft or open")


def unknown(slug: str) -> NotFound:
    """What a preview link that does not open ``slug`` gets, whether the study exists or not: a 403 for an
    existing draft would tell the link's holder that a study of that slug is being prepared (issue 36)."""
    return NotFound(f"no study {slug!r}, or this preview link is not valid for it (expired, or of another "
                    "study); get a new one from the study's page")


def previewed_study(session: Session, slug: str, token: str, secret: bytes) -> Study:
    """The study ``slug`` for a pilot run with the preview ``token`` (a draft too): one 404 for an unknown study
    and for a token that is not this study's."""
    study = session.scalar(select(Study).where(Study.slug == slug))
    if study is None:
        raise unknown(slug)
    check_preview(study, token, secret)
    return study
