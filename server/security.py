"""Protections around every request: body size limit, hostile JSON, security headers on every response (errors
included), and the rate limits of logins and of new participant sessions."""

from __future__ import annotations

import hashlib
import json
import logging
import math
import re
import time
from collections import deque
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass
from typing import Any

from sqlalchemy import BigInteger, Float, Index, Integer, String, delete, select, text
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Mapped, Session, mapped_column
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from .db import Base

MAX_BODY_BYTES = 64 * 1024  # a vote with its playback report is well under 20 KB
RETRY_AFTER_S = 2
# The pages load only their own scripts, styles and media (videos come as blob: URLs once downloaded).
CONTENT_SECURITY_POLICY = ("default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data: blob:; "
                           "media-src 'self' blob:; connect-src 'self'; object-src 'none'; base-uri 'none'; "
                           "form-action 'self'; frame-ancestors 'none'")
SECURITY_HEADERS = [
    (b"content-security-policy", CONTENT_SECURITY_POLICY.encode()),
    (b"x-content-type-options", b"nosniff"),
    (b"x-frame-options", b"DENY"),
    (b"referrer-policy", b"no-referrer"),
    (b"cross-origin-opener-policy", b"same-origin"),
]
#: Sent on every response to a request that came over HTTPS (never over plain HTTP, where a browser ignores it
#: and where it could pin a host that has no certificate yet): browsers then use HTTPS only for a year.
HSTS = (b"strict-transport-security", b"max-age=31536000")
_SURROGATE = re.compile("[\ud800-\udfff]")
#: Bidirectional embeddings, overrides and isolates (U+202A..U+202E, U+2066..U+2069): in a title or a label they
#: make text display in another order than it is stored ("Trojan Source").  The marks LRM, RLM and ALM, which
#: right-to-left text needs, are allowed.
BIDI_CONTROLS = re.compile("[\u202a-\u202e\u2066-\u2069]")
_FORM_TYPES = (b"application/x-www-form-urlencoded", b"multipart/form-data")
log = logging.getLogger(__name__)


async def _json(send: Send, status: int, detail: Any, headers: list[tuple[bytes, bytes]] | None = None) -> None:
    body = json.dumps({"detail": detail}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                            *SECURITY_HEADERS, *(headers or [])]})
    await send({"type": "http.response.body", "body": body})


def hostile_json(body: bytes) -> dict[str, Any] | None:
    """The first value of a JSON body that no JSON-based code path can handle, as a validation error like
    FastAPI's (``loc``, ``msg``, ``type``), or None.

    Python's ``json`` accepts ``NaN``, ``Infinity`` and ``-Infinity`` (not JSON) and ``"\\ud800"`` (a lone
    surrogate, which is not a character and cannot be encoded as UTF-8): further down they made building the 422
    body, or storing the value, fail with a 500.  A body that is not JSON at all is left to the endpoint.
    """
    try:
        text = body.decode("utf-8")
    except UnicodeDecodeError as exc:
        return {"type": "unicode", "loc": ["body"], "msg": f"the body is not valid UTF-8 (byte {exc.start})"}
    try:
        value = json.loads(text)
    except (ValueError, RecursionError):
        return None
    queue: deque[tuple[tuple[str | int, ...], Any]] = deque([((), value)])
    while queue:
        path, v = queue.popleft()
        if isinstance(v, float) and not math.isfinite(v):
            return {"type": "finite_number", "loc": ["body", *path],
                    "msg": "Input should be a finite number (NaN and Infinity are not JSON)"}
        if isinstance(v, str) and _SURROGATE.search(v):
            return {"type": "unicode", "loc": ["body", *path],
                    "msg": "Input should be valid Unicode text (it holds a lone surrogate)"}
        if isinstance(v, dict):
            for key, item in v.items():
                if _SURROGATE.search(key):
                    return {"type": "unicode", "loc": ["body", *path, _SURROGATE.sub("\ufffd", key)],
                            "msg": "Field names should be valid Unicode text (this one holds a lone surrogate)"}
                queue.append(((*path, key), item))
        elif isinstance(v, list):
            queue.extend(((*path, i), item) for i, item in enumerate(v))
    return None


