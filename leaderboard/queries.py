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
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Generic, TypeVar

from pydantic import BaseModel, ConfigDict, SerializerFunctionWrapHandler, field_serializer
from sqlalchemy import ColumnElement, Select, case, func, select
from sqlalchemy.orm import Session, selectinload

from leaderboard.cache import cache_for
from leaderboard.errors import NotFound
from leaderboard.models import (
    DEFAULT_CAR,
    Race,
    RaceEntry,
    RaceLog,
    RatingHistory,
    Submission,
    SubmissionVersion,
    TrackRecord,
    User,
)
from leaderboard.timeline import Penalty, TimelineEvent, penalties, timeline

T = TypeVar("T")
MAX_PER_PAGE = 200
_IN_CHUNK = 1000  # ids per IN (...) list (SQLite and psycopg cap a statement's parameters)
PROVISIONAL_RACES = 5  # default of Settings.provisional_races
SNAPSHOT_MAX_AGE_S = 30.0  # default of Settings.cache_max_age_s


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


class UtcModel(BaseModel):
    """A model whose times are written in JSON as UTC with a ``Z`` (RFC 3339 ``date-time``).

    Times are stored naive UTC (:func:`leaderboard.models.utcnow`); without the zone their
    JSON would not be the ``date-time`` the OpenAPI schema promises.
    """

    @field_serializer("*", mode="wrap", when_used="json")
    def _utc(self, value: Any, handler: SerializerFunctionWrapHandler) -> Any:
        if isinstance(value, datetime) and value.tzinfo is None:
            value = value.replace(tzinfo=UTC)
        return handler(value)


class _Model(UtcModel):
    model_config = ConfigDict(from_attributes=True)


class LeaderboardRow(_Model):
    """One line of the leaderboard (ordinal = μ − 3σ; win rate = wins / races).

    ``provisional``: fewer than ``k`` rated races (``Settings.provisional_races``); such rows
    come after every established one, ranked among themselves by ordinal.
    """

    rank: int
    provisional: bool
    submission_id: int
    name: str
    author: str
    version: int | None
    car: str  # its car class (its ladder)
    ordinal: float
    mu: float
    sigma: float
    races: int
    wins: int
    win_rate: float
    # The racing version's robustness score, m/s (leaderboard.robustness); None until run.
    robust_score: float | None = None
    robust_race_id: int | None = None


class VersionInfo(_Model):
    """One uploaded version of a submission."""

    version: int
    status: str  # pending | validated | rejected
    format: str
    car: str
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
    race_time: float | None = None  # s, before penalties
    penalties: float | None = None  # s added
    penalty_items: list[Penalty] = []  # what each penalty was for
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
    kind: str  # validation | ranked | robustness | tournament
    status: str  # queued | running | finished | failed
    track: str
    car: str
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
    penalties: bool = True  # DeepRacer time penalties apply
    events: list[TimelineEvent] = []


class SubmissionSummary(_Model):
    """A submission in a list."""

    id: int
    name: str
    author: str
    status: str  # pending | active | rejected | withdrawn
    version: int | None  # the version that races
    latest_version: int | None
    car: str | None  # the car class its versions drive (None before its first upload)
    mu: float
    sigma: float
    ordinal: float
    races: int
    wins: int
    win_rate: float
    created_at: datetime


class RobustPoint(_Model):
    """One lap of a robustness run: its perturbation and how the car did (m, s, m/s)."""

    perturbation: dict[str, float]  # friction, motor, steer_offset (rad), latency (steps)
    score: float  # effective speed, m/s
    finished: bool
    distance: float
    time: float
    dnf_reason: str | None


class RobustnessRun(UtcModel):
    """A version's robustness run (:mod:`leaderboard.robustness`): ``score`` is the grid's
    worst-10 % mean effective speed, m/s; ``points`` the nominal lap first, then the grid."""

    race_id: int
    version: int
    status: str  # queued | running | finished | failed
    track: str
    car: str
    laps: int
    seed: int
    score: float | None = None
    nominal: float | None = None
    mean: float | None = None
    worst: float | None = None
    worst_over_nominal: float | None = None
    dnf_reason: str | None = None  # the policy's failure that ended the run, if any
    points: list[RobustPoint] = []
    error: str | None = None  # why the run failed (status failed)
    finished_at: datetime | None = None


