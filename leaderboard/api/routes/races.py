"""``GET /api/races``, ``GET /api/races/{id}`` (results and replay links) and
``GET /api/races/{id}/logs`` (the caller's own cars only: DNF detail, output, sandbox)."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query

from leaderboard import queries
from leaderboard.api.deps import CurrentUser, IdPath, PageDep, SessionDep

router = APIRouter(tags=["races"])


@router.get("/races", response_model=queries.Page[queries.RaceSummary])
def list_races(
    session: SessionDep,
    pages: PageDep,
    track: Annotated[str | None, Query(description="only races on this track")] = None,
    status: Annotated[
        Literal["queued", "running", "finished", "failed"] | None, Query(description="race status")
    ] = None,
    kind: Annotated[
        Literal["validation", "ranked", "tournament", "robustness"] | None,
        Query(description="race kind (robustness runs are listed only when asked for)"),
    ] = None,
    submission: Annotated[
        int | None, Query(ge=1, le=2**31 - 1, description="only races of this submission")
    ] = None,
) -> queries.Page[queries.RaceSummary]:
    """Races, newest first."""
    return queries.races(
        session,
        page=pages.page,
        per_page=pages.per_page,
        track=track,
        status=status,
        kind=kind,
        submission_id=submission,
    )


@router.get("/races/{race_id}", response_model=queries.RaceDetail)
def get_race(session: SessionDep, race_id: IdPath) -> queries.RaceDetail:
    """One race: each car's result and lap times, rating changes, replay URLs."""
    return queries.race_detail(session, race_id)


@router.get("/races/{race_id}/logs", response_model=list[queries.CarLog])
def get_race_logs(
    session: SessionDep,
    user: CurrentUser,
    race_id: IdPath,
    submission: Annotated[int | None, Query(ge=1, le=2**31 - 1)] = None,
) -> list[queries.CarLog]:
    """The caller's cars in a race: DNF detail (traceback), policy output, sandbox mode.

    Other people's cars are never included; a race without the caller's cars gives ``[]``.
    """
    return queries.race_logs(session, race_id, user_id=user.id, submission_id=submission)
