"""``slipstream demo``: a leaderboard with real races, on this machine, in one command.

1. A fresh service folder (``artifacts/demo/site`` by default: SQLite database, bundles,
   replays), deleted and made again on every run.
2. A ``house`` user enters the three baselines (``pursuit``, ``gap``, ``random``; they race
   in-process) and the shipped PPO checkpoints (:data:`SHIPPED`: ``agents/data/ppo_racer.zip``
   and the robust ``ppo_robust.zip``), each wrapped in a submission bundle and uploaded like
   any user's (they race in the sandbox).
3. A local worker runs the validation races and then ``--races`` ranked races picked by the
   matchmaker, recording a replay and a 3D ``.viser`` file for each (progress bar).
4. The leaderboard is printed (a table, or ``--json``), then the site is served on
   http://127.0.0.1:8000 until Ctrl-C (``--no-serve`` stops after the table).
"""

# ruff: noqa: PLC0415 - a subcommand module: imports wait for the handler (fast --help)

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any

from leaderboard.errors import LeaderboardError

DEFAULT_DIR = Path("artifacts/demo/site")
SHIPPED_DIR = Path(__file__).resolve().parents[1] / "agents" / "data"
# The shipped checkpoints the demo enters (submission name -> file, description).
SHIPPED = {
    "ppo_racer": (SHIPPED_DIR / "ppo_racer.zip", "the shipped PPO checkpoint (nominal)"),
    "ppo_robust": (
        SHIPPED_DIR / "ppo_robust.zip",
        "the shipped robust PPO checkpoint (a CVaR objective under domain randomisation)",
    ),
}
CHECKPOINT = SHIPPED["ppo_racer"][0]
MARKER = ".slipstream-demo"  # marks a folder this command made, so it may delete it
HOUSE = "house"
ENV_KEYS = ("lidar_rays", "k_opponents")  # a checkpoint's env settings a manifest can declare


def register(sub: Any) -> None:
    """Add ``demo`` to the ``slipstream`` subcommands."""
    p = sub.add_parser(
        "demo",
        help="seed a local leaderboard with baselines and the shipped checkpoint, race, serve",
        description=(
            "Set up a fresh leaderboard in --data-dir, enter the baselines and the shipped PPO "
            "checkpoint as submissions, run the validation races and --races ranked races with "
            "a local worker, print the leaderboard, then serve the site until Ctrl-C."
        ),
    )
    p.add_argument("--host", default="127.0.0.1", help="address to serve on")
    p.add_argument("--port", type=int, default=8000, help="port to serve on")
    p.add_argument("--races", type=int, default=12, help="ranked races after validation")
    p.add_argument("--workers", type=int, default=2, help="races run at once")
    p.add_argument("--data-dir", type=Path, default=DEFAULT_DIR, help="service folder (made fresh)")
    p.add_argument("--no-serve", action="store_true", help="stop after printing the table")
    p.add_argument("--json", action="store_true", help="print the leaderboard as JSON")
    p.set_defaults(handler=_run)


def fresh_dir(path: Path) -> Path:
    """Empty ``path`` for a new demo; only a folder a previous demo made may be deleted.

    Raises:
        LeaderboardError: ``path`` exists, is not empty and was not made by this command.
    """
    if path.exists():
        if not path.is_dir():
            raise LeaderboardError(f"{path} is not a folder")
        if any(path.iterdir()) and not (path / MARKER).exists():
            raise LeaderboardError(f"{path} is not empty and was not made by `slipstream demo`")
        shutil.rmtree(path)
    path.mkdir(parents=True)
    (path / MARKER).write_text("made by `slipstream demo`; deleted by the next run\n")
    return path


def checkpoint_bundle(out: Path, author: str = HOUSE, name: str = "ppo_racer") -> Path:
    """The shipped checkpoint ``name`` (a key of :data:`SHIPPED`) wrapped in a submission
    bundle (zip) at ``out``."""
    import zipfile

    from arena.version import ENV_VERSION
    from submissions.bundle import Manifest, make_bundle

    checkpoint, description = SHIPPED[name]
    with zipfile.ZipFile(checkpoint) as zf:
        meta = json.loads(zf.read("meta.json"))
    declared = {k: int(v) for k, v in meta.get("env_config", {}).items() if k in ENV_KEYS}
    manifest = Manifest(
        name=name,
        author=author,
        format="slipstream",
        entry="policy.zip",
        env_version=ENV_VERSION,
        obs_mode=meta.get("obs_mode", "vector"),
        action_mode=meta.get("action_mode", "continuous"),
        env=declared,
        description=f"{description} (agents/data/{checkpoint.name})",
    )
    return make_bundle(out, manifest, {"policy.zip": checkpoint})


