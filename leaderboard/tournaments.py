"""Tournaments: an operator's event beside the ladder, run by the same workers from the same
queue, unrated.

An operator defines one (:func:`create_tournament`: ``slipstream tournament create`` or
``POST /api/tournaments`` with the admin token): the entrants (submissions by id, or the
top N of a car class's ladder; each races the version that was racing when the tournament
was created), the tracks, the seeds, the laps, and the format. A **round** is one
(track, seed) pair: rounds = tracks × seeds.

=====================  =========================================================================
format                 what runs
=====================  =========================================================================
``round_robin``        every round, the entrants split into heats of at most ``heat_size`` cars
                       (balanced sizes, never a car alone: with heats of 2 and an odd field
                       one heat has 3; with N ≤ ``heat_size`` one heat of everyone); the grid
                       rotates round by round and, with several heats, who meets whom is
                       reshuffled each round (seeded), so everyone races once per round
``time_trial``         a solo trial per entrant and round, then a **final**: the fastest
                       ``final_size`` (2–8) race one heat on the first round's track and seed,
                       the fastest on pole
=====================  =========================================================================

**Points** (F1's for the first eight places): 25, 18, 15, 12, 10, 8, 6, 4 for 1st … 8th in a
heat or the final; a car that does not finish scores 0. Round-robin standings: total points,
then wins, then second places, … (countback), then the best lap, then the seeding.
Time-trial standings: the finalists by their place in the final (with its points), then the
others by qualifying. Qualifying: trials finished (more first), then the sum of their race
times (s, penalties included). Before the final has run, the standings are the qualifying
order.

Races are planned when the tournament is created (``races`` rows of kind ``tournament``,
``stage`` = ``heat``, ``trial`` or ``final``; the final once every trial is done) and fed to
the queue a few at a time by :func:`advance` (each worker cycle): at most ``slots`` of its
jobs wait or run at once, at the ranked races' priority, so the ladder's top-up (which does
not count them) keeps running beside the tournament. Heats are unrated: no rating, record or
ladder count changes. A tournament is ``finished`` when all its races have run (a race that
fails for good counts as run: its cars score nothing).
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

from sqlalchemy import Row, func, select
from sqlalchemy.orm import Session

from leaderboard import queries
from leaderboard.cache import cache_for
from leaderboard.errors import Conflict, LeaderboardError, NotFound
from leaderboard.matchmaking import RANKED_PRIORITY, grid_entries, library_tracks, track_pool
from leaderboard.models import (
    DEFAULT_CAR,
    Job,
    Race,
    RaceEntry,
    Submission,
    SubmissionVersion,
    Tournament,
    TournamentEntrant,
    utcnow,
)
from leaderboard.queries import MAX_PER_PAGE, SNAPSHOT_MAX_AGE_S, Page, UtcModel
from leaderboard.queue import enqueue
from leaderboard.settings import Settings

FORMATS = ("round_robin", "time_trial")
POINTS = (25, 18, 15, 12, 10, 8, 6, 4)  # per place in a heat or final; a DNF scores 0
MAX_RACES = 400  # races one tournament may plan
MAX_ENTRANTS = 64
MAX_LAPS = 10
MAX_SEEDS = 20
MIN_CARS, MAX_CARS = 2, 8  # cars in a heat (submissions.jobs.MIN_CARS, MAX_CARS)


class TournamentError(LeaderboardError):
    """A tournament that cannot be created as asked (422: the message says why)."""

    status_code = 422


def points_for(position: int | None, finished: bool) -> int:
    """Points of one place (see the module docstring).

    >>> points_for(1, True), points_for(8, True), points_for(9, True), points_for(1, False)
    (25, 4, 0, 0)
    """
    if not finished or position is None or not 1 <= position <= len(POINTS):
        return 0
    return POINTS[position - 1]


def split_heats(n: int, heat_size: int) -> list[int]:
    """Balanced heat sizes for ``n`` ≥ 2 entrants, each at most ``heat_size``, except that no
    car races alone: with heats of 2 and an odd field, one heat takes 3.

    >>> split_heats(9, 4), split_heats(4, 4), split_heats(5, 8), split_heats(5, 2)
    ([3, 3, 3], [4], [5], [3, 2])
    """
    k = math.ceil(n / heat_size)
    sizes = [n // k + (1 if i < n % k else 0) for i in range(k)]
    if len(sizes) > 1 and sizes[-1] < MIN_CARS:  # only heat_size 2 with n odd
        sizes[0] += sizes.pop()
    return sizes


def plan_round_robin(n: int, rounds: int, heat_size: int, seed: int = 0) -> list[list[list[int]]]:
    """Heats of a round-robin: per round, lists of entrant indices (pole first).

    Everyone races once per round. With one heat per round the grid rotates (entrant ``r``
    starts from pole in round ``r``); with several, the groups are reshuffled each round
    (seeded by ``seed`` and the round), so the entrants meet different opponents.
    """
    sizes = split_heats(n, heat_size)
    plan = []
    for r in range(rounds):
        order = [(i + r) % n for i in range(n)]
        if len(sizes) > 1:
            random.Random(f"{seed}-{r}").shuffle(order)
        heats, start = [], 0
        for size in sizes:
            heats.append(order[start : start + size])
            start += size
        plan.append(heats)
    return plan


# ---- creating ------------------------------------------------------------------------------


def _check(
    fmt: str, tracks: Sequence[str], seeds: Sequence[int], laps: int, heat_size: int
) -> None:
    if fmt not in FORMATS:
        raise TournamentError(f"format must be one of {', '.join(FORMATS)}, not {fmt!r}")
    if not tracks:
        raise TournamentError("a tournament needs at least one track")
    known = set(library_tracks())
    unknown = [t for t in tracks if t not in known]
    if unknown:
        raise TournamentError(
            f"unknown track {unknown[0]!r} (built-in: {', '.join(sorted(known))})"
        )
    if not seeds or len(seeds) > MAX_SEEDS:
        raise TournamentError(f"give 1 to {MAX_SEEDS} seeds")
    if any(not isinstance(s, int) or isinstance(s, bool) or not 0 <= s < 2**31 for s in seeds):
        raise TournamentError("seeds are integers in [0, 2^31)")
    if not 1 <= laps <= MAX_LAPS:
        raise TournamentError(f"laps must be 1 to {MAX_LAPS}, not {laps}")
    if not MIN_CARS <= heat_size <= MAX_CARS:
        raise TournamentError(f"heat size must be {MIN_CARS} to {MAX_CARS}, not {heat_size}")


def _entrants(
    session: Session, entrants: Sequence[int] | None, top: int | None, car: str | None
) -> tuple[list[tuple[Submission, SubmissionVersion]], str]:
    """The entrants' submissions and racing versions, in seeding order, and their car class."""
    if (entrants is None) == (top is None):
        raise TournamentError("give either the entrants (submission ids) or top N, not both")
    if top is not None:
        if not MIN_CARS <= top <= MAX_ENTRANTS:
            raise TournamentError(f"top must be {MIN_CARS} to {MAX_ENTRANTS}, not {top}")
        car = car or DEFAULT_CAR
        rows = queries.leaderboard(session, per_page=top, car=car, max_age_s=0.0).items
        entrants = [r.submission_id for r in rows]
    assert entrants is not None
    if len(set(entrants)) != len(entrants):
        raise TournamentError("an entrant is listed twice")
    if not MIN_CARS <= len(entrants) <= MAX_ENTRANTS:
        raise TournamentError(
            f"a tournament takes {MIN_CARS} to {MAX_ENTRANTS} entrants, not {len(entrants)}"
        )
    out = []
    for sub_id in entrants:
        sub = session.get(Submission, sub_id)
        if sub is None:
            raise NotFound(f"no submission {sub_id}")
        version = session.get(SubmissionVersion, sub.active_version_id or 0)
        if sub.status != "active" or version is None:
            raise Conflict(
                f"submission {sub_id} ({sub.name!r}) is not ranked (status {sub.status})"
            )
        out.append((sub, version))
    cars = {v.car for _, v in out}
    if len(cars) > 1 or (car is not None and cars != {car}):
        wanted = f" (asked for {car})" if car is not None else ""
        raise Conflict(
            f"entrants drive different cars ({', '.join(sorted(cars))}){wanted}: "
            "a tournament is one car class"
        )
    return out, cars.pop()


