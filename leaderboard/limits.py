"""The service's front door: request-body caps, authentication before uploads, rate limits.

Two ASGI middlewares, added by :func:`leaderboard.app.create_app`:

:class:`BodyGuard`
    Every request body is capped *as it is received*, whatever its framing (``Content-Length``
    or chunked): an upload route (:data:`UPLOAD_ROUTES`) at ``settings.max_upload_bytes`` plus
    1 MiB of multipart framing, everything else at ``settings.max_request_kb``. A declared
    length over the cap is refused before the first byte is read; a chunked body is cut off
    the moment it passes the cap. Upload routes are **authenticated before any of the body is
    read**: no token, or an unknown or revoked one, is answered 401 at once; a user whose daily
    upload quota is spent gets 429 (``Retry-After``), and one who already has
    ``settings.max_concurrent_uploads`` uploads in flight gets 429 too, so one account cannot
    make the server hold more than that many bodies at once. Each wait for the next piece of a
    body is bounded by ``settings.body_idle_timeout_s``; a whole upload by
    ``settings.upload_timeout_s`` and any other body by ``body_idle_timeout_s`` (408). Every
    early refusal carries ``Connection: close``, so the server stops reading the socket
    instead of draining what the client still sends.

:class:`RateLimit`
    Moving-window limits from the maintained ``limits`` library, answered with 429 and
    ``Retry-After`` (seconds): ``settings.rate_limit_ip`` per client address,
    ``settings.rate_limit_token`` per bearer token, and ``settings.rate_limit_auth_failures``
    401 answers per address (once spent, requests from that address that carry credentials —
    a bearer token, or the website's sign-in form — get 429 until the window frees). Counters
    live in ``settings.rate_limit_storage``
    (``memory://`` per process; ``redis://...`` to share them between server processes).
    Behind a reverse proxy, run uvicorn with ``--proxy-headers`` so the client address is the
    real one.

Several server processes (``slipstream serve --web-workers N``, ``settings.web_workers``)
each keep their own in-memory counters, and the kernel hands each new connection to any of
them. So each process enforces its share of every limit, ``floor(limit / N)`` (at least 1,
:func:`process_share`): whichever processes a client's requests reach, together they let
through at most the configured limit; a client whose requests all reach one process (one
keep-alive connection) gets at least ``1/N`` of it. The same holds for
``max_concurrent_uploads``. With a shared storage (``redis://...``) the rate limits are not
divided.
"""

from __future__ import annotations

import asyncio
import hashlib
import math
import re
import time
from collections.abc import Callable
from typing import Any

import anyio
import limits
from limits.aio.strategies import MovingWindowRateLimiter
from limits.storage import storage_from_string
from starlette.datastructures import Headers
from starlette.exceptions import HTTPException
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from leaderboard.auth import user_for_token
from leaderboard.errors import LeaderboardError, NotAuthenticated, QuotaExceeded
from leaderboard.settings import Settings

MULTIPART_SLACK = 1 << 20  # bytes of form framing allowed on top of the bundle size limit
# POST routes that take a bundle: authenticated before their body is read, with the large cap.
UPLOAD_ROUTES = (
    re.compile(r"^/api/submissions/?$"),
    re.compile(r"^/api/submissions/[0-9]+/versions/?$"),
)
CLOSE = (b"connection", b"close")
SIGNIN_PATH = "/signin"  # the website's sign-in form: a token in a POST body
UPLOAD_BUSY_RETRY_S = 10  # Retry-After of a refusal for too many uploads in flight, s


def is_upload(scope: Scope) -> bool:
    """Whether a request is a bundle upload (POST to an :data:`UPLOAD_ROUTES` path)."""
    return scope["method"] == "POST" and any(r.match(scope["path"]) for r in UPLOAD_ROUTES)


def bearer_token(scope: Scope) -> str | None:
    """The token of an ``Authorization: Bearer <token>`` header, or None."""
    value = Headers(scope=scope).get("authorization", "")
    scheme, _, token = value.partition(" ")
    if scheme.lower() != "bearer" or not token.strip():
        return None
    return token.strip()


async def refuse(
    scope: Scope,
    receive: Receive,
    send: Send,
    status: int,
    detail: str,
    headers: dict[str, str] | None = None,
) -> None:
    """Answer ``{"detail": detail}`` with ``status`` and close the connection afterwards."""
    response = JSONResponse({"detail": detail}, status_code=status, headers=headers)
    response.raw_headers.append(CLOSE)
    await response(scope, receive, send)


class BodyTooLarge(HTTPException):
    """A request body went past its cap while being received (answered 413)."""

    def __init__(self, limit: int) -> None:
        detail = f"request body is larger than {_size(limit)}"
        super().__init__(413, detail, {"connection": "close"})


