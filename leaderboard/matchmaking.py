"""Matchmaking: which submissions race, where, and when (after Kaggle and Halite III).

* A new version first gets a **validation race** (unrated): one lap on
  ``settings.validation_track`` against the ``settings.validation_opponent`` baseline. It must
  drive without a policy failure (crash, invalid action, deadline) to enter the pool.
  Validation is **fair-queued per user**: a user's first waiting validation race goes ahead of
  the ranked races (priority 0: quick feedback); while it waits, their further ones queue with
  the ranked races, in arrival order (priority 10). One user's burst of uploads therefore puts
  at most one race ahead of everyone else's, and another user's upload still jumps the queue.
* **Ranked races** then draw from the active submissions. The *seed* submission is drawn
  with weight (σ/σ₀)² / (1 + races + 2·queued): under-played and uncertain submissions race
  most, and one with races already queued waits its turn. Its opponents are drawn from the
  ones nearest in μ, within a window that is usually small and sometimes wide (Halite's
  ``5 / (0.01 + U)^0.65``), so ratings meet similar ratings without forming closed groups.
* 2–8 cars (``settings.min_cars``..``settings.max_cars``, never more than the pool), the grid
  shuffled, on the track used least in the last 200 ranked races of its car class (ties at
  random), with a fresh seed.
* **One ladder per car class.** A version drives the car its manifest declares
  (``f1tenth`` by default, or ``deepracer``: :mod:`arena.cars`); every version of a
  submission declares the same one (an upload that changes it is refused), and a race's
  entrants all come from the seed's class, so a submission only ever meets cars like its
  own. Its validation race is run with its car too.
"""

from __future__ import annotations

import random
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache
from typing import Protocol

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from leaderboard.errors import Conflict
from leaderboard.models import (
    DEFAULT_CAR,
    SIGMA0,
    Job,
    Race,
    RaceEntry,
    Submission,
    SubmissionVersion,
)
from leaderboard.queue import enqueue
from leaderboard.settings import Settings

VALIDATION_PRIORITY = 0
RANKED_PRIORITY = 10
RECENT_RACES = 200  # races looked at to vary the tracks
# Race kinds that are not the ladder's (robustness runs, tournament heats): they neither count
# as a submission's queued ladder races nor hold back the ranked top-up.
OFF_LADDER = ("robustness", "tournament")


@dataclass(frozen=True)
class Candidate:
    """An active submission as matchmaking sees it."""

    submission_id: int
    version_id: int
    name: str
    source: str
    mu: float
    sigma: float
    races: int
    queued: int
    car: str = DEFAULT_CAR

    @property
    def weight(self) -> float:
        """Seed weight: uncertain and under-played submissions first."""
        return (self.sigma / SIGMA0) ** 2 / (1 + self.races + 2 * self.queued)


class _Driver(Protocol):
    """What a race entry is made from (a :class:`Candidate`, a tournament entrant)."""

    @property
    def submission_id(self) -> int: ...
    @property
    def version_id(self) -> int | None: ...
    @property
    def name(self) -> str: ...
    @property
    def source(self) -> str: ...


def grid_entries(cars: Sequence[_Driver]) -> list[RaceEntry]:
    """A race's entries, car ``i`` = ``cars[i]`` (pole first)."""
    return [
        RaceEntry(
            car=i,
            submission_id=c.submission_id,
            version_id=c.version_id,
            name=c.name,
            source=c.source,
        )
        for i, c in enumerate(cars)
    ]


def version_entry(session: Session, version: SubmissionVersion) -> RaceEntry:
    """Car 0 of a race of one version (named ``<submission>:v<version>``)."""
    sub = session.get(Submission, version.submission_id)
    name = sub.name if sub is not None else f"submission-{version.submission_id}"
    return RaceEntry(
        car=0,
        submission_id=version.submission_id,
        version_id=version.id,
        name=f"{name}:v{version.version}",
        source=version.source,
    )


def waiting_validations(session: Session, user_id: int) -> int:
    """A user's validation races that are queued or running."""
    return int(
        session.scalar(
            select(func.count(func.distinct(Race.id)))
            .join(RaceEntry, RaceEntry.race_id == Race.id)
            .join(Submission, Submission.id == RaceEntry.submission_id)
            .where(
                Race.kind == "validation",
                Race.status.in_(("queued", "running")),
                Submission.user_id == user_id,
            )
        )
        or 0
    )


def validation_priority(session: Session, user_id: int | None) -> int:
    """Queue priority of a user's next validation race (see the module docstring)."""
    if user_id is None or waiting_validations(session, user_id) == 0:
        return VALIDATION_PRIORITY
    return RANKED_PRIORITY


def assign_car(session: Session, version: SubmissionVersion) -> str:
    """Set a new version's car class from its manifest (``car``, default ``f1tenth``).

    Raises:
        Conflict: another (not rejected) version of the submission drives another car.
    """
    car = str((version.manifest or {}).get("car") or DEFAULT_CAR)
    other = session.scalar(
        select(SubmissionVersion.car).where(
            SubmissionVersion.submission_id == version.submission_id,
            SubmissionVersion.id != version.id,
            SubmissionVersion.status != "rejected",
            SubmissionVersion.car != car,
        )
    )
    if other is not None:
        raise Conflict(
            f"this submission races the {other!r} car; a {car!r} bundle needs a submission "
            "of its own (give its manifest another name)"
        )
    version.car = car
    return car