def create_tournament(
    session: Session,
    settings: Settings,
    *,
    name: str,
    fmt: str = "round_robin",
    entrants: Sequence[int] | None = None,
    top: int | None = None,
    car: str | None = None,
    tracks: Sequence[str] | None = None,
    seeds: Sequence[int] = (0,),
    laps: int = 2,
    heat_size: int = 4,
    final_size: int = 4,
    created_by: str = "",
) -> Tournament:
    """Define a tournament and plan its heats (or trials); the caller commits.

    Args:
        session: the caller's transaction.
        settings: the ranked track pool (the default tracks).
        name: shown on its page, 1–64 characters.
        fmt: ``round_robin`` or ``time_trial``.
        entrants: submission ids, top seed first (or ``top``).
        top: the top N of ``car``'s ladder (by rating), instead of ``entrants``.
        car: the car class (default: the entrants'; ``f1tenth`` with ``top``).
        tracks: built-in track names (default: the first of the ranked pool).
        seeds: one round per track and seed.
        laps: laps per heat, trial and final.
        heat_size: most cars per heat (``round_robin``), 2–8.
        final_size: finalists (``time_trial``), 2–8 (at most the entrants).
        created_by: who defined it (shown on its page).

    Raises:
        TournamentError: a bad argument (422). NotFound: an unknown submission. Conflict: an
        entrant that is not ranked, or entrants of different car classes.
    """
    name = name.strip()
    if not 1 <= len(name) <= 64 or any(ord(c) < 32 for c in name):
        raise TournamentError("the name must be 1 to 64 printable characters")
    tracks = list(tracks) if tracks else track_pool(settings)[:1]
    seeds = list(seeds)
    _check(fmt, tracks, seeds, laps, heat_size)
    chosen, car_class = _entrants(session, entrants, top, car)
    n = len(chosen)
    final = min(final_size, n, MAX_CARS) if fmt == "time_trial" else 0
    if fmt == "time_trial" and final < MIN_CARS:
        raise TournamentError(f"final size must be {MIN_CARS} to {MAX_CARS}, not {final_size}")
    rounds = [(t, s) for t in tracks for s in seeds]
    planned = len(rounds) * (n if fmt == "time_trial" else len(split_heats(n, heat_size))) + (
        1 if final else 0
    )
    if planned > MAX_RACES:
        raise TournamentError(f"that is {planned} races; at most {MAX_RACES}")
    tournament = Tournament(
        name=name,
        format=fmt,
        car=car_class,
        tracks=tracks,
        seeds=seeds,
        laps=laps,
        heat_size=heat_size,
        final_size=final,
        created_by=created_by[:64],
        entrants=[
            TournamentEntrant(
                submission_id=sub.id,
                version_id=ver.id,
                seed_rank=i + 1,
                name=f"{sub.name}:v{ver.version}",
                source=ver.source,
            )
            for i, (sub, ver) in enumerate(chosen)
        ],
    )
    session.add(tournament)
    session.flush()
    ordered = tournament.entrants
    if fmt == "round_robin":
        plan = plan_round_robin(n, len(rounds), heat_size, seed=tournament.id)
        for (track, seed), heats in zip(rounds, plan, strict=True):
            for heat in heats:
                _add_race(session, tournament, "heat", track, seed, [ordered[i] for i in heat])
    else:
        for track, seed in rounds:
            for entrant in ordered:
                _add_race(session, tournament, "trial", track, seed, [entrant])
    session.flush()
    return tournament


