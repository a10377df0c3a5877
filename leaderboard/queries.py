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
from sqlalchemy import ColumnElement, Select, bindparam, case, func, select
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


def _ladder_state(submissions: Any) -> list[Any]:
    """What changes whenever the leaderboard can, as scalar subqueries over ``submissions``
    (the table or an alias): every writer bumps ``updated_at`` (its latest: an index
    look-up); the active count also catches a status changed by hand (an index scan)."""
    return [
        select(func.max(submissions.c.updated_at)).scalar_subquery(),
        select(func.count())
        .select_from(submissions)
        .where(submissions.c.status == "active")
        .scalar_subquery(),
    ]


_LEADERBOARD_FINGERPRINT = select(*_ladder_state(Submission.__table__))


def _leaderboard_fingerprint(session: Session) -> tuple[Any, ...]:
    """:func:`_ladder_state`, read: ``(latest updated_at, active submissions)``."""
    return tuple(session.execute(_LEADERBOARD_FINGERPRINT).one())


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
    sub: Any, author: str, version: int | None, latest: int | None, car: str | None
) -> dict[str, Any]:
    """A :class:`SubmissionSummary`'s fields; ``sub``: a :class:`Submission` or a row with
    its columns."""
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
    car = session.scalar(
        select(SubmissionVersion.car).where(SubmissionVersion.id == sub.active_version_id)
    )
    return _rank(session, sub.id, sub.status, car, provisional_races, SNAPSHOT_MAX_AGE_S, None)


def _rank(
    session: Session,
    submission_id: int,
    status: str,
    car: str | None,
    provisional_races: int,
    max_age_s: float,
    ladder: tuple[Any, ...] | None,
) -> int | None:
    """:func:`submission_rank` of a submission in ``status`` racing a ``car``; ``ladder``:
    the :func:`_leaderboard_fingerprint` if the caller has read it."""
    if status != "active":
        return None
    if ladder is None:
        ladder = _leaderboard_fingerprint(session)
    ranks = _ladder_ranks(session, car or DEFAULT_CAR, provisional_races, max_age_s, ladder)
    return ranks.get(submission_id)


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
    return _ladder_ranks(
        session, car, provisional_races, max_age_s, _leaderboard_fingerprint(session)
    )


def _ladder_ranks(
    session: Session,
    car: str,
    provisional_races: int,
    max_age_s: float,
    fingerprint: tuple[Any, ...],
) -> dict[int, int]:
    """:func:`ladder_ranks` under a :func:`_leaderboard_fingerprint` already read."""

    def compute() -> dict[int, int]:
        ids = session.scalars(
            select(Submission.id)
            .join(SubmissionVersion, SubmissionVersion.id == Submission.active_version_id)
            .where(Submission.status == "active", SubmissionVersion.car == car)
            .order_by(_provisional(provisional_races), Submission.ordinal.desc(), Submission.id)
        )
        return {sub_id: rank for rank, sub_id in enumerate(ids, start=1)}

    return cache_for(session).get(
        ("ladder-ranks", car, provisional_races), fingerprint, compute, max_age_s
    )


# ---- one submission: its page and /api/submissions/{id} ---------------------------------------
# A first view of a submission ran ~25 statements, and building a statement costs SQLAlchemy
# 0.1-0.3 ms (more than most of these take to run): so they are built once, here, with bound
# parameters, over Core columns (plain tuples back, no ORM objects or result machinery), and
# each section is one statement (issue 13).

_SUB = Submission.__table__.c
_VER = SubmissionVersion.__table__.c
_RACE = Race.__table__.c
_ENTRY = RaceEntry.__table__.c
_USER = User.__table__.c
_HIST = RatingHistory.__table__.c
_REC = TrackRecord.__table__.c


def _sid() -> Any:
    """The ``:submission_id`` parameter of the statements below."""
    return bindparam("submission_id")


