"""Executors: run many race jobs at once, on this machine or on a Ray cluster.

Both take the same job function (:func:`submissions.jobs.run_race_job` by default) and offer
``run(jobs, progress=None) -> Iterator[JobResult]``, yielding each job's result exactly once,
in the order the jobs finish.

* :class:`LocalExecutor` (the default): one fresh process per job, at most ``workers`` at a
  time, started from a fork server that has the simulator already imported. A process per job
  (rather than a long-lived pool) means a job that kills its worker — a segfault in the
  physics, the OOM killer, ``os._exit`` — is attributed to that job alone: it is run again up
  to ``max_retries`` times, and the other jobs are untouched. A job that *raises* is not
  retried (it would raise again): its result carries the error. ``job_timeout_s`` kills a job
  that runs too long (its sandboxed policies die with it: ``--die-with-parent``).
* :class:`RayExecutor` (``--ray-address``): the same function as a Ray task with
  ``max_retries`` (Ray re-runs a task whose worker process died, not one that raised). Every
  node must see the bundles and ``out_dir`` at the same paths (a shared file system).

A job that fails for good yields a :class:`~submissions.jobs.JobResult` whose ``error`` says
why (``ok`` is False), so one bad job never stops the batch.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import sys
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from typing import Any, Protocol

from submissions.errors import SubmissionError
from submissions.jobs import JobResult, RaceJob, run_race_job

JobFn = Callable[[RaceJob], JobResult]
ProgressFn = Callable[[int, int], None]  # (jobs done, jobs in the batch)
PRELOAD = ["submissions.jobs", "arena.race", "agents.baselines"]  # imported once, in the server


class Executor(Protocol):
    """What :func:`make_executor` returns."""

    def run(
        self, jobs: Sequence[RaceJob], progress: ProgressFn | None = None
    ) -> Iterator[JobResult]:
        """Run ``jobs``; yield each one's result once, as they finish."""
        ...


def _child(fn: JobFn, job: RaceJob, conn: Connection) -> None:
    """A job process: run the job, send back ("ok", result dict) or ("error", one line)."""
    try:
        message: tuple[str, Any] = ("ok", fn(job).to_dict())
    except Exception as err:  # reported to the parent as the job's error, not retried
        message = ("error", f"{type(err).__name__}: {err}")
    conn.send(message)
    conn.close()


@dataclass
class _Running:
    job: RaceJob
    attempt: int
    process: Any  # multiprocessing.Process of the chosen context
    conn: Connection
    started: float
    message: tuple[str, Any] | None = None


class LocalExecutor:
    """Runs jobs in fresh local processes, ``workers`` at a time (see the module docstring).

    Args:
        workers: jobs at once (each uses about one core, plus its sandboxed policies).
        max_retries: extra runs for a job whose process died.
        fn: the job function; a top-level (importable) function.
        job_timeout_s: kill a job after this many seconds (None: no limit).
        start_method: ``"forkserver"`` (default on Linux) or ``"spawn"``.
    """

    def __init__(
        self,
        workers: int = 2,
        max_retries: int = 2,
        fn: JobFn = run_race_job,
        job_timeout_s: float | None = None,
        start_method: str | None = None,
    ) -> None:
        if workers < 1:
            raise SubmissionError(f"workers must be at least 1, not {workers}")
        if max_retries < 0:
            raise SubmissionError(f"max_retries must be 0 or more, not {max_retries}")
        self.workers = workers
        self.max_retries = max_retries
        self.fn = fn
        self.job_timeout_s = job_timeout_s
        method = start_method or ("forkserver" if sys.platform == "linux" else "spawn")
        self.context = mp.get_context(method)
        if method == "forkserver":
            self.context.set_forkserver_preload(PRELOAD)

    def _start(self, job: RaceJob, attempt: int) -> _Running:
        recv, send = self.context.Pipe(duplex=False)
        proc = self.context.Process(  # type: ignore[attr-defined]
            target=_child, args=(self.fn, job, send), name=f"slipstream-job-{job.job_id}"
        )
        proc.start()
        send.close()  # the child holds the only write end: EOF when it dies
        return _Running(job, attempt, proc, recv, time.monotonic())

    def _outcome(self, run: _Running) -> JobResult | None:
        """The job's final result, or None when it should run again."""
        elapsed = round(time.monotonic() - run.started, 3)
        if run.message is not None:
            kind, payload = run.message
            if kind == "ok":
                result = JobResult.from_dict(payload)
                result.attempts = run.attempt
                return result
            return JobResult.failed(run.job, str(payload), run.attempt, elapsed)
        if run.attempt <= self.max_retries:
            return None
        code = run.process.exitcode
        return JobResult.failed(
            run.job,
            f"the job's worker process died (exit code {code}) on all {run.attempt} attempts",
            run.attempt,
            elapsed,
        )

    def run(
        self, jobs: Sequence[RaceJob], progress: ProgressFn | None = None
    ) -> Iterator[JobResult]:
        """Run ``jobs``; yield each one's result once, as they finish."""
        queue: deque[tuple[RaceJob, int]] = deque((job, 1) for job in jobs)
        running: list[_Running] = []
        done, total = 0, len(queue)
        try:
            while queue or running:
                while queue and len(running) < self.workers:
                    running.append(self._start(*queue.popleft()))
                ready = set(
                    wait([r.conn for r in running] + [r.process.sentinel for r in running], 1.0)
                )
                for run in list(running):
                    if run.conn in ready and run.message is None:
                        # EOF: it died without a word; judged below, once it is gone.
                        with contextlib.suppress(EOFError, OSError):
                            run.message = run.conn.recv()
                    timed_out = (
                        self.job_timeout_s is not None
                        and time.monotonic() - run.started > self.job_timeout_s
                    )
                    if timed_out and run.process.is_alive():
                        run.process.kill()
                        run.message = ("error", f"timed out after {self.job_timeout_s} s")
                    if run.process.is_alive():
                        continue
                    run.process.join()
                    run.conn.close()
                    running.remove(run)
                    result = self._outcome(run)
                    if result is None:
                        queue.appendleft((run.job, run.attempt + 1))
                        continue
                    done += 1
                    if progress is not None:
                        progress(done, total)
                    yield result
        finally:
            for run in running:  # interrupted (or the consumer stopped early)
                run.process.kill()
                run.process.join()
                run.conn.close()


