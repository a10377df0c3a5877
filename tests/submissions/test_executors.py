"""Executors: the local process pool and Ray run the same job function; a job whose worker
process dies is run again, and every job's result is yielded exactly once; whatever way a
job ends, nothing of it (process, cgroup, folder, mount) remains."""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from submissions import sandbox
from submissions.bundle import make_bundle, open_bundle
from submissions.errors import SubmissionError
from submissions.executors import LocalExecutor, RayExecutor, make_executor, plan_batches
from submissions.jobs import Entrant, JobResult, RaceJob
from submissions.remote import SandboxedPolicy

from .conftest import manifest_for, python_source, sandbox_processes


def make_jobs(out: Path, n: int) -> list[RaceJob]:
    return [
        RaceJob(
            f"job{i}",
            (Entrant("p", "pursuit"), Entrant("g", "gap")),
            "oval",
            str(out),
            laps=1,
            seed=i,
            record_viser=False,
        )
        for i in range(n)
    ]


def fake_result(job: RaceJob) -> JobResult:
    return JobResult(job.job_id, {"cars": [], "pid": os.getpid()}, "", None, "none", 0.0)


# Job functions for the tests: top level, so the worker processes can import them.


def die_once(job: RaceJob) -> JobResult:
    """Kill the worker process the first time each job runs (the marker says it ran, and
    in which process)."""
    marker = Path(job.out_dir) / f"{job.job_id}.ran"
    if not marker.exists():
        marker.write_text(str(os.getpid()))
        os._exit(9)
    return fake_result(job)


def always_die(job: RaceJob) -> JobResult:
    os._exit(9)


def raise_error(job: RaceJob) -> JobResult:
    (Path(job.out_dir) / f"{job.job_id}.{time.time_ns()}.run").touch()
    raise ValueError("a bug in the job")


def sleep_unless_first(job: RaceJob) -> JobResult:
    if job.job_id != "job0":
        (Path(job.out_dir) / f"{job.job_id}.pid").write_text(str(os.getpid()))
        time.sleep(60)
    else:
        time.sleep(1.0)  # let the other job start and write its pid
    return fake_result(job)


def sleep_long(job: RaceJob) -> JobResult:
    time.sleep(60)
    return fake_result(job)


def sleep_if_slow(job: RaceJob) -> JobResult:
    if job.job_id.startswith("slow"):
        time.sleep(60)
    return fake_result(job)


@pytest.mark.slow
def test_local_pool_runs_real_races(tmp_path: Path) -> None:
    seen: list[tuple[int, int]] = []
    results = list(make_executor(workers=2).run(make_jobs(tmp_path, 3), lambda *a: seen.append(a)))
    assert sorted(r.job_id for r in results) == ["job0", "job1", "job2"]
    assert all(r.ok and r.attempts == 1 for r in results)
    assert seen == [(1, 3), (2, 3), (3, 3)]
    assert all(Path(r.replay_path).exists() for r in results)
    assert {r.result["seed"] for r in results} == {0, 1, 2}


def test_dead_worker_is_retried_and_yielded_once(tmp_path: Path) -> None:
    jobs = make_jobs(tmp_path, 4)
    results = list(LocalExecutor(workers=2, max_retries=2, fn=die_once).run(jobs))
    assert sorted(r.job_id for r in results) == [j.job_id for j in jobs]  # once each
    assert all(r.ok and r.attempts == 2 for r in results)
    for r in results:  # each ran again in another process than the one it killed
        assert str(r.result["pid"]) != (tmp_path / f"{r.job_id}.ran").read_text()


def test_worker_dying_every_time_gives_up(tmp_path: Path) -> None:
    (res,) = LocalExecutor(workers=1, max_retries=1, fn=always_die).run(make_jobs(tmp_path, 1))
    assert not res.ok and res.attempts == 2
    assert "died (exit code -9" in str(res.error) or "died (exit code 9" in str(res.error)


def test_raising_job_is_not_retried(tmp_path: Path) -> None:
    (res,) = LocalExecutor(workers=1, max_retries=3, fn=raise_error).run(make_jobs(tmp_path, 1))
    assert res.error == "ValueError: a bug in the job"
    assert len(list(tmp_path.glob("job0.*.run"))) == 1


