"""The logged-in researcher as a router dependency (``ResearcherDep``): here rather than in :mod:`server.deps`, so
that the shared dependencies know nothing of researchers and the researchers' router can use them."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends
from fastapi.security import OAuth2PasswordBearer

from server.deps import SessionDep, SettingsDep

from .models import Researcher
from .service import researcher_from_token

_researcher_bearer = OAuth2PasswordBearer(tokenUrl="/api/v1/auth/token", auto_error=False)


def current_researcher(session: SessionDep, settings: SettingsDep,
                       token: Annotated[str | None, Depends(_researcher_bearer)]) -> Researcher:
    return researcher_from_token(session, token, settings.secret)


ResearcherDep = Annotated[Researcher, Depends(current_researcher)]
