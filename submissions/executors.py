"""Executors: run many race jobs at once, on this machine or on a Ray cluster.

Both take the same job function (:func:`submissions.jobs.run_race_job` by default) and offer
``run(jobs, progress=None) -> Iterator[JobResult]``, yielding each job's result exactly once,
in the order the jobs finish.

* :class:`LocalExecutor` (the default): one fresh process per job, at most ``workers`` at a
  time, started with multiprocessing's ``spawn`` method: no fork server, so the runner has
  no listening socket a policy could reach (Python 3.11's fork server accepts unauthenticated
  connections and unpickles what it is sent); the job and its parent talk over a pipe. A
  process per job means a job that kills its worker — a segfault in the physics, the OOM
  killer, ``os._exit`` — is attributed to that job alone: it is run again up to
  ``max_retries`` times, and the other jobs are untouched. A job that *raises* is not
  retried (it would raise again): its result carries the error.
* :class:`RayExecutor` (``--ray-address``): each Ray task runs its job through a one-job
  :class:`LocalExecutor` on its node, so timeouts, retries and clean-up are the same. Every
  node must see the bundles and ``out_dir`` at the same paths (a shared file system).

Lifetime: each job process gets a private scratch folder (``<tmp>/slipstream-job-<executor
pid>-<n>``, its ``tempfile`` folder: the bundles it extracts and every sandbox folder land
there), a parent-death signal and SIGINT ignored (Ctrl-C is the runner's to handle). A job
that outlives ``job_timeout_s`` (default :data:`JOB_TIMEOUT_S`) is killed and counted failed
(``error`` starts with ``"timed out"``), never retried. Whenever a job process ends —
finished, raised, died, timed out, or the executor stopped — its scratch folder is reaped
(:func:`submissions.sandbox.reap_tree`: sandbox processes, cgroups, tmpfs mounts, files).
Each ``run`` first reaps what a SIGKILLed runner left (:func:`submissions.sandbox.reap_stale`).

A job that fails for good yields a :class:`~submissions.jobs.JobResult` whose ``error`` says
why (``ok`` is False), so one bad job never stops the batch.
"""

from __future__ import annotations

import contextlib
import itertools
import multiprocessing as mp
import os
import signal
import tempfile
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import Any, Protocol

from submissions.errors import SubmissionError
from submissions.jobs import JobResult, RaceJob, run_race_job
from submissions.sandbox import JOB_PREFIX, WEAK_ENV, reap_stale, reap_tree, weak_sandbox_allowed

JobFn = Callable[[RaceJob], JobResult]
ProgressFn = Callable[[int, int], None]  # (jobs done, jobs in the batch)
JOB_TIMEOUT_S = 900.0  # a job's wall-clock backstop, s (a race has its own, shorter limit)
TIMED_OUT = "timed out"  # how a timed-out job's error starts (failed by its policies)
TASK_GRACE_S = 120.0  # a Ray task's allowance on top of its jobs' limits, s
CANCELLED = "cancelled"  # how a job cancelled by its runner's :meth:`cancel` errors start
_SCRATCH = itertools.count()


class Executor(Protocol):
    """What :func:`make_executor` returns."""

    def run(
        self, jobs: Sequence[RaceJob], progress: ProgressFn | None = None
    ) -> Iterator[JobResult]:
        """Run ``jobs``; yield each one's result once, as they finish."""
        ...

    def cancel(self, job_id: str, reason: str) -> None:
        """Kill a running (or pending) job from any thread; its result's ``error`` is
        ``"cancelled: <reason>"`` and it is not retried."""
        ...


