"""``GET /api/leaderboard``: active submissions ranked by ordinal (μ − 3σ)."""

from __future__ import annotations

from fastapi import APIRouter

from leaderboard import queries
from leaderboard.api.deps import PageDep, SessionDep

router = APIRouter(tags=["leaderboard"])


@router.get("/leaderboard", response_model=queries.Page[queries.LeaderboardRow])
def get_leaderboard(session: SessionDep, pages: PageDep) -> queries.Page[queries.LeaderboardRow]:
    """The leaderboard: rank, name, author, ordinal, μ, σ, races, wins, win rate."""
    return queries.leaderboard(session, page=pages.page, per_page=pages.per_page)
