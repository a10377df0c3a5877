"""Robustness jobs: one submission driven solo over a fixed perturbation grid, sandboxed.

The leaderboard gives every ranked version a robustness score (issue 17): a
:class:`~submissions.jobs.RaceJob` with ``robustness`` set (its points) and one entrant is run
by :func:`run_robustness_job` instead of a race, through the same job function, executors and
sandbox as a ranked race. The policy drives one car alone, deterministic, from the grid,
``laps`` laps, once at the nominal car and once per point, in **one** sandbox (started once:
a run is a handful of laps, and the sandbox's start-up would otherwise dominate), on a
``fixed``-mode env (:mod:`arena.uncertainty`: the point is the reset's perturbation). Each
lap is scored as ``slipstream robustness`` scores it (:func:`agents.robustness.run_episode`:
effective speed, m/s), and the run's score is the grid's worst-10 % mean
(:func:`agents.robustness.summarise`; the nominal lap is reported beside it, not in it).

:func:`leaderboard_grid` is the grid: the corners of :data:`agents.robustness.GRID`'s box over
friction × motor gain × steering offset (each at its two extremes), at its middle latency:
8 points, so a run is 9 laps (about 10–30 s of wall time). With 8 points the worst-10 %
mean is the worst corner.

A policy failure (crash, timeout, invalid action) ends the run: that lap and every later one
score 0 with the failure's reason (a policy that fails under perturbation is not robust; the
owner sees the detail in the race's logs, as for a race).

The result document (``JobResult.result``)::

    {"kind": "robustness", "track": ..., "car": ..., "laps": 1, "seed": 0,
     "env_version": ..., "score": worst10_mean, "nominal": m/s, "mean": ..., "worst": ...,
     "worst10_mean": ..., "worst_over_nominal": ...,
     "points": [{"perturbation": {...}, "score": m/s, "finished": bool, "distance": m,
                 "time": s, "dnf_reason": str | None}, ...],   # nominal first
     "cars": [{"agent": "car_0", "name": ..., "status": "finished" | "dnf",
               "dnf_reason": ..., "dnf_detail": ...}]}
"""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

from submissions.bundle import EnvSpec
from submissions.jobs import (
    CONTROL_HZ,
    MAX_DETAIL,
    WALL_CLOCK_FACTOR,
    JobResult,
    RaceJob,
    open_entrant,
    progress_path,
    resolve_car,
    weakest_mode,
    write_progress,
)

if TYPE_CHECKING:
    from submissions.bundle import Bundle
    from submissions.remote import SandboxPool

MIDDLE = "latency"  # the axis held at its middle value (the others take their extremes)


def leaderboard_grid() -> list[dict[str, float]]:
    """The leaderboard's grid (see the module docstring), from :data:`agents.robustness.GRID`.

    >>> len(leaderboard_grid())
    8
    """
    from agents.robustness import GRID, grid_points  # noqa: PLC0415 - numpy; lazily

    box: dict[str, tuple[float, ...]] = {
        name: (min(values), max(values)) for name, values in GRID.items() if name != MIDDLE
    }
    values = GRID[MIDDLE]
    box[MIDDLE] = (values[len(values) // 2],)
    return grid_points(1.0, box)


def run_robustness_job(
    job: RaceJob, tmp: Path, bundles: dict[str, Bundle], pool: SandboxPool | None
) -> JobResult:
    """Run a robustness job (see the module docstring); ``job.robustness`` holds its points.

    Args:
        job: one entrant; ``track``, ``laps``, ``seed``, ``car``, ``limits`` as for a race.
        tmp: where its bundle is extracted (cached by source in ``bundles``).
        bundles: bundles already extracted, by source.
        pool: sandboxes to reuse (None: a fresh one, killed at the end).

    Raises:
        SubmissionError: the bundle is invalid or the sandbox cannot be set up.
    """
    from agents.robustness import NOMINAL, Episode, run_episode, summarise  # noqa: PLC0415
    from arena.env import RacingEnv  # noqa: PLC0415 - heavy: the simulator
    from arena.uncertainty import UncertaintyConfig  # noqa: PLC0415
    from arena.version import ENV_VERSION  # noqa: PLC0415
    from submissions.protocol import cap_text  # noqa: PLC0415
    from submissions.remote import PolicyFailure  # noqa: PLC0415 - the sandbox
    from submissions.sandbox import mode_label  # noqa: PLC0415

    assert job.robustness is not None
    start = time.perf_counter()
    started = time.monotonic()
    env_spec = EnvSpec.current()
    (entrant,) = job.entrants
    Path(job.out_dir).mkdir(parents=True, exist_ok=True)
    progress_file = progress_path(job)
    points = [dict(NOMINAL), *(dict(p) for p in job.robustness)]
    car = resolve_car(job, env_spec, tmp, bundles)
    policy, bundle = open_entrant(entrant, job, env_spec, tmp, bundles, pool, car)
    episodes: list[Episode] = []
    failure: PolicyFailure | None = None
    env = None
    try:
        env = RacingEnv(
            track=job.track,
            n_cars=1,
            laps=job.laps,
            uncertainty=UncertaintyConfig("fixed"),
            lidar_rays=env_spec.lidar_rays,
            k_opponents=env_spec.k_opponents,
            control_hz=CONTROL_HZ,
            car=car,
        )
        if bundle is not None:  # the whole run's wall clock, as a race's (one per lap)
            wall = job.wall_clock_s or (
                WALL_CLOCK_FACTOR * len(points) * env.max_cycles / CONTROL_HZ
                + policy.limits.startup_s
            )
            policy.race_deadline = started + wall
        steps = 0
        for point in points:
            if failure is None:
                try:
                    episodes.append(run_episode(env, policy, seed=job.seed, perturbation=point))
                    steps += env.steps
                    write_progress(progress_file, steps)
                    continue
                except PolicyFailure as err:
                    failure = err
            episodes.append(Episode(0.0, False, 0.0, 0.0, failure.dnf_reason, perturbation=point))
        logs = {}
        if bundle is not None:
            logs["car_0"] = {"output": policy.output, "sandbox_mode": mode_label(policy.mode)}
    finally:
        if env is not None:
            env.close()
        if bundle is not None:
            policy.close()
        progress_file.unlink(missing_ok=True)
    nominal, grid = episodes[0], episodes[1:]
    summary = summarise([e.score for e in grid], nominal.score)
    doc: dict[str, Any] = {
        "kind": "robustness",
        "track": job.track,
        "car": car,
        "laps": job.laps,
        "seed": job.seed,
        "env_version": ENV_VERSION,
        "score": summary["worst10_mean"],
        "nominal": nominal.score,
        **summary,
        "points": [
            {"perturbation": p, **{k: v for k, v in asdict(e).items() if k != "perturbation"}}
            for p, e in zip(points, episodes, strict=True)
        ],
        "cars": [
            {
                "agent": "car_0",
                "name": entrant.name,
                "status": "dnf" if failure is not None else "finished",
                "dnf_reason": None if failure is None else failure.dnf_reason,
                "dnf_detail": None if failure is None else cap_text(str(failure), MAX_DETAIL),
            }
        ],
    }
    return JobResult(
        job_id=job.job_id,
        result=doc,
        replay_path="",
        viser_path=None,
        sandbox=weakest_mode([policy.mode] if bundle is not None else []),
        duration_s=round(time.perf_counter() - start, 3),
        entrants=[asdict(e) for e in job.entrants],
        logs=logs,
    )


__all__ = ["leaderboard_grid", "run_robustness_job"]
