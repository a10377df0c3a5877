"""``slipstream evaluate``: validate a submission bundle, then race it, sandboxed, headless.

1. The bundle is checked (:func:`submissions.bundle.open_bundle`) before anything runs.
2. A *validation race* (like Kaggle's validation episode): the bundle against copies of itself,
   every car sandboxed. If any copy crashes, misses its deadlines or returns invalid actions
   (``dnf`` with reason ``error`` / ``timeout`` / ``invalid``), the evaluation stops there.
3. ``--races`` races of the bundle against the ``--against`` cars, tracks cycled, seeds
   ``seed, seed + 1, …``, the bundle's grid slot rotating so it starts from every position.

Every race writes its replay log and ``.viser`` 3D replay into ``--out``. Jobs run in a local
process pool (``--workers``) or on Ray (``--ray-address``), each with a wall-clock limit
(``--job-timeout``). A job process runs one race after another and keeps the bundle's
sandboxes running between them (:mod:`submissions.executors`), so the validation race and
the races pay the sandboxes' start-up once per process.

The bundle is untrusted: it runs only in the bubblewrap namespace sandbox. Where that cannot
run, ``evaluate`` refuses (exit 2) unless ``--allow-weak-sandbox`` accepts the weaker seccomp
fallback (logged; every result then records ``sandbox: seccomp-weak``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from submissions.errors import SubmissionError

POLICY_FAILURES = ("error", "timeout", "invalid")


def register(sub: Any) -> None:
    """Add ``evaluate`` to the ``slipstream`` subcommands."""
    p = sub.add_parser(
        "evaluate",
        help="validate a submission bundle and race it, sandboxed, against baselines",
        description=(
            "Check a submission bundle (zip or folder), run a validation race against copies "
            "of itself, then race it against the --against cars. Every bundle runs in its own "
            "sandboxed process; replays (.replay.json.gz and .viser) go to --out."
        ),
    )
    p.add_argument("bundle", type=Path, help="the submission bundle: a .zip or a folder")
    p.add_argument(
        "--against",
        default="pursuit,gap",
        help="comma-separated opponents: baselines (pursuit, gap, random) or bundle paths",
    )
    p.add_argument("--races", type=int, default=2, help="number of races after validation")
    p.add_argument("--tracks", default="oval", help="comma-separated tracks, cycled over the races")
    p.add_argument("--laps", type=int, default=2, help="race distance in laps")
    p.add_argument("--seed", type=int, default=0, help="seed of the first race")
    p.add_argument("--out", type=Path, default=None, help="output folder for replays")
    p.add_argument(
        "--ray-address",
        default=None,
        help="run the races on Ray ('auto', 'ray://host:10001', or 'local'); "
        "default: a local process pool",
    )
    p.add_argument("--workers", type=int, default=2, help="races at once in the local pool")
    p.add_argument(
        "--job-timeout",
        type=float,
        default=None,
        metavar="S",
        help="kill a race (and every process of it) after S seconds (default: 900)",
    )
    p.add_argument(
        "--allow-weak-sandbox",
        action="store_true",
        help="where bubblewrap cannot run, race the bundle in the weaker seccomp fallback "
        "(logged and recorded on every result) instead of refusing",
    )
    p.add_argument(
        "--no-viser", action="store_true", help="skip the .viser 3D replays (logs are kept)"
    )
    p.add_argument(
        "--json",
        nargs="?",
        const="-",
        default=None,
        metavar="FILE",
        help="write the results as JSON to FILE (bare --json: stdout)",
    )
    p.set_defaults(handler=evaluate_command)


def _entrants(args: argparse.Namespace, bundle: Path, name: str) -> list[Any]:
    from submissions.jobs import BASELINE_NAMES, Entrant

    against: list[Any] = []
    for i, item in enumerate(a.strip() for a in args.against.split(",") if a.strip()):
        source = item if item in BASELINE_NAMES else str(Path(item).resolve())
        label = item if item in BASELINE_NAMES else Path(item).stem
        against.append(Entrant(name=f"{label}#{i + 1}", source=source))
    return [Entrant(name=name, source=str(bundle)), *against]


def build_jobs(args: argparse.Namespace, bundle: Path, name: str, out: Path) -> list[Any]:
    """The validation job, then one job per race (see the module docstring)."""
    from submissions.jobs import Entrant, RaceJob

    entrants = _entrants(args, bundle, name)
    tracks = [t.strip() for t in args.tracks.split(",") if t.strip()]
    if not tracks:
        raise SubmissionError("--tracks needs at least one track")
    if args.races < 0:
        raise SubmissionError("--races must be 0 or more")
    common = {"out_dir": str(out), "laps": args.laps, "record_viser": not args.no_viser}
    copies = tuple(
        Entrant(name=f"{name}#{i}", source=str(bundle)) for i in range(max(2, len(entrants)))
    )
    jobs = [RaceJob(f"{name}-validation", copies, tracks[0], seed=args.seed, **common)]
    for k in range(args.races):
        slot = k % len(entrants)  # the bundle starts from each grid slot in turn
        order = entrants[1 : slot + 1] + entrants[:1] + entrants[slot + 1 :]
        jobs.append(
            RaceJob(
                f"{name}-race{k + 1:03d}",
                tuple(order),
                tracks[k % len(tracks)],
                seed=args.seed + k,
                **common,
            )
        )
    return jobs


def _validation_failures(result: dict[str, Any]) -> list[str]:
    return [
        f"{car['name']}: {car['dnf_reason']}"
        for car in result["cars"]
        if car["status"] == "dnf" and car["dnf_reason"] in POLICY_FAILURES
    ]


def summary_table(name: str, results: Sequence[Any]) -> Any:
    """A rich table: one row per race, the bundle's position and times."""
    from rich.table import Table

    table = Table(title=f"{name}: {len(results)} race(s)")
    for col in ("race", "track", "seed", "pos", "status", "best lap", "total time", "sandbox"):
        table.add_column(col, justify="right" if col in ("seed", "pos") else "left")
    for res in results:
        car = next(c for c in res.result["cars"] if c["name"] == name)
        status = car["status"] if car["status"] == "finished" else f"dnf ({car['dnf_reason']})"
        table.add_row(
            res.job_id.rsplit("-", 1)[-1],
            res.result["track"],
            str(res.result["seed"]),
            f"{car['position']}/{len(res.result['cars'])}",
            status,
            f"{car['best_lap']:.2f} s" if car["best_lap"] is not None else "–",
            f"{car['total_time']:.2f} s" if car["total_time"] is not None else "–",
            res.sandbox,
        )
    return table