def _fingerprint_stmt() -> Select[Any]:
    others = Submission.__table__.alias("others")  # every submission, not the one viewed
    races = Race.__table__

    def count_races(status: str) -> Any:
        return select(func.count()).select_from(races).where(_RACE.status == status)

    return select(
        # Its row: every writer of its rating, versions, status or robustness score bumps
        # updated_at; name and description are compared too, for edits by hand.
        _SUB.updated_at,
        _SUB.races,
        _SUB.status,
        _SUB.active_version_id,
        _SUB.name,
        _SUB.description,
        # Its newest race (a race queued with it).
        select(func.max(_ENTRY.race_id)).where(_ENTRY.submission_id == _SUB.id).scalar_subquery(),
        # Every race's state: its races starting, finishing, failing or handed back.
        select(func.max(_RACE.id)).scalar_subquery(),
        select(func.max(_RACE.finished_at)).scalar_subquery(),
        count_races("queued").scalar_subquery(),
        count_races("running").scalar_subquery(),
        # The ladder (its rank).
        *_ladder_state(others),
    ).where(_SUB.id == _sid())


_FINGERPRINT = _fingerprint_stmt()


def submission_fingerprint(session: Session, submission_id: int) -> tuple[Any, ...]:
    """What a submission's detail and page are computed from changes whenever this does.

    Its own row (every writer of its rating, versions, status or robustness score bumps
    ``updated_at``; its name and description are compared too, for edits by hand), its
    newest race (a race queued with it), the state of every race (the newest id, the latest
    finish, how many wait and run: its races starting, finishing or failing) and the ladder
    (its rank; the last item, as :func:`_leaderboard_fingerprint` reads it): one statement of
    index look-ups instead of the ~15 ms of queries the page costs (issue 13).

    Raises:
        NotFound: no such submission.
    """
    row = session.execute(_FINGERPRINT, {"submission_id": submission_id}).first()
    if row is None:
        raise NotFound(f"no submission {submission_id}")
    return tuple(row[:6]), row[6], tuple(row[7:11]), tuple(row[11:13])


def submission_detail(
    session: Session,
    submission_id: int,
    *,
    races: int = 20,
    provisional_races: int = PROVISIONAL_RACES,
    max_age_s: float = SNAPSHOT_MAX_AGE_S,
    fingerprint: tuple[Any, ...] | None = None,
    cache: bool = True,
) -> SubmissionDetail:
    """A submission with its versions, its ``races`` latest races and its rating history;
    its rank counts ``provisional_races`` as the leaderboard does. Cached under
    :func:`submission_fingerprint` (the answer is shared: never change it); ``fingerprint``:
    that fingerprint, if the caller has just read it; ``cache=False``: computed, not kept (for
    callers that cache what they make of it: one snapshot per view, not two).

    Raises:
        NotFound: no such submission.
    """
    if fingerprint is None:
        fingerprint = submission_fingerprint(session, submission_id)
    ladder = fingerprint[-1]

    def compute() -> SubmissionDetail:
        return _submission_detail(
            session, submission_id, races, provisional_races, max_age_s, ladder
        )

    if not cache:
        return compute()
    return cache_for(session).get(
        ("submission-detail", submission_id, races, provisional_races),
        fingerprint,
        compute,
        max_age_s,
    )


_HEAD_COLUMNS = (
    *("id", "name", "description", "status", "active_version_id"),
    *("mu", "sigma", "ordinal", "races", "wins", "created_at"),
)
_RUN_COLUMNS = ("id", "status", "track", "car", "laps", "seed", "result", "error", "finished_at")
_VERSION_COLUMNS = ("id", "submission_id", *VersionInfo.model_fields)


