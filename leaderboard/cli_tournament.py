"""``slipstream tournament create | list | show``: an operator's tournaments, on the database.

* ``create --name N (--entrants 3,5,8 | --top N) [--format round-robin|time-trial]
  [--car C] [--tracks oval,bean] [--seeds 0,1] [--laps L] [--heat-size H] [--final-size F]``:
  define a tournament (:func:`leaderboard.tournaments.create_tournament`); the workers
  (``slipstream worker`` on the same database) run its heats from the queue.
* ``list``: every tournament, newest first. ``show ID``: its standings and heats.

Like ``users add``, these work on the database (``--db`` / ``--data-dir``); over HTTP,
``POST /api/tournaments`` with the admin token does what ``create`` does. Every command takes
``--json``.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

from leaderboard.cli_server import _db_options, settings_from


def _ints(text: str) -> list[int]:
    try:
        return [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers: {text!r}") from None


def _names(text: str) -> list[str]:
    return [x.strip() for x in text.split(",") if x.strip()]


def register(sub: Any) -> None:
    """Add ``tournament`` to the ``slipstream`` subcommands."""
    t = sub.add_parser(
        "tournament",
        help="define and follow tournaments (run by the workers beside the ladder)",
    )
    tsub = t.add_subparsers(dest="tournament_command", required=True, metavar="ACTION")
    c = tsub.add_parser(
        "create",
        help="define a tournament",
        description="Define a tournament. Round-robin: every round (track × seed) the "
        "entrants race in heats of at most --heat-size cars; time trial: a solo trial per "
        "entrant and round, then a final of the --final-size fastest. Points per place "
        "25, 18, 15, 12, 10, 8, 6, 4 (a DNF scores 0). Unrated.",
    )
    c.add_argument("--name", required=True, help="shown on its page")
    c.add_argument(
        "--format", choices=("round-robin", "time-trial"), default="round-robin", help="format"
    )
    who = c.add_mutually_exclusive_group(required=True)
    who.add_argument("--entrants", type=_ints, help="submission ids, top seed first: 3,5,8")
    who.add_argument("--top", type=int, help="the top N of the car class's ladder")
    c.add_argument("--car", default=None, help="car class (default: the entrants'; f1tenth)")
    c.add_argument("--tracks", type=_names, default=None, help="built-in tracks: oval,bean")
    c.add_argument("--seeds", type=_ints, default=[0], help="one round per track and seed")
    c.add_argument("--laps", type=int, default=2, help="laps per heat")
    c.add_argument("--heat-size", type=int, default=4, help="most cars per heat (round-robin)")
    c.add_argument("--final-size", type=int, default=4, help="finalists (time trial)")
    c.add_argument("--json", action="store_true", help="print the tournament as JSON")
    _db_options(c)
    c.set_defaults(handler=create_command)

    ls = tsub.add_parser("list", help="every tournament, newest first")
    ls.add_argument("--json", action="store_true", help="print as JSON")
    _db_options(ls)
    ls.set_defaults(handler=list_command)

    show = tsub.add_parser("show", help="a tournament's standings and heats")
    show.add_argument("id", type=int, help="tournament id")
    show.add_argument("--json", action="store_true", help="print as JSON")
    _db_options(show)
    show.set_defaults(handler=show_command)


def create_command(args: argparse.Namespace) -> int:
    """Run ``slipstream tournament create``."""
    from leaderboard import tournaments  # noqa: PLC0415 - lazy: keeps `slipstream --help` fast
    from leaderboard.db import connect, session_scope  # noqa: PLC0415

    settings = settings_from(args)
    settings.ensure_dirs()
    with connect(settings.db_url, migrate=True) as sessions, session_scope(sessions) as session:
        created = tournaments.create_tournament(
            session,
            settings,
            name=args.name,
            fmt=args.format.replace("-", "_"),
            entrants=args.entrants,
            top=args.top,
            car=args.car,
            tracks=args.tracks,
            seeds=args.seeds,
            laps=args.laps,
            heat_size=args.heat_size,
            final_size=args.final_size,
            created_by="cli",
        )
        session.commit()
        detail = tournaments.tournament_detail(session, created.id)
    if args.json:
        print(detail.model_dump_json())
    else:
        print(
            f"tournament {detail.id} ({detail.name!r}, {detail.format.replace('_', ' ')}, "
            f"{detail.car}): {detail.entrants} entrants, {detail.races} races planned; "
            f"the workers run them. Page: /tournaments/{detail.id}"
        )
    return 0


def list_command(args: argparse.Namespace) -> int:
    """Run ``slipstream tournament list``."""
    from leaderboard import tournaments  # noqa: PLC0415
    from leaderboard.db import connect  # noqa: PLC0415

    settings = settings_from(args)
    with connect(settings.db_url, migrate=True) as sessions, sessions() as session:
        page = tournaments.tournament_list(session, per_page=200)
    if args.json:
        print(page.model_dump_json())
        return 0
    if not page.items:
        print("no tournaments")
    for t in page.items:
        leader = f", leader {t.leader}" if t.leader else ""
        progress = f"{t.status} {t.races_done}/{t.races}"
        print(f"{t.id:>4}  {t.name}  [{t.format}, {t.car}]  {progress}{leader}")
    return 0


def show_command(args: argparse.Namespace) -> int:
    """Run ``slipstream tournament show``."""
    from leaderboard import tournaments  # noqa: PLC0415
    from leaderboard.db import connect  # noqa: PLC0415

    settings = settings_from(args)
    with connect(settings.db_url, migrate=True) as sessions, sessions() as session:
        detail = tournaments.tournament_detail(session, args.id)
    if args.json:
        print(json.dumps(json.loads(detail.model_dump_json()), indent=2))
        return 0
    progress = f"{detail.status}, {detail.races_done}/{detail.races} races"
    print(f"tournament {detail.id}: {detail.name} ({progress})")
    for row in detail.standings:
        print(
            f"{row.rank:>3}. {row.name:<32} {row.points:>4} pts  {row.races} races  {row.wins} wins"
        )
    if detail.final is not None:
        print(f"final: race {detail.final.race_id} ({detail.final.status})")
    return 0


__all__ = ["register"]
