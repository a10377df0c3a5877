"""``slipstream race``: a local head-to-head race between baselines and checkpoints."""

from __future__ import annotations

import argparse
import sys
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from tracks.errors import SlipstreamError


def register(sub: Any) -> None:
    """Add ``race`` to the ``slipstream`` subcommands."""
    p = sub.add_parser(
        "race",
        help="race baselines and checkpoints head to head",
        description=(
            "Race policies on one track: each agent is a baseline name (pursuit, gap, "
            "random) or a checkpoint path. Shows a progress bar, then the results table."
        ),
    )
    p.add_argument("--track", default="oval", help="built-in name, file or random:<seed>")
    p.add_argument(
        "--agents",
        default="pursuit,gap",
        help="comma-separated baselines (pursuit, gap, random; raceline on a track with a "
        "race line) or checkpoint paths",
    )
    p.add_argument(
        "--car",
        default="f1tenth",
        help="car preset: f1tenth (1/10) or deepracer (1/18); a checkpoint trained with "
        "another car races anyway, with a one-line warning",
    )
    p.add_argument("--laps", type=int, default=2, help="race distance in laps")
    p.add_argument("--seed", type=int, default=0, help="seed for the grid and the policies")
    p.add_argument(
        "--grid",
        choices=["fixed", "random"],
        default="fixed",
        help="grid order: as listed (fixed) or shuffled by the seed",
    )
    p.add_argument(
        "--ranked",
        action="store_true",
        help="DeepRacer penalties: +2 s per off-track, +5 s per at-fault collision",
    )
    p.add_argument(
        "--json",
        type=Path,
        default=None,
        metavar="FILE",
        help="write the result JSON here ('-' for stdout)",
    )
    p.add_argument(
        "--replay",
        type=Path,
        default=None,
        metavar="FILE",
        help="write the replay log (.replay.json.gz) here",
    )
    p.add_argument(
        "--watch",
        action="store_true",
        help="show the race live in the browser (a viser server, the site's 3D renderer), "
        "paced to real time",
    )
    p.add_argument("--watch-port", type=int, default=8080, help="port of the --watch server")
    p.add_argument(
        "--trusted",
        action="store_true",
        help="allow SB3/TorchScript files, which run code when loaded (your own only)",
    )
    p.set_defaults(handler=race_command)

    e = sub.add_parser(
        "export",
        help="convert your own stable-baselines3 PPO zip into a safe Slipstream checkpoint",
        description=(
            "SB3 zips unpickle code when loaded, so only your own trusted files are accepted "
            "(--trusted). The result is a zip of meta.json + safetensors that anyone can load "
            "without running code."
        ),
    )
    e.add_argument("source", type=Path, help="the SB3 PPO .zip")
    e.add_argument("--out", type=Path, required=True, help="checkpoint to write")
    e.add_argument("--name", default=None, help="policy name (default: the file stem)")
    e.add_argument(
        "--car",
        default=None,
        help="the car preset it was trained with, recorded in the checkpoint (default: none "
        "recorded, which reads as f1tenth)",
    )
    e.add_argument(
        "--trusted",
        action="store_true",
        help="confirm the SB3 file is your own: loading it runs its pickled code",
    )
    e.set_defaults(handler=export_command)


