"""Read-side queries: what the JSON API and the website show, as pydantic models.

Every function takes a session and returns plain models (no ORM objects escape), so the API
returns them as they are and the Jinja2 templates read their attributes. Lists are paginated
with :class:`Page` (``page`` counts from 1). Missing objects raise
:class:`~leaderboard.errors.NotFound`.

Replay URLs follow the site's layout: ``/replays/<race id>.viser`` (3D, for the viewer at
``/viewer/?playbackPath=...``) and ``/replays/<race id>.replay.json.gz`` (the raw log).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from datetime import datetime
from pathlib import Path
from typing import Any, Generic, TypeVar

from pydantic import BaseModel, ConfigDict
from sqlalchemy import Select, func, select
from sqlalchemy.orm import Session, selectinload

from leaderboard.errors import NotFound
from leaderboard.models import (
    Race,
    RaceEntry,
    RatingHistory,
    Submission,
    SubmissionVersion,
    TrackRecord,
    User,
)

T = TypeVar("T")
MAX_PER_PAGE = 200


class Page(BaseModel, Generic[T]):
    """One page of a list: ``items``, and where it sits in the whole (``total`` rows)."""

    items: list[T]
    total: int
    page: int
    per_page: int

    @property
    def pages(self) -> int:
        """Number of pages (at least 1)."""
        return max(1, math.ceil(self.total / self.per_page))


class _Model(BaseModel):
    model_config = ConfigDict(from_attributes=True)


class LeaderboardRow(_Model):
    """One line of the leaderboard (ordinal = μ − 3σ; win rate = wins / races)."""

    rank: int
    submission_id: int
    name: str
    author: str
    version: int | None
    ordinal: float
    mu: float
    sigma: float
    races: int
    wins: int
    win_rate: float


class VersionInfo(_Model):
    """One uploaded version of a submission."""

    version: int
    status: str  # pending | validated | rejected
    format: str
    size_bytes: int
    sha256: str
    error: str | None
    created_at: datetime


class RatingPoint(_Model):
    """A submission's rating after one ranked race."""

    race_id: int
    mu: float
    sigma: float
    ordinal: float
    created_at: datetime


class EntryInfo(_Model):
    """One car of a race and how it did (times in s; μ/σ before and after the race)."""

    car: int
    submission_id: int | None
    name: str
    author: str | None
    position: int | None
    rank: int | None
    status: str | None
    dnf_reason: str | None
    laps_completed: int | None
    best_lap: float | None
    total_time: float | None
    lap_times: list[float]
    collisions: int | None
    at_fault_collisions: int | None
    off_track: int | None
    mu_before: float | None
    sigma_before: float | None
    mu_after: float | None
    sigma_after: float | None


class RaceSummary(_Model):
    """A race in a list."""

    id: int
    kind: str  # validation | ranked
    status: str  # queued | running | finished | failed
    track: str
    laps: int
    seed: int
    n_cars: int
    winner: str | None
    winner_submission_id: int | None
    created_at: datetime
    finished_at: datetime | None


class RaceDetail(RaceSummary):
    """A race with its cars, and links to its replays."""

    entries: list[EntryInfo]
    duration_s: float | None
    sandbox: str | None
    error: str | None
    viser_url: str | None
    replay_url: str | None


class SubmissionSummary(_Model):
    """A submission in a list."""

    id: int
    name: str
    author: str
    status: str  # pending | active | rejected | withdrawn
    version: int | None  # the version that races
    latest_version: int | None
    mu: float
    sigma: float
    ordinal: float
    races: int
    wins: int
    win_rate: float
    created_at: datetime


class SubmissionDetail(SubmissionSummary):
    """A submission with its versions, recent races and rating history."""

    description: str
    rank: int | None
    versions: list[VersionInfo]
    recent_races: list[RaceSummary]
    rating_history: list[RatingPoint]


class RecordRow(_Model):
    """A submission's best lap on a track."""

    rank: int
    submission_id: int
    name: str
    author: str
    best_lap: float
    race_id: int
    set_at: datetime