class BodyTimeout(HTTPException):
    """A request body arrived too slowly (answered 408)."""

    def __init__(self, seconds: float) -> None:
        super().__init__(
            408, f"request body not received within {seconds:g} s", {"connection": "close"}
        )


def _size(n_bytes: int) -> str:
    return f"{n_bytes / 2**20:.0f} MiB" if n_bytes >= 2**20 else f"{n_bytes / 1024:.0f} KiB"


class BodyGuard:
    """ASGI middleware: body caps, checks before an upload's body, body-read timeouts.

    Args:
        app: the wrapped application.
        settings: caps, quotas and timeouts (see the module docstring).
        check_uploader: ``(scope, token) -> user id``, run in a worker thread before an
            upload's body is read; raises a :class:`~leaderboard.errors.LeaderboardError`
            (its status and message are the answer) to refuse the upload (default:
            :func:`check_uploader`).
    """

    def __init__(
        self,
        app: ASGIApp,
        settings: Settings,
        check_uploader: Callable[[Scope, str], int] | None = None,
    ) -> None:
        self.app = app
        self.upload_cap = settings.max_upload_bytes + MULTIPART_SLACK
        self.request_cap = int(settings.max_request_kb * 1024)
        self.idle_s = settings.body_idle_timeout_s
        self.upload_s = settings.upload_timeout_s
        # Counted per process: each of web_workers processes allows its share (module doc).
        self.max_in_flight = process_share(settings.max_concurrent_uploads, processes(settings))
        self.check_uploader = check_uploader or check_uploader_default
        self.in_flight: dict[int, int] = {}  # user id -> uploads being received (this process)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Guard one HTTP request."""
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        upload = is_upload(scope)
        cap = self.upload_cap if upload else self.request_cap
        length = Headers(scope=scope).get("content-length")
        if length is not None and (not length.isdigit() or int(length) > cap):
            bad = not length.isdigit()
            detail = "bad Content-Length" if bad else f"request body is larger than {_size(cap)}"
            await refuse(scope, receive, send, 400 if bad else 413, detail)
            return
        if not upload:
            await self._guarded(scope, receive, send, cap, self.idle_s)
            return
        token = bearer_token(scope)
        try:
            if token is None:
                raise NotAuthenticated("missing API token: send 'Authorization: Bearer <token>'")
            user_id = await anyio.to_thread.run_sync(self.check_uploader, scope, token)
        except LeaderboardError as err:
            await refuse(scope, receive, send, err.status_code, str(err), _error_headers(err))
            return
        if self.in_flight.get(user_id, 0) >= self.max_in_flight:
            detail = (
                f"{self.max_in_flight} of your uploads are still being received; "
                "wait for them to finish"
            )
            headers = {"Retry-After": str(UPLOAD_BUSY_RETRY_S)}
            await refuse(scope, receive, send, 429, detail, headers)
            return
        self.in_flight[user_id] = self.in_flight.get(user_id, 0) + 1
        try:
            await self._guarded(scope, receive, send, cap, self.upload_s)
        finally:
            self.in_flight[user_id] -= 1
            if not self.in_flight[user_id]:
                del self.in_flight[user_id]

    async def _guarded(
        self, scope: Scope, receive: Receive, send: Send, cap: int, total_s: float
    ) -> None:
        """Run the app with the body capped at ``cap`` bytes and ``total_s`` seconds."""
        started = False

        async def send_tracking(message: Message) -> None:
            nonlocal started
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, self._capped(receive, cap, total_s), send_tracking)
        except (BodyTooLarge, BodyTimeout) as err:
            # Raised outside a route's own error handling (a mount, a middleware): answer here.
            if started:
                raise
            await refuse(scope, receive, send, err.status_code, err.detail)

    def _capped(self, receive: Receive, cap: int, total_s: float) -> Receive:
        received = 0
        deadline = time.monotonic() + total_s
        idle_s = self.idle_s

        async def capped_receive() -> Message:
            nonlocal received
            wait = min(idle_s, deadline - time.monotonic())
            if wait <= 0:
                raise BodyTimeout(total_s)
            try:
                message = await asyncio.wait_for(receive(), timeout=wait)
            except TimeoutError:
                raise BodyTimeout(idle_s if wait == idle_s else total_s) from None
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > cap:
                    raise BodyTooLarge(cap)
            return message

        return capped_receive


def _error_headers(err: LeaderboardError) -> dict[str, str] | None:
    if isinstance(err, QuotaExceeded):
        return {"Retry-After": str(err.retry_after)}
    if isinstance(err, NotAuthenticated):
        return {"WWW-Authenticate": "Bearer"}
    return None


