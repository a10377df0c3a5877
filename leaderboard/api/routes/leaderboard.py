"""``GET /api/leaderboard``: active submissions ranked by ordinal (μ − 3σ)."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query

from leaderboard import queries
from leaderboard.api.deps import PageDep, SessionDep, SettingsDep

router = APIRouter(tags=["leaderboard"])

CarQuery = Annotated[
    str | None,
    Query(max_length=16, description="one car class's ladder (f1tenth, deepracer); 404 if unknown"),
]

OrderQuery = Annotated[
    Literal["rating", "robust"],
    Query(description="rating: by ordinal (the ladder); robust: by robustness score"),
]


@router.get("/leaderboard", response_model=queries.Page[queries.LeaderboardRow])
def get_leaderboard(
    session: SessionDep,
    settings: SettingsDep,
    pages: PageDep,
    car: CarQuery = None,
    order: OrderQuery = "rating",
) -> queries.Page[queries.LeaderboardRow]:
    """The leaderboard: rank, name, author, car, ordinal, μ, σ, races, wins, win rate,
    robustness score (m/s); submissions with fewer than ``provisional_races`` rated races are
    ``provisional`` and come last. ``car`` keeps one car class's ladder (ratings compare
    within a class); ``order=robust`` ranks by the robustness score instead (not yet scored:
    last)."""
    return queries.leaderboard(
        session,
        page=pages.page,
        per_page=pages.per_page,
        provisional_races=settings.provisional_races,
        max_age_s=settings.cache_max_age_s,
        car=queries.check_car(car),
        order=order,
    )
