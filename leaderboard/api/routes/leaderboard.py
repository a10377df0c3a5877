"""``GET /api/leaderboard``: active submissions ranked by ordinal (μ − 3σ)."""

from __future__ import annotations

from fastapi import APIRouter

from leaderboard import queries
from leaderboard.api.deps import PageDep, SessionDep, SettingsDep

router = APIRouter(tags=["leaderboard"])


@router.get("/leaderboard", response_model=queries.Page[queries.LeaderboardRow])
def get_leaderboard(
    session: SessionDep, settings: SettingsDep, pages: PageDep
) -> queries.Page[queries.LeaderboardRow]:
    """The leaderboard: rank, name, author, ordinal, μ, σ, races, wins, win rate; submissions
    with fewer than ``provisional_races`` rated races are ``provisional`` and come last."""
    return queries.leaderboard(
        session,
        page=pages.page,
        per_page=pages.per_page,
        provisional_races=settings.provisional_races,
        max_age_s=settings.cache_max_age_s,
    )