def check_uploader_default(scope: Scope, token: str) -> int:
    """The id of the user of ``token`` if they may upload now (nothing is written).

    Raises:
        NotAuthenticated: an unknown or revoked token.
        QuotaExceeded: the user's daily upload quota is spent.
    """
    from leaderboard.uploads import check_daily_quota  # noqa: PLC0415 - uploads imports a lot

    app = scope["app"]
    session = app.state.sessionmaker()
    try:
        user = user_for_token(session, token)
        if user is None:
            raise NotAuthenticated("invalid or revoked API token")
        check_daily_quota(session, app.state.settings, user)
        return int(user.id)
    finally:
        session.rollback()
        session.close()


# ---- rate limits ------------------------------------------------------------------------------


def parse_limit(text: str) -> limits.RateLimitItem:
    """A ``limits`` rate (``"600/minute"``, ``"20 per 10 seconds"``).

    Raises:
        ValueError: not a rate the library understands.
    """
    return limits.parse(text)


def processes(settings: Settings) -> int:
    """How many server processes share the service (``settings.web_workers``, default 1)."""
    return settings.web_workers or 1


def process_share(amount: int, n_processes: int) -> int:
    """One process's share of a limit of ``amount`` split between ``n_processes``:
    ``floor(amount / n_processes)``, at least 1 (so the shares never add up to more than
    ``amount`` unless ``amount`` < ``n_processes``)."""
    return max(1, amount // max(1, n_processes))


def share_of_rate(item: limits.RateLimitItem, n_processes: int) -> limits.RateLimitItem:
    """The rate ``item`` with its amount divided by :func:`process_share` (same window)."""
    if n_processes <= 1:
        return item
    return type(item)(process_share(item.amount, n_processes), item.multiples, item.namespace)


def _client_ip(scope: Scope) -> str:
    client = scope.get("client")
    return str(client[0]) if client else "unknown"


def _token_key(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()[:32]


class RateLimit:
    """ASGI middleware: per-address, per-token and failed-authentication rate limits (429).

    Args:
        app: the wrapped application.
        settings: the limits and the counter storage (see the module docstring).
    """

    def __init__(self, app: ASGIApp, settings: Settings) -> None:
        self.app = app
        uri = settings.rate_limit_storage
        storage: Any = storage_from_string(uri if uri.startswith("async+") else f"async+{uri}")
        self.limiter = MovingWindowRateLimiter(storage)
        # In-memory counters are this process's own: enforce its share (module docstring).
        n = processes(settings) if uri.removeprefix("async+").startswith("memory") else 1
        self.per_ip = share_of_rate(parse_limit(settings.rate_limit_ip), n)
        self.per_token = share_of_rate(parse_limit(settings.rate_limit_token), n)
        self.auth_failures = share_of_rate(parse_limit(settings.rate_limit_auth_failures), n)
        self.processes = n

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Count one HTTP request against its limits; 429 once one is spent."""
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        ip = _client_ip(scope)
        token = bearer_token(scope)
        checks = [(self.per_ip, "ip", ip)]
        if token is not None:
            checks.append((self.per_token, "token", _token_key(token)))
        signin = scope["method"] == "POST" and scope["path"] == SIGNIN_PATH
        credentials = token is not None or signin
        if credentials and not await self.limiter.test(self.auth_failures, "authfail", ip):
            await self._too_many(scope, receive, send, self.auth_failures, "authfail", ip)
            return
        for item, *key in checks:
            if not await self.limiter.hit(item, *key):
                await self._too_many(scope, receive, send, item, *key)
                return

        async def send_counting(message: Message) -> None:
            if message["type"] == "http.response.start" and message["status"] == 401:
                await self.limiter.hit(self.auth_failures, "authfail", ip)
            await send(message)

        await self.app(scope, receive, send_counting)

    async def _too_many(
        self, scope: Scope, receive: Receive, send: Send, item: limits.RateLimitItem, *key: str
    ) -> None:
        stats = await self.limiter.get_window_stats(item, *key)
        retry = max(1, math.ceil(stats.reset_time - time.time()))
        what = {"ip": "address", "token": "token", "authfail": "failed authentications"}[key[0]]
        share = f" (this server process's share, of {self.processes})" if self.processes > 1 else ""
        await refuse(
            scope,
            receive,
            send,
            429,
            f"rate limit of {item} per {what}{share} reached; retry in {retry} s",
            {"Retry-After": str(retry)},
        )


__all__ = [
    "MULTIPART_SLACK",
    "UPLOAD_ROUTES",
    "BodyGuard",
    "BodyTimeout",
    "BodyTooLarge",
    "RateLimit",
    "bearer_token",
    "check_uploader_default",
    "is_upload",
    "parse_limit",
    "process_share",
    "processes",
    "share_of_rate",
]
