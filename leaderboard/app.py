"""The FastAPI application: ``create_app(settings)`` builds one, with its own database.

Nothing happens at import time: no engine, no settings read. ``create_app`` creates the data
folders, connects, migrates the schema to ``head`` (Alembic; ``settings.auto_migrate``),
includes the JSON API (``/api``, documented at ``/docs``) and the website
(:mod:`leaderboard.web`: HTML pages, ``/viewer/``, ``/replays/``). The web process never
imports pybullet or torch: it stores and serves what the workers produce.

Every request passes, outermost first: :class:`~leaderboard.security.SecurityHeaders` (CSP,
nosniff, Referrer-Policy, framing), ``TrustedHostMiddleware`` (``settings.allowed_hosts``),
:class:`~leaderboard.limits.RateLimit` (429 + ``Retry-After``),
:class:`~leaderboard.limits.BodyGuard` (body caps whatever the framing, uploads authenticated
before their body is read, body-read timeouts), gzip, ``HEAD`` served as ``GET``, and weak
ETags with ``304`` on JSON and HTML answers (:mod:`leaderboard.cache`).
``/docs`` and ``/redoc`` work offline (:mod:`leaderboard.docs`).

Run it with ``slipstream serve`` (uvicorn), or ``uvicorn --factory leaderboard.app:create_app``
(settings from ``SLIPSTREAM_*`` environment variables).
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from importlib.metadata import PackageNotFoundError, version

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse
from sqlalchemy.exc import DataError
from starlette.middleware.gzip import DEFAULT_EXCLUDED_CONTENT_TYPES, GZipMiddleware
from starlette.middleware.trustedhost import TrustedHostMiddleware

from leaderboard import web
from leaderboard.api import api_router
from leaderboard.cache import ETagMiddleware
from leaderboard.db import make_engine, make_sessionmaker
from leaderboard.docs import add_offline_docs
from leaderboard.errors import LeaderboardError, QuotaExceeded
from leaderboard.limits import BodyGuard, RateLimit
from leaderboard.migrations import upgrade
from leaderboard.security import HeadAsGet, SecurityHeaders
from leaderboard.settings import Settings
from leaderboard.web.viewer import VIEWER_PREFIX

GZIP_MIN_BYTES = 1024  # smaller responses are sent as they are
# Already compressed (.viser replays are zstd) or binary: not worth gzipping again.
GZIP_SKIP = (*DEFAULT_EXCLUDED_CONTENT_TYPES, "application/octet-stream")


def _version() -> str:
    try:
        return version("slipstream")
    except PackageNotFoundError:  # pragma: no cover - running from a source tree
        return "0"


async def _leaderboard_error(_request: Request, exc: Exception) -> JSONResponse:
    status = getattr(exc, "status_code", 400)
    headers = {"WWW-Authenticate": "Bearer"} if status == 401 else None
    if isinstance(exc, QuotaExceeded):
        headers = {"Retry-After": str(exc.retry_after)}
    return JSONResponse({"detail": str(exc)}, status_code=status, headers=headers)


async def _out_of_range(_request: Request, _exc: Exception) -> JSONResponse:
    """A number too large for the database column (an id past 2^31 on PostgreSQL, 2^63 on
    SQLite) names nothing that exists: 404, not a 500."""
    return JSONResponse({"detail": "no such object (number out of range)"}, status_code=404)


def _csp_for(app: FastAPI) -> Callable[[str], str | None]:
    def csp_for(path: str) -> str | None:
        if path.startswith(VIEWER_PREFIX):
            policy: str | None = getattr(app.state, "viewer_csp", None)
            return policy
        return None

    return csp_for


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
        docs_url=None,
        redoc_url=None,
    )
    app.state.settings = settings
    app.state.engine = engine
    app.state.sessionmaker = make_sessionmaker(engine)
    app.add_exception_handler(LeaderboardError, _leaderboard_error)
    app.add_exception_handler(OverflowError, _out_of_range)  # SQLite: integer past 2^63
    app.add_exception_handler(DataError, _out_of_range)  # PostgreSQL: out of the column's range
    # Middlewares, innermost first (the last added sees a request first).
    app.add_middleware(ETagMiddleware)
    app.add_middleware(HeadAsGet)
    app.add_middleware(
        GZipMiddleware,
        minimum_size=GZIP_MIN_BYTES,
        compresslevel=6,
        exclude_content_types=GZIP_SKIP,
    )
    app.add_middleware(BodyGuard, settings=settings)
    if settings.rate_limits:
        app.add_middleware(RateLimit, settings=settings)
    if "*" not in settings.allowed_hosts:
        app.add_middleware(TrustedHostMiddleware, allowed_hosts=settings.allowed_hosts)
    app.add_middleware(SecurityHeaders, csp_for=_csp_for(app))
    app.include_router(api_router)
    add_offline_docs(app)
    app.include_router(web.web_router)
    web.mount(app, settings)
    return app