def _add_race(
    session: Session,
    tournament: Tournament,
    stage: str,
    track: str,
    seed: int,
    cars: Sequence[TournamentEntrant],
) -> Race:
    """A planned race of the tournament (no job yet: :func:`advance` queues it)."""
    race = Race(
        kind="tournament",
        stage=stage,
        tournament_id=tournament.id,
        track=track,
        car=tournament.car,
        seed=seed,
        laps=tournament.laps,
        penalties=True,  # the ranked races' rules: DeepRacer's time penalties
        entries=grid_entries(cars),
    )
    session.add(race)
    return race


# ---- running -------------------------------------------------------------------------------


def advance(session: Session, settings: Settings, slots: int = 1) -> int:
    """Move the running tournaments on (from each worker cycle; the caller commits): plan the
    final of a time trial whose trials are done, mark finished tournaments, and queue planned
    races until ``slots`` tournament jobs wait or run. Returns how many were queued."""
    running = list(
        session.scalars(
            select(Tournament).where(Tournament.status == "running").order_by(Tournament.id)
        )
    )
    if not running:
        return 0
    for tournament in running:
        races = list(session.scalars(select(Race).where(Race.tournament_id == tournament.id)))
        done = all(r.status in ("finished", "failed") for r in races)
        if not done:
            continue
        has_final = any(r.stage == "final" for r in races)
        if tournament.format == "time_trial" and not has_final and tournament.final_size:
            finalists = qualifying(session, tournament)[: tournament.final_size]
            if len(finalists) >= MIN_CARS:
                by_id = {e.id: e for e in tournament.entrants}
                _add_race(
                    session,
                    tournament,
                    "final",
                    tournament.tracks[0],
                    tournament.seeds[0],
                    [by_id[q.entrant_id] for q in finalists],
                )
                continue
        tournament.status = "finished"
        tournament.finished_at = utcnow()
    session.flush()
    waiting = int(
        session.scalar(
            select(func.count(Job.id))
            .join(Race, Race.id == Job.race_id)
            .where(Race.kind == "tournament", Job.status.in_(("queued", "leased")))
        )
        or 0
    )
    free = max(0, slots - waiting)
    if not free:
        return 0
    planned = session.scalars(
        select(Race)
        .outerjoin(Job, Job.race_id == Race.id)
        .join(Tournament, Tournament.id == Race.tournament_id)
        .where(Tournament.status == "running", Race.status == "queued", Job.id.is_(None))
        .order_by(Race.tournament_id, Race.id)
        .limit(free)
    ).all()
    for race in planned:
        enqueue(session, race, priority=RANKED_PRIORITY, max_attempts=settings.max_attempts)
    return len(planned)


