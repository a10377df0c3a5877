"""Workers: results stored through the queue, real races through run_race_job, a worker
killed mid-race whose race runs again with its rating applied exactly once, leases renewed
only while a race progresses, a graceful stop that spends no attempt, and a worker that
refuses to run bundles without the namespace sandbox unless allowed."""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from leaderboard import matchmaking
from leaderboard.models import (
    Job,
    Race,
    RaceLog,
    RatingHistory,
    Submission,
    SubmissionVersion,
)
from leaderboard.settings import Settings
from leaderboard.worker import Worker, progress_path
from submissions import sandbox
from submissions.errors import SandboxError
from submissions.jobs import JobResult, RaceJob
from tests.leaderboard import factories
from tests.leaderboard.conftest import Account

REPO = Path(__file__).resolve().parents[2]


def _fake_runner(db_settings: Settings, fail: set[str] | None = None):  # type: ignore[no-untyped-def]
    """A runner that answers each job with a made-up result (car 0 wins) without racing."""
    from leaderboard.db import make_engine, make_sessionmaker

    sessions = make_sessionmaker(make_engine(db_settings.db_url))

    def run(jobs: Sequence[RaceJob]) -> Iterator[JobResult]:
        for job in jobs:
            if fail and job.job_id in fail:
                yield JobResult.failed(job, "boom", attempts=1, duration_s=0.0)
                continue
            with sessions() as s:
                race = s.get(Race, int(job.job_id))
                assert race is not None
                result = factories.fake_result(race)
            yield JobResult(job.job_id, result, "", None, "none", 0.1)

    return run


def test_worker_stores_results_and_schedules_more(db: Session, settings: Settings) -> None:
    factories.seed(db, settings, n_submissions=3, n_races=0)
    worker = Worker(settings, workers=2, runner=_fake_runner(settings))
    try:
        stats = worker.run(max_races=6)
    finally:
        worker.close()
    assert (stats.completed, stats.failed, stats.discarded) == (6, 0, 0)
    assert db.scalar(select(func.count(Race.id)).where(Race.status == "finished")) == 3 + 6
    assert db.scalar(select(func.sum(Submission.races))) == db.scalar(
        select(func.count(RatingHistory.id))
    )


def test_a_job_that_errors_is_retried_then_failed(db: Session, settings: Settings) -> None:
    factories.seed(db, settings, n_submissions=2, n_races=0)
    (race,) = matchmaking.schedule_ranked(db, settings, 1, random.Random(0))
    db.commit()
    worker = Worker(settings, runner=_fake_runner(settings, fail={str(race.id)}), schedule=False)
    try:
        for _ in range(settings.max_attempts):
            worker.run(once=True)
    finally:
        worker.close()
    db.expire_all()
    failed = db.get(Race, race.id)
    assert failed is not None and failed.status == "failed" and failed.error == "boom"
    assert db.scalar(select(Job.attempts).where(Job.race_id == race.id)) == settings.max_attempts


@pytest.mark.slow
def test_worker_runs_real_races_end_to_end(
    client: TestClient, db: Session, settings: Settings, alice: Account, bundle_zip
) -> None:
    """Upload → sandboxed validation race → ranked races → ratings, replays on disk."""
    # Races only: robustness runs (tests/leaderboard/test_robustness.py) would go first.
    settings = settings.model_copy(update={"race_laps": 1, "tracks": ["oval"], "robustness": False})
    factories.seed(db, settings, n_submissions=2, n_races=0)  # pursuit-0, gap-1 (validated)
    with bundle_zip("uploaded").open("rb") as f:
        r = client.post("/api/submissions", headers=alice.headers, files={"file": ("u.zip", f)})
    assert r.status_code == 201
    upload = r.json()
    worker = Worker(settings, workers=2)
    try:
        stats = worker.run(max_races=3)
    finally:
        worker.close()
    assert stats.completed == 3 and stats.failed == 0
    db.expire_all()
    validation = db.get(Race, upload["validation_race_id"])
    assert validation is not None and validation.status == "finished"
    assert validation.sandbox in ("bwrap", "seccomp-weak")  # the upload ran sandboxed
    version = db.scalar(
        select(SubmissionVersion).where(SubmissionVersion.submission_id == upload["submission_id"])
    )
    assert version is not None and version.status == "validated", version.error if version else ""
    # The owner-only logs of the sandboxed car (JobResult.logs) are stored with the result.
    logs = db.scalars(select(RaceLog).where(RaceLog.race_id == validation.id)).all()
    assert logs and all(row.sandbox_mode in ("bwrap", "seccomp-weak") for row in logs)
    ranked = db.scalars(select(Race).where(Race.kind == "ranked", Race.status == "finished")).all()
    assert len(ranked) == 2
    for race in ranked:
        assert race.result is not None and race.result["track"] == "oval"
        assert Path(race.replay_path or "").is_file() and Path(race.viser_path or "").is_file()
        assert Path(race.viser_path or "").parent == settings.replays_dir.resolve()
        assert all(e.mu_after is not None for e in race.entries)
    page = client.get(f"/api/races/{ranked[0].id}").json()
    assert client.get(page["viser_url"]).status_code == 200


