"""``GET /api/races`` and ``GET /api/races/{id}``: race results and replay links."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query

from leaderboard import queries
from leaderboard.api.deps import PageDep, SessionDep

router = APIRouter(tags=["races"])


@router.get("/races", response_model=queries.Page[queries.RaceSummary])
def list_races(
    session: SessionDep,
    pages: PageDep,
    track: Annotated[str | None, Query(description="only races on this track")] = None,
    status: Annotated[
        Literal["queued", "running", "finished", "failed"] | None, Query(description="race status")
    ] = None,
    kind: Annotated[Literal["validation", "ranked"] | None, Query()] = None,
) -> queries.Page[queries.RaceSummary]:
    """Races, newest first."""
    return queries.races(
        session, page=pages.page, per_page=pages.per_page, track=track, status=status, kind=kind
    )


@router.get("/races/{race_id}", response_model=queries.RaceDetail)
def get_race(session: SessionDep, race_id: int) -> queries.RaceDetail:
    """One race: each car's result and lap times, rating changes, replay URLs."""
    return queries.race_detail(session, race_id)