def test_job_timeout_kills_the_worker(tmp_path: Path) -> None:
    executor = LocalExecutor(workers=2, fn=sleep_long, job_timeout_s=1.0)
    start = time.monotonic()
    results = list(executor.run(make_jobs(tmp_path, 2)))
    assert time.monotonic() - start < 30
    assert all(str(r.error).startswith("timed out after 1 s") for r in results)
    assert all(r.attempts == 1 for r in results)  # failed by the job, never retried


def test_a_process_runs_a_bounded_batch_and_a_timeout_costs_only_its_job(
    tmp_path: Path,
) -> None:
    # One process at a time, two jobs per process: job0 and job1 share one; slow2 hangs and
    # is killed with its process at its own limit; the jobs queued behind it run in a fresh
    # process, its last batch; nothing of any process remains.
    jobs = make_jobs(tmp_path, 5)
    jobs[2] = RaceJob("slow2", jobs[2].entrants, "oval", str(tmp_path), record_viser=False)
    executor = LocalExecutor(workers=1, fn=sleep_if_slow, job_timeout_s=3.0, batch_size=2)
    results = {r.job_id: r for r in executor.run(jobs)}
    assert sorted(results) == ["job0", "job1", "job3", "job4", "slow2"]
    slow = results.pop("slow2")
    assert str(slow.error).startswith("timed out after 3 s") and slow.attempts == 1
    assert all(r.ok and r.attempts == 1 for r in results.values()), results
    pids = {k: r.result["pid"] for k, r in results.items()}
    assert pids["job0"] == pids["job1"] != pids["job3"] == pids["job4"]
    assert scratch_folders(os.getpid()) == [] and executor.warm == 0


def test_idle_processes_are_kept_warm_between_runs_then_ended(tmp_path: Path) -> None:
    executor = LocalExecutor(workers=1, fn=fake_result, keep_warm_s=30.0)
    (first,) = executor.run(make_jobs(tmp_path, 1))
    assert executor.warm == 1 and len(scratch_folders(os.getpid())) == 1
    (second,) = executor.run(make_jobs(tmp_path / "again", 1))
    assert second.result["pid"] == first.result["pid"]  # the same process, still warm
    executor.close()
    assert executor.warm == 0 and scratch_folders(os.getpid()) == []
    with pytest.raises(ProcessLookupError):
        os.kill(first.result["pid"], 0)
    # Not taken within keep_warm_s: ended by the executor's timer.
    brief = LocalExecutor(workers=1, fn=fake_result, keep_warm_s=0.3)
    list(brief.run(make_jobs(tmp_path / "brief", 1)))
    deadline = time.monotonic() + 10
    while (brief.warm or scratch_folders(os.getpid())) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert brief.warm == 0 and scratch_folders(os.getpid()) == []


def test_prestarted_processes_run_the_first_jobs_and_are_reaped(tmp_path: Path) -> None:
    # slipstream evaluate and the leaderboard worker start their job processes before the
    # first run (while the bundle is checked): the run hands its jobs to those processes,
    # already started, instead of spawning its own.
    executor = LocalExecutor(workers=2, fn=fake_result, keep_warm_s=30.0)
    assert executor.prestart(wait_s=60.0) == 2
    started = {w.process.pid for w in executor._warm}
    assert all(w.ready for w in executor._warm) and len(scratch_folders(os.getpid())) == 2
    assert executor.prestart() == 2  # idempotent: still two, the same two
    assert {w.process.pid for w in executor._warm} == started
    results = list(executor.run(make_jobs(tmp_path, 4)))
    assert all(r.ok for r in results) and {r.result["pid"] for r in results} == started
    # One of them dies while idle: the next prestart replaces it, the run never sees it.
    dead = executor._warm[0].process
    os.kill(dead.pid, signal.SIGKILL)
    dead.join()
    assert executor.prestart(wait_s=60.0) == 2 and dead.pid not in {
        w.process.pid for w in executor._warm
    }
    assert len(scratch_folders(os.getpid())) == 2  # the dead one's folder reaped
    executor.close()
    assert executor.warm == 0 and scratch_folders(os.getpid()) == []
    # Not taken within keep_warm_s: ended by the timer, like a run's idle processes.
    brief = LocalExecutor(workers=1, fn=fake_result, keep_warm_s=0.3)
    brief.prestart()
    deadline = time.monotonic() + 10
    while (brief.warm or scratch_folders(os.getpid())) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert brief.warm == 0 and scratch_folders(os.getpid()) == []
    # Ray starts nothing here.
    assert RayExecutor("ray://nowhere:1").prestart() == 0