class SubmissionDetail(SubmissionSummary):
    """A submission with its versions, recent races, rating history and the robustness run
    of the version that races."""

    description: str
    rank: int | None
    versions: list[VersionInfo]
    recent_races: list[RaceSummary]
    rating_history: list[RatingPoint]
    robustness: RobustnessRun | None = None


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


def _provisional(k: int) -> ColumnElement[int]:
    """0 for an established submission (at least ``k`` rated races), 1 for a provisional one."""
    return case((Submission.races < k, 1), else_=0)


def car_classes() -> tuple[str, ...]:
    """The car classes, one ladder each (:data:`arena.cars.CAR_PRESETS`; no pybullet)."""
    from arena.cars import CAR_PRESETS  # noqa: PLC0415 - light; keeps queries' imports lean

    return tuple(CAR_PRESETS)


def check_car(car: str | None) -> str | None:
    """``car`` if it names a car class, None for None or "" (every class).

    Raises:
        NotFound: no such car class.
    """
    if not car:
        return None
    if car not in car_classes():
        raise NotFound(f"no car class {car!r} (one of {', '.join(car_classes())})")
    return car


ORDERS = ("rating", "robust")
"""Orderings of the leaderboard: by ordinal (the ladder), or by robustness score."""


def _leaderboard_fingerprint(session: Session) -> tuple[Any, ...]:
    """What changes whenever the leaderboard can: every writer bumps ``updated_at``; the
    active count also catches a status changed by hand (both are index look-ups)."""
    latest = session.scalar(select(func.max(Submission.updated_at)))
    active = session.scalar(select(func.count(Submission.id)).where(Submission.status == "active"))
    return latest, active


def leaderboard(
    session: Session,
    *,
    page: int = 1,
    per_page: int = 50,
    provisional_races: int = PROVISIONAL_RACES,
    max_age_s: float = SNAPSHOT_MAX_AGE_S,
    car: str | None = None,
    order: str = "rating",
) -> Page[LeaderboardRow]:
    """Active submissions by ordinal (μ − 3σ), best first; provisional ones after the rest.

    A submission with fewer than ``provisional_races`` rated races is *provisional*: its
    ordinal says little yet (a new one starts at 0, above many established negative ones), so
    it is listed after every established submission, marked ``provisional``. ``car`` keeps
    one car class's ladder (None: every class, each row saying its car). ``order="robust"``
    orders by the racing version's robustness score instead (best first; submissions not
    scored yet last, by ordinal). Snapshots are cached per page (:mod:`leaderboard.cache`)
    until a submission changes.

    Raises:
        NotFound: ``order`` is not one of :data:`ORDERS`.
    """
    if order not in ORDERS:
        raise NotFound(f"no leaderboard order {order!r} (one of {', '.join(ORDERS)})")
    page, per_page = _clamp(page, per_page)
    return cache_for(session).get(
        ("leaderboard", page, per_page, provisional_races, car, order),
        _leaderboard_fingerprint(session),
        lambda: _leaderboard_page(session, page, per_page, provisional_races, car, order),
        max_age_s,
    )


def _leaderboard_page(
    session: Session,
    page: int,
    per_page: int,
    provisional_races: int,
    car: str | None,
    order: str,
) -> Page[LeaderboardRow]:
    where: list[ColumnElement[bool]] = [Submission.status == "active"]
    if car is not None:
        where.append(SubmissionVersion.car == car)
    total = _count(
        session,
        select(func.count(Submission.id))
        .outerjoin(SubmissionVersion, SubmissionVersion.id == Submission.active_version_id)
        .where(*where),
    )
    ranking: tuple[Any, ...] = (
        _provisional(provisional_races),
        Submission.ordinal.desc(),
        Submission.id,
    )
    if order == "robust":
        score = SubmissionVersion.robust_score
        ranking = (score.is_(None), score.desc(), Submission.ordinal.desc(), Submission.id)
    rows = session.execute(
        select(Submission, User.name, SubmissionVersion)
        .join(User, User.id == Submission.user_id)
        .outerjoin(SubmissionVersion, SubmissionVersion.id == Submission.active_version_id)
        .where(*where)
        .order_by(*ranking)
        .offset((page - 1) * per_page)
        .limit(per_page)
    ).all()
    items = [
        LeaderboardRow(
            rank=(page - 1) * per_page + i + 1,
            provisional=sub.races < provisional_races,
            submission_id=sub.id,
            name=sub.name,
            author=author,
            version=ver.version if ver else None,
            car=ver.car if ver else DEFAULT_CAR,
            ordinal=sub.ordinal,
            mu=sub.mu,
            sigma=sub.sigma,
            races=sub.races,
            wins=sub.wins,
            win_rate=_win_rate(sub.wins, sub.races),
            robust_score=ver.robust_score if ver else None,
            robust_race_id=ver.robust_race_id if ver else None,
        )
        for i, (sub, author, ver) in enumerate(rows)
    ]
    return Page(items=items, total=total, page=page, per_page=per_page)


