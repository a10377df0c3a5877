"""``GET /api/health`` and ``GET /api/jobs``: liveness, schema revision, queue depth."""

from __future__ import annotations

from fastapi import APIRouter
from pydantic import BaseModel
from sqlalchemy import text

from leaderboard import queue
from leaderboard.api.deps import SessionDep

router = APIRouter(tags=["service"])


class QueueStats(BaseModel):
    """Jobs per status."""

    queued: int
    leased: int
    done: int
    failed: int


class Health(BaseModel):
    """The service is up and its database answers."""

    status: str
    database: str
    revision: str | None
    queue: QueueStats


@router.get("/health", response_model=Health)
def health(session: SessionDep) -> Health:
    """Liveness: the database dialect, its migration revision and the queue depth."""
    revision = session.execute(text("SELECT version_num FROM alembic_version")).scalar()
    return Health(
        status="ok",
        database=session.get_bind().dialect.name,
        revision=revision,
        queue=QueueStats(**queue.stats(session)),
    )


@router.get("/jobs", response_model=QueueStats)
def jobs(session: SessionDep) -> QueueStats:
    """How many race jobs are queued, leased (running), done and failed."""
    return QueueStats(**queue.stats(session))