# ---- standings -----------------------------------------------------------------------------


@dataclass
class Standing:
    """One entrant's tournament so far (times in s)."""

    entrant_id: int
    submission_id: int
    name: str
    seed_rank: int
    points: int = 0
    races: int = 0  # heats (or trials, and the final) run
    wins: int = 0
    places: list[int] = field(default_factory=lambda: [0] * len(POINTS))  # 1st, 2nd, … counts
    best_lap: float | None = None
    trials_finished: int = 0
    qualifying_time: float | None = None  # sum of finished trials' times (time_trial)
    final_position: int | None = None  # place in the final (time_trial)
    finalist: bool = False


# The columns the standings and the heats read: plain rows, not ORM objects (a race's
# ``result`` and ``events`` documents, decoded for every heat, were most of a page's time).
_HEAT_COLUMNS = (
    Race.id.label("race_id"),
    Race.stage,
    Race.track,
    Race.seed,
    Race.status.label("race_status"),
    Race.viser_path,
    Race.replay_path,
    Race.finished_at,
    RaceEntry.submission_id,
    RaceEntry.name,
    RaceEntry.position,
    RaceEntry.status,
    RaceEntry.dnf_reason,
    RaceEntry.best_lap,
    RaceEntry.total_time,
)


def _by_entry(session: Session, tournament: Tournament) -> list[Row[Any]]:
    """One row per car of every race of ``tournament`` (:data:`_HEAT_COLUMNS`), in the order
    the races were planned, pole first."""
    rows: Sequence[Any] = session.execute(
        select(*_HEAT_COLUMNS)
        .join(RaceEntry, RaceEntry.race_id == Race.id)
        .where(Race.tournament_id == tournament.id)
        .order_by(Race.id, RaceEntry.car)
    ).all()
    return list(rows)


