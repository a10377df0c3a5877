"""Race throughput: races per minute with sandboxed cars, local process pool against Ray.

One batch of identical race jobs (``--races`` races of ``--cars`` cars on ``--track``,
``--laps`` laps, seeds 0, 1, …) is run twice with the same job function
(:func:`submissions.jobs.run_race_job`):

1. by the local process pool (:class:`submissions.executors.LocalExecutor`, ``--workers``);
2. as one batch in one process (:func:`submissions.jobs.run_race_jobs`): each car's sandbox
   is started once and kept for all the races (:class:`submissions.remote.SandboxPool`), the
   races run one after another — what the executors would gain by batching;
3. by Ray (:class:`submissions.executors.RayExecutor`) on a local Ray instance with
   ``--workers`` CPUs (skipped with ``--no-ray``; ``--ray-address`` for a cluster).

Each car is our shipped PPO checkpoint wrapped in a bundle, so every car runs in its own
sandbox (``--baselines`` races in-process baselines instead, to see the sandbox's share).
Figures: wall time of the batch, races per minute, and the mean job duration (seconds inside
the job: sandbox start-up, the race, the replay files). Ray's start-up (``ray.init``) is
timed separately and not counted in its batch.

The batch runs in this (the runner's) process, so ``batch`` shows no job-process start-up
either; the local pool starts one spawned process per job.

Usage::

    python bench/race_throughput.py [--races 4] [--cars 4] [--laps 1] [--track oval]
                                    [--workers 2] [--no-ray] [--baselines] [--viser] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from arena.version import ENV_VERSION
from submissions.bundle import Manifest, make_bundle
from submissions.executors import LocalExecutor, RayExecutor
from submissions.jobs import Entrant, JobResult, RaceJob, run_race_jobs

CHECKPOINT = Path(__file__).resolve().parents[1] / "agents" / "data" / "ppo_racer.zip"


def make_jobs(args: argparse.Namespace, bundle: Path, out: Path) -> list[RaceJob]:
    """The batch: ``args.races`` identical jobs but for their seeds."""
    source = "pursuit" if args.baselines else str(bundle)
    entrants = tuple(Entrant(f"car{i}", source) for i in range(args.cars))
    return [
        RaceJob(
            f"race{k:03d}",
            entrants,
            args.track,
            str(out),
            laps=args.laps,
            seed=k,
            record_viser=args.viser,
        )
        for k in range(args.races)
    ]


class _OneBatch:
    """All the jobs in this process, sandboxes kept between races (run_race_jobs)."""

    def run(self, jobs: list[RaceJob]) -> list[JobResult]:
        return run_race_jobs(jobs)


def time_batch(executor: Any, jobs: list[RaceJob]) -> dict[str, Any]:
    """Run the batch; wall time, races per minute, mean job duration, failures."""
    start = time.perf_counter()
    results: list[JobResult] = list(executor.run(jobs))
    wall = time.perf_counter() - start
    failed = [r.error for r in results if not r.ok]
    return {
        "wall_s": round(wall, 2),
        "races_per_min": round(60.0 * len(results) / wall, 2),
        "mean_job_s": round(sum(r.duration_s for r in results) / max(len(results), 1), 2),
        "sandbox": sorted({r.sandbox for r in results}),
        "failed": failed,
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Both executors on the same batch (see the module docstring)."""
    with tempfile.TemporaryDirectory(prefix="slipstream-bench-") as tmp:
        manifest = Manifest(
            name="ppo_racer",
            author="bench",
            format="slipstream",
            entry="policy.zip",
            env_version=ENV_VERSION,
        )
        bundle = make_bundle(Path(tmp) / "ppo.zip", manifest, {"policy.zip": CHECKPOINT})
        report: dict[str, Any] = {
            "machine": {
                "cpus": os.cpu_count(),
                "processor": platform.processor() or platform.machine(),
                "python": sys.version.split()[0],
            },
            "batch": {
                "races": args.races,
                "cars": args.cars,
                "laps": args.laps,
                "track": args.track,
                "workers": args.workers,
                "sandboxed": not args.baselines,
                "viser": args.viser,
            },
        }
        jobs = make_jobs(args, bundle, Path(tmp) / "local")
        report["local"] = time_batch(LocalExecutor(workers=args.workers), jobs)
        report["batch"] = time_batch(_OneBatch(), make_jobs(args, bundle, Path(tmp) / "batch"))
        if not args.no_ray:
            ray_exec = RayExecutor(args.ray_address or "local", num_cpus=args.workers)
            start = time.perf_counter()
            ray = ray_exec.connect()  # start (or connect) before timing the batch
            report["ray_init_s"] = round(time.perf_counter() - start, 2)
            try:
                report["ray"] = time_batch(ray_exec, make_jobs(args, bundle, Path(tmp) / "ray"))
            finally:
                ray.shutdown()
            report["ray_over_local"] = round(report["ray"]["wall_s"] / report["local"]["wall_s"], 3)
    return report


def main(argv: list[str] | None = None) -> int:
    """Parse arguments, run, print a table or JSON."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--races", type=int, default=4, help="races in the batch")
    parser.add_argument("--cars", type=int, default=4, help="cars per race (2-8)")
    parser.add_argument("--laps", type=int, default=1, help="laps per race")
    parser.add_argument("--track", default="oval", help="track of every race")
    parser.add_argument("--workers", type=int, default=2, help="races at once")
    parser.add_argument("--no-ray", action="store_true", help="skip the Ray run")
    parser.add_argument("--ray-address", default=None, help="a Ray cluster (default: local)")
    parser.add_argument("--baselines", action="store_true", help="in-process pursuit cars")
    parser.add_argument("--viser", action="store_true", help="also record .viser replays")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    args = parser.parse_args(argv)
    report = run(args)
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    batch = report["batch"]
    print(
        f"{batch['races']} races × {batch['cars']} {'sandboxed' if batch['sandboxed'] else ''}"
        f" cars, {batch['laps']} lap(s) of {batch['track']}, {batch['workers']} workers, "
        f"{report['machine']['cpus']} CPUs"
    )
    print(f"{'executor':10s} {'wall s':>8s} {'races/min':>10s} {'mean job s':>11s}  sandbox")
    for key in ("local", "batch", "ray"):
        if key in report:
            r = report[key]
            print(
                f"{key:10s} {r['wall_s']:8.2f} {r['races_per_min']:10.2f} "
                f"{r['mean_job_s']:11.2f}  {','.join(r['sandbox'])}"
                + (f"  FAILED: {r['failed']}" if r["failed"] else "")
            )
    if "ray" in report:
        print(f"ray start-up {report['ray_init_s']:.2f} s (not in its batch); "
              f"ray / local wall time = {report['ray_over_local']:.3f}")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