def test_stopping_early_kills_running_jobs(tmp_path: Path) -> None:
    gen = LocalExecutor(workers=2, fn=sleep_unless_first).run(make_jobs(tmp_path, 2))
    assert next(gen).job_id == "job0"
    gen.close()  # the consumer stops: the job still running is killed
    pid = int((tmp_path / "job1.pid").read_text())
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)


@pytest.mark.slow
def test_ray_runs_the_same_job_function(tmp_path: Path) -> None:
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        executor = RayExecutor(max_retries=2, fn=die_once)
        results = list(executor.run(make_jobs(tmp_path, 3)))
        assert sorted(r.job_id for r in results) == ["job0", "job1", "job2"]
        assert all(r.ok for r in results)
        (real,) = RayExecutor().run(make_jobs(tmp_path / "real", 1))
        assert real.ok and Path(real.replay_path).exists()
        assert [c["name"] for c in real.result["cars"]] == ["p", "g"]
        # The per-job wall-clock limit holds on Ray too: killed on its node, not retried.
        slow = RayExecutor(max_retries=2, fn=sleep_long, job_timeout_s=1.0)
        (stuck,) = slow.run(make_jobs(tmp_path / "slow", 1))
        assert str(stuck.error).startswith("timed out after 1 s") and stuck.attempts == 1
    finally:
        ray.shutdown()


# ---- nothing left behind --------------------------------------------------------------


def hold_a_sandbox(job: RaceJob) -> JobResult:
    """Open the job's bundle, start its sandbox, say its id, then hang (to be killed)."""
    bundle = open_bundle(Path(job.entrants[0].source), Path(tempfile.mkdtemp()) / "b")
    policy = SandboxedPolicy(bundle)
    policy.reset(0)  # loaded: the worker, its cgroups, folder and (fallback) tmpfs exist
    Path(job.out_dir).mkdir(parents=True, exist_ok=True)
    (Path(job.out_dir) / f"{job.job_id}.sid").write_text(str(policy.sandbox_id))
    if job.job_id.startswith("die"):
        os.kill(os.getpid(), signal.SIGKILL)  # the job process dies, its sandbox alive
    time.sleep(600)
    return fake_result(job)


def sandbox_traces(sandbox_id: str) -> list[str]:
    """What of a sandbox still exists on the host: processes, cgroups, folders, mounts."""
    found = [f"pid {pid}" for pid in sandbox_processes(sandbox_id)]
    found += [str(d) for d in sandbox.CgroupCaps.existing(sandbox_id).dirs]
    found += [str(d) for d in Path(tempfile.gettempdir()).glob(f"slipstream-*{sandbox_id}*")]
    found += [m for m in Path("/proc/self/mounts").read_text().splitlines() if sandbox_id in m]
    return found


def scratch_folders(owner: int) -> list[Path]:
    return list(Path(tempfile.gettempdir()).glob(f"{sandbox.JOB_PREFIX}{owner}-*"))


@pytest.fixture
def holding_bundle(tmp_path: Path) -> Path:
    source = python_source("class Policy(Driver):\n    pass\n").encode()
    return make_bundle(tmp_path / "holder.zip", manifest_for("holder"), {"agent.py": source})


def holding_jobs(out: Path, bundle: Path, n: int, prefix: str = "hold") -> list[RaceJob]:
    entrants = (Entrant("holder", str(bundle)), Entrant("p", "pursuit"))
    return [RaceJob(f"{prefix}{i}", entrants, "oval", str(out), laps=1) for i in range(n)]