def _head_stmt() -> Select[Any]:
    racing = SubmissionVersion.__table__.alias("racing")  # its active version (or, by hand,
    run = Race.__table__.alias("run")  # another's) and that version's latest robustness run
    runs, run_entries = Race.__table__.alias("runs"), RaceEntry.__table__.alias("run_entries")
    # Found through the version's entries (ix_entries_version_id, 0007: before it SQLite
    # scanned every entry, 11 ms at 100,000 races).
    latest_run = (
        select(func.max(runs.c.id))
        .select_from(run_entries.join(runs, runs.c.id == run_entries.c.race_id))
        .where(
            run_entries.c.submission_id == racing.c.submission_id,
            run_entries.c.version_id == racing.c.id,
            runs.c.kind == "robustness",
        )
        .correlate(racing)
        .scalar_subquery()
    )
    return (
        select(
            *(_SUB[name] for name in _HEAD_COLUMNS),
            _USER.name,
            racing.c.car,
            racing.c.submission_id,
            racing.c.version,
            *(run.c[name] for name in _RUN_COLUMNS),
            *(_VER[name] for name in _VERSION_COLUMNS),
        )
        .select_from(
            Submission.__table__.outerjoin(User.__table__, _USER.id == _SUB.user_id)
            .outerjoin(racing, racing.c.id == _SUB.active_version_id)
            .outerjoin(run, run.c.id == latest_run)
            .outerjoin(SubmissionVersion.__table__, _VER.submission_id == _SUB.id)
        )
        .where(_SUB.id == _sid())
        .order_by(_VER.version.desc())
    )


# The submission; its author; its racing version's car, submission and number; that
# version's robustness run; then its own versions, newest first: a row per version (one,
# with None there, before its first upload). One statement: on PostgreSQL each round trip
# cost 0.5-3 ms on the loaded machine.
_HEAD = _head_stmt()


def _submission_detail(
    session: Session,
    submission_id: int,
    races: int,
    provisional_races: int,
    max_age_s: float = SNAPSHOT_MAX_AGE_S,
    ladder: tuple[Any, ...] | None = None,
) -> SubmissionDetail:
    """The detail, computed; ``ladder``: the :func:`_leaderboard_fingerprint` if read."""
    rows = session.execute(_HEAD, {"submission_id": submission_id}).all()
    if not rows:
        raise NotFound(f"no submission {submission_id}")
    sub = rows[0]
    author, car, _owner, racing_version, *run = sub[len(_HEAD_COLUMNS) : -len(_VERSION_COLUMNS)]
    versions = [
        dict(zip(_VERSION_COLUMNS, row[-len(_VERSION_COLUMNS) :], strict=True)) for row in rows
    ]
    versions = [v for v in versions if v["id"] is not None]
    active = next((v for v in versions if v["id"] == sub.active_version_id), None)
    rank = _rank(session, sub.id, sub.status, car, provisional_races, max_age_s, ladder)
    return SubmissionDetail(
        **_summary(
            sub,
            author or "",
            active["version"] if active else None,
            versions[0]["version"] if versions else None,
            versions[0]["car"] if versions else None,
        ),
        description=sub.description,
        rank=rank,
        versions=[VersionInfo.model_validate(v) for v in versions],
        recent_races=_recent_races(session, submission_id, races) if races else [],
        rating_history=rating_history(session, submission_id),
        robustness=_robustness(dict(zip(_RUN_COLUMNS, run, strict=True)), racing_version),
    )


def _robustness(run: dict[str, Any], version: int | None) -> RobustnessRun | None:
    """A robustness run of version ``version`` from its race's :data:`_RUN_COLUMNS` (None
    if there is none: its id None)."""
    if run["id"] is None or version is None:
        return None
    doc = run["result"] or {}
    car = (doc.get("cars") or [{}])[0]
    return RobustnessRun(
        race_id=run["id"],
        version=version,
        status=run["status"],
        track=run["track"],
        car=run["car"],
        laps=run["laps"],
        seed=run["seed"],
        score=doc.get("score"),
        nominal=doc.get("nominal"),
        mean=doc.get("mean"),
        worst=doc.get("worst"),
        worst_over_nominal=doc.get("worst_over_nominal"),
        dnf_reason=car.get("dnf_reason"),
        points=[RobustPoint.model_validate(p) for p in doc.get("points", [])],
        error=run["error"],
        finished_at=run["finished_at"],
    )


