"""Caching of what every visitor asks for, and ETags on the pages and the API.

:class:`SnapshotCache`
    Keeps computed snapshots (a leaderboard page, the track records) per database, each
    under a *fingerprint* of the rows it was computed from: a query that costs a few index
    look-ups (for the leaderboard, the submissions' count and latest ``updated_at``, which
    every writer bumps). A snapshot is reused while its fingerprint is unchanged and it is
    younger than ``max_age_s`` (so a writer whose clock lags cannot keep it stale for long).
    Several server processes each keep their own; nothing needs invalidating by hand.

:class:`ETagMiddleware`
    Gives every ``200`` JSON or HTML answer to a ``GET`` a weak ``ETag`` (a hash of the body)
    and answers ``304 Not Modified`` when the request's ``If-None-Match`` holds it, so a
    browser or a polling client re-downloads a page only when it changed.
"""

from __future__ import annotations

import hashlib
import threading
import time
import weakref
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Any, TypeVar

from sqlalchemy import Engine
from sqlalchemy.orm import Session
from starlette.datastructures import Headers, MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

T = TypeVar("T")
MAX_ENTRIES = 512  # snapshots kept per database (least recently used dropped first)
ETAG_TYPES = ("application/json", "text/html")


class SnapshotCache:
    """A bounded map ``key -> (fingerprint, time, value)``, safe across threads."""

    def __init__(self, max_entries: int = MAX_ENTRIES) -> None:
        self.max_entries = max_entries
        self._items: OrderedDict[Hashable, tuple[Hashable, float, Any]] = OrderedDict()
        self._lock = threading.Lock()

    def get(
        self, key: Hashable, fingerprint: Hashable, compute: Callable[[], T], max_age_s: float
    ) -> T:
        """The value stored under ``key`` for ``fingerprint``, computed (and kept) if missing."""
        now = time.monotonic()
        with self._lock:
            hit = self._items.get(key)
            if hit is not None and hit[0] == fingerprint and now - hit[1] <= max_age_s:
                self._items.move_to_end(key)
                value: T = hit[2]
                return value
        value = compute()
        with self._lock:
            self._items[key] = (fingerprint, now, value)
            self._items.move_to_end(key)
            while len(self._items) > self.max_entries:
                self._items.popitem(last=False)
        return value

    def clear(self) -> None:
        """Forget every snapshot."""
        with self._lock:
            self._items.clear()


_caches: weakref.WeakKeyDictionary[Engine, SnapshotCache] = weakref.WeakKeyDictionary()
_caches_lock = threading.Lock()


def cache_for(session: Session) -> SnapshotCache:
    """The snapshot cache of the database ``session`` is bound to."""
    bind = session.get_bind()
    engine = bind if isinstance(bind, Engine) else bind.engine
    with _caches_lock:
        cache = _caches.get(engine)
        if cache is None:
            cache = _caches[engine] = SnapshotCache()
        return cache


class ETagMiddleware:
    """ASGI middleware: weak ETags and ``304`` for ``GET`` answers (see the module docstring)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Buffer a 200 JSON/HTML answer, tag it, and answer 304 if the client has it."""
        if scope["type"] != "http" or scope["method"] != "GET":
            await self.app(scope, receive, send)
            return
        if_none_match = Headers(scope=scope).get("if-none-match")
        start: Message | None = None
        chunks: list[bytes] = []
        passthrough = False

        async def send_tagged(message: Message) -> None:
            nonlocal start, passthrough
            if passthrough:
                await send(message)
                return
            if message["type"] == "http.response.start":
                headers = Headers(raw=message.get("headers", []))
                kind = headers.get("content-type", "")
                if message["status"] != 200 or "etag" in headers or not kind.startswith(ETAG_TYPES):
                    passthrough = True
                    await send(message)
                    return
                start = message
                return
            if message["type"] != "http.response.body" or start is None:
                await send(message)
                return
            chunks.append(message.get("body", b""))
            if message.get("more_body", False):
                return
            body = b"".join(chunks)
            etag = 'W/"' + hashlib.blake2b(body, digest_size=16).hexdigest() + '"'
            headers = MutableHeaders(scope=start)
            headers["etag"] = etag
            headers.setdefault("cache-control", "no-cache")  # may keep it, must revalidate
            if if_none_match is not None and etag in {t.strip() for t in if_none_match.split(",")}:
                del headers["content-length"]
                start["status"] = 304
                await send(start)
                await send({"type": "http.response.body", "body": b"", "more_body": False})
                return
            await send(start)
            await send({"type": "http.response.body", "body": body, "more_body": False})

        await self.app(scope, receive, send_tagged)


__all__ = ["ETagMiddleware", "SnapshotCache", "cache_for"]