@pytest.mark.slow
def test_jobs_killed_at_random_points_leave_nothing(
    mode: str, tmp_path: Path, holding_bundle: Path
) -> None:
    # Timeouts drawn at random kill jobs before or while their sandboxes start; then jobs
    # whose process dies (SIGKILL) with a live, loaded sandbox.
    rng = random.Random(12)
    rounds = [("hold", rng.uniform(0.5, 5.0)), ("hold", rng.uniform(0.5, 5.0)), ("die", 60.0)]
    seen: list[str] = []
    for k, (prefix, timeout) in enumerate(rounds):
        out = tmp_path / f"round{k}"
        executor = LocalExecutor(workers=2, max_retries=0, fn=hold_a_sandbox, job_timeout_s=timeout)
        results = list(executor.run(holding_jobs(out, holding_bundle, 2, prefix)))
        expected = "timed out" if prefix == "hold" else "the job's worker process died"
        assert all(str(r.error).startswith(expected) for r in results), results
        seen += [p.read_text() for p in out.glob("*.sid")]
        for sid in seen:
            assert sandbox_traces(sid) == []
        assert scratch_folders(os.getpid()) == []
    assert len(seen) >= 2  # the dying jobs' sandboxes were up when their jobs died


@pytest.mark.slow
def test_a_sigkilled_runner_leaves_nothing_once_the_next_one_starts(
    mode: str, tmp_path: Path, holding_bundle: Path
) -> None:
    # The runner (an executor in its own process) is SIGKILLed while its job holds a live
    # sandbox: the job and the sandbox die with it (parent-death signals), and nothing of
    # them (folders, cgroups, mounts) remains.
    script = (
        "import sys; from pathlib import Path\n"
        "from submissions.executors import LocalExecutor\n"
        "from tests.submissions.test_executors import hold_a_sandbox, holding_jobs\n"
        "jobs = holding_jobs(Path(sys.argv[1]), Path(sys.argv[2]), 1)\n"
        "list(LocalExecutor(workers=1, fn=hold_a_sandbox).run(jobs))\n"
    )
    runner = subprocess.Popen(
        [sys.executable, "-c", script, str(tmp_path), str(holding_bundle)], cwd=Path.cwd()
    )
    sid_file = tmp_path / "hold0.sid"
    deadline = time.monotonic() + 90
    while not sid_file.exists() and time.monotonic() < deadline:
        time.sleep(0.2)
    sid = sid_file.read_text()
    assert sandbox_processes(sid)
    runner.send_signal(signal.SIGKILL)
    runner.wait()
    deadline = time.monotonic() + 10
    while sandbox_processes(sid) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert sandbox_processes(sid) == []  # nothing of the policy outlived its runner
    # The job reaps its own scratch folder on its parent-death signal (SIGTERM); whatever
    # a harder death left, the next runner reaps first.
    sandbox.reap_stale()
    assert sandbox_traces(sid) == []
    assert scratch_folders(runner.pid) == []


def test_ray_batches_group_jobs_by_their_bundles_and_spread_over_the_cpus(tmp_path: Path) -> None:
    def job(i: int, *sources: str) -> RaceJob:
        entrants = tuple(Entrant(f"c{k}", s) for k, s in enumerate((*sources, "pursuit", "gap")))
        return RaceJob(f"j{i}", entrants, "oval", str(tmp_path))

    a, b = str(tmp_path / "a.zip"), str(tmp_path / "b.zip")
    jobs = [job(0, a), job(1, b, a), job(2, a, a), job(3, a), job(4, a, b), job(5), job(6, a)]
    batches = [[j.job_id for j in batch] for batch in plan_batches(jobs, 2, 8)]
    # {a}: j0 j2 j3 j6 in two batches (two CPUs); {a, b}: j1 j4; baselines only: j5
    assert batches == [["j0", "j2"], ["j3", "j6"], ["j1"], ["j4"], ["j5"]]
    # one CPU: batches of at most batch_size
    one_bundle = [job(i, a) for i in range(7)]
    assert [len(batch) for batch in plan_batches(one_bundle, 1, 3)] == [3, 3, 1]


def test_the_executor_never_uses_a_fork_server() -> None:
    # Python 3.11's fork server listens on a Unix socket and unpickles what it is sent: a
    # policy that found it in /proc/net/unix escaped (issue 12). No listener, no start method.
    assert LocalExecutor().context.get_start_method() == "spawn"
    with pytest.raises(SubmissionError, match="spawn or fork"):
        LocalExecutor(start_method="forkserver")
    with pytest.raises(SubmissionError, match="positive"):
        LocalExecutor(job_timeout_s=0)
