"""The race queue, kept in the database: enqueue, claim with a lease, heartbeat, complete.

A worker claims a job and holds a *lease* on it: an owner name, a random token and an expiry.
It renews the lease while the race runs (:func:`heartbeat`). If the worker dies, the lease
runs out and the next :func:`claim` hands the job to another worker, with a new token, until
``max_attempts`` claims have been used (then :func:`expire` marks the race failed).

Exactly once: :func:`complete` first flips the job from ``leased`` to ``done`` *only if the
caller's token still holds it* (one conditional ``UPDATE``), then stores the result and the
rating update in the same transaction. A late result from a worker whose lease was taken over
changes no row and is discarded; two results for one job cannot both commit.

Claiming is one transaction: on PostgreSQL ``SELECT … FOR UPDATE SKIP LOCKED`` (workers never
wait for each other), on SQLite one ``UPDATE … WHERE id = (SELECT …) RETURNING`` (SQLite
serialises writers; a stale snapshot raises and is retried).
"""

from __future__ import annotations

import time
import uuid
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import ColumnElement, and_, func, or_, select, update
from sqlalchemy.exc import OperationalError
from sqlalchemy.orm import Session

from leaderboard.models import Job, Race, utcnow
from leaderboard.results import fail_race, store_result

_SQLITE_RETRIES = 20


@dataclass(frozen=True)
class Lease:
    """A worker's hold on one job (pass it back to heartbeat, complete or fail)."""

    job_id: int
    race_id: int
    token: str
    owner: str
    attempt: int
    expires_at: datetime


def enqueue(session: Session, race: Race, *, priority: int = 10, max_attempts: int = 3) -> Job:
    """Queue a race (lower ``priority`` runs sooner; validation races use 0)."""
    job = Job(race=race, priority=priority, max_attempts=max_attempts)
    session.add(job)
    session.flush()
    return job


def _claimable(now: datetime) -> ColumnElement[bool]:
    return or_(
        Job.status == "queued",
        and_(
            Job.status == "leased",
            Job.lease_expires_at < now,
            Job.attempts < Job.max_attempts,
        ),
    )


def claim(
    session: Session, *, owner: str, lease_s: float, now: datetime | None = None
) -> Lease | None:
    """Lease the next job (lowest priority, then oldest), or None if nothing is claimable.

    Commits its own transaction, so call it on a session with nothing pending.
    """
    for attempt in range(_SQLITE_RETRIES):
        try:
            lease = _claim_once(session, owner=owner, lease_s=lease_s, now=now or utcnow())
            session.commit()
            session.expire_all()  # rows changed behind the identity map's back
            return lease
        except OperationalError:
            session.rollback()
            if session.get_bind().dialect.name != "sqlite" or attempt == _SQLITE_RETRIES - 1:
                raise
            time.sleep(0.05 * (attempt + 1))
    return None  # pragma: no cover - the loop returns or raises


def _claim_once(session: Session, *, owner: str, lease_s: float, now: datetime) -> Lease | None:
    token = uuid.uuid4().hex
    expires = now + timedelta(seconds=lease_s)
    values: dict[str, Any] = {
        "status": "leased",
        "lease_owner": owner,
        "lease_token": token,
        "lease_expires_at": expires,
        "attempts": Job.attempts + 1,
        "updated_at": now,
    }
    pick = select(Job.id).where(_claimable(now)).order_by(Job.priority, Job.id).limit(1)
    if session.get_bind().dialect.name == "postgresql":
        job_id = session.scalar(pick.with_for_update(skip_locked=True))
        if job_id is None:
            return None
        row = session.execute(
            update(Job)
            .where(Job.id == job_id)
            .values(**values)
            .returning(Job.id, Job.race_id, Job.attempts)
        ).one()
    else:
        row_or_none = session.execute(
            update(Job)
            .where(Job.id == pick.scalar_subquery(), _claimable(now))
            .values(**values)
            .returning(Job.id, Job.race_id, Job.attempts)
            .execution_options(synchronize_session=False)
        ).one_or_none()
        if row_or_none is None:
            return None
        row = row_or_none
    session.execute(
        update(Race)
        .where(Race.id == row.race_id)
        .values(status="running", started_at=now)
        .execution_options(synchronize_session=False)
    )
    return Lease(
        job_id=row.id,
        race_id=row.race_id,
        token=token,
        owner=owner,
        attempt=row.attempts,
        expires_at=expires,
    )


