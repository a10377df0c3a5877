"""A small, realistic leaderboard for the website tests, built without the simulator.

The real service code does everything (users, baseline submissions, validation and ranked
races scheduled by matchmaking, leases, results, ratings, records); only the race itself is
faked: :class:`FakeRunner` stands in for the evaluation executor and returns made-up but
well-formed race results (and, when asked, a real ``.viser`` replay of cars driving along the
track's centre line).
"""

from __future__ import annotations

import math
import random
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from leaderboard import auth
from leaderboard.db import make_engine, make_sessionmaker
from leaderboard.settings import Settings
from leaderboard.uploads import add_baseline
from leaderboard.worker import Worker
from submissions.jobs import JobResult, RaceJob

SKILL = {"pursuit": 3.0, "gap": 2.0, "random": 1.0}  # who beats whom in the fake races
SPEED = {"pursuit": 6.0, "gap": 5.0, "random": 1.0}  # m/s along the centre line
FAKE_FPS = 10.0  # frames per second of the fake replay logs
FAKE_TRACEBACK = 'Traceback (most recent call last):\n  File "agent.py", line 3\nZeroDivisionError'


def _baseline_of(name: str) -> str:
    """``"pursuit:v1"`` → ``"pursuit"``."""
    return name.split(":", maxsplit=1)[0]


def fake_replay(job: RaceJob, seconds: float = 6.0) -> object:
    """A ``ReplayLog`` of the job's cars following the centre line at their baseline's speed."""
    from arena.replay import ReplayLog
    from arena.sim import car_colour
    from tracks import load_track

    track = load_track(job.track)
    n = len(job.entrants)
    log = ReplayLog(
        track=track,
        dt=1.0 / FAKE_FPS,
        cars=[
            {"agent": f"car_{i}", "name": e.name, "colour": list(car_colour(i))}
            for i, e in enumerate(job.entrants)
        ],
        env_version="test",
    )
    speeds = np.array([SPEED.get(_baseline_of(e.name), 3.0) for e in job.entrants])
    offsets = np.linspace(-0.3, 0.3, n)  # m, side by side
    for k in range(int(seconds * FAKE_FPS)):
        t = k / FAKE_FPS
        s = track.wrap_s(speeds * t - 1.5 * np.arange(n))
        xy = track.to_cartesian(np.column_stack([s, offsets]))
        poses = np.column_stack([xy, track.heading_at(s)])
        log.add_frame(t, poses, np.zeros(n), speeds, np.ones(n, dtype=bool))
    # Events shaped like arena.race's _EventRecorder writes them: both cars of a contact
    # record it; the car behind is at fault.
    log.add_event(1.5, "off_track", "car_0")
    if n > 1:
        log.add_event(2.0, "collision", "car_1", other="car_0", at_fault=True, closing_speed=1.2)
        log.add_event(2.0, "collision", "car_0", other="car_1", at_fault=False, closing_speed=1.2)
    log.add_event(4.0, "lap", "car_0", lap=1, lap_time=4.0)
    return log


@dataclass
class FakeRunner:
    """Runs jobs by making up their results; real ``.viser`` files for the races in ``viser``.

    The other races get a placeholder ``.viser`` file (a few bytes, not a replay).
    """

    viser: frozenset[int] = frozenset()
    jobs: list[RaceJob] = field(default_factory=list)

    def __call__(self, jobs: Sequence[RaceJob]) -> Iterator[JobResult]:
        for job in jobs:
            self.jobs.append(job)
            yield self.result(job, real_viser=int(job.job_id) in self.viser)

    def result(self, job: RaceJob, *, real_viser: bool) -> JobResult:
        """A finished race: the better baseline wins; ``random`` never finishes. A robustness
        job gets :func:`fake_robustness`."""
        if job.robustness is not None:
            return fake_robustness(job)
        out = Path(job.out_dir)
        order = sorted(
            range(len(job.entrants)),
            key=lambda i: (-SKILL.get(_baseline_of(job.entrants[i].name), 0.0), i),
        )
        cars = []
        for position, i in enumerate(order, start=1):
            base = _baseline_of(job.entrants[i].name)
            finished = base != "random"
            laps = [round(10.0 + position + 0.1 * lap + 0.01 * i, 3) for lap in range(job.laps)]
            cars.append(
                {
                    "agent": f"car_{i}",
                    "name": job.entrants[i].name,
                    "position": position,
                    "status": "finished" if finished else "dnf",
                    "dnf_reason": None if finished else "time_limit",
                    "laps_completed": job.laps if finished else 0,
                    "lap_times": laps if finished else [],
                    "best_lap": min(laps) if finished else None,
                    "total_time": math.fsum(laps) + 5.0 * (i == 1) if finished else None,
                    "race_time": math.fsum(laps) if finished else None,
                    "penalties": 5.0 * (i == 1) if job.ranked else 0.0,
                    "collisions": position - 1,
                    "at_fault_collisions": int(i == 1),
                    "off_track": 0 if finished else 3,
                    # owner-only fields, as the worker reports them (submissions.jobs)
                    "dnf_detail": None if finished else FAKE_TRACEBACK,
                    "output": f"{job.entrants[i].name} says hello\n",
                    "sandbox_mode": "bwrap",
                }
            )
        result = {
            "track": job.track,
            "seed": job.seed,
            "laps": job.laps,
            "env_version": "test",
            "ranked": job.ranked,
            "steps": 100,
            "sim_time": 30.0,
            "cars": sorted(cars, key=lambda c: c["agent"]),
        }
        viser_path = out / f"{job.job_id}.viser"
        replay_path = out / f"{job.job_id}.replay.json.gz"
        log = fake_replay(job)
        log.save(replay_path)  # type: ignore[attr-defined]
        if real_viser:
            from submissions.viser_replay import write_viser

            write_viser(log, viser_path)  # type: ignore[arg-type]
        else:
            viser_path.write_bytes(b"not a real viser file")
        return JobResult(
            job_id=job.job_id,
            result=result,
            replay_path=str(replay_path),
            viser_path=str(viser_path),
            sandbox="none",
            duration_s=0.5,
        )