def schedule_validation(session: Session, settings: Settings, version: SubmissionVersion) -> Race:
    """Queue the validation race of a new version (one lap against a baseline, with the
    version's car), fair-queued.

    Raises:
        Conflict: the version's car is not its submission's (:func:`assign_car`).
    """
    car = assign_car(session, version)
    sub = session.get(Submission, version.submission_id)
    priority = validation_priority(session, sub.user_id if sub is not None else None)
    race = Race(
        kind="validation",
        track=settings.validation_track,
        car=car,
        seed=random.randrange(2**31),
        laps=1,
        penalties=False,
        entries=[
            version_entry(session, version),
            RaceEntry(
                car=1,
                name=settings.validation_opponent,
                source=settings.validation_opponent,
            ),
        ],
    )
    session.add(race)
    enqueue(session, race, priority=priority, max_attempts=settings.max_attempts)
    return race


def candidates(session: Session) -> list[Candidate]:
    """Active submissions with a validated version, with their queued ladder-race counts."""
    queued = dict(
        session.execute(
            select(RaceEntry.submission_id, func.count())
            .join(Race, Race.id == RaceEntry.race_id)
            .where(
                Race.status.in_(("queued", "running")),
                Race.kind.not_in(OFF_LADDER),
                RaceEntry.submission_id.is_not(None),
            )
            .group_by(RaceEntry.submission_id)
        ).all()
    )
    rows = session.execute(
        select(Submission, SubmissionVersion)
        .join(SubmissionVersion, SubmissionVersion.id == Submission.active_version_id)
        .where(Submission.status == "active")
    ).all()
    return [
        Candidate(
            submission_id=sub.id,
            version_id=ver.id,
            name=f"{sub.name}:v{ver.version}",
            source=ver.source,
            mu=sub.mu,
            sigma=sub.sigma,
            races=sub.races,
            queued=int(queued.get(sub.id, 0)),
            car=ver.car,
        )
        for sub, ver in rows
    ]


def pick_entrants(
    pool: Sequence[Candidate], rng: random.Random, *, min_cars: int = 2, max_cars: int = 4
) -> list[Candidate]:
    """Draw one race's entrants: a seed by weight, then opponents of similar μ in its car
    class.

    Returns an empty list if no car class has ``min_cars`` submissions in the pool.
    """
    ladders: dict[str, list[Candidate]] = {}
    for c in pool:
        ladders.setdefault(c.car, []).append(c)
    eligible = [c for c in pool if len(ladders[c.car]) >= max(min_cars, 2)]
    if not eligible:
        return []
    seed = rng.choices(eligible, weights=[c.weight for c in eligible], k=1)[0]
    ladder = ladders[seed.car]
    n_cars = rng.randint(min_cars, min(max_cars, len(ladder)))
    others = sorted(
        (c for c in ladder if c.submission_id != seed.submission_id),
        key=lambda c: (abs(c.mu - seed.mu), rng.random()),
    )
    window = int(5 / (0.01 + rng.random()) ** 0.65)
    window = min(len(others), max(n_cars - 1, window))
    chosen = [seed, *rng.sample(others[:window], n_cars - 1)]
    rng.shuffle(chosen)  # the grid order
    return chosen


def pick_track(
    session: Session, tracks: Sequence[str], rng: random.Random, car: str = DEFAULT_CAR
) -> str:
    """The track used least in the last ranked races of car class ``car`` (ties broken at
    random)."""
    recent = (
        select(Race.track)
        .where(Race.kind == "ranked", Race.car == car)
        .order_by(Race.id.desc())
        .limit(RECENT_RACES)
        .subquery()
    )
    used: Counter[str] = Counter(
        dict(session.execute(select(recent.c.track, func.count()).group_by(recent.c.track)).all())
    )
    fewest = min(used.get(t, 0) for t in tracks)
    return rng.choice([t for t in tracks if used.get(t, 0) == fewest])


@cache
def library_tracks() -> tuple[str, ...]:
    """The built-in track names (read once: the library does not change while serving)."""
    from tracks import list_tracks  # noqa: PLC0415 - numpy/scipy only; loaded when scheduling

    return tuple(list_tracks())


def track_pool(settings: Settings) -> list[str]:
    """Tracks for ranked races: ``settings.tracks``, else the built-in library."""
    return list(settings.tracks or library_tracks())


def schedule_ranked(
    session: Session, settings: Settings, n_races: int, rng: random.Random | None = None
) -> list[Race]:
    """Queue up to ``n_races`` ranked races (fewer if the pool is too small)."""
    rng = rng or random.Random()
    tracks = track_pool(settings)
    races: list[Race] = []
    for _ in range(n_races):
        pool = candidates(session)
        entrants = pick_entrants(pool, rng, min_cars=settings.min_cars, max_cars=settings.max_cars)
        if not entrants:
            break
        car = entrants[0].car  # one class per race (pick_entrants)
        race = Race(
            kind="ranked",
            track=pick_track(session, tracks, rng, car),
            car=car,
            seed=rng.randrange(2**31),
            laps=settings.race_laps,
            penalties=True,
            entries=grid_entries(entrants),
        )
        session.add(race)
        enqueue(session, race, priority=RANKED_PRIORITY, max_attempts=settings.max_attempts)
        session.flush()
        races.append(race)
    return races


def ladder_pending(session: Session) -> int:
    """Jobs of the ladder (validation and ranked races) waiting or running."""
    return int(
        session.scalar(
            select(func.count(Job.id))
            .join(Race, Race.id == Job.race_id)
            .where(Job.status.in_(("queued", "leased")), Race.kind.not_in(OFF_LADDER))
        )
        or 0
    )


def top_up(
    session: Session, settings: Settings, target: int, rng: random.Random | None = None
) -> int:
    """Queue ranked races until ``target`` ladder jobs are waiting or running (robustness
    runs and tournament heats are not counted: the ladder keeps running beside them);
    returns how many."""
    missing = target - ladder_pending(session)
    if missing <= 0:
        return 0
    return len(schedule_ranked(session, settings, missing, rng))