def _summary(
    sub: Submission, author: str, version: int | None, latest: int | None, car: str | None
) -> dict[str, Any]:
    return {
        "id": sub.id,
        "name": sub.name,
        "author": author,
        "status": sub.status,
        "version": version,
        "latest_version": latest,
        "car": car,
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
    count = select(func.count(Submission.id)).join(User, User.id == Submission.user_id)
    total = cache_for(session).get(  # only a new submission changes it: until the newest id moves
        ("submission-count", author),
        session.scalar(select(func.max(Submission.id))),
        lambda: _count(session, count.where(*where)),
        SNAPSHOT_MAX_AGE_S,
    )
    latest = (
        select(func.max(SubmissionVersion.version))
        .where(SubmissionVersion.submission_id == Submission.id)
        .correlate(Submission)
        .scalar_subquery()
    )
    rows = session.execute(
        select(Submission, User.name, SubmissionVersion.version, latest, _car_of_submission())
        .join(User, User.id == Submission.user_id)
        .outerjoin(SubmissionVersion, SubmissionVersion.id == Submission.active_version_id)
        .where(*where)
        .order_by(Submission.id.desc())
        .offset((page - 1) * per_page)
        .limit(per_page)
    ).all()
    items = [SubmissionSummary(**_summary(s, a, v, lv, c)) for s, a, v, lv, c in rows]
    return Page(items=items, total=total, page=page, per_page=per_page)


def _car_of_submission() -> Any:
    """A correlated subquery: the car class of a submission's newest version."""
    return (
        select(SubmissionVersion.car)
        .where(SubmissionVersion.submission_id == Submission.id)
        .order_by(SubmissionVersion.version.desc())
        .limit(1)
        .correlate(Submission)
        .scalar_subquery()
    )


def submission_rank(
    session: Session, sub: Submission, *, provisional_races: int = PROVISIONAL_RACES
) -> int | None:
    """The rank of an active submission in its car class's ladder (None otherwise), in
    :func:`leaderboard`'s order: established submissions first, then provisional ones."""
    if sub.status != "active":
        return None
    car = session.scalar(
        select(SubmissionVersion.car).where(SubmissionVersion.id == sub.active_version_id)
    )
    ranks = ladder_ranks(session, car or DEFAULT_CAR, provisional_races=provisional_races)
    return ranks.get(sub.id)


def ladder_ranks(
    session: Session,
    car: str,
    *,
    provisional_races: int = PROVISIONAL_RACES,
    max_age_s: float = SNAPSHOT_MAX_AGE_S,
) -> dict[int, int]:
    """Submission id → rank in the ``car`` ladder, for every active submission of that class.

    One ordered read of the ladder, cached like the leaderboard's pages (it changes when they
    do), so a submission page looks its rank up instead of counting the submissions above it
    (a scan of the table on every view, issue 13)."""

    def compute() -> dict[int, int]:
        ids = session.scalars(
            select(Submission.id)
            .join(SubmissionVersion, SubmissionVersion.id == Submission.active_version_id)
            .where(Submission.status == "active", SubmissionVersion.car == car)
            .order_by(_provisional(provisional_races), Submission.ordinal.desc(), Submission.id)
        )
        return {sub_id: rank for rank, sub_id in enumerate(ids, start=1)}

    return cache_for(session).get(
        ("ladder-ranks", car, provisional_races),
        _leaderboard_fingerprint(session),
        compute,
        max_age_s,
    )


def _races_fingerprint(session: Session) -> tuple[Any, ...]:
    """What changes whenever any race is queued, starts, finishes, fails or is handed back:
    the newest race id, the latest finish, and how many races wait and run (index look-ups:
    the pending ones are few)."""
    newest = session.scalar(select(func.max(Race.id)))
    finished = session.scalar(select(func.max(Race.finished_at)))
    pending = session.execute(
        select(Race.status, func.count(Race.id))
        .where(Race.status.in_(("queued", "running")))
        .group_by(Race.status)
        .order_by(Race.status)
    ).all()
    return newest, finished, tuple(tuple(row) for row in pending)


def submission_fingerprint(session: Session, submission_id: int) -> tuple[Any, ...]:
    """What a submission's detail and page are computed from changes whenever this does.

    Its own row (every writer of its rating, versions, status or robustness score bumps
    ``updated_at``; its name and description are compared too, for edits by hand), its
    newest race (a race queued with it), the state of every race
    (:func:`_races_fingerprint`: its races starting, finishing or failing) and the ladder (its
    rank): a few index look-ups instead of the ~15 ms of queries the page costs (issue 13).

    Raises:
        NotFound: no such submission.
    """
    row = session.execute(
        select(
            Submission.updated_at,
            Submission.races,
            Submission.status,
            Submission.active_version_id,
            Submission.name,
            Submission.description,
        ).where(Submission.id == submission_id)
    ).first()
    if row is None:
        raise NotFound(f"no submission {submission_id}")
    newest = session.scalar(
        select(func.max(RaceEntry.race_id)).where(RaceEntry.submission_id == submission_id)
    )
    return (
        tuple(row),
        newest,
        _races_fingerprint(session),
        _leaderboard_fingerprint(session),
    )


def submission_detail(
    session: Session,
    submission_id: int,
    *,
    races: int = 20,
    provisional_races: int = PROVISIONAL_RACES,
    max_age_s: float = SNAPSHOT_MAX_AGE_S,
) -> SubmissionDetail:
    """A submission with its versions, its ``races`` latest races and its rating history;
    its rank counts ``provisional_races`` as the leaderboard does. Cached under
    :func:`submission_fingerprint` (the answer is shared: never change it).

    Raises:
        NotFound: no such submission.
    """
    return cache_for(session).get(
        ("submission-detail", submission_id, races, provisional_races),
        submission_fingerprint(session, submission_id),
        lambda: _submission_detail(session, submission_id, races, provisional_races),
        max_age_s,
    )


def _submission_detail(
    session: Session, submission_id: int, races: int, provisional_races: int
) -> SubmissionDetail:
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
        **_summary(
            sub,
            author,
            active,
            versions[0].version if versions else None,
            versions[0].car if versions else None,
        ),
        description=sub.description,
        rank=submission_rank(session, sub, provisional_races=provisional_races),
        versions=[VersionInfo.model_validate(v) for v in versions],
        recent_races=submission_races(session, submission_id, per_page=races).items
        if races
        else [],
        rating_history=rating_history(session, submission_id),
        robustness=robustness_run(session, sub.active_version_id)
        if sub.active_version_id
        else None,
    )


