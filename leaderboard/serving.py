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

:func:`serve_processes` is what ``slipstream serve`` runs: one process (:func:`serve`), or
``--web-workers N`` uvicorn worker processes answering on one socket. One process runs Python
on one core at a time (one GIL), so under concurrent requests they queue behind each other;
several processes use several cores. The database is migrated once, by the parent, before
any worker starts; each worker builds the app with :func:`worker_app` from the settings the
parent hands down (:data:`SETTINGS_ENV`). What each process keeps for itself is either
checked against the database on every use (the snapshot caches' fingerprints,
:mod:`leaderboard.cache`), kept on disk (track pictures), or divided between the processes
(the in-memory rate-limit counters and the uploads-in-flight cap, :mod:`leaderboard.limits`).

Under another server (``uvicorn --factory leaderboard.app:create_app``), pass the class:
``--http leaderboard.serving:HeaderTimeoutH11`` (10 s) — or put a reverse proxy with its own
header timeout in front — and with ``--workers N`` set ``SLIPSTREAM_WEB_WORKERS=N`` so the
rate limits are divided between the processes.
"""

from __future__ import annotations

import asyncio
import gc
import json
import math
import os
import socket
from typing import TYPE_CHECKING, Any

from pydantic import SecretStr
from uvicorn.protocols.http.h11_impl import H11Protocol

from leaderboard.errors import LeaderboardError
from leaderboard.settings import Settings

if TYPE_CHECKING:
    from fastapi import FastAPI

SETTINGS_ENV = "SLIPSTREAM_SERVE_SETTINGS"  # the parent's settings, as JSON, for its workers
WORKER_HEALTHCHECK_S = 30  # a worker importing the app on a busy machine is not hung
# One: on the 2 shared cores measured (bench/leaderboard_load.py --web-workers 1,2, README),
# a second process lowered the 8-client p50 (69 -> 59 ms, median of 35 endpoints) but raised
# the p99 (283 -> 355 ms): the processes, the load generator and the rest of the machine
# compete for the same two cores. On a machine with cores to spare, set --web-workers.
DEFAULT_WEB_WORKERS = 1
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


class WorkerH11(HeaderTimeoutH11):
    """The protocol of ``--web-workers`` processes (uvicorn imports it by name in each one);
    :func:`worker_app` sets its ``header_timeout_s`` from the settings.

    It turns Nagle's algorithm off on every connection. uvicorn's supervisor binds the shared
    socket itself, without naming the protocol (``proto`` 0), and asyncio sets
    ``TCP_NODELAY`` only on connections accepted from a socket whose ``proto`` is TCP; without
    it an answer's body waited for the client's delayed ACK of its head: 40 ms added to every
    request on Linux (measured: one client's p50 18 → 60 ms with two processes).
    """

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        """Send small writes at once (see the class docstring), then as the parent does."""
        sock = transport.get_extra_info("socket")
        if sock is not None and sock.family in (socket.AF_INET, socket.AF_INET6):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        super().connection_made(transport)


def _uvicorn_options(settings: Settings) -> dict[str, Any]:
    """uvicorn options of every process: keep-alive timeout, connection limit, logging."""
    return {
        "log_level": "warning",
        "timeout_keep_alive": math.ceil(settings.keep_alive_s),  # idle connections closed
        "limit_concurrency": settings.max_connections,  # 503 beyond, instead of exhausting FDs
    }


def uvicorn_config(app: Any, settings: Settings, host: str, port: int) -> Any:
    """The uvicorn ``Config`` for ``app``: head/keep-alive timeouts, connection limit."""
    import uvicorn  # noqa: PLC0415 - the server only where it is run

    return uvicorn.Config(
        app,
        host=host,
        port=port,
        http=http_protocol(settings.header_timeout_s),
        **_uvicorn_options(settings),
    )


def settle_heap() -> None:
    """Collect once, then exempt every object alive now (modules, the app, its routes and
    templates, the ORM's metadata: ~150k objects) from the cyclic garbage collector's scans.

    A full collection walks every tracked object; in a server process with the app loaded
    that took 40-160 ms (measured with ``gc.callbacks`` under ``bench/leaderboard_load.py``),
    a stall every request in flight waits out: the 8-client p99. Frozen objects are still
    freed by reference counting; only cycles among them would outlive their use, and the
    app's startup objects live as long as the process. (:func:`gc.freeze`, as CPython's
    docs advise for long-lived servers.)
    """
    gc.collect()
    gc.freeze()


def serve(app: Any, settings: Settings, host: str, port: int) -> None:
    """Run ``app`` under uvicorn on ``host:port`` until interrupted."""
    import uvicorn  # noqa: PLC0415 - the server only where it is run

    settle_heap()
    uvicorn.Server(uvicorn_config(app, settings, host, port)).run()


def default_web_workers() -> int:
    """``slipstream serve``'s process count when neither ``--web-workers`` nor
    ``SLIPSTREAM_WEB_WORKERS`` says: :data:`DEFAULT_WEB_WORKERS`."""
    return DEFAULT_WEB_WORKERS


def settings_json(settings: Settings) -> str:
    """``settings`` as JSON that :class:`Settings` reads back, secrets included (for the
    worker processes' environment: readable only by the same user, like the parent's)."""
    data = {
        name: value.get_secret_value() if isinstance(value, SecretStr) else value
        for name, value in settings.model_dump().items()
    }
    return json.dumps(data, default=str)


def worker_app() -> FastAPI:
    """The app of one ``--web-workers`` process (a uvicorn factory), from the settings its
    parent put in :data:`SETTINGS_ENV`; the parent has already migrated the database.

    Raises:
        LeaderboardError: :data:`SETTINGS_ENV` is not set (not started by
            :func:`serve_processes`).
    """
    from leaderboard.app import create_app  # noqa: PLC0415 - the app imports this module's users

    text = os.environ.get(SETTINGS_ENV)
    if not text:
        raise LeaderboardError(f"{SETTINGS_ENV} is not set: start workers with `slipstream serve`")
    settings = Settings(**json.loads(text))
    WorkerH11.header_timeout_s = settings.header_timeout_s  # this process's protocol class
    app = create_app(settings)
    settle_heap()
    return app


def serve_processes(settings: Settings, host: str, port: int, workers: int) -> None:
    """Serve the app on ``host:port`` from ``workers`` processes until interrupted.

    One worker runs in this process (:func:`serve`). Several: the schema is migrated here
    first (``settings.auto_migrate``), then uvicorn's supervisor binds the socket and starts
    ``workers`` processes that share it (a dead one is replaced), each building the app with
    :func:`worker_app`; ``settings.web_workers`` tells each how many there are.

    Raises:
        LeaderboardError: ``workers`` < 1.
    """
    import uvicorn  # noqa: PLC0415 - the server only where it is run

    from leaderboard.app import create_app  # noqa: PLC0415 - builds the app, after settings

    if workers < 1:
        raise LeaderboardError(f"--web-workers must be at least 1, not {workers}")
    settings = settings.model_copy(update={"web_workers": workers})
    if workers == 1:
        serve(create_app(settings), settings, host, port)
        return
    settings.ensure_dirs()
    if settings.auto_migrate:  # once, before any worker connects
        from leaderboard.db import make_engine  # noqa: PLC0415
        from leaderboard.migrations import upgrade  # noqa: PLC0415 - alembic, here only

        engine = make_engine(settings.db_url)
        try:
            upgrade(settings.db_url, engine=engine)
        finally:
            engine.dispose()
    os.environ[SETTINGS_ENV] = settings_json(settings.model_copy(update={"auto_migrate": False}))
    uvicorn.run(
        "leaderboard.serving:worker_app",
        factory=True,
        host=host,
        port=port,
        workers=workers,
        http="leaderboard.serving:WorkerH11",
        timeout_worker_healthcheck=WORKER_HEALTHCHECK_S,
        **_uvicorn_options(settings),
    )


__all__ = [
    "SETTINGS_ENV",
    "HeaderTimeoutH11",
    "WorkerH11",
    "default_web_workers",
    "http_protocol",
    "serve",
    "serve_processes",
    "settings_json",
    "uvicorn_config",
    "worker_app",
]
