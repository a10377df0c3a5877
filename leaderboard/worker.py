"""Evaluation worker: claims races from the queue, runs them, stores results exactly once.

``slipstream worker --db URL`` runs :class:`Worker`: each cycle it fails races whose leases
ran out too often, tops the queue up with ranked races (:mod:`leaderboard.matchmaking`),
claims up to ``workers`` races with a lease (:mod:`leaderboard.queue`), runs them through
:func:`submissions.jobs.run_race_job` on a local process pool or a Ray cluster
(:func:`submissions.executors.make_executor`), and stores each result with its rating update
in one transaction. A thread renews the leases while the races run; a worker that dies stops
renewing, so its races are claimed again by another worker once the leases expire, and a
result that arrives after its lease was taken over is discarded.

Replays are written to ``settings.replays_dir`` as ``<race id>.viser`` and
``<race id>.replay.json.gz`` (the race id is the job id).
"""

from __future__ import annotations

import logging
import os
import random
import socket
import threading
import uuid
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from sqlalchemy import select
from sqlalchemy.orm import selectinload

from leaderboard import matchmaking, queue
from leaderboard.db import make_engine, make_sessionmaker
from leaderboard.migrations import upgrade
from leaderboard.models import Race
from leaderboard.settings import Settings

if TYPE_CHECKING:
    from submissions.jobs import JobResult, RaceJob

log = logging.getLogger(__name__)

Runner = Callable[[Sequence["RaceJob"]], Iterable["JobResult"]]
ProgressFn = Callable[["WorkerStats"], None]


@dataclass
class WorkerStats:
    """What a worker did: races stored, results discarded (lease lost), races failed."""

    completed: int = 0
    discarded: int = 0
    failed: int = 0


def race_job(race: Race, settings: Settings) -> RaceJob:
    """The evaluation job of a queued race (car ``i`` is entry ``car == i``)."""
    from submissions.jobs import Entrant, RaceJob  # noqa: PLC0415 - light, but not web-side

    return RaceJob(
        job_id=str(race.id),
        entrants=tuple(
            Entrant(
                name=e.name,
                source=e.source,
                submission_id=str(e.submission_id) if e.submission_id is not None else None,
            )
            for e in sorted(race.entries, key=lambda e: e.car)
        ),
        track=race.track,
        out_dir=str(settings.replays_dir.resolve()),
        laps=race.laps,
        seed=race.seed,
        ranked=race.penalties,
    )


def default_runner(workers: int = 1, ray_address: str | None = None) -> Runner:
    """Run jobs with :func:`submissions.executors.make_executor` (a process pool or Ray)."""
    from submissions.executors import make_executor  # noqa: PLC0415 - imports the simulator

    executor = make_executor(ray_address=ray_address, workers=workers)
    return executor.run