_RATING_HISTORY = (
    select(_HIST.race_id, _HIST.mu, _HIST.sigma, _HIST.ordinal, _HIST.created_at)
    .where(_HIST.submission_id == _sid())
    .order_by(_HIST.id)
)


def rating_history(session: Session, submission_id: int) -> list[RatingPoint]:
    """A submission's rating after each of its ranked races, oldest first."""
    rows = session.execute(_RATING_HISTORY, {"submission_id": submission_id}).all()
    return [  # one per race, often hundreds: tuples unpacked, keywords (the fastest way in)
        RatingPoint(race_id=race, mu=mu, sigma=sigma, ordinal=ordinal, created_at=at)
        for race, mu, sigma, ordinal, at in rows
    ]


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
    rows = {row.id: row for row in session.execute(_RACE_ROWS, {"ids": ids})}
    return _summaries(session, [rows[i] for i in ids if i in rows])


_SUMMARY = tuple(_RACE[name] for name in _SUMMARY_COLUMNS)
_RACE_ROWS = select(*_SUMMARY).where(_RACE.id.in_(bindparam("ids", expanding=True)))
_RACE_CARS = select(
    _ENTRY.race_id, _ENTRY.position, _ENTRY.status, _ENTRY.name, _ENTRY.submission_id
).where(_ENTRY.race_id.in_(bindparam("ids", expanding=True)))


def _summaries(session: Session, rows: Sequence[Any]) -> list[RaceSummary]:
    """Summaries of races, in order: ``rows`` have the :data:`_SUMMARY_COLUMNS`."""
    if not rows:
        return []
    cars: dict[int, list[Any]] = {row.id: [] for row in rows}
    for car in session.execute(_RACE_CARS, {"ids": list(cars)}).all():
        cars[car.race_id].append(car)
    return [RaceSummary(**_race_fields(row, cars[row.id])) for row in rows]


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


def _robustness_ids() -> Select[Any]:
    """The ids of robustness runs (races of kind ``robustness``)."""
    return select(_RACE.id).where(_RACE.kind == "robustness")


def _mine(entries: Any = _ENTRY) -> ColumnElement[bool]:
    """A submission's (``:submission_id``) cars in ``entries``, robustness runs left out."""
    return (entries.submission_id == _sid()) & ~entries.race_id.in_(_robustness_ids())


_MY_COUNT = select(func.count(_ENTRY.id)).where(_mine())
_MY_RACES = (
    select(*_SUMMARY)
    .select_from(RaceEntry.__table__.join(Race.__table__, _RACE.id == _ENTRY.race_id))
    .where(_mine())
    .order_by(_ENTRY.race_id.desc())
    .offset(bindparam("offset"))
    .limit(bindparam("limit"))
)


def submission_races(
    session: Session, submission_id: int, *, page: int = 1, per_page: int = 20
) -> Page[RaceSummary]:
    """The races a submission took part in, newest first (robustness runs left out)."""
    page, per_page = _clamp(page, per_page)
    total = int(session.scalar(_MY_COUNT, {"submission_id": submission_id}) or 0)
    items = _recent_races(session, submission_id, per_page, (page - 1) * per_page)
    return Page(items=items, total=total, page=page, per_page=per_page)


def _recent_races(
    session: Session, submission_id: int, limit: int, offset: int = 0
) -> list[RaceSummary]:
    """:func:`submission_races`' items without their count (the detail needs no pager)."""
    params = {"submission_id": submission_id, "offset": offset, "limit": _clamp(1, limit)[1]}
    return _summaries(session, session.execute(_MY_RACES, params).all())


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