def progress_bar(console: Any, description: str, unit: str = "") -> Any:
    """A transient rich progress bar on ``console`` (a ``rich.console.Console``): the
    ``description`` column (rich markup; ``{task.description}`` is the task's own), a bar,
    ``done/total unit`` and the elapsed time. Use it as a context manager."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    count = "{task.completed}/{task.total}" + (f" {unit}" if unit else "")
    return Progress(
        TextColumn(description),
        BarColumn(),
        TextColumn(count),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    )


def race_command(args: argparse.Namespace) -> int:
    """Run ``slipstream race``."""
    from rich.console import Console

    from agents.loading import load_policy
    from arena.race import run_race

    names = [a.strip() for a in args.agents.split(",") if a.strip()]
    if not 1 <= len(names) <= 16:
        raise SlipstreamError("--agents takes 1 to 16 comma-separated agents")
    from arena.cars import car_params
    from tracks import load_track

    params = car_params(args.car)
    track = load_track(args.track)
    with one_line_warnings():  # a checkpoint of another car (CarMismatchWarning), say
        policies = [load_policy(n, trusted=args.trusted, params=params, track=track) for n in names]
    for i, pol in enumerate(policies):  # same baseline twice: tell them apart in the table
        if names.count(names[i]) > 1:
            pol.name = f"{pol.name}#{i}"
    to_stdout = args.json is not None and str(args.json) == "-"
    console = Console(stderr=to_stdout)
    with progress_bar(console, "[bold]racing[/] {task.description}", "steps") as bar:
        task = bar.add_task(f"{args.track}, {args.laps} laps", total=None)

        def progress(step: int, total: int) -> None:
            bar.update(task, completed=step, total=total)

        with _watching(args, policies, console):
            result, replay = run_race(
                policies,
                track=track,
                laps=args.laps,
                seed=args.seed,
                ranked=args.ranked,
                grid_order="random" if args.grid == "random" else None,
                progress=progress,
                record=True,  # the replay also keeps why a policy left the race
                env_kwargs={"car": params},
            )
    console.print(results_table(result.to_dict()))
    who = {car.agent: car.name for car in result.cars}
    for event in replay.events if replay is not None else []:
        if event["type"] == "dnf" and event.get("detail"):
            console.print(
                f"{who[event['car']]}: dnf ({event['reason']}) at {event['t']:.2f} s: "
                f"{event['detail']}",
                markup=False,
                soft_wrap=True,  # one line, whole, as the error was raised
            )
    if args.replay is not None and replay is not None:
        replay.save(args.replay)
        console.print(f"replay written to {args.replay}")
    if args.json is not None:
        if to_stdout:
            sys.stdout.write(result.to_json() + "\n")
        else:
            result.to_json(args.json)
            console.print(f"results written to {args.json}")
    return 0


@contextmanager
def one_line_warnings() -> Iterator[None]:
    """Inside: every warning is printed as one line on stderr, ``slipstream: warning: …``
    (Python's default adds the file, line and source of the code that warned)."""

    def show(message: Warning | str, *_: Any, **__: Any) -> None:
        print(f"slipstream: warning: {message}", file=sys.stderr)

    with warnings.catch_warnings():  # restores the default display on the way out
        warnings.showwarning = show
        yield


@contextmanager
def _watching(args: argparse.Namespace, policies: list[Any], console: Any) -> Iterator[None]:
    """With ``--watch``: a live viser scene that draws every recorded frame of the race."""
    if not args.watch:
        yield
        return
    from arena.cars import car_params
    from arena.colours import car_colour
    from arena.replay import observe
    from arena.viser_scene import LiveScene, LiveWatcher
    from tracks import load_track

    cars = [
        {"agent": f"car_{i}", "name": getattr(p, "name", f"car_{i}"), "colour": car_colour(i)}
        for i, p in enumerate(policies)
    ]
    scene = LiveScene(
        load_track(args.track), cars, port=args.watch_port, laps=args.laps, car=car_params(args.car)
    )
    console.print(f"watch the race live at {scene.url}")
    try:
        with observe(LiveWatcher(scene)):
            yield
    finally:
        scene.close()


def export_command(args: argparse.Namespace) -> int:
    """Run ``slipstream export``."""
    from agents.loading import convert_sb3

    env_config = {} if args.car is None else {"car": args.car}
    out = convert_sb3(
        args.source, args.out, name=args.name, trusted=args.trusted, env_config=env_config
    )
    print(f"wrote {out}")
    return 0


def results_table(result: dict[str, Any]) -> Any:
    """A rich table of a race result dict (positions, laps, best lap, time, penalties)."""
    from rich.table import Table

    table = Table(
        title=f"{result['track']} · {result['laps']} lap{'s' if result['laps'] != 1 else ''}"
        f" · seed {result['seed']}" + (" · ranked" if result["ranked"] else "")
    )
    for col in ("pos", "name", "laps", "best lap", "total time", "penalties", "status"):
        table.add_column(col, justify="left" if col in ("name", "status") else "right")
    for car in sorted(result["cars"], key=lambda c: c["position"]):
        status = car["status"] if car["status"] == "finished" else f"dnf ({car['dnf_reason']})"
        table.add_row(
            str(car["position"]),
            car["name"],
            str(car["laps_completed"]),
            f"{car['best_lap']:.2f} s" if car["best_lap"] is not None else "–",
            f"{car['total_time']:.2f} s" if car["total_time"] is not None else "–",
            f"{car['penalties']:.0f} s" if car["penalties"] else "",
            status,
        )
    return table