def _tally(
    session: Session, tournament: Tournament, rows: Sequence[Row[Any]] | None = None
) -> list[Standing]:
    """Each entrant's points, places, best lap and qualifying so far, from ``rows`` (those
    of :func:`_by_entry`, read if not given)."""
    table = {
        e.submission_id: Standing(e.id, e.submission_id, e.name, e.seed_rank)
        for e in tournament.entrants
    }
    for car in _by_entry(session, tournament) if rows is None else rows:
        row = table.get(car.submission_id or 0)
        if row is None or car.race_status != "finished":
            continue
        finished = car.status == "finished"
        row.races += 1
        if car.best_lap is not None:
            row.best_lap = min(row.best_lap or math.inf, car.best_lap)
        if car.stage == "trial":
            if finished and car.total_time is not None:
                row.trials_finished += 1
                row.qualifying_time = (row.qualifying_time or 0.0) + car.total_time
            continue
        if car.stage == "final":
            row.finalist = True
            row.final_position = car.position
        row.points += points_for(car.position, finished)
        if finished and car.position is not None and 1 <= car.position <= len(POINTS):
            row.places[car.position - 1] += 1
            row.wins += car.position == 1
    return list(table.values())


def qualifying(
    session: Session, tournament: Tournament, rows: Sequence[Row[Any]] | None = None
) -> list[Standing]:
    """A time trial's qualifying order: more trials finished first, then less total time."""
    return sorted(
        _tally(session, tournament, rows),
        key=lambda r: (-r.trials_finished, r.qualifying_time or math.inf, r.seed_rank),
    )


def standings(
    session: Session, tournament: Tournament, rows: Sequence[Row[Any]] | None = None
) -> list[Standing]:
    """The standings (see the module docstring for the order); ``rows`` as :func:`_tally`."""
    if tournament.format == "time_trial":
        table = qualifying(session, tournament, rows)
        finalists = sorted(
            (r for r in table if r.finalist),
            key=lambda r: (r.final_position or math.inf, r.seed_rank),
        )
        return finalists + [r for r in table if not r.finalist]
    return sorted(
        _tally(session, tournament, rows),
        key=lambda r: (
            -r.points,
            [-c for c in r.places],
            r.best_lap if r.best_lap is not None else math.inf,
            r.seed_rank,
        ),
    )


def get_tournament(session: Session, tournament_id: int) -> Tournament:
    """A tournament by id.

    Raises:
        NotFound: no such tournament.
    """
    tournament = session.get(Tournament, tournament_id)
    if tournament is None:
        raise NotFound(f"no tournament {tournament_id}")
    return tournament


# ---- what the pages and the API show -------------------------------------------------------


class StandingRow(UtcModel):
    """One line of a tournament's standings (times in s)."""

    rank: int
    submission_id: int
    name: str
    seed_rank: int  # 1 = top seed
    points: int
    races: int
    wins: int
    best_lap: float | None
    trials_finished: int = 0  # time_trial
    qualifying_time: float | None = None  # time_trial: sum of finished trials' times
    finalist: bool = False
    final_position: int | None = None


class HeatCar(UtcModel):
    """One car of a heat, and the points it scored."""

    name: str
    submission_id: int | None
    position: int | None
    status: str | None
    dnf_reason: str | None
    total_time: float | None
    points: int


