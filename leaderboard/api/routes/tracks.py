"""``GET /api/tracks`` and ``GET /api/tracks/{name}``: race counts and lap records."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query

from leaderboard import queries
from leaderboard.api.deps import SessionDep, SettingsDep
from leaderboard.matchmaking import track_pool

router = APIRouter(tags=["tracks"])


@router.get("/tracks", response_model=list[queries.TrackSummary])
def list_tracks(session: SessionDep, settings: SettingsDep) -> list[queries.TrackSummary]:
    """The tracks ranked races use, with race counts and lap records."""
    return queries.tracks(session, track_pool(settings))


@router.get("/tracks/{name}", response_model=queries.TrackDetail)
def get_track(
    session: SessionDep,
    settings: SettingsDep,
    name: str,
    limit: Annotated[int, Query(ge=1, le=200, description="records and races shown")] = 20,
) -> queries.TrackDetail:
    """One track: the best lap of each submission, and recent races."""
    return queries.track_detail(session, name, known=track_pool(settings), limit=limit)