def _wait_for(predicate, timeout: float, what: str) -> None:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.2)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.mark.slow
def test_killed_worker_race_runs_again_and_rating_is_applied_once(
    db: Session, settings: Settings
) -> None:
    # Three laps (≈15 s of racing) so the kill surely lands while the race runs.
    settings = settings.model_copy(update={"lease_s": 3.0, "race_laps": 3})
    factories.seed(db, settings, n_submissions=2, n_races=0)
    (race,) = matchmaking.schedule_ranked(db, settings, 1, random.Random(0))
    db.commit()
    cmd = [
        sys.executable, "-m", "leaderboard.cli", "worker", "--db", settings.db_url,
        "--data-dir", str(settings.data_dir), "--once", "--no-schedule", "--lease-s", "3",
    ]  # fmt: skip
    proc = subprocess.Popen(
        cmd, cwd=REPO, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )
    try:

        def leased() -> bool:
            db.expire_all()
            return db.scalar(select(Job.status).where(Job.race_id == race.id)) == "leased"

        _wait_for(leased, 60, "the subprocess worker to claim the race")
        time.sleep(1.5)  # the race is under way in the worker's job process
        assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the worker and its job process
        proc.wait(timeout=30)
    db.expire_all()
    job = db.scalar(select(Job).where(Job.race_id == race.id))
    assert job is not None and (job.status, job.attempts) == ("leased", 1)
    assert db.scalar(select(func.count(RatingHistory.id))) == 0

    worker = Worker(settings, schedule=False)  # claims it once the dead worker's lease expires
    try:
        stats = worker.run(max_races=1, poll_s=0.5)
    finally:
        worker.close()
    assert stats.completed == 1
    db.expire_all()
    job = db.scalar(select(Job).where(Job.race_id == race.id))
    assert job is not None and (job.status, job.attempts) == ("done", 2)
    finished = db.get(Race, race.id)
    assert finished is not None and finished.status == "finished"
    n_cars = len(finished.entries)
    assert db.scalar(select(func.count(RatingHistory.id))) == n_cars
    assert db.scalar(select(func.sum(Submission.races))) == n_cars


# ---- fail closed, progress, graceful stop --------------------------------------------------


def _one_race(db: Session, settings: Settings) -> Race:
    factories.seed(db, settings, n_submissions=2, n_races=0)
    (race,) = matchmaking.schedule_ranked(db, settings, 1, random.Random(0))
    db.commit()
    return race


def _job(db: Session, race: Race) -> Job:
    db.expire_all()
    job = db.scalar(select(Job).where(Job.race_id == race.id))
    assert job is not None
    return job