class RayExecutor:
    """Runs jobs as Ray tasks (see the module docstring).

    Args:
        address: the cluster (``ray.init(address=...)``: ``"auto"``, ``"ray://host:10001"``),
            ``"local"`` to start a Ray instance on this machine, or None to use the Ray
            already initialised in this process (or start a local one).
        max_retries: Ray's retries for a task whose worker died.
        fn: the job function.
        num_cpus: CPUs for a local instance (None: Ray's choice).
    """

    def __init__(
        self,
        address: str | None = None,
        max_retries: int = 2,
        fn: JobFn = run_race_job,
        num_cpus: int | None = None,
    ) -> None:
        self.address = address
        self.max_retries = max_retries
        self.fn = fn
        self.num_cpus = num_cpus

    def connect(self) -> Any:
        try:
            import ray  # noqa: PLC0415 - optional `eval` extra, only with --ray-address
        except ImportError as err:
            raise SubmissionError(
                "the Ray executor needs ray: pip install 'slipstream[eval]'"
            ) from err
        if not ray.is_initialized():
            address = None if self.address in (None, "local") else self.address
            try:
                ray.init(
                    address=address,
                    num_cpus=self.num_cpus if address is None else None,
                    include_dashboard=False,
                    log_to_driver=False,
                )
            except (ConnectionError, RuntimeError, ValueError) as err:
                raise SubmissionError(f"cannot connect to Ray at {self.address!r}: {err}") from None
        return ray

    def run(
        self, jobs: Sequence[RaceJob], progress: ProgressFn | None = None
    ) -> Iterator[JobResult]:
        """Run ``jobs`` as Ray tasks; yield each one's result once, as they finish."""
        ray = self.connect()
        task = ray.remote(max_retries=self.max_retries, num_cpus=1)(self.fn)
        started = time.monotonic()
        refs = {task.remote(job): job for job in jobs}
        pending = list(refs)
        done = 0
        try:
            while pending:
                ready, pending = ray.wait(pending, num_returns=1)
                for ref in ready:
                    job = refs[ref]
                    try:
                        result = ray.get(ref)
                    except ray.exceptions.RayTaskError as err:  # the job raised
                        cause = err.cause if err.cause is not None else err
                        line = f"{type(cause).__name__}: {cause}".splitlines()[0]
                        result = JobResult.failed(job, line, 1, time.monotonic() - started)
                    except ray.exceptions.RayError as err:  # worker died past max_retries, …
                        line = f"{type(err).__name__}: {str(err).splitlines()[0]}"
                        result = JobResult.failed(
                            job, line, self.max_retries + 1, time.monotonic() - started
                        )
                    done += 1
                    if progress is not None:
                        progress(done, len(refs))
                    yield result
        finally:
            for ref in pending:
                ray.cancel(ref, force=True)


def make_executor(
    ray_address: str | None = None, workers: int = 2, max_retries: int = 2
) -> LocalExecutor | RayExecutor:
    """A :class:`RayExecutor` when ``ray_address`` is given, else a :class:`LocalExecutor`."""
    if ray_address:
        return RayExecutor(ray_address, max_retries=max_retries, num_cpus=workers)
    return LocalExecutor(workers=workers, max_retries=max_retries)


__all__ = ["Executor", "LocalExecutor", "RayExecutor", "make_executor"]
