"""The FastAPI application: ``create_app(settings)`` builds one, with its own database.

Nothing happens at import time: no engine, no settings read. ``create_app`` creates the data
folders, connects, migrates the schema to ``head`` (Alembic; ``settings.auto_migrate``),
includes the JSON API (``/api``, documented at ``/docs``) and the website
(:mod:`leaderboard.web`: HTML pages, ``/viewer/``, ``/replays/``). The web process never
imports pybullet or torch: it stores and serves what the workers produce.

Run it with ``slipstream serve`` (uvicorn), or ``uvicorn --factory leaderboard.app:create_app``
(settings from ``SLIPSTREAM_*`` environment variables).
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from importlib.metadata import PackageNotFoundError, version

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse
from starlette.types import ASGIApp, Receive, Scope, Send

from leaderboard import web
from leaderboard.api import api_router
from leaderboard.db import make_engine, make_sessionmaker
from leaderboard.errors import LeaderboardError
from leaderboard.migrations import upgrade
from leaderboard.settings import Settings

UPLOAD_PREFIX = "/api/submissions"
MULTIPART_SLACK = 1 << 20  # bytes of form framing allowed on top of the bundle size limit


def _version() -> str:
    try:
        return version("slipstream")
    except PackageNotFoundError:  # pragma: no cover - running from a source tree
        return "0"


class UploadSizeLimit:
    """Refuse an upload whose ``Content-Length`` is over the limit before reading its body.

    Bodies without a length (chunked) are still capped while they are saved.
    """

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if (
            scope["type"] == "http"
            and scope["method"] == "POST"
            and scope["path"].startswith(UPLOAD_PREFIX)
        ):
            length = dict(scope["headers"]).get(b"content-length")
            if length is not None and length.isdigit() and int(length) > self.max_bytes:
                limit = (self.max_bytes - MULTIPART_SLACK) / 2**20
                response = JSONResponse(
                    {"detail": f"bundle is larger than {limit:.0f} MiB"}, status_code=413
                )
                await response(scope, receive, send)
                return
        await self.app(scope, receive, send)


async def _leaderboard_error(_request: Request, exc: Exception) -> JSONResponse:
    status = getattr(exc, "status_code", 400)
    headers = {"WWW-Authenticate": "Bearer"} if status == 401 else None
    return JSONResponse({"detail": str(exc)}, status_code=status, headers=headers)


def create_app(settings: Settings | None = None) -> FastAPI:
    """A leaderboard app on the database of ``settings`` (default: from the environment)."""
    settings = settings or Settings()
    settings.ensure_dirs()
    engine = make_engine(settings.db_url)
    if settings.auto_migrate:
        upgrade(settings.db_url, engine=engine)

    @asynccontextmanager
    async def lifespan(_app: FastAPI) -> AsyncIterator[None]:
        yield
        engine.dispose()

    app = FastAPI(
        title="Slipstream leaderboard",
        version=_version(),
        description=(
            "Upload racing policies, see them ranked (OpenSkill PlackettLuce, by μ − 3σ), "
            "open any race and watch its replay. Authenticate uploads with "
            "`Authorization: Bearer <token>`."
        ),
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.engine = engine
    app.state.sessionmaker = make_sessionmaker(engine)
    app.add_exception_handler(LeaderboardError, _leaderboard_error)
    app.add_middleware(UploadSizeLimit, max_bytes=settings.max_upload_bytes + MULTIPART_SLACK)
    app.include_router(api_router)
    app.include_router(web.web_router)
    web.mount(app, settings)
    return app
