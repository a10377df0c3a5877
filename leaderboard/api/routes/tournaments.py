"""Tournaments: ``/api/tournaments`` (list; create with the admin token) and
``/api/tournaments/{id}`` (standings, heats with replay links, the final)."""

from __future__ import annotations

from typing import Literal

from fastapi import APIRouter, Depends, status
from pydantic import BaseModel, Field

from leaderboard import tournaments
from leaderboard.api.deps import IdPath, PageDep, SessionDep, SettingsDep, require_admin
from leaderboard.queries import Page

router = APIRouter(tags=["tournaments"])


class TournamentCreate(BaseModel):
    """A tournament to run (see :mod:`leaderboard.tournaments`): ``entrants`` (submission ids,
    top seed first) or ``top`` (the top N of the car class's ladder)."""

    name: str = Field(min_length=1, max_length=64)
    format: Literal["round_robin", "time_trial"] = "round_robin"
    entrants: list[int] | None = Field(default=None, max_length=tournaments.MAX_ENTRANTS)
    top: int | None = Field(default=None, ge=2, le=tournaments.MAX_ENTRANTS)
    car: str | None = Field(default=None, max_length=16)
    tracks: list[str] | None = Field(default=None, max_length=20)
    seeds: list[int] = Field(default=[0], min_length=1, max_length=tournaments.MAX_SEEDS)
    laps: int = Field(default=2, ge=1, le=tournaments.MAX_LAPS)
    heat_size: int = Field(default=4, ge=2, le=8)
    final_size: int = Field(default=4, ge=2, le=8)


@router.get("/tournaments", response_model=Page[tournaments.TournamentSummary])
def list_tournaments(session: SessionDep, pages: PageDep) -> Page[tournaments.TournamentSummary]:
    """Every tournament, newest first: format, car, status, progress, the leader."""
    return tournaments.tournament_list(session, page=pages.page, per_page=pages.per_page)


@router.post(
    "/tournaments",
    response_model=tournaments.TournamentDetail,
    status_code=status.HTTP_201_CREATED,
    dependencies=[Depends(require_admin)],
)
def create_tournament(
    session: SessionDep, settings: SettingsDep, body: TournamentCreate
) -> tournaments.TournamentDetail:
    """Define a tournament (admin only); the workers run its heats from the queue."""
    created = tournaments.create_tournament(
        session,
        settings,
        name=body.name,
        fmt=body.format,
        entrants=body.entrants,
        top=body.top,
        car=body.car,
        tracks=body.tracks,
        seeds=body.seeds,
        laps=body.laps,
        heat_size=body.heat_size,
        final_size=body.final_size,
        created_by="api",
    )
    session.commit()
    return tournaments.tournament_detail(session, created.id)


@router.get("/tournaments/{tournament_id}", response_model=tournaments.TournamentDetail)
def get_tournament(session: SessionDep, tournament_id: IdPath) -> tournaments.TournamentDetail:
    """A tournament: standings (points per place, see ``points``), every heat with its replay
    links, and the final (``time_trial``)."""
    return tournaments.tournament_detail(session, tournament_id)