def robustness_run(session: Session, version_id: int) -> RobustnessRun | None:
    """The latest robustness run of a version, with every grid point (None if never queued)."""
    # Through the submission's entries (their (submission, race) index): entries have no
    # index on the version, and SQLite scanned all of them (11 ms at 100,000 races).
    submission_id = session.scalar(
        select(SubmissionVersion.submission_id).where(SubmissionVersion.id == version_id)
    )
    row = session.execute(
        select(Race, SubmissionVersion.version)
        .join(RaceEntry, RaceEntry.race_id == Race.id)
        .join(SubmissionVersion, SubmissionVersion.id == RaceEntry.version_id)
        .where(
            RaceEntry.submission_id == submission_id,
            RaceEntry.version_id == version_id,
            Race.kind == "robustness",
        )
        .order_by(Race.id.desc())
        .limit(1)
    ).first()
    if row is None:
        return None
    race, version = row
    doc = race.result or {}
    car = (doc.get("cars") or [{}])[0]
    return RobustnessRun(
        race_id=race.id,
        version=version,
        status=race.status,
        track=race.track,
        car=race.car,
        laps=race.laps,
        seed=race.seed,
        score=doc.get("score"),
        nominal=doc.get("nominal"),
        mean=doc.get("mean"),
        worst=doc.get("worst"),
        worst_over_nominal=doc.get("worst_over_nominal"),
        dnf_reason=car.get("dnf_reason"),
        points=[RobustPoint.model_validate(p) for p in doc.get("points", [])],
        error=race.error,
        finished_at=race.finished_at,
    )


