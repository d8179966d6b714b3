"""Dependencies shared by the routers (``Annotated`` aliases)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer, OAuth2PasswordBearer
from sqlalchemy.orm import Session

from .config import Settings
from .db import SQLITE_BEGIN
from .participants.models import ParticipantSession
from .participants.service import authorize
from .researchers.models import Researcher
from .researchers.service import researcher_from_token


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_session(request: Request) -> Iterator[Session]:
    with request.app.state.session_factory() as session:
        if request.method in ("GET", "HEAD"):  # never writes: let SQLite read beside the writers
            session.connection(execution_options={SQLITE_BEGIN: "DEFERRED"})
        yield session


SettingsDep = Annotated[Settings, Depends(get_settings)]
SessionDep = Annotated[Session, Depends(get_session)]

_participant_bearer = HTTPBearer(auto_error=False, description="the token returned when the session was created")
_researcher_bearer = OAuth2PasswordBearer(tokenUrl="/api/v1/auth/token", auto_error=False)


def current_participant(session_id: str, session: SessionDep,
                        credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_participant_bearer)],
                        ) -> ParticipantSession:
    return authorize(session, session_id, credentials.credentials if credentials else None)


def current_researcher(session: SessionDep, settings: SettingsDep,
                       token: Annotated[str | None, Depends(_researcher_bearer)]) -> Researcher:
    return researcher_from_token(session, token, settings.secret)


ParticipantDep = Annotated[ParticipantSession, Depends(current_participant)]
ResearcherDep = Annotated[Researcher, Depends(current_researcher)]
