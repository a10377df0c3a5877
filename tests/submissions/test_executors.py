"""Executors: the local process pool and Ray run the same job function; a job whose worker
process dies is run again, and every job's result is yielded exactly once."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from submissions.executors import LocalExecutor, RayExecutor, make_executor
from submissions.jobs import Entrant, JobResult, RaceJob


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
    """Kill the worker process the first time each job runs (the marker says it ran)."""
    marker = Path(job.out_dir) / f"{job.job_id}.ran"
    if not marker.exists():
        marker.touch()
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
    assert len({r.result["pid"] for r in results}) == 4  # a fresh process per run


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
    assert all(r.error == "timed out after 1.0 s" for r in results)


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
    finally:
        ray.shutdown()