class Heat(UtcModel):
    """One race of a tournament (``stage``: heat, trial or final) with its replay links."""

    race_id: int
    number: int  # 1, 2, … in the order they were planned
    stage: str
    track: str
    seed: int
    status: str  # queued | running | finished | failed
    cars: list[HeatCar]
    viser_url: str | None
    replay_url: str | None
    finished_at: datetime | None


class TournamentSummary(UtcModel):
    """A tournament in the list."""

    id: int
    name: str
    format: str  # round_robin | time_trial
    car: str
    tracks: list[str]
    seeds: list[int]
    laps: int
    heat_size: int
    final_size: int
    status: str  # running | finished
    entrants: int
    races: int
    races_done: int
    leader: str | None  # first in the standings (the winner once finished)
    leader_submission_id: int | None
    created_by: str
    created_at: datetime
    finished_at: datetime | None


class TournamentDetail(TournamentSummary):
    """A tournament: standings, every heat with its replay, and the final (time_trial)."""

    points: list[int]  # per place, 1st first; a DNF scores 0
    standings: list[StandingRow]
    heats: list[Heat]
    final: Heat | None


def _heats(rows: Sequence[Row[Any]]) -> list[Heat]:
    """Every race of a tournament with its cars, from :func:`_by_entry`'s rows."""
    heats: dict[int, Heat] = {}
    for car in rows:
        heat = heats.get(car.race_id)
        if heat is None:
            heat = heats[car.race_id] = Heat(
                race_id=car.race_id,
                number=len(heats) + 1,
                stage=car.stage or "heat",
                track=car.track,
                seed=car.seed,
                status=car.race_status,
                cars=[],
                viser_url=f"/replays/{Path(car.viser_path).name}" if car.viser_path else None,
                replay_url=f"/replays/{Path(car.replay_path).name}" if car.replay_path else None,
                finished_at=car.finished_at,
            )
        finished = car.status == "finished"
        heat.cars.append(
            HeatCar(
                name=car.name,
                submission_id=car.submission_id,
                position=car.position,
                status=car.status,
                dnf_reason=car.dnf_reason,
                total_time=car.total_time,
                points=0 if car.stage == "trial" else points_for(car.position, finished),
            )
        )
    for heat in heats.values():
        heat.cars.sort(key=lambda c: (c.position is None, c.position or 0))
    return list(heats.values())


@dataclass(frozen=True)
class _Progress:
    """Where a tournament's races stand: the key its cached pages are kept under.

    Any change a page shows moves it: a race queued, started (a later ``started_at``),
    handed back (one fewer running), finished or failed (its result is stored in the same
    transaction), a final planned (one more race), the tournament finished.
    """

    status: str  # the tournament's
    by_status: tuple[tuple[str, int], ...]  # races per status
    last_started: datetime | None
    last_finished: datetime | None

    @property
    def races(self) -> int:
        """Races planned so far."""
        return sum(n for _, n in self.by_status)

    @property
    def done(self) -> int:
        """Races run (finished, or failed for good)."""
        return sum(n for status, n in self.by_status if status in ("finished", "failed"))


def _progress(session: Session, tournaments: Sequence[Tournament]) -> dict[int, _Progress]:
    """:class:`_Progress` of each of ``tournaments``, in one grouped read of their races.

    The ids are a range (a page of the list, or one tournament), so the read is one range
    of the ``(tournament_id, id)`` index: no ``IN`` list to plan.
    """
    if not tournaments:
        return {}
    ids = [t.id for t in tournaments]
    counts: dict[int, list[tuple[str, int]]] = {i: [] for i in ids}
    started: dict[int, datetime | None] = dict.fromkeys(ids)
    finished: dict[int, datetime | None] = dict.fromkeys(ids)
    for tid, status, n, last_start, last_finish in session.execute(
        select(
            Race.tournament_id,
            Race.status,
            func.count(Race.id),
            func.max(Race.started_at),
            func.max(Race.finished_at),
        )
        .where(Race.tournament_id.between(min(ids), max(ids)))
        .group_by(Race.tournament_id, Race.status)
    ):
        if tid not in counts:  # a tournament between two of the page's (not on it)
            continue
        counts[tid].append((status, int(n)))
        started[tid] = max(filter(None, (started[tid], last_start)), default=None)
        finished[tid] = max(filter(None, (finished[tid], last_finish)), default=None)
    return {
        t.id: _Progress(
            status=t.status,
            by_status=tuple(sorted(counts[t.id])),
            last_started=started[t.id],
            last_finished=finished[t.id],
        )
        for t in tournaments
    }