def _child(fn: JobFn, job: RaceJob, conn: Connection, scratch: str) -> None:
    """A job process: run the job, send back ("ok", result dict) or ("error", one line).

    It dies with its parent (SIGTERM: it reaps its scratch folder first), ignores Ctrl-C
    (the runner handles it) and keeps every temporary file in ``scratch``.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    def parent_died(signum: int, frame: object) -> None:
        reap_tree(Path(scratch))
        os._exit(1)

    signal.signal(signal.SIGTERM, parent_died)
    _set_parent_death_signal(signal.SIGTERM)
    if os.getppid() == 1:  # the parent died before the line above
        parent_died(0, None)
    tempfile.tempdir = scratch
    try:
        message: tuple[str, Any] = ("ok", fn(job).to_dict())
    except Exception as err:  # reported to the parent as the job's error, not retried
        message = ("error", f"{type(err).__name__}: {err}")
    conn.send(message)
    conn.close()


def _set_parent_death_signal(sig: int) -> None:
    import ctypes  # noqa: PLC0415 - only in job processes

    ctypes.CDLL(None).prctl(1, int(sig), 0, 0, 0)  # PR_SET_PDEATHSIG


@dataclass
class _Running:
    job: RaceJob
    attempt: int
    process: Any  # multiprocessing.Process of the chosen context
    conn: Connection
    started: float
    scratch: Path
    message: tuple[str, Any] | None = None


class LocalExecutor:
    """Runs jobs in fresh local processes, ``workers`` at a time (see the module docstring).

    Args:
        workers: jobs at once (each uses about one core, plus its sandboxed policies).
        max_retries: extra runs for a job whose process died.
        fn: the job function; a top-level (importable) function.
        job_timeout_s: kill a job after this many seconds (counted failed, not retried).
        start_method: ``"spawn"`` (default) or ``"fork"``; never ``"forkserver"`` (a
            listening socket the sandbox could reach).

    Raises:
        SubmissionError: bad arguments.
    """

    def __init__(
        self,
        workers: int = 2,
        max_retries: int = 2,
        fn: JobFn = run_race_job,
        job_timeout_s: float = JOB_TIMEOUT_S,
        start_method: str = "spawn",
    ) -> None:
        if workers < 1:
            raise SubmissionError(f"workers must be at least 1, not {workers}")
        if max_retries < 0:
            raise SubmissionError(f"max_retries must be 0 or more, not {max_retries}")
        self.workers = workers
        self.max_retries = max_retries
        self.fn = fn
        if not job_timeout_s > 0:
            raise SubmissionError(f"job_timeout_s must be positive, not {job_timeout_s}")
        if start_method not in ("spawn", "fork"):
            raise SubmissionError(f"start_method must be spawn or fork, not {start_method!r}")
        self.job_timeout_s = job_timeout_s
        self.context = mp.get_context(start_method)
        self._cancelled: dict[str, str] = {}  # job id -> reason, set from any thread

    def cancel(self, job_id: str, reason: str) -> None:
        """Kill job ``job_id`` (see :meth:`Executor.cancel`); thread-safe."""
        self._cancelled[job_id] = reason

    def _start(self, job: RaceJob, attempt: int) -> _Running:
        scratch = Path(tempfile.gettempdir()) / f"{JOB_PREFIX}{os.getpid()}-{next(_SCRATCH)}"
        scratch.mkdir(mode=0o711)  # sandboxes' folders lie inside; others may pass through
        recv, send = self.context.Pipe(duplex=False)
        proc = self.context.Process(  # type: ignore[attr-defined]
            target=_child,
            args=(self.fn, job, send, str(scratch)),
            name=f"slipstream-job-{job.job_id}",
        )
        try:
            proc.start()
        except BaseException:
            reap_tree(scratch)
            raise
        send.close()  # the child holds the only write end: EOF when it dies
        return _Running(job, attempt, proc, recv, time.monotonic(), scratch)

    @staticmethod
    def _end(run: _Running) -> None:
        """Kill the job process if it still runs, then reap everything it left."""
        if run.process.is_alive():
            run.process.kill()
        run.process.join()
        run.conn.close()
        reap_tree(run.scratch)

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
        reap_stale()
        queue: deque[tuple[RaceJob, int]] = deque((job, 1) for job in jobs)
        running: list[_Running] = []
        done, total = 0, len(queue)
        try:
            while queue or running:
                while queue and len(running) < self.workers:
                    job, attempt = queue.popleft()
                    if (reason := self._cancelled.pop(job.job_id, None)) is not None:
                        done += 1
                        yield JobResult.failed(job, f"{CANCELLED}: {reason}", attempt - 1, 0.0)
                        continue
                    running.append(self._start(job, attempt))
                ready = set(
                    wait([r.conn for r in running] + [r.process.sentinel for r in running], 1.0)
                )
                for run in list(running):
                    if run.conn in ready and run.message is None:
                        # EOF: it died without a word; judged below, once it is gone.
                        with contextlib.suppress(EOFError, OSError):
                            run.message = run.conn.recv()
                    reason = self._cancelled.pop(run.job.job_id, None)
                    if reason is not None and run.process.is_alive():
                        run.process.kill()
                        run.message = ("error", f"{CANCELLED}: {reason}")
                    timed_out = time.monotonic() - run.started > self.job_timeout_s
                    if timed_out and run.process.is_alive():
                        run.process.kill()
                        run.message = (
                            "error",
                            f"{TIMED_OUT} after {self.job_timeout_s:g} s: every process of "
                            "the job was killed",
                        )
                    if run.process.is_alive():
                        continue
                    self._end(run)
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
                self._end(run)


def run_isolated(
    job: RaceJob, fn: JobFn, max_retries: int, job_timeout_s: float, allow_weak: bool
) -> JobResult:
    """One job through a one-job :class:`LocalExecutor` (what a Ray task runs)."""
    if allow_weak:
        os.environ[WEAK_ENV] = "1"
    executor = LocalExecutor(1, max_retries, fn, job_timeout_s)
    (result,) = executor.run([job])
    return result


class RayExecutor:
    """Runs jobs as Ray tasks (see the module docstring).

    Args:
        address: the cluster (``ray.init(address=...)``: ``"auto"``, ``"ray://host:10001"``),
            ``"local"`` to start a Ray instance on this machine, or None to use the Ray
            already initialised in this process (or start a local one).
        max_retries: extra runs for a job whose process died (on the node, as locally).
        fn: the job function.
        num_cpus: CPUs for a local instance (None: Ray's choice).
        job_timeout_s: each job's wall-clock limit on its node; the driver also cancels a
            task that has not answered ``TASK_GRACE_S`` after all its attempts could end.
    """

    def __init__(
        self,
        address: str | None = None,
        max_retries: int = 2,
        fn: JobFn = run_race_job,
        num_cpus: int | None = None,
        job_timeout_s: float = JOB_TIMEOUT_S,
    ) -> None:
        self.address = address
        self.max_retries = max_retries
        self.fn = fn
        self.num_cpus = num_cpus
        self.job_timeout_s = job_timeout_s
        self._cancelled: dict[str, str] = {}
        self._refs: dict[str, Any] = {}  # job id -> its running task

    def cancel(self, job_id: str, reason: str) -> None:
        """Cancel job ``job_id``'s Ray task (see :meth:`Executor.cancel`); thread-safe."""
        self._cancelled[job_id] = reason
        ref = self._refs.get(job_id)
        if ref is not None:
            self.connect().cancel(ref, force=True)

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
        task = ray.remote(max_retries=0, num_cpus=1)(run_isolated)
        weak = weak_sandbox_allowed()
        started = time.monotonic()
        refs = {
            task.remote(job, self.fn, self.max_retries, self.job_timeout_s, weak): job
            for job in jobs
        }
        self._refs = {job.job_id: ref for ref, job in refs.items()}
        limit = self.job_timeout_s * (self.max_retries + 1) + TASK_GRACE_S
        pending = list(refs)
        done = 0
        try:
            while pending:
                ready, pending = ray.wait(pending, num_returns=1, timeout=1.0)
                results = []
                for ref in ready:
                    job = refs[ref]
                    try:
                        results.append(ray.get(ref))
                    except ray.exceptions.RayTaskError as err:  # the job raised
                        cause = err.cause if err.cause is not None else err
                        line = f"{type(cause).__name__}: {cause}".splitlines()[0]
                        results.append(JobResult.failed(job, line, 1, time.monotonic() - started))
                    except ray.exceptions.RayError as err:  # its node or worker died, …
                        line = f"{type(err).__name__}: {str(err).splitlines()[0]}"
                        if job.job_id in self._cancelled:
                            line = f"{CANCELLED}: {self._cancelled.pop(job.job_id)}"
                        results.append(JobResult.failed(job, line, 1, time.monotonic() - started))
                if time.monotonic() - started > limit:  # the node never answered: give up
                    for ref in pending:
                        ray.cancel(ref, force=True)
                        line = f"{TIMED_OUT} after {limit:g} s (the Ray task was cancelled)"
                        results.append(JobResult.failed(refs[ref], line, 1, limit))
                    pending = []
                for result in results:
                    done += 1
                    if progress is not None:
                        progress(done, len(refs))
                    yield result
        finally:
            for ref in pending:
                ray.cancel(ref, force=True)


def make_executor(
    ray_address: str | None = None,
    workers: int = 2,
    max_retries: int = 2,
    job_timeout_s: float = JOB_TIMEOUT_S,
) -> LocalExecutor | RayExecutor:
    """A :class:`RayExecutor` when ``ray_address`` is given, else a :class:`LocalExecutor`."""
    if ray_address:
        return RayExecutor(
            ray_address, max_retries=max_retries, num_cpus=workers, job_timeout_s=job_timeout_s
        )
    return LocalExecutor(workers=workers, max_retries=max_retries, job_timeout_s=job_timeout_s)


__all__ = ["Executor", "LocalExecutor", "RayExecutor", "make_executor"]
