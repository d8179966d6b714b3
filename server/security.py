"""Protections around every request: body size limit, hostile JSON, security headers on every response (errors
included), and the rate limits of logins and of new participant sessions."""

from __future__ import annotations

import json
import logging
import math
import re
import threading
import time
from collections import defaultdict, deque
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass
from typing import Any

from starlette.types import ASGIApp, Message, Receive, Scope, Send

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
    for text in texts:
        if isinstance(text, str) and (found := BIDI_CONTROLS.search(text)):
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
                 streamed: Sequence[StreamedRoute] = ()) -> None:
        self.app = app
        self.max_body = max_body
        self.streamed = tuple(streamed)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = dict(scope["headers"])
        declared = headers.get(b"content-length")
        route = next((r for r in self.streamed if r.matches(scope)), None)
        limit = route.max_body if route else self.max_body
        too_large = f"request body larger than {limit} bytes"
        if declared is not None and (not declared.isdigit() or int(declared) > limit):
            await _json(send, 413, too_large)
            return
        if route is not None:  # the endpoint streams the body itself and stops at the limit
            await self._run(scope, receive, send)
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
                await _json(send, 413, too_large)
                return
            more = message.get("more_body", False)
        body = b"".join(chunks)
        content_type = headers.get(b"content-type", b"").split(b";")[0].strip().lower()
        if body and not content_type.startswith(_FORM_TYPES) and (problem := hostile_json(body)) is not None:
            await _json(send, 422, [problem])
            return

        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self._run(scope, replay, send)

    async def _run(self, scope: Scope, receive: Receive, send: Send) -> None:
        """The app, with the security headers added and an unhandled error answered with a JSON 500."""
        started = False

        async def with_headers(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
                present = {k.lower() for k, _ in message.get("headers", [])}
                message = {**message, "headers": [*message.get("headers", []),
                                                  *(h for h in SECURITY_HEADERS if h[0] not in present)]}
            await send(message)

        try:
            await self.app(scope, receive, with_headers)
        except Exception:
            if started:
                raise
            log.exception("unhandled error in %s %s", scope["method"], scope["path"])
            await _json(send, 500, "internal error; nothing was stored")


Clock = Callable[[], float]


class _Window:
    """Event times per key over the last ``window_s`` seconds (keys with no recent events are forgotten)."""

    def __init__(self, window_s: float) -> None:
        self.window = window_s
        self._events: dict[Hashable, deque[float]] = defaultdict(deque)

    def recent(self, key: Hashable, now: float) -> deque[float]:
        q = self._events.get(key)
        if q is None:
            return deque()
        while q and now - q[0] >= self.window:
            q.popleft()
        if not q:
            del self._events[key]
        return q

    def add(self, key: Hashable, now: float) -> None:
        self.recent(key, now)
        self._events[key].append(now)

    def clear(self, key: Hashable) -> None:
        self._events.pop(key, None)


def _seconds(wait: float) -> int:
    return max(1, math.ceil(wait))


class RateLimiter:
    """At most ``limit`` events per key in any ``window_s`` seconds (sliding window); ``limit`` 0 is no limit.

    In memory, per process: with several workers the limit applies once per worker.
    """

    def __init__(self, limit: int, window_s: float = 60.0, clock: Clock = time.monotonic) -> None:
        self.limit = limit
        self.clock = clock
        self._window = _Window(window_s)
        self._lock = threading.Lock()

    def hit(self, key: Hashable) -> int | None:
        """Count an event for ``key``; if the limit is reached already, count nothing and return the seconds
        until the next one is allowed."""
        if self.limit <= 0:
            return None
        now = self.clock()
        with self._lock:
            q = self._window.recent(key, now)
            if len(q) >= self.limit:
                return _seconds(q[-self.limit] + self._window.window - now)
            self._window.add(key, now)
        return None


class LoginLimiter:
    """Throttles password guessing without letting anyone lock a researcher out.

    - per (address, account): ``per_pair`` failures in ``window_s`` -> 429 for that address and that account;
    - per address: ``per_address`` failures in ``window_s`` (any accounts) -> 429 for that address;
    - per account, against addresses that are *unknown* (never logged in to it) and have failed before: after
      ``account_free`` failures in ``window_s`` (from anywhere) each further attempt waits 1, 2, 4, ... up to
      ``max_delay_s`` seconds after the account's last failure.  The account is slowed, never blocked: the right
      password from an address without failures, or from one that has logged in to the account before, gets in.

    In memory, per process (several workers each keep their own counts).
    """

    def __init__(self, per_pair: int = 10, per_address: int = 50, account_free: int = 10,
                 max_delay_s: float = 60.0, window_s: float = 900.0, clock: Clock = time.monotonic) -> None:
        self.per_pair, self.per_address, self.account_free = per_pair, per_address, account_free
        self.max_delay = max_delay_s
        self.clock = clock
        self._pair = _Window(window_s)
        self._address = _Window(window_s)
        self._account = _Window(window_s)
        self._known: dict[str, set[str]] = defaultdict(set)
        self._lock = threading.Lock()

    def retry_after(self, address: str, account: str) -> int | None:
        """Seconds to wait before ``address`` may try a password for ``account``, or None."""
        now = self.clock()
        window = self._pair.window
        waits = []
        with self._lock:
            pair = self._pair.recent((address, account), now)
            if len(pair) >= self.per_pair:
                waits.append(pair[-self.per_pair] + window - now)
            by_address = self._address.recent(address, now)
            if len(by_address) >= self.per_address:
                waits.append(by_address[-self.per_address] + window - now)
            if by_address and address not in self._known.get(account, ()):
                by_account = self._account.recent(account, now)
                excess = len(by_account) - self.account_free
                if excess >= 0:
                    waits.append(by_account[-1] + min(self.max_delay, 2.0 ** excess) - now)
        waits = [w for w in waits if w > 0]
        return _seconds(max(waits)) if waits else None

    def failed(self, address: str, account: str) -> None:
        now = self.clock()
        with self._lock:
            self._pair.add((address, account), now)
            self._address.add(address, now)
            self._account.add(account, now)

    def succeeded(self, address: str, account: str) -> None:
        """The address knows the password: its own failures for the account are forgotten and it is no longer
        slowed by failures elsewhere.  The account's failures stay (an attack may still be going on)."""
        with self._lock:
            self._pair.clear((address, account))
            self._known[account].add(address)