def evaluate_command(args: argparse.Namespace) -> int:
    """Run ``slipstream evaluate``."""
    from rich.console import Console

    from agents.cli import progress_bar, results_table
    from submissions.bundle import open_bundle
    from submissions.executors import JOB_TIMEOUT_S, KEEP_WARM_S, make_executor
    from submissions.sandbox import allow_weak_sandbox, sandbox_mode
    from submissions.scheduling import check_settings

    if args.allow_weak_sandbox:
        allow_weak_sandbox()
    sandbox_mode()  # fail closed here, in one line, before anything runs
    check_settings()  # and a malformed scheduling setting likewise
    bundle = args.bundle.resolve()
    timeout = JOB_TIMEOUT_S if args.job_timeout is None else args.job_timeout
    if not timeout > 0:
        raise SubmissionError(f"--job-timeout must be positive, not {args.job_timeout}")
    # The job processes start now, while the bundle is checked, and stay warm from the
    # validation race to the races: the bundle's sandboxes start once per process (all
    # closed when the block ends, however it ends).
    executor = make_executor(
        args.ray_address, workers=args.workers, job_timeout_s=timeout, keep_warm_s=KEEP_WARM_S
    )
    to_stdout = args.json == "-"
    console = Console(stderr=to_stdout)
    results: list[Any] = []
    with contextlib.ExitStack() as stack:
        stack.enter_context(executor)
        executor.prestart()
        with tempfile.TemporaryDirectory(prefix="slipstream-check-") as tmp:
            opened = open_bundle(bundle, Path(tmp) / "bundle")  # fail fast, clearly
            manifest = opened.manifest
            if manifest.format == "slipstream":  # data only: meta.json names the car it learned
                from agents.loading import checkpoint_car_mismatch

                mismatch = checkpoint_car_mismatch(opened.entry_path, manifest.car)
                if mismatch is not None:  # the races run the manifest's car
                    print(f"slipstream: warning: {mismatch}", file=sys.stderr)
        out = (args.out or Path("artifacts") / "evaluate" / manifest.name).resolve()
        jobs = build_jobs(args, bundle, manifest.name, out)
        bar = stack.enter_context(
            progress_bar(console, "[bold]evaluating[/] {task.description}", "races")
        )
        task = bar.add_task(f"{manifest.name}: validation", total=len(jobs))
        (validation,) = executor.run(jobs[:1])
        bar.update(task, completed=1, description=f"{manifest.name}: races")
        if not validation.ok:
            raise SubmissionError(f"validation race could not run: {validation.error}")
        console.print(results_table(validation.result))
        failures = _validation_failures(validation.result)
        if failures:
            raise SubmissionError(f"validation race failed: {'; '.join(failures)}")

        def progress(done: int, total: int) -> None:
            bar.update(task, completed=1 + done)

        for res in executor.run(jobs[1:], progress):
            if not res.ok:
                raise SubmissionError(f"race {res.job_id} could not run: {res.error}")
            results.append(res)
    results.sort(key=lambda r: r.job_id)
    if results:
        console.print(summary_table(manifest.name, results))
    console.print(f"replays in {out}")
    if args.json is not None:
        doc = {
            "bundle": str(bundle),
            "manifest": manifest.to_dict(),
            "validation": validation.to_dict(),
            "races": [r.to_dict() for r in results],
        }
        text = json.dumps(doc, indent=2)
        if to_stdout:
            sys.stdout.write(text + "\n")
        else:
            Path(args.json).write_text(text + "\n", encoding="utf-8")
            console.print(f"results written to {args.json}")
    return 0