class TrackSummary(_Model):
    """A track with its race count and lap record."""

    name: str
    races: int
    record: float | None
    record_holder: str | None


class TrackDetail(TrackSummary):
    """A track with its records table and recent races."""

    records: list[RecordRow]
    recent_races: list[RaceSummary]


def _clamp(page: int, per_page: int) -> tuple[int, int]:
    return max(1, page), max(1, min(MAX_PER_PAGE, per_page))


def _count(session: Session, stmt: Select[Any]) -> int:
    return int(session.scalar(stmt) or 0)


def _win_rate(wins: int, races: int) -> float:
    return wins / races if races else 0.0


# ---- leaderboard and submissions -------------------------------------------------------------


def leaderboard(session: Session, *, page: int = 1, per_page: int = 50) -> Page[LeaderboardRow]:
    """Active submissions by ordinal (μ − 3σ), best first."""
    page, per_page = _clamp(page, per_page)
    total = _count(session, select(func.count(Submission.id)).where(Submission.status == "active"))
    rows = session.execute(
        select(Submission, User.name, SubmissionVersion.version)
        .join(User, User.id == Submission.user_id)
        .outerjoin(SubmissionVersion, SubmissionVersion.id == Submission.active_version_id)
        .where(Submission.status == "active")
        .order_by(Submission.ordinal.desc(), Submission.id)
        .offset((page - 1) * per_page)
        .limit(per_page)
    ).all()
    items = [
        LeaderboardRow(
            rank=(page - 1) * per_page + i + 1,
            submission_id=sub.id,
            name=sub.name,
            author=author,
            version=version,
            ordinal=sub.ordinal,
            mu=sub.mu,
            sigma=sub.sigma,
            races=sub.races,
            wins=sub.wins,
            win_rate=_win_rate(sub.wins, sub.races),
        )
        for i, (sub, author, version) in enumerate(rows)
    ]
    return Page(items=items, total=total, page=page, per_page=per_page)


def _summary(
    sub: Submission, author: str, version: int | None, latest: int | None
) -> dict[str, Any]:
    return {
        "id": sub.id,
        "name": sub.name,
        "author": author,
        "status": sub.status,
        "version": version,
        "latest_version": latest,
        "mu": sub.mu,
        "sigma": sub.sigma,
        "ordinal": sub.ordinal,
        "races": sub.races,
        "wins": sub.wins,
        "win_rate": _win_rate(sub.wins, sub.races),
        "created_at": sub.created_at,
    }


def submissions(
    session: Session, *, page: int = 1, per_page: int = 50, author: str | None = None
) -> Page[SubmissionSummary]:
    """All submissions (any status), newest first; optionally one author's."""
    page, per_page = _clamp(page, per_page)
    where = [User.name == author] if author else []
    total = _count(
        session,
        select(func.count(Submission.id)).join(User, User.id == Submission.user_id).where(*where),
    )
    latest = (
        select(func.max(SubmissionVersion.version))
        .where(SubmissionVersion.submission_id == Submission.id)
        .correlate(Submission)
        .scalar_subquery()
    )
    rows = session.execute(
        select(Submission, User.name, SubmissionVersion.version, latest)
        .join(User, User.id == Submission.user_id)
        .outerjoin(SubmissionVersion, SubmissionVersion.id == Submission.active_version_id)
        .where(*where)
        .order_by(Submission.id.desc())
        .offset((page - 1) * per_page)
        .limit(per_page)
    ).all()
    items = [SubmissionSummary(**_summary(s, a, v, lv)) for s, a, v, lv in rows]
    return Page(items=items, total=total, page=page, per_page=per_page)


def submission_rank(session: Session, sub: Submission) -> int | None:
    """The leaderboard rank of an active submission (None otherwise)."""
    if sub.status != "active":
        return None
    better = _count(
        session,
        select(func.count(Submission.id)).where(
            Submission.status == "active",
            (Submission.ordinal > sub.ordinal)
            | ((Submission.ordinal == sub.ordinal) & (Submission.id < sub.id)),
        ),
    )
    return better + 1