def rating_history(session: Session, submission_id: int) -> list[RatingPoint]:
    """A submission's rating after each of its ranked races, oldest first."""
    columns = [RatingHistory.__table__.c[name] for name in RatingPoint.model_fields]
    rows = session.execute(  # plain rows: one per race, often hundreds
        select(*columns)
        .where(RatingHistory.submission_id == submission_id)
        .order_by(RatingHistory.id)
    )
    return [RatingPoint.model_validate(r) for r in rows]


# ---- races -----------------------------------------------------------------------------------


def _race_fields(race: Any, entries: Sequence[Any]) -> dict[str, Any]:
    """A :class:`RaceSummary`'s fields: ``race`` has the race's columns as attributes (a
    :class:`Race`, or a row read by :func:`_race_summaries`), ``entries`` its cars (objects
    with ``position``, ``status``, ``name``, ``submission_id``)."""
    winner = next((e for e in entries if e.position == 1 and e.status == "finished"), None)
    return {
        **{name: getattr(race, name) for name in _SUMMARY_COLUMNS},
        "n_cars": len(entries),
        "winner": winner.name if winner else None,
        "winner_submission_id": winner.submission_id if winner else None,
    }


# The RaceSummary fields stored as they are in the races table (the rest come from the cars).
_SUMMARY_COLUMNS = tuple(name for name in RaceSummary.model_fields if name in Race.__table__.c)


def _race_summaries(session: Session, ids_stmt: Select[Any]) -> list[RaceSummary]:
    """Summaries of the races whose ids ``ids_stmt`` selects, in its order.

    Plain rows, not ORM objects: a list page reads 50 races and their ~250 cars, and building
    objects with every column (JSON decoded) was most of its time (issue 13)."""
    ids = list(session.scalars(ids_stmt))
    if not ids:
        return []
    columns = [Race.__table__.c[name] for name in _SUMMARY_COLUMNS]
    rows = {row.id: row for row in session.execute(select(*columns).where(Race.id.in_(ids)))}
    cars: dict[int, list[Any]] = {race_id: [] for race_id in ids}
    for car in session.execute(
        select(
            RaceEntry.race_id,
            RaceEntry.position,
            RaceEntry.status,
            RaceEntry.name,
            RaceEntry.submission_id,
        ).where(RaceEntry.race_id.in_(ids))
    ):
        cars[car.race_id].append(car)
    return [RaceSummary(**_race_fields(rows[i], cars[i])) for i in ids if i in rows]


def races(
    session: Session,
    *,
    page: int = 1,
    per_page: int = 50,
    track: str | None = None,
    status: str | None = None,
    kind: str | None = None,
    submission_id: int | None = None,
) -> Page[RaceSummary]:
    """Races, newest first; optionally of one track, status, kind or submission."""
    page, per_page = _clamp(page, per_page)
    # Robustness runs are queued as races but are not races: listed only when asked for.
    where: list[ColumnElement[bool]] = [] if kind else [Race.kind != "robustness"]
    if submission_id is not None:
        where.append(
            Race.id.in_(select(RaceEntry.race_id).where(RaceEntry.submission_id == submission_id))
        )
    if track:
        where.append(Race.track == track)
    if status:
        where.append(Race.status == status)
    if kind:
        where.append(Race.kind == kind)
    count = select(func.count(Race.id)).where(*where)
    if status or submission_id is not None:
        total = _count(session, count)
    else:  # only new races change these counts: cached until the newest race id moves (H13)
        total = cache_for(session).get(
            ("race-count", track, kind),
            session.scalar(select(func.max(Race.id))),
            lambda: _count(session, count),
            SNAPSHOT_MAX_AGE_S,
        )
    items = _race_summaries(
        session,
        select(Race.id)
        .where(*where)
        .order_by(Race.id.desc())
        .offset((page - 1) * per_page)
        .limit(per_page),
    )
    return Page(items=items, total=total, page=page, per_page=per_page)


def submission_races(
    session: Session, submission_id: int, *, page: int = 1, per_page: int = 20
) -> Page[RaceSummary]:
    """The races a submission took part in, newest first (robustness runs left out)."""
    page, per_page = _clamp(page, per_page)
    mine = (RaceEntry.submission_id == submission_id) & ~RaceEntry.race_id.in_(_robustness_ids())
    total = _count(session, select(func.count(RaceEntry.id)).where(mine))
    items = _race_summaries(
        session,
        select(RaceEntry.race_id)
        .where(mine)
        .order_by(RaceEntry.race_id.desc())
        .offset((page - 1) * per_page)
        .limit(per_page),
    )
    return Page(items=items, total=total, page=page, per_page=per_page)