def fake_robustness(job: RaceJob) -> JobResult:
    """A robustness run's result, shaped like :func:`submissions.robustness.run_robustness_job`
    writes it: each baseline slows down under perturbation by its own share (``random``
    crawls), so the robust order differs from the rating order."""
    from agents.robustness import NOMINAL, summarise

    (entrant,) = job.entrants
    base = _baseline_of(entrant.name)
    nominal = SPEED.get(base, 3.0)
    loss = {"pursuit": 0.45, "gap": 0.1, "random": 0.5}.get(base, 0.3)  # worst-case share lost
    points = [dict(NOMINAL), *(job.robustness or ())]
    scores = [nominal] + [
        nominal * (1.0 - loss * (k + 1) / len(points)) for k in range(len(points) - 1)
    ]
    summary = summarise(scores[1:], nominal)
    doc = {
        "kind": "robustness",
        "track": job.track,
        "car": job.car or "f1tenth",
        "laps": job.laps,
        "seed": job.seed,
        "env_version": "test",
        "score": summary["worst10_mean"],
        "nominal": nominal,
        **summary,
        "points": [
            {
                "perturbation": p,
                "score": s,
                "finished": True,
                "distance": 50.0,
                "time": 50.0 / s,
                "dnf_reason": None,
            }
            for p, s in zip(points, scores, strict=True)
        ],
        "cars": [
            {"agent": "car_0", "name": entrant.name, "status": "finished", "dnf_reason": None}
        ],
    }
    return JobResult(job.job_id, doc, "", None, "none", 0.5)


@dataclass
class Site:
    """What :func:`seed_site` made: the settings, the house user's token and the fake runner."""

    settings: Settings
    token: str
    runner: FakeRunner


def seed_site(
    data_dir: Path,
    *,
    ranked: int = 6,
    viser: Sequence[int] = (),
    seed: int = 0,
    robustness: bool = False,
) -> Site:
    """A leaderboard with the three baselines, their validation races and ``ranked`` races.

    Args:
        data_dir: the service's data folder (SQLite database, replays).
        ranked: ranked races to run after the three validation races.
        viser: the race ids that get a real ``.viser`` replay (races 1-3 validate the
            baselines; ranked races follow).
        seed: seed of the matchmaker's draws.
        robustness: also run each baseline's robustness run (:func:`fake_robustness`; they
            run before the ranked races and take race ids).
    """
    settings = Settings(
        data_dir=data_dir, tracks=["oval", "bean"], max_cars=3, robustness=robustness
    )
    settings.ensure_dirs()
    engine = make_engine(settings.db_url)
    try:
        from leaderboard.migrations import upgrade

        upgrade(settings.db_url, engine=engine)
        with make_sessionmaker(engine)() as session:
            user, token = auth.create_user(session, name="house")
            for baseline in ("pursuit", "gap", "random"):
                add_baseline(session, settings, user=user, baseline=baseline)
            session.commit()
    finally:
        engine.dispose()
    runner = FakeRunner(viser=frozenset(viser))
    worker = Worker(settings, runner=runner, schedule=True, workers=1, owner="test")
    worker.rng = random.Random(seed)  # the same matchmaking draws every run
    try:
        worker.run(max_races=3 + ranked + 3 * robustness, poll_s=0.0)
    finally:
        worker.close()
    return Site(settings=settings, token=token, runner=runner)