def _my_entries_stmt() -> Select[Any]:
    others = RaceEntry.__table__.alias("others")  # the race's cars, not correlated to ours
    n_cars = (
        select(func.count(others.c.id))
        .where(others.c.race_id == _RACE.id)
        .correlate(Race.__table__)
        .scalar_subquery()
    )
    return (
        select(  # in MyRace's order (unpacked so), then the ratings before and after
            *(_RACE[name] for name in ("id", "kind", "status", "track")),
            n_cars,
            _ENTRY.position,
            _ENTRY.status,
            *(_ENTRY[name] for name in ("dnf_reason", "best_lap", "total_time", "penalties")),
            _RACE.finished_at,
            *(_ENTRY[name] for name in ("mu_before", "mu_after", "sigma_before", "sigma_after")),
            _MY_COUNT.scalar_subquery(),  # the pager's total, with the rows (one round trip)
        )
        .select_from(RaceEntry.__table__.join(Race.__table__, _RACE.id == _ENTRY.race_id))
        .where(_mine())
        .order_by(_ENTRY.race_id.desc())  # its index's order: no sort of all its races
        .offset(bindparam("offset"))
        .limit(bindparam("limit"))
    )


_MY_ENTRIES = _my_entries_stmt()


def submission_entries(
    session: Session, submission_id: int, *, page: int = 1, per_page: int = 20
) -> Page[MyRace]:
    """A submission's races, newest first, each with its own position, penalties, best lap
    and rating change (robustness runs left out: the page shows them apart)."""
    page, per_page = _clamp(page, per_page)
    params = {"submission_id": submission_id, "offset": (page - 1) * per_page, "limit": per_page}
    rows = session.execute(_MY_ENTRIES, params).all()
    if rows:
        total = int(rows[0][-1])
    else:  # none on this page: none at all on the first, else counted apart
        total = int(session.scalar(_MY_COUNT, params) or 0) if page > 1 else 0

    def change(after: float | None, before: float | None) -> float | None:
        return after - before if after is not None and before is not None else None

    items = [
        MyRace(
            race_id=race_id,
            kind=kind,
            status=status,
            track=track,
            n_cars=int(n_cars),
            position=position,
            car_status=car_status,
            dnf_reason=dnf_reason,
            best_lap=best_lap,
            total_time=total_time,
            penalties=penalties,
            mu_change=change(mu_after, mu_before),
            sigma_change=change(sigma_after, sigma_before),
            finished_at=finished_at,
        )
        for (
            race_id,
            kind,
            status,
            track,
            n_cars,
            position,
            car_status,
            dnf_reason,
            best_lap,
            total_time,
            penalties,
            finished_at,
            mu_before,
            mu_after,
            sigma_before,
            sigma_after,
            _total,
        ) in rows
    ]
    return Page(items=items, total=total, page=page, per_page=per_page)


# Its records by the submission's index (0007). Every record is set by a ranked race it drove,
# so these are the tracks it has raced ranked.
_TRACK_BESTS = (
    select(_REC.track, _REC.best_lap, _REC.race_id)
    .where(_REC.submission_id == _sid())
    .order_by(_REC.track)
)


def track_bests(session: Session, submission_id: int) -> list[TrackBest]:
    """A submission's best lap on every track it has raced ranked, by track name."""
    rows = session.execute(_TRACK_BESTS, {"submission_id": submission_id})
    return [TrackBest(track=r.track, best_lap=r.best_lap, race_id=r.race_id) for r in rows]


def head_to_head(
    session: Session,
    submission_id: int,
    *,
    races: int = 2000,
    max_age_s: float = SNAPSHOT_MAX_AGE_S,
    rated: int | None = None,
) -> list[HeadToHead]:
    """The submission's record against each submission it met in its latest ``races`` finished
    ranked races, most-met first (a DNF is behind every finisher; two DNFs draw).

    Cached under the submission's rated race count, which every finished ranked race it
    drives moves (and nothing else changes the record); ``rated``: that count, if the caller
    has just read it."""
    if rated is None:
        rated = session.scalar(select(_SUB.races).where(_SUB.id == submission_id))
    return cache_for(session).get(
        ("head-to-head", submission_id, races),
        rated,
        lambda: _head_to_head(session, submission_id, races),
        max_age_s,
    )


