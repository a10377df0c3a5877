"""Serving the app with uvicorn, with the connection limits the app itself cannot enforce.

The ASGI middlewares (:mod:`leaderboard.limits`) see a request only once its head (request
line and headers) has arrived. Before that the connection belongs to uvicorn, which times out
only an idle keep-alive connection, and only until its first byte: a client that opens a
connection and sends nothing, or trickles one header every few seconds ("slowloris"), holds
one of ``settings.max_connections`` slots for as long as it likes, and a few hundred such
clients shut everyone else out (uvicorn answers 503 past the limit).

:func:`http_protocol` therefore gives uvicorn an HTTP protocol class whose connections must
deliver each request head within ``settings.header_timeout_s`` of the connection opening, or
of the previous answer; otherwise the connection is closed. Bodies are then timed by
:class:`~leaderboard.limits.BodyGuard`, and idle keep-alive connections by uvicorn
(``settings.keep_alive_s``).

:func:`serve` is what ``slipstream serve`` runs. Under another server (``uvicorn --factory
leaderboard.app:create_app``), pass the class: ``--http leaderboard.serving:HeaderTimeoutH11``
(10 s) — or put a reverse proxy with its own header timeout in front.
"""

from __future__ import annotations

import asyncio
import math
from typing import Any

from uvicorn.protocols.http.h11_impl import H11Protocol

from leaderboard.settings import Settings

DEFAULT_HEADER_TIMEOUT_S = 10.0  # = Settings.header_timeout_s's default


class HeaderTimeoutH11(H11Protocol):
    """uvicorn's h11 protocol, closing connections whose request head is late (see above)."""

    header_timeout_s: float = DEFAULT_HEADER_TIMEOUT_S

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._head_deadline: asyncio.TimerHandle | None = None

    def _waiting_for_head(self) -> bool:
        """Whether no request is being handled (the next request's head is awaited)."""
        return self.cycle is None or self.cycle.response_complete

    def _arm_head_deadline(self) -> None:
        if self._head_deadline is not None:
            self._head_deadline.cancel()
        self._head_deadline = self.loop.call_later(self.header_timeout_s, self._head_late)

    def _head_late(self) -> None:
        self._head_deadline = None
        if self._waiting_for_head() and not self.transport.is_closing():
            self.transport.close()

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        """Start the clock for the first request head."""
        super().connection_made(transport)
        self._arm_head_deadline()

    def data_received(self, data: bytes) -> None:
        """Parse as usual; stop the clock once a request head is complete."""
        super().data_received(data)
        if self._head_deadline is not None and not self._waiting_for_head():
            self._head_deadline.cancel()
            self._head_deadline = None

    def on_response_complete(self) -> None:
        """After an answer, the next request's head gets its own deadline."""
        super().on_response_complete()
        if not self.transport.is_closing() and self._waiting_for_head():
            self._arm_head_deadline()

    def connection_lost(self, exc: Exception | None) -> None:
        """Stop the clock."""
        if self._head_deadline is not None:
            self._head_deadline.cancel()
            self._head_deadline = None
        super().connection_lost(exc)


def http_protocol(header_timeout_s: float) -> type[HeaderTimeoutH11]:
    """A :class:`HeaderTimeoutH11` subclass with ``header_timeout_s`` (s)."""
    return type(
        "HeaderTimeoutH11", (HeaderTimeoutH11,), {"header_timeout_s": float(header_timeout_s)}
    )


def uvicorn_config(app: Any, settings: Settings, host: str, port: int) -> Any:
    """The uvicorn ``Config`` for ``app``: head/keep-alive timeouts, connection limit."""
    import uvicorn  # noqa: PLC0415 - the server only where it is run

    return uvicorn.Config(
        app,
        host=host,
        port=port,
        log_level="warning",
        http=http_protocol(settings.header_timeout_s),
        timeout_keep_alive=math.ceil(settings.keep_alive_s),  # idle connections closed
        limit_concurrency=settings.max_connections,  # 503 beyond, instead of exhausting FDs
    )


def serve(app: Any, settings: Settings, host: str, port: int) -> None:
    """Run ``app`` under uvicorn on ``host:port`` until interrupted."""
    import uvicorn  # noqa: PLC0415 - the server only where it is run

    uvicorn.Server(uvicorn_config(app, settings, host, port)).run()


__all__ = ["HeaderTimeoutH11", "http_protocol", "serve", "uvicorn_config"]
