"""Sandbox overhead: per-step cost of a sandboxed policy, and races per minute with 4 of them.

1. **Per step.** Observations are recorded from a pursuit car driving the track; then the
   same pursuit policy answers them in-process (``policy.act``) and from a sandbox (a python
   bundle that wraps the baseline, :class:`submissions.remote.SandboxedPolicy`), and a
   sandboxed policy that only returns zeros gives the round trip alone (pipes, frames,
   checks). The figure is a ratio from one run: sandboxed / in-process time per step. On a
   shared, loaded machine the three are timed interleaved, in ``--blocks`` blocks each (one
   block of each in turn), and each figure is the median of its blocks' means, so a burst
   of load elsewhere hits all three alike.
2. **Races per minute.** One-lap races with four sandboxed pursuit cars, against the same
   race with four in-process pursuit cars, two ways: ``fresh`` (each race starts four
   sandboxes, loads the policies, races, kills them) and ``pooled`` (the races of the run
   are one batch: :class:`submissions.remote.SandboxPool` keeps the four sandboxes between
   races, as :func:`submissions.jobs.run_race_jobs` does). On a 2-core machine the four
   workers share the cores with the simulator.

Each figure is per sandbox mode (``--modes bwrap seccomp``; a mode that cannot run here is
skipped). Nothing is pinned: the sandboxed worker is a second process by design.

Usage::

    python bench/sandbox_overhead.py [--track oval] [--steps 1000] [--blocks 10] [--races 3]
                                     [--modes bwrap seccomp] [--json] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path
from typing import Any

PURSUIT_SOURCE = """
from agents.baselines import make_baseline
from arena.observations import ObservationLayout


class Policy:
    def __init__(self, env_spec):
        layout = ObservationLayout(env_spec["lidar_rays"], env_spec["k_opponents"])
        self.inner = make_baseline("pursuit", layout)

    def reset(self, seed):
        self.inner.reset(seed)

    def act(self, obs):
        return self.inner.act(obs)
"""

ZERO_SOURCE = """
import numpy as np


class Policy:
    def act(self, obs):
        return np.zeros(2, dtype=np.float32)
"""


def _bundle(folder: Path, name: str, source: str) -> Any:
    from arena.version import ENV_VERSION
    from submissions.bundle import Manifest, make_bundle, open_bundle

    manifest = Manifest(
        name=name, author="bench", format="python", entry="agent.py", env_version=ENV_VERSION
    )
    zipped = make_bundle(folder / f"{name}.zip", manifest, {"agent.py": source.encode()})
    return open_bundle(zipped, folder / name)


def record_observations(track: str, steps: int) -> list[Any]:
    """``steps`` observations of car 0 of two pursuit cars (the race restarts when over)."""
    import numpy as np

    from agents.baselines import make_baseline
    from agents.loading import DEFAULT_LAYOUT
    from arena.env import RacingEnv

    env = RacingEnv(track=track, n_cars=2, laps=50)
    drivers = [make_baseline("pursuit", DEFAULT_LAYOUT) for _ in range(2)]
    out: list[Any] = []
    obs, _ = env.reset(seed=0)
    while len(out) < steps:
        if not env.agents:
            obs, _ = env.reset(seed=0)
        vectors = {a: np.asarray(obs[a], dtype=np.float32) for a in env.agents}
        out.append(vectors["car_0"].copy())
        obs, *_ = env.step({a: drivers[env.agent_index[a]].act(v) for a, v in vectors.items()})
    env.close()
    return out


def time_per_step(policy: Any, observations: list[Any]) -> float:
    """Mean seconds per ``act`` over ``observations``."""
    start = time.perf_counter()
    for obs in observations:
        policy.act(obs)
    return (time.perf_counter() - start) / len(observations)


def per_step(
    folder: Path, track: str, steps: int, limits: Any, blocks: int = 10
) -> dict[str, float]:
    """In-process, sandboxed and round-trip-only seconds per step (medians of interleaved
    blocks, after a reset and 20 warm-up steps each), and the ratio."""
    import statistics

    from agents.baselines import make_baseline
    from agents.loading import DEFAULT_LAYOUT
    from submissions.remote import SandboxedPolicy

    observations = record_observations(track, steps)
    chunk = max(1, len(observations) // blocks)
    parts = [observations[i : i + chunk] for i in range(0, len(observations), chunk)]
    with (
        SandboxedPolicy(_bundle(folder, "pursuit_boxed", PURSUIT_SOURCE), limits) as boxed,
        SandboxedPolicy(_bundle(folder, "zeros_boxed", ZERO_SOURCE), limits) as zeros,
    ):
        policies = [make_baseline("pursuit", DEFAULT_LAYOUT), boxed, zeros]
        times: list[list[float]] = [[], [], []]
        for policy in policies:
            policy.reset(0)
            for obs in observations[:20]:
                policy.act(obs)
        for part in parts:
            for policy, out in zip(policies, times, strict=True):
                out.append(time_per_step(policy, part))
    in_process, sandboxed, round_trip = (statistics.median(t) for t in times)
    return {
        "in_process_us": in_process * 1e6,
        "sandboxed_us": sandboxed * 1e6,
        "round_trip_us": round_trip * 1e6,
        "overhead_us": (sandboxed - in_process) * 1e6,
        "ratio": sandboxed / in_process,
    }


def races_per_minute(folder: Path, track: str, races: int, limits: Any) -> dict[str, float]:
    """One-lap races with 4 sandboxed pursuit cars (fresh, pooled) vs 4 in-process ones."""
    from agents.baselines import make_baseline
    from agents.loading import DEFAULT_LAYOUT
    from arena.race import run_race
    from submissions.remote import SandboxedPolicy

    try:
        from submissions import remote

        pool_class: Any = remote.SandboxPool
    except AttributeError:  # an older checkout, measured for comparison: no pooled figure
        pool_class = None

    bundle = _bundle(folder, "pursuit_race", PURSUIT_SOURCE)
    start = time.perf_counter()
    for seed in range(races):
        run_race(
            [make_baseline("pursuit", DEFAULT_LAYOUT) for _ in range(4)], track=track, seed=seed
        )
    in_process = time.perf_counter() - start
    start = time.perf_counter()
    statuses: list[str] = []
    for seed in range(races):
        cars = [SandboxedPolicy(bundle, limits) for _ in range(4)]
        result, _ = run_race(cars, track=track, seed=seed)
        statuses += [c.status for c in result.cars]
    sandboxed = time.perf_counter() - start
    pooled = float("nan")
    if pool_class is not None:
        start = time.perf_counter()
        with pool_class() as pool:
            for seed in range(races):
                cars = [pool.policy(bundle, limits) for _ in range(4)]
                result, _ = run_race(cars, track=track, seed=seed)
                statuses += [c.status for c in result.cars]
        pooled = time.perf_counter() - start
    return {
        "races": races,
        "in_process_races_per_min": 60 * races / in_process,
        "sandboxed_races_per_min": 60 * races / sandboxed,
        "pooled_races_per_min": 60 * races / pooled,
        "sandboxed_s_per_race": sandboxed / races,
        "fresh_ratio": in_process / sandboxed,
        "pooled_ratio": in_process / pooled,
        "finished_fraction": statuses.count("finished") / len(statuses),
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Measure each mode; the JSON document."""
    from submissions import sandbox
    from submissions.errors import SandboxError
    from submissions.sandbox import SandboxLimits, sandbox_mode

    weak_env = getattr(sandbox, "WEAK_ENV", "SLIPSTREAM_ALLOW_WEAK_SANDBOX")  # older checkouts

    limits = SandboxLimits(step_deadline_s=1.0, overage_s=60.0)  # measure, never time out
    results: dict[str, Any] = {}
    load_before = os.getloadavg()
    for mode in args.modes:
        os.environ["SANDBOX"] = mode
        if mode == "seccomp":  # measuring the fallback is the operator's explicit choice
            os.environ[weak_env] = "1"
        try:
            sandbox_mode()
        except SandboxError as err:
            results[mode] = {"skipped": str(err)}
            continue
        with tempfile.TemporaryDirectory(prefix="slipstream-bench-") as tmp:
            folder = Path(tmp)
            results[mode] = {
                "per_step": per_step(folder, args.track, args.steps, limits, args.blocks),
                "races": races_per_minute(folder, args.track, args.races, limits),
            }
    return {
        "benchmark": "sandbox_overhead",
        "track": args.track,
        "steps": args.steps,
        "machine": {
            "platform": platform.platform(),
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
            "load_average_before": load_before,
            "load_average": os.getloadavg(),
        },
        "modes": results,
    }


