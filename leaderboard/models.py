"""The leaderboard's tables (SQLAlchemy 2.0 typed models); Alembic migrations mirror them.

=================  =====================================================================
table              holds
=================  =====================================================================
users              people who upload (name, admin flag)
api_tokens         bearer tokens, stored as SHA-256 hashes (the token itself is shown once)
submissions        a named entry of a user: status, current rating (μ, σ, ordinal), counts
submission_versions  each uploaded bundle of a submission (validated or rejected), its car
races              a scheduled or run race: track, car, seed, laps, status, result JSON, replays
race_entries       one car of a race: which submission/version, its result, rating change
race_logs          one car's owner-only logs: DNF detail, policy output, sandbox mode
web_sessions       signed-in browsers (cookie hash, the API token used, CSRF token)
rating_history     a submission's (μ, σ) after each ranked race
jobs               the work queue: one job per race, with lease owner/token/expiry, attempts
track_records      best lap of each submission on each track
tournaments        an operator's tournament: format, car, tracks, laps, seeds, status
tournament_entrants  who takes part in a tournament (the version pinned when it was created)
=================  =====================================================================

Times are naive UTC (:func:`utcnow`), so SQLite and PostgreSQL store the same values.
Lap times and durations are seconds; μ and σ are OpenSkill units (defaults 25 and 25/3).
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

from sqlalchemy import (
    JSON,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    String,
    Text,
    UniqueConstraint,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship

MU0 = 25.0  # OpenSkill's default initial μ
DEFAULT_CAR = "f1tenth"  # = arena.cars.DEFAULT_CAR (tested equal; no simulator here)
SIGMA0 = 25.0 / 3.0  # OpenSkill's default initial σ


def utcnow() -> datetime:
    """The current time, naive UTC (how every timestamp is stored)."""
    return datetime.now(UTC).replace(tzinfo=None)


class Base(DeclarativeBase):
    """Declarative base of every leaderboard table."""


class User(Base):
    """Someone who uploads submissions."""

    __tablename__ = "users"

    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(64), unique=True)
    is_admin: Mapped[bool] = mapped_column(Boolean, default=False)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)

    tokens: Mapped[list[ApiToken]] = relationship(back_populates="user")
    submissions: Mapped[list[Submission]] = relationship(back_populates="user")


class ApiToken(Base):
    """A bearer token; only its SHA-256 hash is stored."""

    __tablename__ = "api_tokens"

    id: Mapped[int] = mapped_column(primary_key=True)
    user_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"), index=True)
    token_hash: Mapped[str] = mapped_column(String(64), unique=True)
    prefix: Mapped[str] = mapped_column(String(16))  # first characters, to tell tokens apart
    label: Mapped[str] = mapped_column(String(64), default="")
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
    last_used_at: Mapped[datetime | None] = mapped_column(DateTime)
    revoked_at: Mapped[datetime | None] = mapped_column(DateTime)

    user: Mapped[User] = relationship(back_populates="tokens")


class Submission(Base):
    """A user's named entry; its versions are the bundles uploaded under that name.

    ``status``: ``pending`` (no version validated yet), ``active`` (races with
    ``active_version``), ``rejected`` (no version passed validation), ``withdrawn``.
    """

    __tablename__ = "submissions"
    __table_args__ = (
        UniqueConstraint("user_id", "name", name="uq_submissions_user_name"),
        Index("ix_submissions_status_ordinal", "status", "ordinal"),
        Index("ix_submissions_updated_at", "updated_at"),  # leaderboard cache fingerprint
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    user_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"), index=True)
    name: Mapped[str] = mapped_column(String(64))
    description: Mapped[str] = mapped_column(Text, default="")
    status: Mapped[str] = mapped_column(String(16), default="pending")
    active_version_id: Mapped[int | None] = mapped_column(
        ForeignKey("submission_versions.id", use_alter=True, name="fk_submissions_active_version")
    )
    mu: Mapped[float] = mapped_column(Float, default=MU0)
    sigma: Mapped[float] = mapped_column(Float, default=SIGMA0)
    ordinal: Mapped[float] = mapped_column(Float, default=MU0 - 3 * SIGMA0)
    races: Mapped[int] = mapped_column(Integer, default=0)  # ranked races with a result
    wins: Mapped[int] = mapped_column(Integer, default=0)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)

    user: Mapped[User] = relationship(back_populates="submissions")
    versions: Mapped[list[SubmissionVersion]] = relationship(
        back_populates="submission",
        foreign_keys="SubmissionVersion.submission_id",
        order_by="SubmissionVersion.version",
    )
    active_version: Mapped[SubmissionVersion | None] = relationship(
        foreign_keys=[active_version_id], post_update=True
    )


class SubmissionVersion(Base):
    """One uploaded bundle of a submission.

    ``source`` is what the evaluation worker races: the stored bundle path, or a baseline
    name (``pursuit``, ``gap``, ``random``) for the house entries. ``status``: ``pending``
    until its validation race, then ``validated`` or ``rejected`` (with ``error``).
    """

    __tablename__ = "submission_versions"
    __table_args__ = (
        UniqueConstraint("submission_id", "version", name="uq_versions_submission_version"),
        Index("ix_versions_sha256", "sha256"),  # duplicate bundles are refused
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    submission_id: Mapped[int] = mapped_column(
        ForeignKey("submissions.id", ondelete="CASCADE"), index=True
    )
    version: Mapped[int] = mapped_column(Integer)
    source: Mapped[str] = mapped_column(String(1024))
    format: Mapped[str] = mapped_column(String(16))
    manifest: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    size_bytes: Mapped[int] = mapped_column(Integer, default=0)
    sha256: Mapped[str] = mapped_column(String(64), default="")
    status: Mapped[str] = mapped_column(String(16), default="pending")
    error: Mapped[str | None] = mapped_column(Text)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
    # The car class it races in (the manifest's ``car``; every version of a submission has
    # the same one): its ladder.
    car: Mapped[str] = mapped_column(String(16), default=DEFAULT_CAR, server_default=DEFAULT_CAR)
    # Its robustness run (:mod:`leaderboard.robustness`): the score, m/s (worst-10 % mean of
    # the effective speed over the perturbation grid), and the run (a race of kind
    # ``robustness`` whose result holds every grid point).
    robust_score: Mapped[float | None] = mapped_column(Float)
    robust_race_id: Mapped[int | None] = mapped_column(
        ForeignKey("races.id", ondelete="SET NULL", name="fk_versions_robust_race")
    )

    submission: Mapped[Submission] = relationship(
        back_populates="versions", foreign_keys=[submission_id]
    )


class Race(Base):
    """A race: scheduled (``queued``), being run (``running``), ``finished`` or ``failed``.

    ``kind`` is ``validation`` (a new version's first race, unrated), ``ranked``,
    ``robustness`` (not a race: one version's solo laps over the perturbation grid, queued
    and run like a race; :mod:`leaderboard.robustness`) or ``tournament`` (a heat of a
    tournament, unrated). ``result`` is the race result JSON (``RaceResult.to_dict()``, or a
    robustness run's document); replays are files.
    """

    __tablename__ = "races"
    __table_args__ = (
        Index("ix_races_status_id", "status", "id"),
        Index("ix_races_track_id", "track", "id"),
        Index("ix_races_kind_status_track", "kind", "status", "track"),  # ranked race counts
        Index("ix_races_finished_at", "finished_at"),  # track cache fingerprint
        Index("ix_races_tournament_id", "tournament_id", "id"),  # a tournament's races
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    kind: Mapped[str] = mapped_column(String(16), default="ranked")
    status: Mapped[str] = mapped_column(String(16), default="queued")
    track: Mapped[str] = mapped_column(String(128))
    seed: Mapped[int] = mapped_column(Integer, default=0)
    laps: Mapped[int] = mapped_column(Integer, default=2)
    penalties: Mapped[bool] = mapped_column(Boolean, default=True)  # DeepRacer time penalties
    car: Mapped[str] = mapped_column(String(16), default=DEFAULT_CAR, server_default=DEFAULT_CAR)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(DateTime)
    finished_at: Mapped[datetime | None] = mapped_column(DateTime)
    duration_s: Mapped[float | None] = mapped_column(Float)
    sandbox: Mapped[str | None] = mapped_column(String(16))
    result: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    replay_path: Mapped[str | None] = mapped_column(String(1024))
    viser_path: Mapped[str | None] = mapped_column(String(1024))
    error: Mapped[str | None] = mapped_column(Text)
    # The replay log's events (laps, collisions, off-tracks, finishes, DNFs), for the page's
    # timeline: ``[{"t": s, "type": ..., "car": "car_i", ...}, ...]`` (capped, see results.py).
    events: Mapped[list[dict[str, Any]] | None] = mapped_column(JSON)
    # A tournament's race (kind ``tournament``): its tournament and stage (``heat``, ``trial``
    # or ``final``; leaderboard.tournaments).
    tournament_id: Mapped[int | None] = mapped_column(
        ForeignKey("tournaments.id", ondelete="CASCADE", name="fk_races_tournament")
    )
    stage: Mapped[str | None] = mapped_column(String(16))

    entries: Mapped[list[RaceEntry]] = relationship(
        back_populates="race", order_by="RaceEntry.car", cascade="all, delete-orphan"
    )
    job: Mapped[Job | None] = relationship(back_populates="race")
    logs: Mapped[list[RaceLog]] = relationship(cascade="all, delete-orphan")


class RaceEntry(Base):
    """One car of a race (car index ``car`` = ``car_<car>`` in the result), and its outcome."""

    __tablename__ = "race_entries"
    __table_args__ = (
        UniqueConstraint("race_id", "car", name="uq_entries_race_car"),
        Index("ix_entries_submission_race", "submission_id", "race_id"),
        Index("ix_entries_version_id", "version_id"),  # a version's races (validation, robustness)
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    race_id: Mapped[int] = mapped_column(ForeignKey("races.id", ondelete="CASCADE"))
    car: Mapped[int] = mapped_column(Integer)
    submission_id: Mapped[int | None] = mapped_column(
        ForeignKey("submissions.id", ondelete="SET NULL")
    )
    version_id: Mapped[int | None] = mapped_column(
        ForeignKey("submission_versions.id", ondelete="SET NULL")
    )
    name: Mapped[str] = mapped_column(String(128))
    source: Mapped[str] = mapped_column(String(1024))
    position: Mapped[int | None] = mapped_column(Integer)
    rank: Mapped[int | None] = mapped_column(Integer)  # rating rank: DNFs tie for last
    status: Mapped[str | None] = mapped_column(String(16))
    dnf_reason: Mapped[str | None] = mapped_column(String(32))
    laps_completed: Mapped[int | None] = mapped_column(Integer)
    best_lap: Mapped[float | None] = mapped_column(Float)
    total_time: Mapped[float | None] = mapped_column(Float)
    race_time: Mapped[float | None] = mapped_column(Float)  # s, before penalties
    penalties: Mapped[float | None] = mapped_column(Float)  # s added (ranked races)
    lap_times: Mapped[list[float] | None] = mapped_column(JSON)
    collisions: Mapped[int | None] = mapped_column(Integer)
    at_fault_collisions: Mapped[int | None] = mapped_column(Integer)
    off_track: Mapped[int | None] = mapped_column(Integer)
    mu_before: Mapped[float | None] = mapped_column(Float)
    sigma_before: Mapped[float | None] = mapped_column(Float)
    mu_after: Mapped[float | None] = mapped_column(Float)
    sigma_after: Mapped[float | None] = mapped_column(Float)

    race: Mapped[Race] = relationship(back_populates="entries")
    submission: Mapped[Submission | None] = relationship()


class RaceLog(Base):
    """What only a car's owner sees: its DNF detail, its policy's output, its sandbox mode.

    ``dnf_detail`` is the traceback or error text (at most 4 KiB); ``output`` the kept head
    and tail of the policy's stdout/stderr; ``sandbox_mode`` how that car's policy was
    isolated (``bwrap``, ``seccomp``; ``none`` for our baselines).
    """

    __tablename__ = "race_logs"
    __table_args__ = (UniqueConstraint("race_id", "car", name="uq_logs_race_car"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    race_id: Mapped[int] = mapped_column(ForeignKey("races.id", ondelete="CASCADE"))
    car: Mapped[int] = mapped_column(Integer)
    dnf_detail: Mapped[str | None] = mapped_column(Text)
    output: Mapped[str | None] = mapped_column(Text)
    sandbox_mode: Mapped[str | None] = mapped_column(String(16))


class WebSession(Base):
    """A signed-in browser (:mod:`leaderboard.web.session`): the cookie's SHA-256 hash, the
    API token it was opened with (revoking that token ends the session), its CSRF token."""

    __tablename__ = "web_sessions"

    id: Mapped[int] = mapped_column(primary_key=True)
    session_hash: Mapped[str] = mapped_column(String(64), unique=True)
    user_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"), index=True)
    token_id: Mapped[int] = mapped_column(ForeignKey("api_tokens.id", ondelete="CASCADE"))
    csrf: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
    expires_at: Mapped[datetime] = mapped_column(DateTime)


class RatingHistory(Base):
    """A submission's rating right after one ranked race."""

    __tablename__ = "rating_history"
    __table_args__ = (
        UniqueConstraint("submission_id", "race_id", name="uq_history_submission_race"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    submission_id: Mapped[int] = mapped_column(
        ForeignKey("submissions.id", ondelete="CASCADE"), index=True
    )
    race_id: Mapped[int] = mapped_column(ForeignKey("races.id", ondelete="CASCADE"))
    mu: Mapped[float] = mapped_column(Float)
    sigma: Mapped[float] = mapped_column(Float)
    ordinal: Mapped[float] = mapped_column(Float)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)


class Job(Base):
    """The queue entry of a race.

    ``status``: ``queued`` → ``leased`` (a worker holds it until ``lease_expires_at``,
    identified by ``lease_token``) → ``done`` or ``failed``. An expired lease is claimable
    again; ``attempts`` counts claims.
    """

    __tablename__ = "jobs"
    __table_args__ = (Index("ix_jobs_status_priority_id", "status", "priority", "id"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    race_id: Mapped[int] = mapped_column(ForeignKey("races.id", ondelete="CASCADE"), unique=True)
    status: Mapped[str] = mapped_column(String(16), default="queued")
    priority: Mapped[int] = mapped_column(Integer, default=10)  # lower runs sooner
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    max_attempts: Mapped[int] = mapped_column(Integer, default=3)
    lease_owner: Mapped[str | None] = mapped_column(String(128))
    lease_token: Mapped[str | None] = mapped_column(String(64))
    lease_expires_at: Mapped[datetime | None] = mapped_column(DateTime)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
    error: Mapped[str | None] = mapped_column(Text)

    race: Mapped[Race] = relationship(back_populates="job")


class TrackRecord(Base):
    """The best lap a submission has driven on a track in a ranked race."""

    __tablename__ = "track_records"
    __table_args__ = (
        UniqueConstraint("track", "submission_id", name="uq_records_track_submission"),
        Index("ix_records_track_best_lap", "track", "best_lap"),
        Index("ix_records_set_at", "set_at"),  # track cache fingerprint
        Index("ix_records_submission_id", "submission_id"),  # a submission's bests
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    track: Mapped[str] = mapped_column(String(128))
    submission_id: Mapped[int] = mapped_column(ForeignKey("submissions.id", ondelete="CASCADE"))
    version_id: Mapped[int | None] = mapped_column(
        ForeignKey("submission_versions.id", ondelete="SET NULL")
    )
    race_id: Mapped[int] = mapped_column(ForeignKey("races.id", ondelete="CASCADE"))
    best_lap: Mapped[float] = mapped_column(Float)
    set_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)


class Tournament(Base):
    """A tournament an operator defined (:mod:`leaderboard.tournaments`).

    ``format``: ``round_robin`` (heats: every entrant in one heat per round) or
    ``time_trial`` (a solo trial per entrant and round, then a final of the fastest
    ``final_size``). A round is one (track, seed) pair. ``status``: ``running`` →
    ``finished``. Its races are ``races`` rows of kind ``tournament`` (unrated).
    """

    __tablename__ = "tournaments"

    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(64))
    format: Mapped[str] = mapped_column(String(16))
    car: Mapped[str] = mapped_column(String(16), default=DEFAULT_CAR)
    tracks: Mapped[list[str]] = mapped_column(JSON)
    seeds: Mapped[list[int]] = mapped_column(JSON)
    laps: Mapped[int] = mapped_column(Integer, default=2)
    heat_size: Mapped[int] = mapped_column(Integer, default=4)  # most cars in a heat
    final_size: Mapped[int] = mapped_column(Integer, default=0)  # finalists (time_trial)
    status: Mapped[str] = mapped_column(String(16), default="running")
    created_by: Mapped[str] = mapped_column(String(64), default="")
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
    finished_at: Mapped[datetime | None] = mapped_column(DateTime)

    entrants: Mapped[list[TournamentEntrant]] = relationship(
        order_by="TournamentEntrant.seed_rank", cascade="all, delete-orphan"
    )


class TournamentEntrant(Base):
    """A submission in a tournament, with the version it races (pinned at creation) and its
    seeding (1 = top seed: its ladder rank, or its place in the operator's list)."""

    __tablename__ = "tournament_entrants"
    __table_args__ = (
        UniqueConstraint("tournament_id", "submission_id", name="uq_tournament_entrants"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    tournament_id: Mapped[int] = mapped_column(
        ForeignKey("tournaments.id", ondelete="CASCADE"), index=True
    )
    submission_id: Mapped[int] = mapped_column(ForeignKey("submissions.id", ondelete="CASCADE"))
    version_id: Mapped[int | None] = mapped_column(
        ForeignKey("submission_versions.id", ondelete="SET NULL")
    )
    seed_rank: Mapped[int] = mapped_column(Integer)
    name: Mapped[str] = mapped_column(String(128))  # "<submission>:v<version>"
    source: Mapped[str] = mapped_column(String(1024))
