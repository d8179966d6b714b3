from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Request
from fastapi.security import OAuth2PasswordRequestForm
from pydantic import BaseModel

from server.deps import SessionDep, SettingsDep, client_address
from server.errors import TooManyRequests

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
    # Counted as a failure before the password is checked (committed: no transaction is held during the slow
    # check), so concurrent guesses cannot all pass the check before any is counted; the right password takes
    # it back.
    attempt = limiter.attempt(session, *keys)
    if attempt.wait is not None:
        raise TooManyRequests("too many failed logins; wait and try again", retry_after=attempt.wait)
    researcher = authenticate(session, form.username, form.password)  # Unauthorized: the failure is counted
    limiter.succeeded(session, *keys, attempt)
    return TokenRead(access_token=issue_token(researcher, settings.secret, settings.token_hours))
