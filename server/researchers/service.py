"""Researcher accounts: argon2id password hashes, signed bearer tokens."""

from __future__ import annotations

from datetime import timedelta

import jwt
from argon2 import PasswordHasher, profiles
from argon2.exceptions import InvalidHashError, VerificationError
from sqlalchemy import select
from sqlalchemy.orm import Session

from server.db import utcnow
from server.errors import Conflict, Unauthorized

from .models import Researcher

#: argon2id at RFC 9106's second recommendation (64 MiB, 3 passes, 4 lanes; argon2-cffi's default), ~0.1 s a hash
PASSWORD_PROFILE = profiles.RFC_9106_LOW_MEMORY
_hasher = PasswordHasher.from_parameters(PASSWORD_PROFILE)
ALGORITHM = "HS256"
MIN_PASSWORD = 10


def normalize_email(email: str) -> str:
    return email.strip().lower()


def create_researcher(session: Session, email: str, password: str, admin: bool = False) -> Researcher:
    email = normalize_email(email)
    if "@" not in email:
        raise Conflict(f"{email!r} is not an e-mail address")
    if len(password) < MIN_PASSWORD:
        raise Conflict(f"the password needs at least {MIN_PASSWORD} characters")
    if session.scalar(select(Researcher.id).where(Researcher.email == email)) is not None:
        raise Conflict(f"a researcher {email!r} exists already")
    researcher = Researcher(email=email, password_hash=_hasher.hash(password), is_admin=admin)
    session.add(researcher)
    session.commit()
    return researcher


def authenticate(session: Session, email: str, password: str) -> Researcher:
    researcher = session.scalar(select(Researcher).where(Researcher.email == normalize_email(email)))
    try:
        if researcher is None:
            _hasher.hash(password)  # same time as a real check: do not reveal which e-mails exist
            raise VerificationError
        _hasher.verify(researcher.password_hash, password)
    except (VerificationError, InvalidHashError):
        raise Unauthorized("wrong e-mail or password") from None
    return researcher


def issue_token(researcher: Researcher, secret: bytes, hours: float) -> str:
    now = utcnow()
    claims = {"sub": str(researcher.id), "iat": now, "exp": now + timedelta(hours=hours), "typ": "researcher"}
    return jwt.encode(claims, secret, algorithm=ALGORITHM)


def researcher_from_token(session: Session, token: str | None, secret: bytes) -> Researcher:
    if not token:
        raise Unauthorized("researcher login required")
    try:
        claims = jwt.decode(token, secret, algorithms=[ALGORITHM])
        researcher = session.get(Researcher, int(claims["sub"])) if claims.get("typ") == "researcher" else None
    except (jwt.PyJWTError, KeyError, ValueError):
        researcher = None
    if researcher is None:
        raise Unauthorized("invalid or expired researcher token")
    return researcher
