"""Security headers on every response, and ``HEAD`` for every ``GET``.

:class:`SecurityHeaders` adds, unless the response set its own:

* ``Content-Security-Policy``: the site's pages get :data:`SITE_CSP` — scripts, styles, images,
  frames and connections from the site itself only, no inline scripts, no plugins, and only
  the site may frame it. Inline ``style="..."`` attributes are allowed (``style-src-attr``:
  the race table's colour swatches); they can load nothing (images stay ``'self'``). The
  replay player under ``/viewer/`` and the API docs get their own policies
  (:func:`leaderboard.web.viewer.viewer_csp`, :mod:`leaderboard.docs`).
* ``X-Content-Type-Options: nosniff``, ``Referrer-Policy: same-origin``,
  ``X-Frame-Options: SAMEORIGIN`` (for browsers without ``frame-ancestors``),
  ``Cross-Origin-Opener-Policy: same-origin`` and a ``Permissions-Policy`` that turns off
  camera, microphone, geolocation and payment.

:class:`HeadAsGet` answers ``HEAD`` like ``GET`` without the body (FastAPI routes accept only
the methods they declare; ``HEAD /`` used to be 405).
"""

from __future__ import annotations

import base64
import hashlib
from collections.abc import Callable

from starlette.datastructures import MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

SITE_CSP = (
    "default-src 'self'; script-src 'self'; style-src 'self'; style-src-attr 'unsafe-inline'; "
    "img-src 'self' data:; font-src 'self'; connect-src 'self'; frame-src 'self'; "
    "worker-src 'self'; object-src 'none'; base-uri 'self'; form-action 'self'; "
    "frame-ancestors 'self'"
)
COMMON_HEADERS = {
    "x-content-type-options": "nosniff",
    "referrer-policy": "same-origin",
    "x-frame-options": "SAMEORIGIN",
    "cross-origin-opener-policy": "same-origin",
    "permissions-policy": "camera=(), microphone=(), geolocation=(), payment=()",
}


def csp_hash(script: str) -> str:
    """The CSP source that allows one inline script: ``'sha256-<base64>'``.

    >>> csp_hash("")
    "'sha256-47DEQpj8HBSa+/TImW+5JCeuQeRkm5NMpJWZG3hSuFU='"
    """
    digest = hashlib.sha256(script.encode()).digest()
    return "'sha256-" + base64.b64encode(digest).decode() + "'"


class SecurityHeaders:
    """ASGI middleware: the headers above on every HTTP response.

    Args:
        app: the wrapped application.
        csp_for: ``path -> policy`` for paths with their own policy (None: :data:`SITE_CSP`).
    """

    def __init__(self, app: ASGIApp, csp_for: Callable[[str], str | None] | None = None) -> None:
        self.app = app
        self.csp_for = csp_for or (lambda _path: None)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Add the headers to the response's start message."""
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        csp = self.csp_for(scope["path"]) or SITE_CSP

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                headers.setdefault("content-security-policy", csp)
                for name, value in COMMON_HEADERS.items():
                    headers.setdefault(name, value)
            await send(message)

        await self.app(scope, receive, send_with_headers)


class HeadAsGet:
    """ASGI middleware: a ``HEAD`` request is served as ``GET``, and its body dropped."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Run ``HEAD`` as ``GET``; keep the status and headers, send an empty body."""
        if scope["type"] != "http" or scope["method"] != "HEAD":
            await self.app(scope, receive, send)
            return

        async def send_headers_only(message: Message) -> None:
            if message["type"] == "http.response.body":
                if message.get("more_body", False):
                    return
                message = {"type": "http.response.body", "body": b"", "more_body": False}
            await send(message)

        await self.app({**scope, "method": "GET"}, receive, send_headers_only)


__all__ = ["COMMON_HEADERS", "SITE_CSP", "HeadAsGet", "SecurityHeaders", "csp_hash"]
