"""``GET /api/health`` and ``GET /api/jobs``: liveness, schema revision, queue depth.

Monitoring polls these, so they must stay cheap on a large database: the job counts (a count
over every job ever run) are kept in the snapshot cache (:mod:`leaderboard.cache`) under a
fingerprint that moves whenever a count can — the newest job, the queued and leased counts
(index look-ups on a short queue), and the newest finished race (every job that ends as done
or failed finishes its race).
"""

from __future__ import annotations

from fastapi import APIRouter
from pydantic import BaseModel
from sqlalchemy import func, select, text
from sqlalchemy.orm import Session

from leaderboard import queue
from leaderboard.api.deps import SessionDep, SettingsDep
from leaderboard.cache import cache_for
from leaderboard.models import Job, Race

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


def queue_stats(session: Session, max_age_s: float) -> QueueStats:
    """The job counts per status, cached while nothing that changes them has moved."""
    fingerprint = session.execute(
        select(
            select(func.max(Job.id)).scalar_subquery(),
            select(func.count(Job.id)).where(Job.status == "queued").scalar_subquery(),
            select(func.count(Job.id)).where(Job.status == "leased").scalar_subquery(),
            select(func.max(Race.finished_at)).scalar_subquery(),
        )
    ).one()
    return cache_for(session).get(
        ("queue-stats",),
        tuple(fingerprint),
        lambda: QueueStats(**queue.stats(session)),
        max_age_s,
    )


@router.get("/health", response_model=Health)
def health(session: SessionDep, settings: SettingsDep) -> Health:
    """Liveness: the database dialect, its migration revision and the queue depth."""
    revision = session.execute(text("SELECT version_num FROM alembic_version")).scalar()
    return Health(
        status="ok",
        database=session.get_bind().dialect.name,
        revision=revision,
        queue=queue_stats(session, settings.cache_max_age_s),
    )


@router.get("/jobs", response_model=QueueStats)
def jobs(session: SessionDep, settings: SettingsDep) -> QueueStats:
    """How many race jobs are queued, leased (running), done and failed."""
    return queue_stats(session, settings.cache_max_age_s)
