"""The JSON API (``/api/...``), one router per resource under :mod:`leaderboard.api.routes`.

OpenAPI documentation is served at ``/docs`` (Swagger UI) and ``/openapi.json``.
"""

from fastapi import APIRouter

from leaderboard.api.deps import ERROR_RESPONSES
from leaderboard.api.routes import (
    health,
    leaderboard,
    races,
    submissions,
    tokens,
    tournaments,
    tracks,
    users,
)

api_router = APIRouter(prefix="/api", responses=ERROR_RESPONSES)
for _module in (leaderboard, submissions, races, tournaments, tracks, users, tokens, health):
    api_router.include_router(_module.router)

__all__ = ["api_router"]
