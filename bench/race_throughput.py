"""Race throughput: races per minute through the executors, sandboxed cars against in-process.

One batch of identical race jobs (``--races`` races of ``--cars`` cars on ``--track``,
``--laps`` laps, seeds 0, 1, …) is run through the real path of ``slipstream evaluate`` and
``slipstream worker`` (:func:`submissions.jobs.run_race_job` in the job processes of an
executor, ``--workers`` at once), several ways, in one run (``--rounds`` times in turn, so
load elsewhere hits them alike):

1. ``in_process``: the local executor (:class:`submissions.executors.LocalExecutor`) with
   every car our pursuit baseline, in-process in the job process — the reference;
2. ``pooled``: the local executor as ``evaluate`` and the worker run it, every car the same
   pursuit policy in a sandbox (a python bundle wrapping the baseline): each job process runs
   up to ``batch_size`` jobs one after another and keeps the bundle's sandboxes between them
   (:class:`submissions.remote.SandboxPool`);
3. ``fresh``: the same with ``batch_size=1`` — a fresh job process and fresh sandboxes for
   every job (the executors before sandbox reuse);
4. ``ray``: :class:`submissions.executors.RayExecutor` on a local Ray instance with
   ``--workers`` CPUs, batches as in 2. (skipped with ``--no-ray``; ``--ray-address`` for a
   cluster; Ray's start-up is timed apart and not counted).

``--policy ppo`` races our shipped PPO checkpoint in its bundle instead (sandboxed rows only:
no in-process reference). Figures: wall time of the batch (job processes' start-up
included), races per minute, the ratio to ``in_process``, and the mean job duration (seconds
inside the job: sandbox start-up where it happens, the race, the replay files).

Usage::

    python bench/race_throughput.py [--races 4] [--cars 4] [--laps 1] [--track oval]
                                    [--workers 2] [--rounds 1] [--policy pursuit|ppo]
                                    [--no-ray] [--viser] [--json]
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

from sandbox_overhead import PURSUIT_SOURCE  # bench/ is on sys.path as the script's folder

from arena.version import ENV_VERSION
from submissions.bundle import Manifest, make_bundle
from submissions.executors import LocalExecutor, RayExecutor
from submissions.jobs import Entrant, JobResult, RaceJob

CHECKPOINT = Path(__file__).resolve().parents[1] / "agents" / "data" / "ppo_racer.zip"


def make_bundle_for(policy: str, folder: Path) -> Path:
    """The sandboxed cars' bundle: the pursuit baseline wrapped, or our PPO checkpoint."""
    if policy == "ppo":
        manifest = Manifest(
            name="ppo_racer", author="bench", format="slipstream", entry="policy.zip",
            env_version=ENV_VERSION,
        )  # fmt: skip
        return make_bundle(folder / "ppo.zip", manifest, {"policy.zip": CHECKPOINT})
    manifest = Manifest(
        name="pursuit_boxed", author="bench", format="python", entry="agent.py",
        env_version=ENV_VERSION,
    )  # fmt: skip
    return make_bundle(folder / "pursuit.zip", manifest, {"agent.py": PURSUIT_SOURCE.encode()})


def make_jobs(args: argparse.Namespace, source: str, out: Path) -> list[RaceJob]:
    """The batch: ``args.races`` identical jobs but for their seeds."""
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


def time_batch(executor: Any, jobs: list[RaceJob]) -> dict[str, Any]:
    """Run the batch; wall time, races per minute, mean job duration, failures."""
    start = time.perf_counter()
    try:
        results: list[JobResult] = list(executor.run(jobs))
    finally:
        executor.close()
    wall = time.perf_counter() - start
    return {
        "wall_s": wall,
        "races": len(results),
        "job_s": sum(r.duration_s for r in results),
        "sandbox": sorted({r.sandbox for r in results}),
        "failed": [r.error for r in results if not r.ok],
        "finished": sum(c["status"] == "finished" for r in results for c in r.result["cars"]),
    }