def submission_detail(session: Session, submission_id: int, *, races: int = 20) -> SubmissionDetail:
    """A submission with its versions, its ``races`` latest races and its rating history."""
    sub = session.get(Submission, submission_id)
    if sub is None:
        raise NotFound(f"no submission {submission_id}")
    author = session.scalar(select(User.name).where(User.id == sub.user_id)) or ""
    versions = list(
        session.scalars(
            select(SubmissionVersion)
            .where(SubmissionVersion.submission_id == sub.id)
            .order_by(SubmissionVersion.version.desc())
        )
    )
    active = next((v.version for v in versions if v.id == sub.active_version_id), None)
    return SubmissionDetail(
        **_summary(sub, author, active, versions[0].version if versions else None),
        description=sub.description,
        rank=submission_rank(session, sub),
        versions=[VersionInfo.model_validate(v) for v in versions],
        recent_races=submission_races(session, submission_id, per_page=races).items
        if races
        else [],
        rating_history=rating_history(session, submission_id),
    )


def rating_history(session: Session, submission_id: int) -> list[RatingPoint]:
    """A submission's rating after each of its ranked races, oldest first."""
    rows = session.scalars(
        select(RatingHistory)
        .where(RatingHistory.submission_id == submission_id)
        .order_by(RatingHistory.id)
    )
    return [RatingPoint.model_validate(r) for r in rows]


# ---- races -----------------------------------------------------------------------------------


def _race_summaries(races: Sequence[Race]) -> list[RaceSummary]:
    return [RaceSummary(**_race_fields(r)) for r in races]


def _race_fields(race: Race) -> dict[str, Any]:
    winner = next((e for e in race.entries if e.position == 1 and e.status == "finished"), None)
    return {
        "id": race.id,
        "kind": race.kind,
        "status": race.status,
        "track": race.track,
        "laps": race.laps,
        "seed": race.seed,
        "n_cars": len(race.entries),
        "winner": winner.name if winner else None,
        "winner_submission_id": winner.submission_id if winner else None,
        "created_at": race.created_at,
        "finished_at": race.finished_at,
    }


def races(
    session: Session,
    *,
    page: int = 1,
    per_page: int = 50,
    track: str | None = None,
    status: str | None = None,
    kind: str | None = None,
) -> Page[RaceSummary]:
    """Races, newest first; optionally of one track, status or kind."""
    page, per_page = _clamp(page, per_page)
    where = []
    if track:
        where.append(Race.track == track)
    if status:
        where.append(Race.status == status)
    if kind:
        where.append(Race.kind == kind)
    total = _count(session, select(func.count(Race.id)).where(*where))
    rows = session.scalars(
        select(Race)
        .where(*where)
        .order_by(Race.id.desc())
        .offset((page - 1) * per_page)
        .limit(per_page)
        .options(selectinload(Race.entries))
    ).all()
    return Page(items=_race_summaries(rows), total=total, page=page, per_page=per_page)


def submission_races(
    session: Session, submission_id: int, *, page: int = 1, per_page: int = 20
) -> Page[RaceSummary]:
    """The races a submission took part in, newest first."""
    page, per_page = _clamp(page, per_page)
    total = _count(
        session,
        select(func.count(RaceEntry.id)).where(RaceEntry.submission_id == submission_id),
    )
    ids = session.scalars(
        select(RaceEntry.race_id)
        .where(RaceEntry.submission_id == submission_id)
        .order_by(RaceEntry.race_id.desc())
        .offset((page - 1) * per_page)
        .limit(per_page)
    ).all()
    rows = session.scalars(
        select(Race)
        .where(Race.id.in_(ids))
        .order_by(Race.id.desc())
        .options(selectinload(Race.entries))
    ).all()
    return Page(items=_race_summaries(rows), total=total, page=page, per_page=per_page)