def _summary(tournament: Tournament, progress: _Progress, table: list[Standing]) -> dict[str, Any]:
    started = any(r.races for r in table)
    leader = table[0] if table and started else None
    return {
        "id": tournament.id,
        "name": tournament.name,
        "format": tournament.format,
        "car": tournament.car,
        "tracks": list(tournament.tracks),
        "seeds": list(tournament.seeds),
        "laps": tournament.laps,
        "heat_size": tournament.heat_size,
        "final_size": tournament.final_size,
        "status": tournament.status,
        "entrants": len(tournament.entrants),
        "races": progress.races,
        "races_done": progress.done,
        "leader": leader.name if leader else None,
        "leader_submission_id": leader.submission_id if leader else None,
        "created_by": tournament.created_by,
        "created_at": tournament.created_at,
        "finished_at": tournament.finished_at,
    }


def tournament_detail(
    session: Session, tournament_id: int, *, max_age_s: float = SNAPSHOT_MAX_AGE_S
) -> TournamentDetail:
    """A tournament's page: standings, heats, final.

    Cached (:mod:`leaderboard.cache`) under the tournament's :class:`_Progress`, which
    storing a heat's result moves: a view reads the tournament and one aggregate of its
    races, and recomputes the standings only when they can have changed.

    Raises:
        NotFound: no such tournament.
    """
    tournament = get_tournament(session, tournament_id)
    progress = _progress(session, [tournament])[tournament.id]

    def compute() -> TournamentDetail:
        rows = _by_entry(session, tournament)
        table = standings(session, tournament, rows)
        heats = _heats(rows)
        return TournamentDetail(
            **_summary(tournament, progress, table),
            points=list(POINTS),
            standings=[
                StandingRow(
                    rank=i + 1,
                    submission_id=r.submission_id,
                    name=r.name,
                    seed_rank=r.seed_rank,
                    points=r.points,
                    races=r.races,
                    wins=r.wins,
                    best_lap=r.best_lap,
                    trials_finished=r.trials_finished,
                    qualifying_time=r.qualifying_time,
                    finalist=r.finalist,
                    final_position=r.final_position,
                )
                for i, r in enumerate(table)
            ],
            heats=heats,
            final=next((h for h in heats if h.stage == "final"), None),
        )

    return cache_for(session).get(("tournament", tournament.id), progress, compute, max_age_s)


def tournament_list(
    session: Session, *, page: int = 1, per_page: int = 50, max_age_s: float = SNAPSHOT_MAX_AGE_S
) -> Page[TournamentSummary]:
    """Every tournament, newest first; each line cached as :func:`tournament_detail` is."""
    page, per_page = max(1, page), max(1, min(MAX_PER_PAGE, per_page))
    total = int(session.scalar(select(func.count(Tournament.id))) or 0)
    rows = session.scalars(
        select(Tournament)
        .order_by(Tournament.id.desc())
        .offset((page - 1) * per_page)
        .limit(per_page)
    ).all()
    progress = _progress(session, rows)
    cache = cache_for(session)

    def summary(t: Tournament) -> Callable[[], TournamentSummary]:
        return lambda: TournamentSummary(**_summary(t, progress[t.id], standings(session, t)))

    items = [
        cache.get(("tournament-summary", t.id), progress[t.id], summary(t), max_age_s) for t in rows
    ]
    return Page(items=items, total=total, page=page, per_page=per_page)
