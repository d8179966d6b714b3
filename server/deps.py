"""Dependencies shared by the routers (``Annotated`` aliases); the logged-in researcher is
:data:`server.researchers.deps.ResearcherDep`."""

from __future__ import annotations

import ipaddress
from collections.abc import AsyncIterator
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session
from starlette.types import Scope

from .config import Settings
from .errors import TooManyRequests


async def get_settings(request: Request) -> Settings:
    return request.app.state.settings


async def get_session(request: Request) -> AsyncIterator[Session]:
    """A session for the request, made in the event loop (creating one does no I/O, so it costs no thread hop);
    the participant endpoints use it on the loop, the researcher endpoints in their worker thread."""
    state = request.app.state
    # Reads never write: on SQLite they run beside the writers instead of queueing for the write lock.
    bind = state.read_engine if request.method in ("GET", "HEAD") else state.engine
    session = state.session_factory(bind=bind)
    try:
        yield session
    finally:
        session.close()  # after a commit nothing is left to do; after a read, a rollback on a local connection


SettingsDep = Annotated[Settings, Depends(get_settings)]
# "function": closed as the endpoint returns or raises, before the response is sent.  The participant endpoints
# run on the event loop, and a transaction left open across the await of sending would hold SQLite's writer turn
# while other requests of the same loop wait for it.
SessionDep = Annotated[Session, Depends(get_session, scope="function")]

_participant_bearer = HTTPBearer(auto_error=False, description="the token returned when the session was created")


async def participant_token(
        credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_participant_bearer)]) -> str | None:
    """The bearer token; the endpoint checks it (``authorize``) together with its other queries."""
    return credentials.credentials if credentials else None


def _trusted(address: str, networks: tuple) -> bool:
    try:
        ip = ipaddress.ip_address(address.strip())
    except ValueError:
        return False
    return any(ip in n for n in networks)


def client_address(request: Request) -> str:
    """The client's address: the connecting one, unless that is one of ``ANIMSTUDY_TRUSTED_PROXIES``; then the
    last address of ``X-Forwarded-For`` that is not a trusted proxy (each proxy appends the address it was reached
    from; what comes before was written by the client and proves nothing).  Without trusted proxies the header is
    ignored, so a client cannot choose its address to escape the rate limits."""
    address = request.client.host if request.client else "?"
    networks = request.app.state.settings.proxy_networks
    if not networks or not _trusted(address, networks):
        return address
    hops = [h.strip() for v in request.headers.getlist("x-forwarded-for") for h in v.split(",") if h.strip()]
    for hop in reversed(hops):
        if not _trusted(hop, networks):
            return hop
    return address


def request_is_https(scope: Scope, networks: tuple) -> bool:
    """Whether the client reached us over HTTPS: TLS on this connection, or ``X-Forwarded-Proto: https`` from one
    of ``ANIMSTUDY_TRUSTED_PROXIES`` (the last value: the one the nearest proxy wrote).  From anyone else the
    header proves nothing."""
    if scope.get("scheme") == "https":
        return True
    client = scope.get("client")
    if not networks or not client or not _trusted(client[0], networks):
        return False
    values = [v.strip() for k, raw in scope.get("headers", []) if k == b"x-forwarded-proto"
              for v in raw.decode("latin-1").split(",") if v.strip()]
    return bool(values) and values[-1].lower() == "https"


async def limit_new_sessions(request: Request, session: SessionDep) -> None:
    """``ANIMSTUDY_SESSIONS_PER_MINUTE`` per address (counted in the database, across every instance): 429 with
    ``Retry-After`` beyond it."""
    wait = request.app.state.session_limiter.hit(session, client_address(request))
    if wait is not None:
        raise TooManyRequests("too many new sessions from this address; wait and try again", retry_after=wait)


ParticipantTokenDep = Annotated[str | None, Depends(participant_token)]