def test_the_worker_refuses_to_start_without_the_namespace_sandbox(
    db: Session, settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    race = _one_race(db, settings)
    monkeypatch.setenv("SANDBOX", "seccomp")  # as where bubblewrap cannot run
    monkeypatch.setenv(sandbox.WEAK_ENV, "")
    worker = Worker(settings, schedule=False)
    try:
        with pytest.raises(SandboxError, match="allow-weak-sandbox"):
            worker.run(once=True)
    finally:
        worker.close()
    assert (_job(db, race).status, _job(db, race).attempts) == ("queued", 0)  # nothing claimed
    allowed = Worker(settings, schedule=False, allow_weak_sandbox=True)
    try:
        assert callable(allowed.runner)  # the executor is built: the operator allowed it
        assert os.environ[sandbox.WEAK_ENV] == "1"  # and its job processes inherit that
    finally:
        allowed.close()


@pytest.mark.parametrize(
    ("name", "raw"), [("SLIPSTREAM_SPIN_US", "soon"), ("SLIPSTREAM_CPU_LATENCY_US", "-4")]
)
def test_the_worker_refuses_a_malformed_scheduling_setting_before_claiming(
    db: Session, settings: Settings, monkeypatch: pytest.MonkeyPatch, name: str, raw: str
) -> None:
    # An operator's typo: said once, at the start, not every race's cars retired "error".
    race = _one_race(db, settings)
    monkeypatch.setenv(name, raw)
    worker = Worker(settings, schedule=False, allow_weak_sandbox=True)
    try:
        with pytest.raises(SandboxError, match=name):
            worker.run(once=True)
    finally:
        worker.close()
    assert (_job(db, race).status, _job(db, race).attempts) == ("queued", 0)  # nothing claimed


class _Controlled:
    """A runner whose job "runs" until cancelled (or ``release`` is set), with a progress
    count that a thread advances while ``advancing`` is set."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.cancelled: dict[str, str] = {}
        self.wake = threading.Event()
        self.advancing = threading.Event()
        self.started = threading.Event()

    def cancel(self, job_id: str, reason: str) -> None:
        self.cancelled[job_id] = reason
        self.wake.set()

    def __call__(self, jobs: Sequence[RaceJob]) -> Iterator[JobResult]:
        (job,) = jobs
        path = progress_path(job.out_dir, job.job_id)
        step = 0
        self.started.set()
        deadline = time.monotonic() + 30
        while not self.wake.wait(0.05) and time.monotonic() < deadline:
            if self.advancing.is_set() or step == 0:
                step += 1
                path.write_text(str(step))
        reason = self.cancelled.get(job.job_id, "never cancelled")
        yield JobResult.failed(job, f"cancelled: {reason}", 1, 0.0)


def test_a_lease_is_renewed_only_while_the_race_progresses(db: Session, settings: Settings) -> None:
    settings = settings.model_copy(update={"lease_s": 1.0})
    race = _one_race(db, settings)
    runner = _Controlled(settings)
    runner.advancing.set()
    worker = Worker(settings, runner=runner, schedule=False, stall_s=1.0)
    thread = threading.Thread(target=worker.run, kwargs={"once": True})
    thread.start()
    try:
        assert runner.started.wait(20)
        time.sleep(2.5)  # progressing: renewed past its 1 s lease, never cancelled
        assert runner.cancelled == {}
        assert _job(db, race).status == "leased"
        runner.advancing.clear()  # the race wedges: its count stops moving
        deadline = time.monotonic() + 10
        while not runner.cancelled and time.monotonic() < deadline:
            time.sleep(0.1)
        assert runner.cancelled == {str(race.id): "no progress for 1 s"}
    finally:
        runner.wake.set()
        thread.join(30)
        worker.close()
    job = _job(db, race)
    assert (job.status, job.attempts) == ("queued", 1)  # failed once, queued again (bounded)
    assert not progress_path(settings.replays_dir.resolve(), str(race.id)).exists()


def test_a_graceful_stop_hands_the_race_back_without_spending_an_attempt(
    db: Session, settings: Settings
) -> None:
    race = _one_race(db, settings)
    runner = _Controlled(settings)
    worker = Worker(settings, runner=runner, schedule=False)
    thread = threading.Thread(target=worker.run)  # would run forever without the stop
    thread.start()
    try:
        assert runner.started.wait(20)
        assert _job(db, race).status == "leased"
        worker.request_stop()  # what SIGTERM / Ctrl-C do in `slipstream worker`
        thread.join(30)
        assert not thread.is_alive()
    finally:
        runner.wake.set()
        worker.close()
    assert runner.cancelled == {str(race.id): "the worker stopped"}
    job = _job(db, race)
    assert (job.status, job.attempts, job.lease_token) == ("queued", 0, None)
    assert db.get(Race, race.id).status == "queued"  # type: ignore[union-attr]


@pytest.mark.slow
def test_sigterm_hands_a_real_race_back_and_leaves_no_process(
    db: Session, settings: Settings
) -> None:
    # `slipstream worker` racing a real job in its executor: SIGTERM (systemd's stop) must
    # hand the race back with its attempt unspent, kill the job, and exit.
    settings = settings.model_copy(update={"race_laps": 3})
    race = _one_race(db, settings)
    cmd = [
        sys.executable, "-m", "leaderboard.cli", "worker", "--db", settings.db_url,
        "--data-dir", str(settings.data_dir), "--once", "--no-schedule",
    ]  # fmt: skip
    proc = subprocess.Popen(
        cmd, cwd=REPO, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )
    try:
        _wait_for(lambda: _job(db, race).status == "leased", 60, "the worker to claim the race")
        time.sleep(1.0)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0, proc.stderr.read() if proc.stderr else ""
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    job = _job(db, race)
    assert (job.status, job.attempts) == ("queued", 0)

    def group_gone() -> bool:
        try:
            os.killpg(proc.pid, 0)
        except ProcessLookupError:
            return True
        return False

    _wait_for(group_gone, 10, "the worker's job processes to end")  # none outlives it