def refuse_bidi_controls(value: Any) -> Any:
    """``value`` (a text, or a list or dict of texts) unchanged, or ValueError naming the first
    :data:`BIDI_CONTROLS` character found (for pydantic validators)."""
    texts = value if isinstance(value, list) else list(value.values()) if isinstance(value, dict) else [value]
    for item in texts:
        if isinstance(item, str) and (found := BIDI_CONTROLS.search(item)):
            raise ValueError(f"must not contain the bidirectional control character U+{ord(found.group()):04X} "
                             f"(it shows text in another order than it is stored)")
    return value


@dataclass(frozen=True)
class StreamedRoute:
    """A route whose endpoint reads its (large) body as a stream, e.g. an upload: :class:`Protect` refuses a
    declared ``Content-Length`` over ``max_body`` and otherwise leaves the body to the endpoint, which must stop
    reading at ``max_body`` itself (413) and never holds it in memory; no JSON check."""

    method: str
    path: re.Pattern[str]
    max_body: int

    def matches(self, scope: Scope) -> bool:
        return scope["method"] == self.method and self.path.fullmatch(scope["path"]) is not None


class Protect:
    """ASGI middleware, outermost: refuses bodies over :data:`MAX_BODY_BYTES` with 413 (declared or streamed, e.g.
    chunked; the ``streamed`` routes have their own limit and stream their body, see :class:`StreamedRoute`),
    refuses JSON bodies with non-finite numbers or lone surrogates with 422 (:func:`hostile_json`),
    answers an unhandled exception with a JSON 500 (the connection stays usable), and adds the security headers to
    every response, errors included."""

    def __init__(self, app: ASGIApp, max_body: int = MAX_BODY_BYTES,
                 streamed: Sequence[StreamedRoute] = (), is_https: Callable[[Scope], bool] | None = None) -> None:
        self.app = app
        self.max_body = max_body
        self.streamed = tuple(streamed)
        self.is_https = is_https or (lambda scope: scope.get("scheme") == "https")

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        extra = [HSTS] if self.is_https(scope) else []
        headers = dict(scope["headers"])
        declared = headers.get(b"content-length")
        route = next((r for r in self.streamed if r.matches(scope)), None)
        limit = route.max_body if route else self.max_body
        too_large = f"request body larger than {limit} bytes"
        if declared is not None and (not declared.isdigit() or int(declared) > limit):
            await _json(send, 413, too_large, extra)
            return
        if route is not None:  # the endpoint streams the body itself and stops at the limit
            await self._run(scope, receive, send, extra)
            return
        # The whole body is read here (it is small), so a streamed one over the limit is a 413 before any endpoint
        # runs, and a JSON one can be checked once for everyone.
        chunks: list[bytes] = []
        size, more = 0, True
        while more:
            message = await receive()
            if message["type"] != "http.request":
                return  # the client went away
            chunks.append(message.get("body", b""))
            size += len(chunks[-1])
            if size > self.max_body:
                await _json(send, 413, too_large, extra)
                return
            more = message.get("more_body", False)
        body = b"".join(chunks)
        content_type = headers.get(b"content-type", b"").split(b";")[0].strip().lower()
        if body and not content_type.startswith(_FORM_TYPES) and (problem := hostile_json(body)) is not None:
            await _json(send, 422, [problem], extra)
            return

        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self._run(scope, replay, send, extra)

    async def _run(self, scope: Scope, receive: Receive, send: Send, extra: list[tuple[bytes, bytes]]) -> None:
        """The app, with the security headers (and ``extra``) added and an unhandled error answered with a JSON
        500."""
        started = False

        async def with_headers(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
                present = {k.lower() for k, _ in message.get("headers", [])}
                message = {**message, "headers": [*message.get("headers", []),
                                                  *(h for h in (*SECURITY_HEADERS, *extra) if h[0] not in present)]}
            await send(message)

        try:
            await self.app(scope, receive, with_headers)
        except Exception:
            if started:
                raise
            log.exception("unhandled error in %s %s", scope["method"], scope["path"])
            await _json(send, 500, "internal error; nothing was stored", extra)


Clock = Callable[[], float]
_KEY_SEP = "\x1f"  # joins the parts of a tuple key (addresses and e-mails never hold it)


class RateEvent(Base):
    """One counted event of a limit (a new participant session, a failed login) per ``bucket`` and ``key``, at
    ``at`` (seconds since the epoch).  In the database, so every process and machine serving the study counts
    the same events: several ``animstudy serve`` instances behave as one."""

    __tablename__ = "rate_events"
    __table_args__ = (Index("ix_rate_events_bucket_key_at", "bucket", "key", "at"),
                      Index("ix_rate_events_bucket_at", "bucket", "at"))

    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    bucket: Mapped[str] = mapped_column(String(32))
    key: Mapped[str] = mapped_column(String(400))
    at: Mapped[float] = mapped_column(Float)


class KnownLogin(Base):
    """An address that has logged in to an account (see :class:`LoginLimiter`)."""

    __tablename__ = "known_logins"

    account: Mapped[str] = mapped_column(String(320), primary_key=True)
    address: Mapped[str] = mapped_column(String(64), primary_key=True)


def _key(key: Hashable) -> str:
    return _KEY_SEP.join(map(str, key)) if isinstance(key, tuple) else str(key)


def _serialize(session: Session, bucket: str, key: str) -> None:
    """Makes the check-then-count of one key atomic across processes.  SQLite: every writing transaction holds
    the file's write lock from its BEGIN (``server.db``).  PostgreSQL: a transaction-scoped advisory lock on the
    key (read committed would let two processes each count 59 and both insert the 60th)."""
    if session.get_bind().dialect.name == "postgresql":
        digest = hashlib.blake2b(f"{bucket}{_KEY_SEP}{key}".encode(), digest_size=8).digest()
        session.execute(text("SELECT pg_advisory_xact_lock(:k)"), {"k": int.from_bytes(digest, "big", signed=True)})


class _Window:
    """Event times per key over the last ``window_s`` seconds, in the ``rate_events`` table under ``bucket``
    (events older than the window are deleted as new ones arrive)."""

    def __init__(self, bucket: str, window_s: float) -> None:
        self.bucket = bucket
        self.window = window_s

    def recent(self, session: Session, key: Hashable, now: float) -> list[float]:
        return list(session.scalars(select(RateEvent.at).where(
            RateEvent.bucket == self.bucket, RateEvent.key == _key(key), RateEvent.at > now - self.window)
            .order_by(RateEvent.at)))

    def add(self, session: Session, key: Hashable, now: float) -> int:
        """Count an event (flushed, not committed); its row id."""
        session.execute(delete(RateEvent).where(RateEvent.bucket == self.bucket,
                                                RateEvent.at <= now - self.window))
        event = RateEvent(bucket=self.bucket, key=_key(key), at=now)
        session.add(event)
        session.flush()
        return event.id

    def clear(self, session: Session, key: Hashable) -> None:
        session.execute(delete(RateEvent).where(RateEvent.bucket == self.bucket, RateEvent.key == _key(key)))


def _seconds(wait: float) -> int:
    return max(1, math.ceil(wait))


class RateLimiter:
    """At most ``limit`` events per key in any ``window_s`` seconds (sliding window); ``limit`` 0 is no limit.

    The events are rows of ``rate_events`` (bucket ``bucket``), so the limit holds once across every process and
    instance on the database.  ``clock``: seconds since the epoch (instances on several machines compare times).
    """

    def __init__(self, limit: int, window_s: float = 60.0, clock: Clock = time.time,
                 bucket: str = "session") -> None:
        self.limit = limit
        self.clock = clock
        self._window = _Window(bucket, window_s)

    def hit(self, session: Session, key: Hashable) -> int | None:
        """Count an event for ``key`` and commit it; if the limit is reached already, count nothing and return
        the seconds until the next one is allowed.  ``session`` must have no pending work (it is committed)."""
        if self.limit <= 0:
            return None
        now = self.clock()
        try:
            _serialize(session, self._window.bucket, _key(key))
            q = self._window.recent(session, key, now)
            if len(q) >= self.limit:
                return _seconds(q[-self.limit] + self._window.window - now)
            self._window.add(session, key, now)
            session.commit()
        finally:
            session.rollback()  # ends the transaction (and its lock) when nothing was committed
        return None


@dataclass(frozen=True)
class LoginAttempt:
    """A login attempt as :meth:`LoginLimiter.attempt` counted it: ``wait`` (seconds) if it must wait and was not
    counted, else the ids of the ``rate_events`` rows that count it as a failure until it succeeds."""

    wait: int | None
    events: tuple[int, ...] = ()


class LoginLimiter:
    """Throttles password guessing without letting anyone lock a researcher out.

    - per (address, account): ``per_pair`` failures in ``window_s`` -> 429 for that address and that account;
    - per address: ``per_address`` failures in ``window_s`` (any accounts) -> 429 for that address;
    - per account, against addresses that are *unknown* (never logged in to it) and have failed before: after
      ``account_free`` failures in ``window_s`` (from anywhere) each further attempt waits 1, 2, 4, ... up to
      ``max_delay_s`` seconds after the account's last failure.  The account is slowed, never blocked: the right
      password from an address without failures, or from one that has logged in to the account before, gets in.

    The failures and known addresses are in the database (``rate_events``, ``known_logins``): counted once
    across every process and instance.  ``clock``: seconds since the epoch.
    """

    def __init__(self, per_pair: int = 10, per_address: int = 50, account_free: int = 10,
                 max_delay_s: float = 60.0, window_s: float = 900.0, clock: Clock = time.time) -> None:
        self.per_pair, self.per_address, self.account_free = per_pair, per_address, account_free
        self.max_delay = max_delay_s
        self.clock = clock
        self._pair = _Window("login_pair", window_s)
        self._address = _Window("login_address", window_s)
        self._account = _Window("login_account", window_s)

    def attempt(self, session: Session, address: str, account: str) -> LoginAttempt:
        """Count an attempt of ``address`` on ``account`` as a failure before its password is checked, unless it
        must wait (:attr:`LoginAttempt.wait`, nothing counted); commits.

        Counted first, in one transaction that also checks: checking first and counting after the (slow)
        password check let 30 of 30 concurrent wrong passwords through a limit of 10.  The transaction holds the
        address's and the account's locks (:func:`_serialize`; on SQLite the database's write lock), so attempts
        from every process and instance on the database are counted one after another.  The right password takes
        its attempt back (:meth:`succeeded`)."""
        now = self.clock()
        try:
            # Always the address's lock first, then the account's: two attempts never wait for each other in a
            # cycle.
            _serialize(session, self._address.bucket, address)
            _serialize(session, self._account.bucket, account)
            wait = self._wait(session, address, account, now)
            if wait is not None:
                return LoginAttempt(wait)
            events = (self._pair.add(session, (address, account), now), self._address.add(session, address, now),
                      self._account.add(session, account, now))
            session.commit()
        finally:
            session.rollback()  # ends the transaction (and its locks) when nothing was committed
        return LoginAttempt(None, events)

    def _wait(self, session: Session, address: str, account: str, now: float) -> int | None:
        """Seconds to wait before ``address`` may try a password for ``account``, or None."""
        window = self._pair.window
        waits = []
        pair = self._pair.recent(session, (address, account), now)
        if len(pair) >= self.per_pair:
            waits.append(pair[-self.per_pair] + window - now)
        by_address = self._address.recent(session, address, now)
        if len(by_address) >= self.per_address:
            waits.append(by_address[-self.per_address] + window - now)
        if by_address and session.get(KnownLogin, (account, address)) is None:
            by_account = self._account.recent(session, account, now)
            excess = len(by_account) - self.account_free
            if excess >= 0:
                waits.append(by_account[-1] + min(self.max_delay, 2.0 ** excess) - now)
        waits = [w for w in waits if w > 0]
        return _seconds(max(waits)) if waits else None

    def succeeded(self, session: Session, address: str, account: str, attempt: LoginAttempt | None = None) -> None:
        """The address knows the password: its own failures for the account are forgotten, ``attempt`` (the one
        that succeeded) is not counted, and the address is no longer slowed by failures elsewhere.  The account's
        failures stay (an attack may still be going on).  Commits (``session`` must have no other pending work)."""
        try:
            if attempt is not None and attempt.events:
                session.execute(delete(RateEvent).where(RateEvent.id.in_(attempt.events)))
            self._pair.clear(session, (address, account))
            if session.get(KnownLogin, (account, address)) is None:
                session.add(KnownLogin(account=account, address=address))
            session.commit()
        except IntegrityError:  # another instance recorded the same address at the same moment
            session.rollback()
        finally:
            session.rollback()