def race_detail(session: Session, race_id: int) -> RaceDetail:
    """A race with every car's result and its replay links."""
    race = session.scalar(
        select(Race).where(Race.id == race_id).options(selectinload(Race.entries))
    )
    if race is None:
        raise NotFound(f"no race {race_id}")
    sub_ids = [e.submission_id for e in race.entries if e.submission_id is not None]
    authors = dict(
        session.execute(
            select(Submission.id, User.name)
            .join(User, User.id == Submission.user_id)
            .where(Submission.id.in_(sub_ids))
        ).all()
    )
    entries = [
        EntryInfo(
            car=e.car,
            submission_id=e.submission_id,
            name=e.name,
            author=authors.get(e.submission_id) if e.submission_id else None,
            position=e.position,
            rank=e.rank,
            status=e.status,
            dnf_reason=e.dnf_reason,
            laps_completed=e.laps_completed,
            best_lap=e.best_lap,
            total_time=e.total_time,
            lap_times=list(e.lap_times or []),
            collisions=e.collisions,
            at_fault_collisions=e.at_fault_collisions,
            off_track=e.off_track,
            mu_before=e.mu_before,
            sigma_before=e.sigma_before,
            mu_after=e.mu_after,
            sigma_after=e.sigma_after,
        )
        for e in race.entries
    ]
    return RaceDetail(
        **_race_fields(race),
        entries=entries,
        duration_s=race.duration_s,
        sandbox=race.sandbox,
        error=race.error,
        viser_url=f"/replays/{Path(race.viser_path).name}" if race.viser_path else None,
        replay_url=f"/replays/{Path(race.replay_path).name}" if race.replay_path else None,
    )


# ---- tracks ----------------------------------------------------------------------------------


def track_records(session: Session, track: str, *, limit: int = 20) -> list[RecordRow]:
    """The best laps on a track, one per submission, fastest first."""
    rows = session.execute(
        select(TrackRecord, Submission.name, User.name)
        .join(Submission, Submission.id == TrackRecord.submission_id)
        .join(User, User.id == Submission.user_id)
        .where(TrackRecord.track == track)
        .order_by(TrackRecord.best_lap, TrackRecord.id)
        .limit(limit)
    ).all()
    return [
        RecordRow(
            rank=i + 1,
            submission_id=rec.submission_id,
            name=name,
            author=author,
            best_lap=rec.best_lap,
            race_id=rec.race_id,
            set_at=rec.set_at,
        )
        for i, (rec, name, author) in enumerate(rows)
    ]


def tracks(session: Session, names: Sequence[str]) -> list[TrackSummary]:
    """Each named track with its finished race count and lap record."""
    counts = dict(
        session.execute(
            select(Race.track, func.count(Race.id))
            .where(Race.status == "finished")
            .group_by(Race.track)
        ).all()
    )
    # One query for every track's record: the first row of each track in track_records' order.
    ranked = (
        select(
            TrackRecord.track,
            TrackRecord.best_lap,
            Submission.name,
            func.row_number()
            .over(partition_by=TrackRecord.track, order_by=(TrackRecord.best_lap, TrackRecord.id))
            .label("n"),
        )
        .join(Submission, Submission.id == TrackRecord.submission_id)
        .where(TrackRecord.track.in_(names))
        .subquery()
    )
    best = {
        track: (lap, holder)
        for track, lap, holder in session.execute(
            select(ranked.c.track, ranked.c.best_lap, ranked.c.name).where(ranked.c.n == 1)
        )
    }
    out = []
    for name in names:
        record, holder = best.get(name, (None, None))
        out.append(
            TrackSummary(
                name=name, races=int(counts.get(name, 0)), record=record, record_holder=holder
            )
        )
    return out


def track_detail(
    session: Session, name: str, *, known: Sequence[str] | None = None, limit: int = 20
) -> TrackDetail:
    """A track's records and recent races; ``known`` lists the valid track names.

    Raises:
        NotFound: ``name`` is not in ``known`` and no race was run on it.
    """
    recent = races(session, track=name, status="finished", per_page=limit)
    if (known is None or name not in known) and recent.total == 0:
        raise NotFound(f"no track {name!r}")
    records = track_records(session, name, limit=limit)
    return TrackDetail(
        name=name,
        races=recent.total,
        record=records[0].best_lap if records else None,
        record_holder=records[0].name if records else None,
        records=records,
        recent_races=recent.items,
    )