def _head_to_head_stmt() -> Select[Any]:
    me, them = RaceEntry.__table__.alias("me"), RaceEntry.__table__.alias("them")
    races = Race.__table__.alias("r")
    # Its latest finished ranked races, from its own entries (their (submission, race) index,
    # newest first, which the LIMIT makes the way in), each race tested by its key: not
    # through the (kind, status) index (SQLite walked every finished ranked race: 150 ms).
    mine = (
        select(me.c.race_id, me.c.status, me.c.position)
        .select_from(me.join(races, races.c.id == me.c.race_id))
        .where(me.c.submission_id == _sid(), races.c.kind == "ranked", races.c.status == "finished")
        .order_by(me.c.race_id.desc())
        .limit(bindparam("races"))
        .subquery("mine")
    )
    done_me = func.coalesce(mine.c.status, "") == "finished"
    done_them = func.coalesce(them.c.status, "") == "finished"
    ahead = done_me & (
        ~done_them | (func.coalesce(mine.c.position, 0) < func.coalesce(them.c.position, 0))
    )
    # Names joined before grouping, by key, ~200 look-ups: joined to the ~200 groups after,
    # PostgreSQL hashed all 10,000 submissions (3.1 ms of server time against 2.1).
    return (
        select(
            them.c.submission_id,
            func.count(),
            func.sum(case((ahead, 1), else_=0)),
            func.sum(case((~done_me & ~done_them, 1), else_=0)),  # draws
            func.min(_SUB.name),  # its one name
            func.min(_USER.name),  # its author's
        )
        .select_from(
            mine.join(them, them.c.race_id == mine.c.race_id)
            .outerjoin(Submission.__table__, _SUB.id == them.c.submission_id)
            .outerjoin(User.__table__, _USER.id == _SUB.user_id)
        )
        .where(them.c.submission_id.is_not(None), them.c.submission_id != _sid())
        .group_by(them.c.submission_id)
    )


_HEAD_TO_HEAD = _head_to_head_stmt()


def _head_to_head(session: Session, submission_id: int, races: int) -> list[HeadToHead]:
    # One aggregate in SQL: per opponent met in those races, the races, wins and draws.
    # Rows unpacked as tuples: a Row's attributes cost ~1 us each, on ~200 opponents.
    rows = session.execute(_HEAD_TO_HEAD, {"submission_id": submission_id, "races": races})
    out = [
        HeadToHead(
            submission_id=other,
            name=name if author is not None else "?",  # its submission or user deleted
            author=author if author is not None else "?",
            races=met,
            wins=wins,
            losses=met - wins - draws,
            draws=draws,
        )
        for other, met, wins, draws, name, author in rows.all()
    ]
    # Sorted here, not in SQL: PostgreSQL's collation would order names unlike Python's.
    return sorted(out, key=lambda h: (-h.races, h.name, h.submission_id))


_VALIDATION_RACES = (
    select(_VER.version, func.max(_RACE.id))
    .select_from(
        SubmissionVersion.__table__.join(RaceEntry.__table__, _ENTRY.version_id == _VER.id).join(
            Race.__table__, _RACE.id == _ENTRY.race_id
        )
    )
    .where(_VER.submission_id == _sid(), _RACE.kind == "validation")
    .group_by(_VER.version)
)


def validation_races(session: Session, submission_id: int) -> dict[int, int]:
    """Version number → the id of its latest validation race."""
    rows = session.execute(_VALIDATION_RACES, {"submission_id": submission_id}).all()
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
