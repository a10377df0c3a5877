"""``slipstream robustness``: a policy's robustness to model uncertainty (:mod:`agents.robustness`).

This module stays cheap to import: the env and torch are imported by the handler only.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from agents.robustness import AXES, GRID, SCALES


def register(sub: Any) -> None:
    """Add ``robustness`` to the ``slipstream`` subcommands."""
    p = sub.add_parser(
        "robustness",
        help="score a policy under model uncertainty: grid, random draws, trained nature",
        description=(
            "Race POLICY alone on a track, nominally and over a grid of perturbations "
            "(friction × motor gain × steering offset × latency by default; --mass, "
            "--steer-gain, --action-noise, --lidar-noise and --lidar-dropout add axes), on "
            "random draws of the "
            "default uncertainty set and against a freshly trained nature; prints the "
            "nominal score, the random mean, the worst case, the worst-10 % mean and "
            "worst/nominal (scores: effective speed, m/s), and saves a JSON report and a "
            "degradation plot (PNG)."
        ),
    )
    p.add_argument("policy", help="a baseline name (pursuit, gap, random) or a checkpoint path")
    p.add_argument("--track", default="oval", help="built-in name, file or random:<seed>")
    p.add_argument("--laps", type=int, default=1, help="laps per race")
    p.add_argument("--seed", type=int, default=0, help="seeds races, random draws and nature")
    p.add_argument("--random", type=int, default=20, metavar="N", help="random draws (0: skip)")
    p.add_argument(
        "--nature-steps",
        type=int,
        default=20_000,
        metavar="N",
        help="PPO steps to train the nature against the policy (0: skip)",
    )
    for name, nominal in AXES.items():  # GRID's axes on by default, the others on request
        values = GRID.get(name)
        p.add_argument(
            "--" + name.replace("_", "-"),
            type=float,
            nargs="+",
            default=None if values is None else list(values),
            metavar="X",
            help=f"grid values of {name} (default: {' '.join(map(str, values))})"
            if values
            else f"add {name} to the grid, over these values (nominal {nominal:g})",
        )
    p.add_argument(
        "--scales",
        type=float,
        nargs="+",
        default=list(SCALES),
        metavar="S",
        help="bound scales of the degradation curve (default: 0 0.25 0.5 0.75 1)",
    )
    p.add_argument(
        "--starts",
        type=float,
        nargs="+",
        default=[0.0],
        metavar="F",
        help="standing starts as fractions of the lap (0: the grid); a point scores the mean",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=Path("runs/robustness"),
        metavar="DIR",
        help="where to write <policy>_<track>.json and .png",
    )
    p.add_argument(
        "--backend",
        choices=("pybullet", "batch"),
        default="pybullet",
        help="pybullet: race after race; batch: the whole grid, curve and random draws as one "
        "batch of the batched simulator (seconds), then the worst points re-run on pybullet",
    )
    p.add_argument(
        "--confirm",
        type=int,
        default=3,
        metavar="N",
        help="with --backend batch: worst grid points re-run on pybullet (0: none)",
    )
    p.add_argument(
        "--device", default="numpy", help="array device of --backend batch (numpy, torch:cpu, cuda)"
    )
    p.add_argument("--json", type=Path, default=None, metavar="FILE", help="report ('-': stdout)")
    p.add_argument(
        "--trusted",
        action="store_true",
        help="allow SB3/TorchScript files, which run code when loaded (your own only)",
    )
    p.set_defaults(handler=robustness_command)


def robustness_command(args: argparse.Namespace) -> int:
    """Run ``slipstream robustness``."""
    from rich.console import Console  # noqa: PLC0415 - heavy, imported on use

    from agents.cli import progress_bar  # noqa: PLC0415 - imports on use
    from agents.loading import load_policy  # noqa: PLC0415 - heavy, imported on use
    from agents.policy import PolicyError  # noqa: PLC0415 - heavy, imported on use
    from agents.robustness import evaluate_robustness, save_plot, save_report  # noqa: PLC0415 - heavy, imported on use
    from tracks import load_track  # noqa: PLC0415 - heavy, imported on use

    if args.laps < 1 or args.random < 0 or args.nature_steps < 0 or args.confirm < 0:
        raise PolicyError("--laps must be >= 1; --random, --nature-steps and --confirm >= 0")
    if any(s < 0 for s in args.scales):
        raise PolicyError("--scales must be >= 0")
    if any(not 0 <= x < 1 for x in args.starts):
        raise PolicyError("--starts must be fractions of the lap in [0, 1)")
    load_track(args.track)  # a clear error before anything heavy
    # Its races are built for it: with the perturbation block if it was trained on one.
    policy = load_policy(args.policy, trusted=args.trusted, observe_perturbation=None)
    grid = {name: tuple(v) for name in AXES if (v := getattr(args, name)) is not None}
    to_stdout = args.json is not None and str(args.json) == "-"
    console = Console(stderr=to_stdout)
    with progress_bar(console, "[bold]{task.description}") as bar:
        tasks: dict[str, Any] = {}

        def progress(stage: str, done: int, total: int) -> None:
            if stage not in tasks:
                tasks[stage] = bar.add_task(stage, total=total)
            bar.update(tasks[stage], completed=done, total=total)

        report = evaluate_robustness(
            policy,
            args.track,
            laps=args.laps,
            seed=args.seed,
            n_random=args.random,
            nature_steps=args.nature_steps,
            scales=args.scales,
            grid=grid,
            starts=args.starts,
            progress=progress,
            backend=args.backend,
            confirm=args.confirm,
            device=args.device,
        )
    stem = f"{Path(args.policy).stem}_{Path(args.track).stem}".replace(":", "_")
    json_path = save_report(report, args.out / f"{stem}.json")
    png_path = save_plot(report, args.out / f"{stem}.png")
    # A checkpoint is titled by the file asked for, its run name beside (ppo_racer.zip's is
    # "pilot6": the name alone did not say which file was scored).
    title = Path(args.policy).name
    if report.policy != title:
        title = f"{title} ({report.policy})"
    console.print(summary_table(report.to_dict(), title))
    console.print(f"report {json_path}\nplot   {png_path}")
    if args.json is not None:
        text = json.dumps(report.to_dict(), indent=2)
        if to_stdout:
            sys.stdout.write(text + "\n")
        else:
            args.json.write_text(text + "\n", encoding="utf-8")
    return 0


def summary_table(report: dict[str, Any], title: str | None = None) -> Any:
    """A rich table of a robustness report's headline figures, titled ``title`` (default the
    report's policy name) on its track."""
    from rich.table import Table  # noqa: PLC0415 - heavy, imported on use

    name = title or report["policy"]
    table = Table(title=f"{name} on {report['track']} · effective speed, m/s")
    table.add_column("measure")
    table.add_column("score", justify="right")
    table.add_column("/ nominal", justify="right")
    nominal = report["nominal"]

    def row(label: str, value: float) -> None:
        ratio = f"{value / nominal:.2f}" if nominal > 0 else "–"
        table.add_row(label, f"{value:.3f}", ratio)

    row("nominal", nominal)
    if report["random"] is not None:
        row(f"random mean ({report['random']['n']} draws)", report["random"]["mean"])
    grid = report["grid"]
    row(f"grid mean ({grid['n']} points)", grid["mean"])
    row("grid worst-10% mean", grid["worst10_mean"])
    row("grid worst case", grid["worst"])
    for cell in report.get("confirmed") or []:
        point = " ".join(f"{k}={v:g}" for k, v in cell["perturbation"].items())
        row(f"worst point on pybullet ({point}; batch {cell['batch']:.3f})", cell["pybullet"])
    if report["nature"] is not None:
        row(f"vs. trained nature ({report['nature']['steps']} steps)", report["nature"]["score"])
    return table