def print_table(doc: dict[str, Any]) -> None:
    """Rich tables of the figures."""
    from rich.console import Console
    from rich.table import Table

    console = Console()
    steps = Table(title=f"Per step, pursuit policy ({doc['steps']} observations, {doc['track']})")
    races = Table(title="One-lap races with 4 pursuit cars")
    for name in ("mode", "in-process µs", "sandboxed µs", "round trip µs", "ratio"):
        steps.add_column(name, justify="right")
    for name in (
        "mode",
        "in-process races/min",
        "fresh sandboxes races/min",
        "pooled sandboxes races/min",
        "pooled / in-process",
        "finished",
    ):
        races.add_column(name, justify="right")
    for mode, res in doc["modes"].items():
        if "skipped" in res:
            console.print(f"{mode}: skipped ({res['skipped']})")
            continue
        s, r = res["per_step"], res["races"]
        steps.add_row(
            mode,
            f"{s['in_process_us']:.0f}",
            f"{s['sandboxed_us']:.0f}",
            f"{s['round_trip_us']:.0f}",
            f"{s['ratio']:.2f}×",
        )
        races.add_row(
            mode,
            f"{r['in_process_races_per_min']:.1f}",
            f"{r['sandboxed_races_per_min']:.1f}",
            f"{r['pooled_races_per_min']:.1f}",
            f"{r['pooled_ratio']:.2f}×",
            f"{r['finished_fraction']:.0%}",
        )
    console.print(steps)
    console.print(races)
    machine = doc["machine"]
    console.print(
        f"load average (1, 5, 15 min) before: {machine['load_average_before']}, "
        f"after: {machine['load_average']}"
    )


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--track", default="oval", help="built-in track name or path")
    parser.add_argument(
        "--steps", type=int, default=1000, help="observations timed per step figure"
    )
    parser.add_argument("--races", type=int, default=3, help="races per races-per-minute figure")
    parser.add_argument("--blocks", type=int, default=10, help="interleaved blocks per step figure")
    parser.add_argument(
        "--modes", nargs="+", default=["bwrap", "seccomp"], choices=["bwrap", "seccomp"]
    )
    parser.add_argument("--json", action="store_true", help="print JSON instead of tables")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args(argv)
    doc = run(args)
    if args.out is not None:
        args.out.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    if args.json:
        print(json.dumps(doc, indent=2))
    else:
        print_table(doc)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
