"""Batched-backend speed: agent-steps/s of ``BatchSim.step`` against the batch size.

For each device (numpy on the CPU, torch on the CPU, CUDA when torch sees a GPU) and each
batch size B (1 … 16,384 environments × ``--cars`` cars) the script builds one
:class:`arena.batch.sim.BatchSim` on ``--track`` (64-ray lidar, 20 Hz control, 60 Hz
physics, random starts and automatic resets: the training setting), steps it a few times to
warm up, then times ``--steps`` control steps (fewer for large B) with random actions drawn
in advance on the device, so the policy's cost is excluded. One step is the whole env step:
physics substeps, contacts, lidar, observations, rewards, episode ends and resets.

CPU parallelism: numpy is single-threaded, so ``--workers W`` (default: all cores) splits the
batch over W simulators stepped from W threads (numpy releases the GIL inside its loops);
torch on the CPU uses ``--workers`` intra-op threads instead. CPU-time rates (``per_cpu_s``)
are printed too: on a busy machine they are steadier than wall-clock rates.

Goals from the issue: at least 200,000 agent-steps/s on 2 CPU cores and 20 million on an
H100 (f1tenth_gym reaches about 3,300 on this machine class).

Usage::

    python bench/batch_speed.py [--devices numpy torch:cpu cuda] [--sizes 1 16 ... 16384]
                                [--cars 4] [--steps 200] [--workers 2] [--json] [--out F]
                                [--uncertainty sample]
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import platform
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from anywhere


def cpu_model() -> str:
    """The CPU's model name, as bench/env_speed.py reports it (bench/ holds scripts, not a
    package, so it is loaded from its path)."""
    env_speed = importlib.import_module("env_speed")  # bench/ is on sys.path as a script's dir
    return str(env_speed.cpu_model())


CPU_GOAL = 200_000.0  # agent-steps/s on 2 CPU cores
GPU_GOAL = 20_000_000.0  # agent-steps/s on an H100
DEFAULT_SIZES = (1, 16, 256, 1024, 4096, 16384)
ACTION_SETS = 4  # distinct random action arrays cycled through


@dataclass
class Row:
    """Figures for one device and batch size."""

    device: str
    n_envs: int
    n_cars: int
    workers: int
    steps: int
    agent_steps_per_s: float
    env_steps_per_s: float
    ms_per_step: float
    per_cpu_s: float  # agent-steps per second of CPU time of this process


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        import torch

        torch.cuda.synchronize()


def measure(
    device: str,
    n_envs: int,
    n_cars: int,
    track: str,
    steps: int,
    workers: int,
    uncertainty: str = "nominal",
) -> Row:
    """Time ``steps`` control steps of ``n_envs`` environments on ``device`` (with the
    default uncertainty set in ``uncertainty`` mode, drawn and applied by the simulator)."""
    from arena.batch.sim import BatchSim
    from arena.uncertainty import default_config

    cfg = None if uncertainty == "nominal" else default_config(uncertainty)

    split = workers if device == "numpy" else 1
    split = max(1, min(split, n_envs))
    sizes = [n_envs // split + (k < n_envs % split) for k in range(split)]
    sims = [
        BatchSim(track, b, n_cars, device=device, random_starts=True, seed=k, uncertainty=cfg)
        for k, b in enumerate(sizes)
    ]
    rng = np.random.default_rng(0)
    actions = [
        [sim.ops.asarray(rng.uniform(-1, 1, (sim.n_envs, n_cars, 2))) for _ in range(ACTION_SETS)]
        for sim in sims
    ]
    pool = ThreadPoolExecutor(split) if split > 1 else None

    def one_step(i: int) -> None:
        if pool is None:
            sims[0].step(actions[0][i % ACTION_SETS])
        else:
            list(pool.map(lambda k: sims[k].step(actions[k][i % ACTION_SETS]), range(split)))

    for i in range(3):  # warm-up (caches, CUDA kernels)
        one_step(i)
    _sync(device)
    wall0, cpu0 = time.perf_counter(), time.process_time()
    for i in range(steps):
        one_step(i)
    _sync(device)
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    if pool is not None:
        pool.shutdown()
    agent_steps = n_envs * n_cars * steps
    return Row(
        device=device,
        n_envs=n_envs,
        n_cars=n_cars,
        workers=split if device == "numpy" else workers,
        steps=steps,
        agent_steps_per_s=agent_steps / wall,
        env_steps_per_s=n_envs * steps / wall,
        ms_per_step=1e3 * wall / steps,
        per_cpu_s=agent_steps / max(cpu, 1e-9),
    )


def _available(device: str) -> bool:
    if device == "numpy":
        return True
    try:
        import torch
    except ImportError:
        return False
    return not device.startswith("cuda") or torch.cuda.is_available()


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Run the benchmark; returns (and prints) the figures."""
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--devices", nargs="+", default=["numpy", "torch:cpu", "cuda"])
    parser.add_argument("--sizes", nargs="+", type=int, default=list(DEFAULT_SIZES))
    parser.add_argument("--cars", type=int, default=4)
    parser.add_argument("--track", default="oval")
    parser.add_argument("--steps", type=int, default=200, help="steps timed at small B")
    parser.add_argument("--agent-steps", type=int, default=200_000, help="budget per size")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument(
        "--uncertainty",
        choices=("nominal", "sample"),
        default="nominal",
        help="sample: the default robust set drawn per episode (latency FIFO, noise, reward)",
    )
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args(argv)

    import torch

    torch.set_num_threads(args.workers)
    rows: list[Row] = []
    skipped = [d for d in args.devices if not _available(d)]
    for device in [d for d in args.devices if _available(d)]:
        for b in args.sizes:
            steps = max(3, min(args.steps, args.agent_steps // (b * args.cars)))
            rows.append(
                measure(device, b, args.cars, args.track, steps, args.workers, args.uncertainty)
            )
    best_cpu = max(
        (r.agent_steps_per_s for r in rows if not r.device.startswith("cuda")), default=0.0
    )
    best_gpu = max((r.agent_steps_per_s for r in rows if r.device.startswith("cuda")), default=None)
    report: dict[str, Any] = {
        "machine": {
            "cpu": cpu_model(),
            "cores": os.cpu_count(),
            "load_average": os.getloadavg(),
            "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
            "python": platform.python_version(),
            "torch": torch.__version__,
            "numpy": np.__version__,
        },
        "settings": {
            "track": args.track,
            "cars": args.cars,
            "lidar_rays": 64,
            "control_hz": 20,
            "physics_hz": 60,
            "workers": args.workers,
            "uncertainty": args.uncertainty,
        },
        "rows": [asdict(r) for r in rows],
        "skipped_devices": skipped,
        "best_cpu_agent_steps_per_s": best_cpu,
        "cpu_goal": CPU_GOAL,
        "cpu_goal_met": best_cpu >= CPU_GOAL,
        "best_gpu_agent_steps_per_s": best_gpu,
        "gpu_goal": GPU_GOAL,
        "gpu_goal_met": None if best_gpu is None else best_gpu >= GPU_GOAL,
    }
    if args.out is not None:
        args.out.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        _print_table(report, rows)
    return report


def _print_table(report: dict[str, Any], rows: list[Row]) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title="BatchSim.step — agent-steps/s (policy excluded)")
    for col in (
        "device",
        "envs",
        "agents",
        "workers",
        "agent-steps/s",
        "env-steps/s",
        "ms/step",
        "per CPU-s",
    ):
        table.add_column(col, justify="right")
    for r in rows:
        table.add_row(
            r.device,
            f"{r.n_envs:,}",
            f"{r.n_envs * r.n_cars:,}",
            str(r.workers),
            f"{r.agent_steps_per_s:,.0f}",
            f"{r.env_steps_per_s:,.0f}",
            f"{r.ms_per_step:.2f}",
            f"{r.per_cpu_s:,.0f}",
        )
    console = Console(width=120)
    console.print(table)
    m = report["machine"]
    console.print(
        f"{m['cpu']}, {m['cores']} cores, load average {m['load_average'][0]:.1f}; "
        f"GPU: {m['gpu'] or 'none'}"
    )
    console.print(
        f"best CPU {report['best_cpu_agent_steps_per_s']:,.0f} agent-steps/s "
        f"(goal {CPU_GOAL:,.0f}: {'met' if report['cpu_goal_met'] else 'not met'}); "
        + (
            f"best GPU {report['best_gpu_agent_steps_per_s']:,.0f} (goal {GPU_GOAL:,.0f})"
            if report["best_gpu_agent_steps_per_s"] is not None
            else "GPU: not measured (no CUDA device)"
        )
    )


if __name__ == "__main__":
    main()
