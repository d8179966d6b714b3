from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Request
from fastapi.security import OAuth2PasswordRequestForm
from pydantic import BaseModel

from server.deps import SessionDep, SettingsDep, client_address
from server.errors import TooManyRequests, Unauthorized

from .service import authenticate, issue_token, normalize_email

router = APIRouter(prefix="/api/v1/auth", tags=["researchers"])


class TokenRead(BaseModel):
    access_token: str
    token_type: str = "bearer"


@router.post("/token", response_model=TokenRead)
def login(form: Annotated[OAuth2PasswordRequestForm, Depends()], session: SessionDep, settings: SettingsDep,
          request: Request) -> TokenRead:
    """OAuth2 password flow: ``username`` is the researcher's e-mail.  Repeated failures are throttled
    (``server.security.LoginLimiter``)."""
    limiter = request.app.state.login_limiter
    keys = (client_address(request), normalize_email(form.username))
    wait = limiter.retry_after(session, *keys)
    session.rollback()  # the password check below takes its time: hold no transaction meanwhile
    if wait is not None:
        raise TooManyRequests("too many failed logins; wait and try again", retry_after=wait)
    try:
        researcher = authenticate(session, form.username, form.password)
    except Unauthorized:
        limiter.failed(session, *keys)
        raise
    limiter.succeeded(session, *keys)
    return TokenRead(access_token=issue_token(researcher, settings.secret, settings.token_hours))
