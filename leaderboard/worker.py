"""Evaluation worker: claims races from the queue, runs them, stores results exactly once.

``slipstream worker --db URL`` runs :class:`Worker`: each cycle it fails races whose leases
ran out too often, queues the robustness runs of newly ranked versions
(:mod:`leaderboard.robustness`; they run like races, as :func:`race_job` builds them), feeds
the tournaments' heats to the queue (:mod:`leaderboard.tournaments`), tops
the queue up with ranked races (:mod:`leaderboard.matchmaking`), claims up to ``workers``
races with a lease (:mod:`leaderboard.queue`), runs them through
:func:`submissions.jobs.run_race_job` on a local process pool or a Ray cluster
(:func:`submissions.executors.make_executor`), and stores each result with its rating update
in one transaction. A thread renews the leases while the races run; a worker that dies stops
renewing, so its races are claimed again by another worker once the leases expire, and a
result that arrives after its lease was taken over is discarded.

A lease is renewed only while its race makes progress: the job reports its step count in
``<replays>/.<race id>.progress`` (:func:`progress_path`); a race whose count has not moved
for ``stall_s`` seconds is not renewed again and its job is cancelled (killed with every
process of it), so a wedged race never holds a worker slot for good. Until a job writes its
first count it is renewed (its executor's wall-clock limit bounds it).

Stopping: :meth:`Worker.request_stop` (``slipstream worker`` calls it on SIGTERM and Ctrl-C)
cancels the running jobs and hands their races back to the queue *without* spending an
attempt (:func:`release`); results that already arrived are stored. Untrusted bundles run
only in the namespace sandbox unless the worker is started with ``allow_weak_sandbox``
(``--allow-weak-sandbox``); without it, a machine without bubblewrap refuses to start
before claiming anything.

Replays are written to ``settings.replays_dir`` as ``<race id>.viser`` and
``<race id>.replay.json.gz`` (the race id is the job id).
"""

from __future__ import annotations

import logging
import os
import random
import socket
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sqlalchemy import and_, select, update
from sqlalchemy.orm import Session, selectinload

from leaderboard import matchmaking, queue, robustness, tournaments
from leaderboard.db import make_engine, make_sessionmaker
from leaderboard.migrations import upgrade
from leaderboard.models import Job, Race, utcnow
from leaderboard.settings import Settings

if TYPE_CHECKING:
    from submissions.jobs import JobResult, RaceJob

log = logging.getLogger(__name__)

Runner = Callable[[Sequence["RaceJob"]], Iterable["JobResult"]]
ProgressFn = Callable[["WorkerStats"], None]
STALL_S = 120.0  # a race whose step count has not moved for this long loses its lease, s
CANCELLED = "cancelled"  # = submissions.executors.CANCELLED (not imported: no simulator here)
HANDED_BACK = "the worker stopped"  # the cancel reason of a graceful stop


def progress_path(out_dir: str | Path, job_id: str) -> Path:
    """Where a running job reports its step count (a hidden file beside its replays)."""
    return Path(out_dir) / f".{job_id}.progress"


def release(session: Session, lease: queue.Lease) -> bool:
    """Hand a leased job back to the queue without spending an attempt (a graceful stop).

    Returns False if the lease was no longer held.
    """
    now = utcnow()
    res = session.execute(
        update(Job)
        .where(and_(Job.id == lease.job_id, Job.lease_token == lease.token, Job.status == "leased"))
        .values(
            status="queued",
            attempts=Job.attempts - 1,
            lease_token=None,
            lease_owner=None,
            lease_expires_at=None,
            updated_at=now,
        )
        .execution_options(synchronize_session=False)
    )
    if not res.rowcount:  # type: ignore[attr-defined]
        session.rollback()
        return False
    race = session.get(Race, lease.race_id)
    if race is not None:
        race.status = "queued"
    session.commit()
    return True


@dataclass
class WorkerStats:
    """What a worker did: races stored, results discarded (lease lost), races failed, races
    handed back by a graceful stop, races cancelled for making no progress."""

    completed: int = 0
    discarded: int = 0
    failed: int = 0
    handed_back: int = 0
    stalled: int = 0