def _holds(lease: Lease) -> ColumnElement[bool]:
    return and_(Job.id == lease.job_id, Job.lease_token == lease.token, Job.status == "leased")


def heartbeat(session: Session, lease: Lease, *, lease_s: float) -> bool:
    """Extend a lease; False if the job is no longer held with this token (then stop)."""
    now = utcnow()
    res = session.execute(
        update(Job)
        .where(_holds(lease))
        .values(lease_expires_at=now + timedelta(seconds=lease_s), updated_at=now)
        .execution_options(synchronize_session=False)
    )
    session.commit()
    return bool(res.rowcount)  # type: ignore[attr-defined]


def complete(
    session: Session,
    lease: Lease,
    result: dict[str, Any],
    *,
    replay_path: str | None = None,
    viser_path: str | None = None,
    sandbox: str | None = None,
    duration_s: float | None = None,
    logs: dict[str, dict[str, Any]] | None = None,
) -> bool:
    """Store a job's result and its rating update, once; False if the lease was lost.

    ``logs`` are the owner-only logs per car (``JobResult.logs``: the policy's output and
    sandbox mode), stored with the result in ``race_logs``.

    The job row is updated first (taking the write lock), conditioned on the lease token;
    only if that changed a row are the result and ratings written, and all of it commits
    together.
    """
    now = utcnow()
    res = session.execute(
        update(Job)
        .where(_holds(lease))
        .values(status="done", lease_token=None, lease_expires_at=None, updated_at=now, error=None)
        .execution_options(synchronize_session=False)
    )
    if not res.rowcount:  # type: ignore[attr-defined]
        session.rollback()
        return False
    session.expire_all()  # read the race as it is now, not as a previous query saw it
    race = session.get(Race, lease.race_id)
    if race is None:  # pragma: no cover - jobs cascade with their race
        session.rollback()
        return False
    store_result(
        session,
        race,
        result,
        replay_path=replay_path,
        viser_path=viser_path,
        sandbox=sandbox,
        duration_s=duration_s,
        logs=logs,
    )
    session.commit()
    return True


def fail(session: Session, lease: Lease, error: str) -> bool:
    """Give a job back after an error: queued again while attempts remain, else failed.

    Returns False if the lease was no longer held.
    """
    session.expire_all()
    job = session.scalar(select(Job).where(_holds(lease)).with_for_update())
    if job is None:
        session.rollback()
        return False
    now = utcnow()
    job.error = error[:2000]
    job.lease_token = None
    job.lease_expires_at = None
    job.updated_at = now
    race = job.race
    if job.attempts >= job.max_attempts:
        job.status = "failed"
        fail_race(session, race, job.error)
    else:
        job.status = "queued"
        race.status = "queued"
    session.commit()
    return True


def expire(session: Session, *, now: datetime | None = None) -> int:
    """Fail jobs whose lease ran out with no attempts left; returns how many."""
    now = now or utcnow()
    session.expire_all()
    stale = list(
        session.scalars(
            select(Job)
            .where(
                Job.status == "leased",
                Job.lease_expires_at < now,
                Job.attempts >= Job.max_attempts,
            )
            .with_for_update(skip_locked=True)
        )
    )
    for job in stale:
        job.status = "failed"
        job.error = f"lease lost {job.attempts} times (worker died or hung)"
        job.lease_token = None
        job.updated_at = now
        fail_race(session, job.race, job.error)
    session.commit()
    return len(stale)


def stats(session: Session) -> dict[str, int]:
    """Number of jobs per status (``queued``, ``leased``, ``done``, ``failed``)."""
    counts = {"queued": 0, "leased": 0, "done": 0, "failed": 0}
    for status, n in session.execute(select(Job.status, func.count()).group_by(Job.status)):
        counts[status] = int(n)
    return counts


def pending(session: Session) -> int:
    """Jobs waiting or running (queued + leased)."""
    return int(
        session.scalar(select(func.count(Job.id)).where(Job.status.in_(("queued", "leased")))) or 0
    )