def _robustness_ids() -> Select[Any]:
    """The ids of robustness runs (races of kind ``robustness``)."""
    return select(Race.id).where(Race.kind == "robustness")


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
    events = race.events or []
    items = penalties(events, ranked=race.penalties)
    entries = [
        EntryInfo(
            car=e.car,
            race_time=e.race_time,
            penalties=e.penalties,
            penalty_items=items.get(f"car_{e.car}", []),
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
        **_race_fields(race, race.entries),
        entries=entries,
        duration_s=race.duration_s,
        sandbox=race.sandbox,
        error=race.error,
        viser_url=f"/replays/{Path(race.viser_path).name}" if race.viser_path else None,
        replay_url=f"/replays/{Path(race.replay_path).name}" if race.replay_path else None,
        penalties=race.penalties,
        events=timeline(events, {f"car_{e.car}": e.name for e in race.entries}),
    )


class CarLog(_Model):
    """What only a car's owner sees of one race (``GET /api/races/{id}/logs``)."""

    race_id: int
    car: int
    name: str
    submission_id: int
    status: str | None
    dnf_reason: str | None
    dnf_detail: str | None  # the traceback or error text, at most 4 KiB
    output: str | None  # the kept head and tail of the policy's stdout/stderr
    sandbox_mode: str | None  # bwrap | seccomp


def race_logs(
    session: Session, race_id: int, *, user_id: int, submission_id: int | None = None
) -> list[CarLog]:
    """The logs of ``user_id``'s cars in a race (optionally of one submission only).

    Raises:
        NotFound: no such race.
    """
    race = session.get(Race, race_id)
    if race is None:
        raise NotFound(f"no race {race_id}")
    where = [RaceEntry.race_id == race_id, Submission.user_id == user_id]
    if submission_id is not None:
        where.append(RaceEntry.submission_id == submission_id)
    rows = session.execute(
        select(RaceEntry, RaceLog)
        .join(Submission, Submission.id == RaceEntry.submission_id)
        .outerjoin(RaceLog, (RaceLog.race_id == RaceEntry.race_id) & (RaceLog.car == RaceEntry.car))
        .where(*where)
        .order_by(RaceEntry.car)
    ).all()
    return [
        CarLog(
            race_id=race_id,
            car=entry.car,
            name=entry.name,
            submission_id=entry.submission_id or 0,  # joined on it: never None here
            status=entry.status,
            dnf_reason=entry.dnf_reason,
            dnf_detail=log.dnf_detail if log else None,
            output=log.output if log else None,
            sandbox_mode=log.sandbox_mode if log else race.sandbox,
        )
        for entry, log in rows
    ]


class MyRace(_Model):
    """One race from a submission's point of view (its submission page's races table)."""

    race_id: int
    kind: str
    status: str
    track: str
    n_cars: int
    position: int | None
    car_status: str | None
    dnf_reason: str | None
    best_lap: float | None
    total_time: float | None
    penalties: float | None
    mu_change: float | None  # μ after − μ before (ranked races)
    sigma_change: float | None  # σ after − σ before
    finished_at: datetime | None


class TrackBest(_Model):
    """A submission's best lap on one track, and the race it was driven in."""

    track: str
    best_lap: float
    race_id: int


class HeadToHead(_Model):
    """A submission's record against another one in the ranked races they both drove.

    ``wins``: finished ahead of it; ``losses``: behind; ``draws``: neither finished.
    """

    submission_id: int
    name: str
    author: str
    races: int
    wins: int
    losses: int
    draws: int


def submission_entries(
    session: Session, submission_id: int, *, page: int = 1, per_page: int = 20
) -> Page[MyRace]:
    """A submission's races, newest first, each with its own position, penalties, best lap
    and rating change (robustness runs left out: the page shows them apart)."""
    page, per_page = _clamp(page, per_page)
    where = (RaceEntry.submission_id == submission_id) & ~RaceEntry.race_id.in_(_robustness_ids())
    total = _count(session, select(func.count(RaceEntry.id)).where(where))
    n_cars = (
        select(func.count(RaceEntry.id))
        .where(RaceEntry.race_id == Race.id)
        .correlate(Race)
        .scalar_subquery()
    )
    rows = session.execute(
        select(RaceEntry, Race, n_cars)
        .join(Race, Race.id == RaceEntry.race_id)
        .where(where)
        .order_by(Race.id.desc())
        .offset((page - 1) * per_page)
        .limit(per_page)
    ).all()

    def change(after: float | None, before: float | None) -> float | None:
        return after - before if after is not None and before is not None else None

    items = [
        MyRace(
            race_id=race.id,
            kind=race.kind,
            status=race.status,
            track=race.track,
            n_cars=int(count),
            position=e.position,
            car_status=e.status,
            dnf_reason=e.dnf_reason,
            best_lap=e.best_lap,
            total_time=e.total_time,
            penalties=e.penalties,
            mu_change=change(e.mu_after, e.mu_before),
            sigma_change=change(e.sigma_after, e.sigma_before),
            finished_at=race.finished_at,
        )
        for e, race, count in rows
    ]
    return Page(items=items, total=total, page=page, per_page=per_page)


def track_bests(session: Session, submission_id: int) -> list[TrackBest]:
    """A submission's best lap on every track it has raced ranked, by track name."""
    # The tracks it raced on first (its entries' index), then its records by the
    # (track, submission) index: records have no index on the submission alone, and a scan of
    # every record cost PostgreSQL 20 ms at 100,000 races (issue 13).
    raced = list(
        session.scalars(
            select(Race.track)
            .join(RaceEntry, RaceEntry.race_id == Race.id)
            .where(RaceEntry.submission_id == submission_id)
            .distinct()
        )
    )
    if not raced:
        return []
    rows = session.scalars(
        select(TrackRecord)
        .where(TrackRecord.track.in_(raced), TrackRecord.submission_id == submission_id)
        .order_by(TrackRecord.track)
    )
    return [TrackBest(track=r.track, best_lap=r.best_lap, race_id=r.race_id) for r in rows]


def head_to_head(
    session: Session,
    submission_id: int,
    *,
    races: int = 2000,
    max_age_s: float = SNAPSHOT_MAX_AGE_S,
) -> list[HeadToHead]:
    """The submission's record against each submission it met in its latest ``races`` finished
    ranked races, most-met first (a DNF is behind every finisher; two DNFs draw).

    Cached under the submission's rated race count, which every finished ranked race it
    drives moves (and nothing else changes the record)."""
    rated = session.scalar(select(Submission.races).where(Submission.id == submission_id))
    return cache_for(session).get(
        ("head-to-head", submission_id, races),
        rated,
        lambda: _head_to_head(session, submission_id, races),
        max_age_s,
    )


def _head_to_head(session: Session, submission_id: int, races: int) -> list[HeadToHead]:
    # Driven from the submission's own entries (their index), newest first, a chunk at a time:
    # joined in one query, SQLite walked every finished ranked race (its (kind, status)
    # index) looking for the submission's, 150 ms at 100,000 races (issue 13).
    entries = session.execute(
        select(RaceEntry.race_id, RaceEntry.status, RaceEntry.position)
        .where(RaceEntry.submission_id == submission_id)
        .order_by(RaceEntry.race_id.desc())
    ).all()
    mine: dict[int, tuple[str | None, int | None]] = {}
    for start in range(0, len(entries), _IN_CHUNK):
        chunk = {e.race_id: (e.status, e.position) for e in entries[start : start + _IN_CHUNK]}
        # Kind and status tested here: in SQL, SQLite would scan its (kind, status) index.
        for race_id, kind, status in session.execute(
            select(Race.id, Race.kind, Race.status).where(Race.id.in_(chunk))
        ):
            if kind == "ranked" and status == "finished":
                mine[race_id] = chunk[race_id]
        if len(mine) >= races:
            break
    kept = sorted(mine, reverse=True)[:races]
    rows: list[tuple[int, str | None, int | None, str | None, int | None]] = []
    for start in range(0, len(kept), _IN_CHUNK):
        for other, o_status, o_pos, race_id in session.execute(
            select(
                RaceEntry.submission_id, RaceEntry.status, RaceEntry.position, RaceEntry.race_id
            ).where(
                RaceEntry.race_id.in_(kept[start : start + _IN_CHUNK]),
                RaceEntry.submission_id.is_not(None),
                RaceEntry.submission_id != submission_id,
            )
        ):
            rows.append((other or 0, o_status, o_pos, *mine[race_id]))  # never None here
    record: dict[int, list[int]] = {}
    for other, o_status, o_pos, m_status, m_pos in rows:
        w_l_d = record.setdefault(other, [0, 0, 0])
        m_done, o_done = m_status == "finished", o_status == "finished"
        if not m_done and not o_done:
            w_l_d[2] += 1
        elif m_done and (not o_done or (m_pos or 0) < (o_pos or 0)):
            w_l_d[0] += 1
        else:
            w_l_d[1] += 1
    names = {
        sid: (name, author)
        for sid, name, author in session.execute(
            select(Submission.id, Submission.name, User.name)
            .join(User, User.id == Submission.user_id)
            .where(Submission.id.in_(record))
        ).all()
    }
    out = [
        HeadToHead(
            submission_id=sid,
            name=names.get(sid, ("?", "?"))[0],
            author=names.get(sid, ("?", "?"))[1],
            races=sum(wld),
            wins=wld[0],
            losses=wld[1],
            draws=wld[2],
        )
        for sid, wld in record.items()
    ]
    return sorted(out, key=lambda h: (-h.races, h.name))


def validation_races(session: Session, submission_id: int) -> dict[int, int]:
    """Version number → the id of its latest validation race."""
    rows = session.execute(
        select(SubmissionVersion.version, func.max(Race.id))
        .join(RaceEntry, RaceEntry.version_id == SubmissionVersion.id)
        .join(Race, Race.id == RaceEntry.race_id)
        .where(SubmissionVersion.submission_id == submission_id, Race.kind == "validation")
        .group_by(SubmissionVersion.version)
    ).all()
    return {int(v): int(r) for v, r in rows}


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


def _tracks_fingerprint(session: Session) -> tuple[Any, ...]:
    """What changes when a race finishes or a record falls (two index look-ups)."""
    return (
        session.scalar(select(func.max(Race.finished_at))),
        session.scalar(select(func.max(TrackRecord.set_at))),
    )


def tracks(
    session: Session, names: Sequence[str], *, max_age_s: float = SNAPSHOT_MAX_AGE_S
) -> list[TrackSummary]:
    """Each named track with its finished ranked race count and lap record (cached)."""
    return cache_for(session).get(
        ("tracks", tuple(names)),
        _tracks_fingerprint(session),
        lambda: _tracks(session, names),
        max_age_s,
    )


def _tracks(session: Session, names: Sequence[str]) -> list[TrackSummary]:
    counts = dict(
        session.execute(
            select(Race.track, func.count(Race.id))
            .where(Race.kind == "ranked", Race.status == "finished", Race.track.in_(names))
            .group_by(Race.track)
        ).all()
    )
    out = []
    for name in names:
        # The track's fastest record: one look-up in the (track, best_lap) index.
        best = session.execute(
            select(TrackRecord.best_lap, Submission.name)
            .join(Submission, Submission.id == TrackRecord.submission_id)
            .where(TrackRecord.track == name)
            .order_by(TrackRecord.best_lap, TrackRecord.id)
            .limit(1)
        ).first()
        out.append(
            TrackSummary(
                name=name,
                races=int(counts.get(name, 0)),
                record=best[0] if best else None,
                record_holder=best[1] if best else None,
            )
        )
    return out


def track_detail(
    session: Session,
    name: str,
    *,
    known: Sequence[str] | None = None,
    limit: int = 20,
    max_age_s: float = SNAPSHOT_MAX_AGE_S,
) -> TrackDetail:
    """A track's records and recent ranked races; ``known`` lists the valid track names.

    Raises:
        NotFound: ``name`` is not in ``known`` and no ranked race was run on it.
    """
    return cache_for(session).get(
        ("track", name, limit, tuple(known) if known is not None else None),
        _tracks_fingerprint(session),
        lambda: _track_detail(session, name, known, limit),
        max_age_s,
    )


def track_was_raced(session: Session, name: str) -> bool:
    """Whether any race (any kind or status) is on track ``name`` (one index look-up)."""
    return session.scalar(select(Race.id).where(Race.track == name).limit(1)) is not None


def _track_detail(
    session: Session, name: str, known: Sequence[str] | None, limit: int
) -> TrackDetail:
    recent = races(session, track=name, status="finished", kind="ranked", per_page=limit)
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