def race_job(race: Race, settings: Settings) -> RaceJob:
    """The evaluation job of a queued race (car ``i`` is entry ``car == i``); for a race of
    kind ``robustness``, the robustness run of its one entry over
    :func:`submissions.robustness.leaderboard_grid` (no replay); a tournament's time trial
    is a solo race."""
    from submissions.jobs import Entrant, RaceJob  # noqa: PLC0415 - light, but not web-side

    grid = None
    if race.kind == "robustness":
        from submissions.robustness import leaderboard_grid  # noqa: PLC0415 - numpy

        grid = tuple(leaderboard_grid())
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
        car=race.car,
        record_viser=grid is None,
        robustness=grid,
        solo=race.stage == "trial",  # a tournament's time trial: one car alone
    )


def default_runner(
    workers: int = 1, ray_address: str | None = None, allow_weak_sandbox: bool = False
) -> Any:
    """The executor (:func:`submissions.executors.make_executor`: a process pool or Ray).

    Raises:
        SandboxError: bubblewrap cannot run here and ``allow_weak_sandbox`` is False.
    """
    from submissions.executors import KEEP_WARM_S, make_executor  # noqa: PLC0415 - the simulator
    from submissions.sandbox import allow_weak_sandbox as allow  # noqa: PLC0415
    from submissions.sandbox import sandbox_mode  # noqa: PLC0415
    from submissions.scheduling import check_settings  # noqa: PLC0415

    if allow_weak_sandbox:
        allow()
    sandbox_mode()  # fail closed before any race is claimed
    check_settings()  # a malformed scheduling setting likewise
    # Job processes (and their sandboxes) stay warm between batches: a bundle raced again
    # soon after skips its sandbox's start-up (Worker.close ends them). They start now, so
    # the first race claimed does not wait for them.
    executor = make_executor(ray_address=ray_address, workers=workers, keep_warm_s=KEEP_WARM_S)
    executor.prestart()
    return executor