def seed(settings: Any) -> list[str]:
    """Create the house user and enter the baselines and the shipped checkpoints; their
    names."""
    from leaderboard import auth
    from leaderboard.db import connect, session_scope
    from leaderboard.uploads import BASELINES, add_baseline, upload

    with connect(settings.db_url, migrate=True) as sessions, session_scope(sessions) as session:
        user, _token = auth.create_user(session, name=HOUSE, is_admin=True)
        for baseline in BASELINES:
            add_baseline(session, settings, user=user, baseline=baseline)
        with tempfile.TemporaryDirectory(prefix="slipstream-demo-") as tmp:
            for name in SHIPPED:
                bundle = checkpoint_bundle(Path(tmp) / f"{name}.zip", name=name)
                with bundle.open("rb") as stream:
                    upload(session, settings, user=user, stream=stream)
    return [*BASELINES, *SHIPPED]


def run_races(settings: Any, races: int, workers: int) -> Any:
    """Run the queued validation races, then ``races`` ranked ones; the worker's stats."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

    from leaderboard import queue
    from leaderboard.db import connect
    from leaderboard.worker import Worker

    with connect(settings.db_url) as sessions, sessions() as session:
        validation = queue.pending(session)
    total = validation + races
    worker = Worker(settings, workers=workers, schedule=True, owner="demo")
    try:
        with Progress(
            "[progress.description]{task.description}",
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            console=Console(stderr=True),  # stdout carries only the table or the JSON
        ) as progress:
            task = progress.add_task("races", total=total)

            def show(stats: Any) -> None:
                progress.update(task, completed=stats.completed + stats.failed)

            return worker.run(max_races=total, poll_s=0.5, progress=show)
    finally:
        worker.close()


def leaderboard_rows(settings: Any) -> list[dict[str, Any]]:
    """The leaderboard's rows (as the JSON API gives them)."""
    from leaderboard import queries
    from leaderboard.db import connect

    with connect(settings.db_url) as sessions, sessions() as session:
        page = queries.leaderboard(session, per_page=queries.MAX_PER_PAGE)
    return [row.model_dump() for row in page.items]


def print_table(rows: list[dict[str, Any]]) -> None:
    """The leaderboard as a rich table."""
    from rich.console import Console
    from rich.table import Table

    table = Table(title="Slipstream leaderboard (ordinal = μ − 3σ)")
    for col in ("#", "submission", "author", "ordinal", "μ", "σ", "races", "win rate"):
        table.add_column(col, justify="left" if col in ("submission", "author") else "right")
    for r in rows:
        table.add_row(
            str(r["rank"]),
            f"{r['name']} v{r['version']}",
            r["author"],
            f"{r['ordinal']:.2f}",
            f"{r['mu']:.2f}",
            f"{r['sigma']:.2f}",
            str(r["races"]),
            f"{100 * r['win_rate']:.0f}%",
        )
    Console().print(table)


def serve(settings: Any, host: str, port: int) -> None:
    """Serve the site until Ctrl-C."""
    from leaderboard import serving
    from leaderboard.app import create_app

    print(f"serving the leaderboard on http://{host}:{port}/ (Ctrl-C stops)", file=sys.stderr)
    serving.serve(create_app(settings), settings, host, port)  # as `slipstream serve` does


def _run(args: argparse.Namespace) -> int:
    from leaderboard.settings import Settings

    if args.races < 0 or args.workers < 1:
        raise LeaderboardError("--races must be ≥ 0 and --workers ≥ 1")
    # Races only: the versions' robustness runs (a minute of solo laps) are left out of the
    # demo, so --races N runs exactly N ranked races after the validations.
    settings = Settings(data_dir=fresh_dir(args.data_dir), robustness=False)
    settings.ensure_dirs()
    names = seed(settings)
    print(f"entered {', '.join(names)} as submissions of {HOUSE!r}", file=sys.stderr)
    stats = run_races(settings, args.races, args.workers)
    print(
        f"races stored: {stats.completed}, failed: {stats.failed}, discarded: {stats.discarded}",
        file=sys.stderr,
    )
    rows = leaderboard_rows(settings)
    if args.json:
        print(json.dumps(rows, indent=2, default=str))
    else:
        print_table(rows)
    if not args.no_serve:
        serve(settings, args.host, args.port)
    return 0