class Worker:
    """Claims, runs and stores races (see the module docstring).

    Args:
        settings: database URL, data folder, lease length, matchmaking settings.
        workers: races run at once (and claimed per cycle).
        ray_address: run the races on this Ray cluster instead of local processes.
        runner: runs a batch of jobs and yields their results (default: the executor);
            tests inject a fake one.
        schedule: top the queue up with ranked races when it runs low.
        owner: the name leases are taken under (default: host, pid and a random suffix).
    """

    def __init__(
        self,
        settings: Settings,
        *,
        workers: int = 1,
        ray_address: str | None = None,
        runner: Runner | None = None,
        schedule: bool = True,
        owner: str | None = None,
    ) -> None:
        self.settings = settings
        self.workers = max(1, workers)
        self.schedule = schedule
        self.owner = owner or f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:6]}"
        settings.ensure_dirs()
        self.engine = make_engine(settings.db_url)
        if settings.auto_migrate:
            upgrade(settings.db_url, engine=self.engine)
        self.sessions = make_sessionmaker(self.engine)
        self._runner = runner
        self._ray_address = ray_address
        self.rng = random.Random()

    @property
    def runner(self) -> Runner:
        """The job runner (the executor is created on first use)."""
        if self._runner is None:
            self._runner = default_runner(self.workers, self._ray_address)
        return self._runner

    def close(self) -> None:
        """Release the database connections."""
        self.engine.dispose()

    # ---- one cycle -------------------------------------------------------------------------

    def prepare(self) -> None:
        """Fail races that lost their lease too often; queue ranked races if running low."""
        with self.sessions() as session:
            queue.expire(session)
            if self.schedule:
                matchmaking.top_up(session, self.settings, 2 * self.workers, self.rng)
                session.commit()

    def claim(self, limit: int) -> list[queue.Lease]:
        """Claim up to ``limit`` races."""
        leases: list[queue.Lease] = []
        with self.sessions() as session:
            while len(leases) < limit:
                lease = queue.claim(session, owner=self.owner, lease_s=self.settings.lease_s)
                if lease is None:
                    break
                leases.append(lease)
        return leases

    def run_batch(self, stats: WorkerStats | None = None, limit: int | None = None) -> WorkerStats:
        """One cycle: prepare, claim up to ``limit`` (default ``workers``) races, run, store."""
        stats = stats or WorkerStats()
        self.prepare()
        leases = self.claim(limit or self.workers)
        if not leases:
            return stats
        with self.sessions() as session:
            races = session.scalars(
                select(Race)
                .where(Race.id.in_([lease.race_id for lease in leases]))
                .options(selectinload(Race.entries))
            ).all()
            jobs = {str(r.id): race_job(r, self.settings) for r in races}
        by_job = {str(lease.race_id): lease for lease in leases}
        stop = threading.Event()
        beat = threading.Thread(
            target=self._heartbeat, args=(list(leases), stop), name="lease-heartbeat", daemon=True
        )
        beat.start()
        try:
            for result in self.runner(list(jobs.values())):
                lease = by_job.pop(result.job_id, None)
                if lease is not None:
                    self._store(lease, result, stats)
        finally:
            stop.set()
            beat.join()
            with self.sessions() as session:  # a runner that stopped early: give races back
                for lease in by_job.values():
                    queue.fail(session, lease, "the runner returned no result")
                    stats.failed += 1
        return stats

    def _store(self, lease: queue.Lease, result: JobResult, stats: WorkerStats) -> None:
        with self.sessions() as session:
            if result.error is not None:
                queue.fail(session, lease, result.error)
                stats.failed += 1
                log.warning("race %s failed: %s", lease.race_id, result.error)
                return
            stored = queue.complete(
                session,
                lease,
                result.result,
                replay_path=result.replay_path or None,
                viser_path=result.viser_path,
                sandbox=result.sandbox,
                duration_s=result.duration_s,
            )
        if stored:
            stats.completed += 1
        else:
            stats.discarded += 1
            log.warning("race %s: lease lost, result discarded", lease.race_id)

    def _heartbeat(self, leases: list[queue.Lease], stop: threading.Event) -> None:
        period = max(0.2, self.settings.lease_s / 3)
        while not stop.wait(period):
            with self.sessions() as session:
                for lease in list(leases):
                    if not queue.heartbeat(session, lease, lease_s=self.settings.lease_s):
                        leases.remove(lease)  # taken over: its result will be discarded

    # ---- the loop --------------------------------------------------------------------------

    def run(
        self,
        *,
        max_races: int | None = None,
        once: bool = False,
        poll_s: float = 2.0,
        progress: ProgressFn | None = None,
        stop: threading.Event | None = None,
    ) -> WorkerStats:
        """Work until ``max_races`` races are stored, or after one batch with ``once``.

        Without either, runs until ``stop`` is set (or forever), sleeping ``poll_s`` when
        there is nothing to do.
        """
        stats = WorkerStats()
        stop = stop or threading.Event()
        while not stop.is_set():
            left = None if max_races is None else max_races - stats.completed
            if left is not None and left <= 0:
                break
            before = stats.completed + stats.failed + stats.discarded
            self.run_batch(stats, limit=min(self.workers, left) if left else None)
            if progress is not None:
                progress(stats)
            if once:
                break
            if stats.completed + stats.failed + stats.discarded == before:
                stop.wait(poll_s)
        return stats