class Worker:
    """Claims, runs and stores races (see the module docstring).

    Args:
        settings: database URL, data folder, lease length, matchmaking settings.
        workers: races run at once (and claimed per cycle).
        ray_address: run the races on this Ray cluster instead of local processes.
        runner: runs a batch of jobs and yields their results (default: the executor);
            tests inject a fake one. A runner with a ``cancel(job_id, reason)`` method (the
            executors have one) has stalled or stopped jobs killed; others are only no
            longer renewed.
        schedule: top the queue up with ranked races when it runs low, and (with
            ``settings.robustness``) queue the robustness runs of newly ranked versions.
        owner: the name leases are taken under (default: host, pid and a random suffix).
        allow_weak_sandbox: accept the seccomp fallback where bubblewrap cannot run.
        stall_s: renew a lease only while its race's step count moved in the last
            ``stall_s`` seconds.
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
        allow_weak_sandbox: bool = False,
        stall_s: float = STALL_S,
    ) -> None:
        self.settings = settings
        self.workers = max(1, workers)
        self.schedule = schedule
        self.owner = owner or f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:6]}"
        self.allow_weak_sandbox = allow_weak_sandbox
        self.stall_s = stall_s
        self.stopping = threading.Event()
        settings.ensure_dirs()
        self.engine = make_engine(settings.db_url)
        if settings.auto_migrate:
            upgrade(settings.db_url, engine=self.engine)
        self.sessions = make_sessionmaker(self.engine)
        self._runner = runner
        self._cancel: Callable[[str, str], None] | None = getattr(runner, "cancel", None)
        self._close_runner: Callable[[], None] | None = None  # the executor's close
        self._ray_address = ray_address
        self._running: list[str] = []  # job ids of the batch in progress
        self.rng = random.Random()

    @property
    def runner(self) -> Runner:
        """The job runner (the executor is created on first use; fails closed).

        Raises:
            SandboxError: no namespace sandbox here and the fallback was not allowed.
        """
        if self._runner is None:
            executor = default_runner(self.workers, self._ray_address, self.allow_weak_sandbox)
            self._runner, self._cancel = executor.run, executor.cancel
            self._close_runner = executor.close
        return self._runner

    def request_stop(self) -> None:
        """Stop after handing the running races back (see the module docstring); safe to
        call from a signal handler or another thread."""
        self.stopping.set()
        if self._cancel is not None:
            for job_id in list(self._running):
                self._cancel(job_id, HANDED_BACK)

    def close(self) -> None:
        """End the executor's warm job processes; release the database connections."""
        if self._close_runner is not None:
            self._close_runner()
        self.engine.dispose()

    # ---- one cycle -------------------------------------------------------------------------

    def prepare(self) -> None:
        """Fail races that lost their lease too often; move the tournaments on (queue their
        next heats, plan finals: :func:`leaderboard.tournaments.advance`); queue the
        robustness runs of newly ranked versions (:mod:`leaderboard.robustness`) and ranked
        races if running low."""
        with self.sessions() as session:
            queue.expire(session)
            # An operator's tournaments run whether or not this worker schedules the ladder.
            tournaments.advance(session, self.settings, slots=self.workers)
            if self.schedule:
                if self.settings.robustness:
                    robustness.schedule_robustness(session, self.settings)
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
        self._running = list(jobs)
        if self.stopping.is_set():  # asked to stop while claiming: hand these back at once
            self.request_stop()
        beat = threading.Thread(
            target=self._heartbeat,
            args=(list(leases), stop, stats),
            name="lease-heartbeat",
            daemon=True,
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
            self._running = []
            for job in jobs.values():
                progress_path(job.out_dir, job.job_id).unlink(missing_ok=True)
            with self.sessions() as session:  # a runner that stopped early: give races back
                for lease in by_job.values():
                    if self.stopping.is_set():
                        stats.handed_back += release(session, lease)
                    else:
                        queue.fail(session, lease, "the runner returned no result")
                        stats.failed += 1
        return stats

    def _store(self, lease: queue.Lease, result: JobResult, stats: WorkerStats) -> None:
        with self.sessions() as session:
            if result.error is not None:
                if result.error == f"{CANCELLED}: {HANDED_BACK}":
                    stats.handed_back += release(session, lease)  # not the race's fault
                    return
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
                logs=result.logs,
            )
        if stored:
            stats.completed += 1
        else:
            stats.discarded += 1
            log.warning("race %s: lease lost, result discarded", lease.race_id)

    def _heartbeat(
        self, leases: list[queue.Lease], stop: threading.Event, stats: WorkerStats
    ) -> None:
        """Renew each lease while its race progresses; cancel a stalled race's job."""
        period = max(0.2, min(self.settings.lease_s / 3, self.stall_s / 2))
        seen: dict[int, tuple[str, float]] = {}  # race id -> (last count, when it changed)
        while not stop.wait(period):
            now = time.monotonic()
            with self.sessions() as session:
                for lease in list(leases):
                    if self._stalled(lease, seen, now):
                        leases.remove(lease)  # no renewal: the lease runs out
                        stats.stalled += 1
                        log.warning(
                            "race %s made no progress for %.0f s: its job is cancelled",
                            lease.race_id,
                            self.stall_s,
                        )
                        if self._cancel is not None:
                            self._cancel(str(lease.race_id), f"no progress for {self.stall_s:g} s")
                        continue
                    if not queue.heartbeat(session, lease, lease_s=self.settings.lease_s):
                        leases.remove(lease)  # taken over: its result will be discarded

    def _stalled(self, lease: queue.Lease, seen: dict[int, tuple[str, float]], now: float) -> bool:
        path = progress_path(self.settings.replays_dir.resolve(), str(lease.race_id))
        try:
            count = path.read_text()
        except OSError:
            return False  # not started yet: the executor's wall-clock limit bounds it
        last = seen.get(lease.race_id)
        if last is None or last[0] != count:
            seen[lease.race_id] = (count, now)
            return False
        return now - last[1] > self.stall_s

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
        self.runner  # noqa: B018 - create the executor now: fail closed before claiming
        while not stop.is_set() and not self.stopping.is_set():
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
