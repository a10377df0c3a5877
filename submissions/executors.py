"""Executors: run many race jobs at once, on this machine or on a Ray cluster.

Both take the same job function (:func:`submissions.jobs.run_race_job` by default) and offer
``run(jobs, progress=None) -> Iterator[JobResult]``, yielding each job's result exactly once,
in the order the jobs finish, ``cancel(job_id, reason)`` and ``close()`` (they are context
managers).

* :class:`LocalExecutor` (the default): at most ``workers`` job processes, started with
  multiprocessing's ``spawn`` method: no fork server, so the runner has no listening socket a
  policy could reach (Python 3.11's fork server accepts unauthenticated connections and
  unpickles what it is sent); a job process and its parent talk over two pipes. **Sandbox
  reuse:** a job process runs jobs one at a time, handed to it over its pipe, inside one
  :class:`~submissions.jobs.JobBatch`: the sandboxes a race started stay running for the
  process's next job with the same bundle (:class:`~submissions.remote.SandboxPool`), so a
  batch pays each sandbox's start-up once. Each free process is given the queued job that
  races the most of the bundles its last job raced (bundle affinity; else the first queued);
  a process runs at most ``batch_size`` jobs and is then replaced by a fresh one (a bound on
  how long a policy's process, and its memory, lives). With ``keep_warm_s`` > 0 the idle
  processes (and their sandboxes) outlive ``run`` by that long, for the next ``run`` (the
  validation race of ``slipstream evaluate`` and its races, the leaderboard worker's
  successive batches); ``close()`` ends them at once. :meth:`LocalExecutor.prestart` starts
  them before the first run (``evaluate`` while it checks the bundle, the worker when it
  starts), and a job process imports the race machinery before it says it is ready
  (:func:`submissions.jobs.preload`), so no race waits for a process's start-up.
  A process holds one job at a time, so a job that kills its worker — a segfault in the
  physics, the OOM killer, ``os._exit`` — is attributed to that job alone: it is run again
  up to ``max_retries`` times, and the other jobs are untouched (they were never in that
  process). A job that *raises* is not retried (it would raise again): its result carries
  the error, and its process goes on with the next job.
* :class:`RayExecutor` (``--ray-address``): the jobs are grouped by the bundles they race
  (jobs racing the same set of bundles together) into batches of at most ``batch_size``
  (split further so the cluster's CPUs all get work), and each batch is one Ray task that
  runs its jobs through a one-process :class:`LocalExecutor` on its node — same reuse,
  timeouts, retries and clean-up — and streams each result back as it finishes. Every node
  must see the bundles and ``out_dir`` at the same paths (a shared file system).

Lifetime: each job process gets a private scratch folder (``<tmp>/slipstream-job-<executor
pid>-<n>``, its ``tempfile`` folder: the bundles it extracts and every sandbox folder land
there), a parent-death signal and SIGINT ignored (Ctrl-C is the runner's to handle). A job
that outlives ``job_timeout_s`` (default :data:`JOB_TIMEOUT_S`) from the moment its process
could run it (handed over to a started process, or the process said it started) is killed
with that process — every sandbox it holds — and counted failed (``error`` starts with
``"timed out"``), never retried; the jobs queued behind it go to other processes. A job
process that does not start within :data:`START_TIMEOUT_S` (a loaded machine, not the job's
fault) is killed and its job run again, as after a death. Whenever a job process ends —
retired, raised out, died, timed out, or the executor stopped or closed — its scratch folder
is reaped (:func:`submissions.sandbox.reap_tree`: sandbox processes, cgroups, tmpfs mounts,
files).
Each ``run`` first reaps what a SIGKILLed runner left (:func:`submissions.sandbox.reap_stale`).

A job that fails for good yields a :class:`~submissions.jobs.JobResult` whose ``error`` says
why (``ok`` is False), so one bad job never stops the batch.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import multiprocessing as mp
import os
import signal
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import Any, Protocol

from submissions.errors import SubmissionError
from submissions.jobs import JobResult, RaceJob, run_race_job
from submissions.sandbox import JOB_PREFIX, WEAK_ENV, reap_stale, reap_tree, weak_sandbox_allowed

JobFn = Callable[[RaceJob], JobResult]
ProgressFn = Callable[[int, int], None]  # (jobs done, jobs in the batch)
JOB_TIMEOUT_S = 900.0  # a job's wall-clock backstop, s (a race has its own, shorter limit)
START_TIMEOUT_S = 300.0  # a job process's start-up (interpreter, imports) at most, s
BATCH_SIZE = 8  # jobs one job process runs before a fresh one replaces it
KEEP_WARM_S = 60.0  # how long evaluate's and the leaderboard's idle job processes are kept, s
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

    def prestart(self, wait_s: float = 0.0) -> int:
        """Start what the first run would otherwise wait for; the processes kept warm."""
        ...

    def close(self) -> None:
        """End every process (and sandbox) the executor keeps between runs; idempotent."""
        ...


def bundle_sources(job: RaceJob) -> frozenset[str]:
    """The bundles a job races (its entrants' sources, baselines left out)."""
    return frozenset(e.source for e in job.entrants if not e.is_baseline)


def _child(fn: JobFn, jobs: Connection, results: Connection, scratch: str) -> None:
    """A job process: say ("ready", None) once started, then run each job it is handed, in
    one :func:`submissions.jobs.job_batch` (sandboxes kept between jobs), sending back
    ("ok", result dict) or ("error", one line); ends when its parent closes the pipe or
    sends None.

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
    from submissions.jobs import job_batch  # noqa: PLC0415 - after tempdir: its folder is here

    with job_batch():
        results.send(("ready", None))  # started: its jobs' clocks start now
        while True:
            try:
                job = jobs.recv()
            except (EOFError, OSError):
                return
            if job is None:
                return
            try:
                message: tuple[str, Any] = ("ok", fn(job).to_dict())
            except Exception as err:  # reported to the parent as the job's error, not retried
                message = ("error", f"{type(err).__name__}: {err}")
            results.send(message)


def _set_parent_death_signal(sig: int) -> None:
    import ctypes  # noqa: PLC0415 - only in job processes

    ctypes.CDLL(None).prctl(1, int(sig), 0, 0, 0)  # PR_SET_PDEATHSIG


@dataclass
class _Worker:
    """One job process, and the job it runs (None: idle)."""

    process: Any  # multiprocessing.Process of the chosen context
    jobs: Connection  # ours → its: the jobs
    results: Connection  # its → ours: "ready", then the results (EOF when it dies)
    scratch: Path
    ready: bool = False  # it said it started (its first job's clock starts then)
    warm: frozenset[str] = frozenset()  # the bundles its last job raced (its pool holds them)
    handed: int = 0  # jobs handed to it so far
    job: RaceJob | None = None
    attempt: int = 0
    started: float = 0.0  # when the current job was handed over to a ready process, or
    # (its first job) when the process got ready; before that, when it was handed over
    idle_since: float = field(default_factory=time.monotonic)
    message: tuple[str, Any] | None = None
    killed: bool = False  # by us: its job was cancelled or timed out


def _best(queue: deque[tuple[RaceJob, int]], warm: frozenset[str]) -> int:
    """The index of the queued job that races the most of ``warm``'s bundles (the first
    such; the first job when none does)."""
    best, at = 0, 0
    if warm:
        for i, (job, _) in enumerate(queue):
            shared = len(bundle_sources(job) & warm)
            if shared > best:
                best, at = shared, i
    return at


class LocalExecutor:
    """Runs jobs in local job processes, ``workers`` at a time (see the module docstring).

    Args:
        workers: job processes at once (each uses about one core, plus its sandboxed
            policies).
        max_retries: extra runs for a job whose process died.
        fn: the job function; a top-level (importable) function.
        job_timeout_s: kill a job after this many seconds (counted failed, not retried).
        start_method: ``"spawn"`` (default) or ``"fork"``; never ``"forkserver"`` (a
            listening socket the sandbox could reach).
        batch_size: jobs one process runs (reusing its sandboxes) before it is replaced.
        keep_warm_s: keep idle job processes this long after :meth:`run` for the next one
            (0: end them when ``run`` ends).

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
        batch_size: int = BATCH_SIZE,
        keep_warm_s: float = 0.0,
    ) -> None:
        if workers < 1:
            raise SubmissionError(f"workers must be at least 1, not {workers}")
        if max_retries < 0:
            raise SubmissionError(f"max_retries must be 0 or more, not {max_retries}")
        if not job_timeout_s > 0:
            raise SubmissionError(f"job_timeout_s must be positive, not {job_timeout_s}")
        if start_method not in ("spawn", "fork"):
            raise SubmissionError(f"start_method must be spawn or fork, not {start_method!r}")
        if batch_size < 1:
            raise SubmissionError(f"batch_size must be at least 1, not {batch_size}")
        if not keep_warm_s >= 0:
            raise SubmissionError(f"keep_warm_s must be 0 or more, not {keep_warm_s}")
        self.workers = workers
        self.max_retries = max_retries
        self.fn = fn
        self.job_timeout_s = job_timeout_s
        self.batch_size = batch_size
        self.keep_warm_s = keep_warm_s
        self.context = mp.get_context(start_method)
        self._cancelled: dict[str, str] = {}  # job id -> reason, set from any thread
        self._warm: list[_Worker] = []  # idle processes kept between runs
        self._lock = threading.Lock()  # guards _warm and _timer (the timer is a thread)
        self._timer: threading.Timer | None = None

    def cancel(self, job_id: str, reason: str) -> None:
        """Kill job ``job_id`` (see :meth:`Executor.cancel`); thread-safe."""
        self._cancelled[job_id] = reason

    @property
    def warm(self) -> int:
        """Idle job processes kept for the next :meth:`run`."""
        return len(self._warm)

    def close(self) -> None:
        """End the job processes kept between runs, and their sandboxes; idempotent."""
        with self._lock:
            kept, self._warm = self._warm, []
            self._disarm()
        for worker in kept:
            self._end(worker)

    def prestart(self, wait_s: float = 0.0) -> int:
        """Start job processes now, up to ``workers``, so that the next :meth:`run` does not
        wait for their start-up (a fresh interpreter importing the race machinery,
        :func:`submissions.jobs.preload`: 0.5 s on 2 vCPUs). ``slipstream evaluate`` calls
        it before it checks the bundle, the leaderboard worker when it starts. They are
        kept like the idle processes a run leaves: ``keep_warm_s`` (with 0, until the next
        :meth:`run` or :meth:`close`).

        Args:
            wait_s: block until each process said it started, at most this long, s (0: do
                not wait; a process that never starts is judged by the run that takes it).

        Returns:
            The idle processes now kept (alive).
        """
        with self._lock:
            self._disarm()
            alive: list[_Worker] = []
            dead: list[_Worker] = []
            for worker in self._warm:  # each asked once: it may die meanwhile
                (alive if worker.process.is_alive() else dead).append(worker)
            self._warm = alive
            while len(self._warm) < self.workers:
                self._warm.append(self._spawn())
            waiting = [w for w in self._warm if not w.ready]
            if self.keep_warm_s > 0:
                self._arm()
        for worker in dead:
            self._end(worker)
        deadline = time.monotonic() + wait_s
        while waiting and (left := deadline - time.monotonic()) > 0:
            for conn in wait([w.results for w in waiting], left):
                worker = next(w for w in waiting if w.results is conn)
                waiting.remove(worker)
                with contextlib.suppress(EOFError, OSError):  # died, or ended by the timer
                    worker.ready = worker.results.recv()[0] == "ready"
        return self.warm

    def __enter__(self) -> LocalExecutor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _spawn(self) -> _Worker:
        scratch = Path(tempfile.gettempdir()) / f"{JOB_PREFIX}{os.getpid()}-{next(_SCRATCH)}"
        scratch.mkdir(mode=0o711)  # sandboxes' folders lie inside; others may pass through
        jobs_r, jobs_w = self.context.Pipe(duplex=False)
        results_r, results_w = self.context.Pipe(duplex=False)
        proc = self.context.Process(  # type: ignore[attr-defined]
            target=_child,
            args=(self.fn, jobs_r, results_w, str(scratch)),
            name="slipstream-jobs",
            # Daemonic: an interpreter that exits without close() terminates it (SIGTERM:
            # it reaps its folder) instead of waiting for it; it starts no multiprocessing
            # children of its own (sandboxes are plain subprocesses).
            daemon=True,
        )
        try:
            proc.start()
        except BaseException:
            for conn in (jobs_r, jobs_w, results_r, results_w):
                conn.close()
            reap_tree(scratch)
            raise
        jobs_r.close()  # the child holds the only read end …
        results_w.close()  # … and the only write end: EOF when it dies
        return _Worker(proc, jobs_w, results_r, scratch)

    def _hand(self, worker: _Worker, job: RaceJob, attempt: int) -> None:
        """Give ``job`` to an idle ``worker``; its clock starts now."""
        worker.job, worker.attempt, worker.message = job, attempt, None
        worker.started = time.monotonic()
        worker.handed += 1
        worker.warm = bundle_sources(job)
        with contextlib.suppress(OSError):  # it died: seen as such when it is judged
            worker.jobs.send(job)

    @staticmethod
    def _end(worker: _Worker) -> None:
        """Kill the job process if it still runs, then reap everything it left."""
        if worker.process.is_alive():
            worker.process.kill()
        worker.process.join()
        worker.jobs.close()
        worker.results.close()
        reap_tree(worker.scratch)

    def _outcome(self, worker: _Worker) -> JobResult | None:
        """The current job's final result, or None when it should run again."""
        assert worker.job is not None
        elapsed = round(time.monotonic() - worker.started, 3)
        if worker.message is not None:
            kind, payload = worker.message
            if kind == "ok":
                result = JobResult.from_dict(payload)
                result.attempts = worker.attempt
                return result
            return JobResult.failed(worker.job, str(payload), worker.attempt, elapsed)
        if worker.attempt <= self.max_retries:
            return None
        code = worker.process.exitcode
        return JobResult.failed(
            worker.job,
            f"the job's worker process died (exit code {code}) on all {worker.attempt} attempts",
            worker.attempt,
            elapsed,
        )

    def _judge(self, worker: _Worker, readable: bool) -> bool:
        """Take the current job's message if it came; kill the process of a cancelled or
        timed-out job (recording why). Returns whether the job is over."""
        assert worker.job is not None
        if readable and worker.message is None:
            # EOF: it died without a word; judged below, once it is gone.
            with contextlib.suppress(EOFError, OSError):
                while worker.message is None and worker.results.poll():
                    message = worker.results.recv()
                    if message[0] != "ready":
                        worker.message = message
                    elif not worker.ready:  # the job's clock starts when its process can run it
                        worker.ready, worker.started = True, time.monotonic()
        reason = self._cancelled.pop(worker.job.job_id, None)
        late = time.monotonic() - worker.started > self.job_timeout_s
        if worker.message is None and reason is not None:
            self._kill(worker, ("error", f"{CANCELLED}: {reason}"))
        elif worker.message is None and worker.ready and late:
            line = (
                f"{TIMED_OUT} after {self.job_timeout_s:g} s: every process of the job was killed"
            )
            self._kill(worker, ("error", line))
        elif not worker.ready and time.monotonic() - worker.started > START_TIMEOUT_S:
            self._kill(worker, None)  # never started: its job runs again, like a death's
        return worker.message is not None or not worker.process.is_alive()

    @staticmethod
    def _kill(worker: _Worker, message: tuple[str, Any] | None) -> None:
        """SIGKILL the job process (its sandboxes are reaped by :meth:`_end`); ``message``
        becomes its job's outcome (None: judged as a death)."""
        worker.process.kill()
        worker.process.join()
        worker.killed = True
        worker.message = message

    def _wait_s(self, workers: list[_Worker]) -> float:
        """How long to wait for news: until the nearest deadline, at most 1 s."""
        deadlines = [
            w.started + (self.job_timeout_s if w.ready else START_TIMEOUT_S)
            for w in workers
            if w.job is not None
        ]
        left = min(deadlines, default=math.inf) - time.monotonic()
        return min(1.0, max(0.01, left))

    def run(
        self, jobs: Sequence[RaceJob], progress: ProgressFn | None = None
    ) -> Iterator[JobResult]:
        """Run ``jobs``; yield each one's result once, as they finish."""
        reap_stale()
        queue: deque[tuple[RaceJob, int]] = deque((job, 1) for job in jobs)
        with self._lock:  # take the warm processes: no timer may end them while we run
            workers, self._warm = self._warm, []
            self._disarm()
        done, total = 0, len(queue)
        try:
            while queue or any(w.job is not None for w in workers):
                for worker in [w for w in workers if w.job is None]:
                    if worker.handed >= self.batch_size or not worker.process.is_alive():
                        workers.remove(worker)  # its batch is full, or it died idle
                        self._end(worker)
                while queue:
                    idle = next((w for w in workers if w.job is None), None)
                    if idle is None and len(workers) < self.workers:
                        idle = self._spawn()
                        workers.append(idle)
                    if idle is None:
                        break
                    at = _best(queue, idle.warm)
                    job, attempt = queue[at]
                    del queue[at]
                    if (reason := self._cancelled.pop(job.job_id, None)) is not None:
                        done += 1
                        yield JobResult.failed(job, f"{CANCELLED}: {reason}", attempt - 1, 0.0)
                        continue
                    self._hand(idle, job, attempt)
                busy = [w for w in workers if w.job is not None]
                ready = set(
                    wait(
                        [w.results for w in busy] + [w.process.sentinel for w in busy],
                        self._wait_s(busy),
                    )
                )
                for worker in busy:
                    if not self._judge(worker, worker.results in ready):
                        continue
                    assert worker.job is not None
                    job, attempt = worker.job, worker.attempt
                    result = self._outcome(worker)
                    if worker.process.is_alive() and not worker.killed:  # ready for the next
                        worker.job, worker.idle_since = None, time.monotonic()
                    else:
                        workers.remove(worker)
                        self._end(worker)
                    if result is None:
                        queue.appendleft((job, attempt + 1))
                        continue
                    done += 1
                    if progress is not None:
                        progress(done, total)
                    yield result
        finally:
            self._keep(workers)

    def _keep(self, workers: list[_Worker]) -> None:
        """After a run: keep the healthy idle processes warm (``keep_warm_s``), end the rest
        (running jobs too: the consumer stopped early or the run was interrupted)."""
        kept = []
        for worker in workers:
            healthy = worker.job is None and worker.process.is_alive()
            if healthy and self.keep_warm_s > 0 and worker.handed < self.batch_size:
                kept.append(worker)
            else:
                self._end(worker)
        if not kept:
            return
        with self._lock:
            self._warm = kept
            self._arm()

    def _disarm(self) -> None:
        """(Under the lock.) Stop the timer that would end the kept processes."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _arm(self) -> None:
        """(Under the lock.) End the kept processes in ``keep_warm_s`` unless a run takes them."""
        self._timer = threading.Timer(self.keep_warm_s, self._cool)
        self._timer.daemon = True
        self._timer.start()

    def _cool(self) -> None:
        """End the processes kept warm (no run took them within ``keep_warm_s``)."""
        with self._lock:
            if self._timer is not None and self._timer is not threading.current_thread():
                return  # a later run re-armed it
            kept, self._warm, self._timer = self._warm, [], None
        for worker in kept:
            self._end(worker)


def run_isolated(
    jobs: Sequence[RaceJob], fn: JobFn, max_retries: int, job_timeout_s: float, allow_weak: bool
) -> Iterator[JobResult]:
    """A batch of jobs through a one-process :class:`LocalExecutor` (what a Ray task runs):
    each result as it finishes."""
    if allow_weak:
        os.environ[WEAK_ENV] = "1"
    executor = LocalExecutor(1, max_retries, fn, job_timeout_s, batch_size=max(1, len(jobs)))
    yield from executor.run(jobs)


def plan_batches(jobs: Sequence[RaceJob], parallel: int, batch_size: int) -> list[list[RaceJob]]:
    """Jobs grouped by the bundles they race (:func:`bundle_sources`, in first-seen order),
    each group cut into batches of at most ``batch_size`` and, where it has the jobs, into at
    least ``parallel`` batches (so every CPU gets work)."""
    groups: dict[frozenset[str], list[RaceJob]] = {}
    for job in jobs:
        groups.setdefault(bundle_sources(job), []).append(job)
    batches: list[list[RaceJob]] = []
    for group in groups.values():
        n = max(math.ceil(len(group) / batch_size), min(parallel, len(group)))
        size = math.ceil(len(group) / n)
        batches += [group[i : i + size] for i in range(0, len(group), size)]
    return batches


@dataclass
class _RayBatch:
    """One Ray task: its jobs not yet answered, and when it was submitted."""

    jobs: list[RaceJob]
    started: float
    size: int  # jobs it was given


class RayExecutor:
    """Runs batches of jobs as Ray tasks (see the module docstring).

    Args:
        address: the cluster (``ray.init(address=...)``: ``"auto"``, ``"ray://host:10001"``),
            ``"local"`` to start a Ray instance on this machine, or None to use the Ray
            already initialised in this process (or start a local one).
        max_retries: extra runs for a job whose process died (on the node, as locally).
        fn: the job function.
        num_cpus: CPUs for a local instance (None: Ray's choice).
        job_timeout_s: each job's wall-clock limit on its node; the driver also cancels a
            task that has not finished ``TASK_GRACE_S`` after all its jobs' attempts could
            end.
        batch_size: jobs in one Ray task at most.
    """

    def __init__(
        self,
        address: str | None = None,
        max_retries: int = 2,
        fn: JobFn = run_race_job,
        num_cpus: int | None = None,
        job_timeout_s: float = JOB_TIMEOUT_S,
        batch_size: int = BATCH_SIZE,
    ) -> None:
        if batch_size < 1:
            raise SubmissionError(f"batch_size must be at least 1, not {batch_size}")
        self.address = address
        self.max_retries = max_retries
        self.fn = fn
        self.num_cpus = num_cpus
        self.job_timeout_s = job_timeout_s
        self.batch_size = batch_size
        self._cancelled: dict[str, str] = {}
        self._tasks: dict[str, Any] = {}  # job id -> the task (generator) running it

    def cancel(self, job_id: str, reason: str) -> None:
        """Cancel job ``job_id`` (see :meth:`Executor.cancel`): its batch's Ray task is
        cancelled and the batch's other unfinished jobs run again; thread-safe."""
        self._cancelled[job_id] = reason
        task = self._tasks.get(job_id)
        if task is not None:
            self.connect().cancel(task, force=True)

    def prestart(self, wait_s: float = 0.0) -> int:
        """Nothing to start: each batch's job process starts on a Ray node (0 kept here)."""
        return 0

    def close(self) -> None:
        """Nothing is kept between runs on Ray (each task ends its processes)."""

    def __enter__(self) -> RayExecutor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

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
        """Run ``jobs`` in batches of Ray tasks; yield each one's result once, as they
        finish."""
        ray = self.connect()
        task = ray.remote(max_retries=0, num_cpus=1, num_returns="streaming")(run_isolated)
        weak = weak_sandbox_allowed()
        parallel = self.num_cpus or max(1, int(ray.cluster_resources().get("CPU", 1)))
        running: dict[Any, _RayBatch] = {}
        done, total = 0, len(jobs)

        def submit(batch: list[RaceJob]) -> None:
            gen = task.remote(batch, self.fn, self.max_retries, self.job_timeout_s, weak)
            running[gen] = _RayBatch(list(batch), time.monotonic(), len(batch))
            for job in batch:
                self._tasks[job.job_id] = gen
                if job.job_id in self._cancelled:  # cancelled before it was submitted
                    ray.cancel(gen, force=True)

        def give_up(gen: Any, error: str) -> list[JobResult]:
            """The task ended without answering its remaining jobs: the cancelled ones fail
            as such, the others fail with ``error`` — or run again in a new task when the
            task was cancelled for another job's sake."""
            batch = running.pop(gen)
            for job in batch.jobs:
                self._tasks.pop(job.job_id, None)
            cancelled = [j for j in batch.jobs if j.job_id in self._cancelled]
            failed = [
                JobResult.failed(j, f"{CANCELLED}: {self._cancelled.pop(j.job_id)}", 1, 0.0)
                for j in cancelled
            ]
            others = [j for j in batch.jobs if j not in cancelled]
            if cancelled and others:
                submit(others)  # not their fault
            else:
                elapsed = time.monotonic() - batch.started
                failed += [JobResult.failed(j, error, 1, elapsed) for j in others]
            return failed

        for planned in plan_batches(jobs, parallel, self.batch_size):
            submit(planned)
        try:
            while running:
                ready, _ = ray.wait(list(running), num_returns=1, timeout=1.0)
                results: list[JobResult] = []
                for gen in ready:
                    try:
                        ref = next(gen)
                    except StopIteration:
                        results += give_up(gen, "the Ray task ended without its result")
                        continue
                    try:
                        result = ray.get(ref)
                    except ray.exceptions.RayTaskError as err:  # the task itself raised
                        cause = err.cause if err.cause is not None else err
                        line = f"{type(cause).__name__}: {cause}".splitlines()[0]
                        results += give_up(gen, line)
                        continue
                    except ray.exceptions.RayError as err:  # its node or worker died, …
                        results += give_up(gen, f"{type(err).__name__}: {str(err).splitlines()[0]}")
                        continue
                    answered = running[gen]
                    answered.jobs = [j for j in answered.jobs if j.job_id != result.job_id]
                    self._tasks.pop(result.job_id, None)
                    results.append(result)
                now = time.monotonic()
                for gen, batch in list(running.items()):
                    limit = self.job_timeout_s * (self.max_retries + 1) * batch.size
                    limit += TASK_GRACE_S
                    if now - batch.started > limit:  # the node never answered
                        ray.cancel(gen, force=True)
                        line = f"{TIMED_OUT} after {limit:g} s (the Ray task was cancelled)"
                        results += give_up(gen, line)
                for result in results:
                    done += 1
                    if progress is not None:
                        progress(done, total)
                    yield result
        finally:
            for gen in running:
                ray.cancel(gen, force=True)
            self._tasks.clear()


def make_executor(
    ray_address: str | None = None,
    workers: int = 2,
    max_retries: int = 2,
    job_timeout_s: float = JOB_TIMEOUT_S,
    batch_size: int = BATCH_SIZE,
    keep_warm_s: float = 0.0,
) -> LocalExecutor | RayExecutor:
    """A :class:`RayExecutor` when ``ray_address`` is given, else a :class:`LocalExecutor`
    (``keep_warm_s``: see there; Ray keeps nothing between runs)."""
    if ray_address:
        return RayExecutor(
            ray_address,
            max_retries=max_retries,
            num_cpus=workers,
            job_timeout_s=job_timeout_s,
            batch_size=batch_size,
        )
    return LocalExecutor(
        workers=workers,
        max_retries=max_retries,
        job_timeout_s=job_timeout_s,
        batch_size=batch_size,
        keep_warm_s=keep_warm_s,
    )


__all__ = ["Executor", "LocalExecutor", "RayExecutor", "make_executor", "plan_batches"]