def summarise(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """One row from the rounds of one way: totals over every round."""
    wall = sum(r["wall_s"] for r in runs)
    races = sum(r["races"] for r in runs)
    return {
        "wall_s": round(wall, 2),
        "races_per_min": round(60.0 * races / wall, 2),
        "mean_job_s": round(sum(r["job_s"] for r in runs) / max(races, 1), 2),
        "sandbox": sorted({s for r in runs for s in r["sandbox"]}),
        "failed": [e for r in runs for e in r["failed"]],
        "finished_cars": sum(r["finished"] for r in runs),
        "rounds_wall_s": [round(r["wall_s"], 2) for r in runs],
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Every way on the same batch, ``args.rounds`` times in turn (see the module docstring)."""
    report: dict[str, Any] = {
        "machine": {
            "cpus": os.cpu_count(),
            "processor": platform.processor() or platform.machine(),
            "python": sys.version.split()[0],
            "load_average_before": os.getloadavg(),
        },
        "batch": {
            "races": args.races,
            "cars": args.cars,
            "laps": args.laps,
            "track": args.track,
            "workers": args.workers,
            "rounds": args.rounds,
            "policy": args.policy,
            "viser": args.viser,
        },
    }
    ways: dict[str, Any] = {
        "pooled": lambda: LocalExecutor(workers=args.workers),
        "fresh": lambda: LocalExecutor(workers=args.workers, batch_size=1),
    }
    if args.policy == "pursuit":
        ways = {"in_process": lambda: LocalExecutor(workers=args.workers)} | ways
    ray = None
    if not args.no_ray:
        ray_exec = RayExecutor(args.ray_address or "local", num_cpus=args.workers)
        start = time.perf_counter()
        ray = ray_exec.connect()  # start (or connect) before timing the batches
        report["ray_init_s"] = round(time.perf_counter() - start, 2)
        ways["ray"] = lambda: ray_exec
    runs: dict[str, list[dict[str, Any]]] = {way: [] for way in ways}
    try:
        with tempfile.TemporaryDirectory(prefix="slipstream-bench-") as tmp:
            bundle = str(make_bundle_for(args.policy, Path(tmp)))
            for k in range(args.rounds):
                for way, make in ways.items():
                    source = "pursuit" if way == "in_process" else bundle
                    jobs = make_jobs(args, source, Path(tmp) / f"{way}{k}")
                    runs[way].append(time_batch(make(), jobs))
    finally:
        if ray is not None:
            ray.shutdown()
    for way, got in runs.items():
        report[way] = summarise(got)
    if "in_process" in report:
        base = report["in_process"]["races_per_min"]
        for way in ways:
            report[way]["ratio"] = round(report[way]["races_per_min"] / base, 3)
    report["machine"]["load_average"] = os.getloadavg()
    return report


def main(argv: list[str] | None = None) -> int:
    """Parse arguments, run, print a table or JSON."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--races", type=int, default=4, help="races in the batch")
    parser.add_argument("--cars", type=int, default=4, help="cars per race (2-8)")
    parser.add_argument("--laps", type=int, default=1, help="laps per race")
    parser.add_argument("--track", default="oval", help="track of every race")
    parser.add_argument("--workers", type=int, default=2, help="job processes at once")
    parser.add_argument("--rounds", type=int, default=1, help="times each way runs, in turn")
    parser.add_argument(
        "--policy", choices=("pursuit", "ppo"), default="pursuit", help="the cars' policy"
    )
    parser.add_argument("--no-ray", action="store_true", help="skip the Ray run")
    parser.add_argument("--ray-address", default=None, help="a Ray cluster (default: local)")
    parser.add_argument("--viser", action="store_true", help="also record .viser replays")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    args = parser.parse_args(argv)
    report = run(args)
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    batch = report["batch"]
    print(
        f"{batch['races']} races × {batch['cars']} {batch['policy']} cars, {batch['laps']} "
        f"lap(s) of {batch['track']}, {batch['workers']} job processes, {batch['rounds']} "
        f"round(s), {report['machine']['cpus']} CPUs"
    )
    print(
        f"{'way':11s} {'wall s':>8s} {'races/min':>10s} {'ratio':>6s} {'mean job s':>11s}  sandbox"
    )
    for key in ("in_process", "pooled", "fresh", "ray"):
        if key in report:
            r = report[key]
            ratio = f"{r['ratio']:.2f}" if "ratio" in r else "–"
            print(
                f"{key:11s} {r['wall_s']:8.2f} {r['races_per_min']:10.2f} {ratio:>6s} "
                f"{r['mean_job_s']:11.2f}  {','.join(r['sandbox'])}"
                + (f"  FAILED: {r['failed']}" if r["failed"] else "")
            )
    if "ray" in report:
        print(f"ray start-up {report['ray_init_s']:.2f} s (not in its batch)")
    machine = report["machine"]
    print(f"load average before {machine['load_average_before']}, after {machine['load_average']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
