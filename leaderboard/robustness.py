"""Robustness on the leaderboard: every ranked version's score under a fixed perturbation grid.

No other competition platform ranks this (issue 17): how fast a policy still drives when the
car is not the one it trained on. After a version passes validation and races in the ladder,
the worker queues its **robustness run** (:func:`schedule_robustness`, from
:meth:`leaderboard.worker.Worker.prepare`): one job, carried by a race of kind
``robustness`` (so it is queued, leased, retried and stored exactly like a race) with the
version as its only entry. The worker runs it as
:func:`submissions.robustness.run_robustness_job`: the policy sandboxed exactly as in a
ranked race, solo laps at the nominal car and at each point of
:func:`submissions.robustness.leaderboard_grid` (8 corners of the ``slipstream robustness``
grid's box), scored by effective speed, m/s.

* **Score**: the grid's worst-10 % mean effective speed, m/s (with 8 points: the worst
  corner); the nominal lap is shown beside it. Stored on the version
  (``submission_versions.robust_score``, with ``robust_race_id``: the run, whose result holds
  every point).
* **Track**: rotates with the version: ``tracks[version id % len(tracks)]`` of the ranked
  track pool, so the grid is not learned on one layout; the track is shown with the score.
  (Scores of versions run on different tracks are therefore not strictly comparable: a fast
  layout scores higher. The robust ordering is a second view, not the ladder.)
* **Seed**: :data:`ROBUSTNESS_SEED` for everyone; 1 lap per point; the version's car class.
* Queued at priority 5: after validation races (0), before ranked races (10). One run per
  version: a run that fails for good (its job failed ``max_attempts`` times) is not queued
  again; the version shows no score.

Nothing here imports the simulator: the web process reads the stored results.
"""

from __future__ import annotations

from collections.abc import Sequence

from sqlalchemy import exists, select
from sqlalchemy.orm import Session

from leaderboard.matchmaking import track_pool, version_entry
from leaderboard.models import Race, RaceEntry, Submission, SubmissionVersion, utcnow
from leaderboard.queue import enqueue
from leaderboard.settings import Settings

ROBUSTNESS_PRIORITY = 5  # after validation races (0), before ranked ones (10)
ROBUSTNESS_SEED = 0  # every version faces the same seeded grid
ROBUSTNESS_LAPS = 1


def robustness_track(version_id: int, tracks: Sequence[str]) -> str:
    """The track of a version's robustness run: the pool rotated by version id.

    >>> robustness_track(7, ["oval", "bean", "monza"])
    'bean'
    """
    return tracks[version_id % len(tracks)]


def unscored_versions(session: Session, limit: int) -> list[SubmissionVersion]:
    """Versions that race in the ladder (the active version of an active submission) and
    have no robustness run yet (queued, running, finished or failed), oldest first."""
    has_run = exists(
        select(RaceEntry.id)
        .join(Race, Race.id == RaceEntry.race_id)
        .where(RaceEntry.version_id == SubmissionVersion.id, Race.kind == "robustness")
    )
    return list(
        session.scalars(
            select(SubmissionVersion)
            .join(Submission, Submission.active_version_id == SubmissionVersion.id)
            .where(
                Submission.status == "active",
                SubmissionVersion.status == "validated",
                ~has_run,
            )
            .order_by(SubmissionVersion.id)
            .limit(limit)
        )
    )


def schedule_robustness(session: Session, settings: Settings, limit: int = 50) -> list[Race]:
    """Queue the robustness run of up to ``limit`` versions that need one (see the module
    docstring); the caller commits."""
    versions = unscored_versions(session, limit)
    if not versions:
        return []
    tracks = track_pool(settings)
    races = []
    for version in versions:
        race = Race(
            kind="robustness",
            track=robustness_track(version.id, tracks),
            car=version.car,
            seed=ROBUSTNESS_SEED,
            laps=ROBUSTNESS_LAPS,
            penalties=False,
            entries=[version_entry(session, version)],
        )
        session.add(race)
        enqueue(session, race, priority=ROBUSTNESS_PRIORITY, max_attempts=settings.max_attempts)
        races.append(race)
    session.flush()
    return races


def store_robustness(session: Session, race: Race) -> None:
    """Record a finished robustness run (``race.result``: its document) on its version, in
    the caller's transaction; bumps the submission's ``updated_at`` (the leaderboard cache's
    fingerprint)."""
    entry = race.entries[0] if race.entries else None
    version = (
        session.get(SubmissionVersion, entry.version_id) if entry and entry.version_id else None
    )
    if version is None or race.result is None:
        return
    score = race.result.get("score")
    version.robust_score = float(score) if isinstance(score, int | float) else None
    version.robust_race_id = race.id
    car = (race.result.get("cars") or [{}])[0]
    if entry is not None:
        entry.status = car.get("status")
        entry.dnf_reason = car.get("dnf_reason")
    sub = session.get(Submission, version.submission_id)
    if sub is not None:
        sub.updated_at = utcnow()
