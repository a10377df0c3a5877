"""``slipstream tracks``: list the built-in tracks, draw one, import a track file.

Subcommands::

    slipstream tracks list [--json | --names]
    slipstream tracks show NAME [--out track.png] [--checkpoints N] [--title T] [--json]
    slipstream tracks import FILE [--format f1tenth|deepracer|json] [--name NAME] --out PATH
                             [--scale F] [--width M | --max-width M] [--raceline CSV]
                             [--force] [--json]

``NAME`` is anything :func:`tracks.load_track` takes: a built-in name, a path to a track file,
or ``random:<seed>``. Heavy imports (matplotlib, rich) happen inside the handlers so that
``slipstream --help`` stays fast. User errors raise :class:`tracks.TrackError`; the
dispatcher prints them as one line and exits 2.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path
from typing import Any

import jsonschema

from tracks.errors import TrackError
from tracks.formats import (
    FORMATS,
    TRACK_SCHEMA,
    ImportOptions,
    TrackFormat,
    read_raceline,
    read_track_file,
    track_to_dict,
    write_json,
)
from tracks.geometry import DEFAULT_CHECKPOINTS, Track
from tracks.library import list_tracks, load_track


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``tracks`` and its subcommands to the ``slipstream`` parser."""
    parser = subparsers.add_parser(
        "tracks",
        help="list, draw and import race tracks",
        description="List the built-in tracks, draw one, or import a track file.",
    )
    sub = parser.add_subparsers(dest="tracks_command", required=True, metavar="SUBCOMMAND")

    p_list = sub.add_parser(
        "list",
        help="list the built-in tracks",
        description="Name, lap length, road width range, corners and direction of each "
        "built-in track.",
    )
    fmt = p_list.add_mutually_exclusive_group()
    fmt.add_argument("--json", action="store_true", help="print a JSON list on stdout")
    fmt.add_argument("--names", action="store_true", help="print bare names, one per line")
    p_list.set_defaults(handler=cmd_list)

    p_show = sub.add_parser(
        "show",
        help="draw a track to an image file",
        description="Draw a track seen from above: road, borders, start line, direction, "
        "checkpoint gates and a four-car start grid.",
    )
    p_show.add_argument("name", metavar="NAME", help="built-in name, track file or random:<seed>")
    p_show.add_argument(
        "--out", type=Path, default=None, help="image file (.png/.svg/.pdf); default NAME.png"
    )
    p_show.add_argument(
        "--checkpoints",
        type=int,
        default=DEFAULT_CHECKPOINTS,
        metavar="N",
        help=f"number of lap gates to draw (default {DEFAULT_CHECKPOINTS})",
    )
    p_show.add_argument("--title", default=None, help="figure title (default: track summary)")
    p_show.add_argument("--json", action="store_true", help="print the result as JSON")
    p_show.set_defaults(handler=cmd_show)

    p_import = sub.add_parser(
        "import",
        help="convert an F1TENTH, DeepRacer or JSON track file to Slipstream JSON",
        description="Read a track file, validate it and write it as Slipstream track JSON.",
    )
    p_import.add_argument("file", type=Path, metavar="FILE", help="track file to read")
    p_import.add_argument(
        "--format",
        choices=FORMATS,
        default=None,
        help="input format (default: from the suffix: .csv f1tenth, .npy deepracer, .json)",
    )
    p_import.add_argument(
        "--name",
        default=None,
        help="track name (default: the file's stem; Spielberg_centerline.csv -> Spielberg)",
    )
    p_import.add_argument("--out", type=Path, required=True, help="JSON file to write")
    p_import.add_argument(
        "--scale",
        type=float,
        default=1.0,
        metavar="F",
        help="multiply coordinates and widths by F (e.g. 0.1 for a 1/10 model; default 1)",
    )
    widths = p_import.add_mutually_exclusive_group()
    widths.add_argument(
        "--width", type=float, default=None, metavar="M", help="constant half-width, m"
    )
    widths.add_argument(
        "--max-width", type=float, default=None, metavar="M", help="cap the half-widths at M m"
    )
    p_import.add_argument(
        "--raceline",
        type=Path,
        default=None,
        metavar="CSV",
        help="F1TENTH race line (s_m; x_m; y_m; psi_rad; kappa_radpm; vx_mps; ax_mps2) to keep",
    )
    p_import.add_argument("--force", action="store_true", help="overwrite an existing --out")
    p_import.add_argument("--json", action="store_true", help="print the summary as JSON")
    p_import.set_defaults(handler=cmd_import)


def track_summary(track: Track) -> dict[str, Any]:
    """The facts ``tracks list`` shows, as a JSON-ready dict (lengths in metres)."""
    return {
        "name": track.name,
        "length_m": round(track.length, 2),
        "min_width_m": round(float(track.width.min()), 2),
        "max_width_m": round(float(track.width.max()), 2),
        "corners": track.n_corners,
        "direction": track.orientation,
        "description": track.description,
    }


def cmd_list(args: argparse.Namespace) -> int:
    """``tracks list``: a table, a JSON list or bare names of the built-in tracks."""
    names = list_tracks()
    if args.names:
        for name in names:
            print(name)
        return 0
    rows = [track_summary(load_track(name)) for name in names]
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0

    from rich.console import Console
    from rich.table import Table

    cells = [
        [
            r["name"],
            f"{r['length_m']:.1f}",
            f"{r['min_width_m']:.2f}-{r['max_width_m']:.2f}",
            str(r["corners"]),
            r["direction"],
        ]
        for r in rows
    ]
    # One line per track: the numbers keep their width; the description is cut to fit what is
    # left of the terminal (``--json`` has it in full).
    console = Console()
    table = Table(title=f"Slipstream built-in tracks ({len(rows)})")
    headers = ("name", "length m", "width m", "corners", "dir")
    used = 1  # the table's left border; each column adds 1 + 2 padding + 1 border
    for k, header in enumerate(headers):
        width = max([len(header), *(len(c[k]) for c in cells)])
        table.add_column(header, justify="left" if k in (0, 4) else "right", min_width=width)
        used += width + 3
    table.add_column(
        "description",
        no_wrap=True,
        overflow="ellipsis",
        max_width=max(12, console.width - used - 3),
    )
    for c, r in zip(cells, rows, strict=True):
        table.add_row(*c, r["description"])
    console.print(table)
    return 0


def _file_stem(name: str) -> str:
    """A file-name-safe version of a track name (``random:7`` → ``random-7``)."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "-", name).strip("-.") or "track"


def cmd_show(args: argparse.Namespace) -> int:
    """``tracks show``: draw a track to an image file."""
    if args.checkpoints < 2:
        raise TrackError(f"--checkpoints must be at least 2, got {args.checkpoints}")
    track = load_track(args.name)
    out: Path = args.out if args.out is not None else Path(f"{_file_stem(track.name)}.png")
    if out.suffix.lower() not in (".png", ".svg", ".pdf", ".jpg", ".jpeg"):
        raise TrackError(f"--out {out}: use a .png, .svg, .pdf or .jpg file name")

    from tracks.plot import plot_track

    plot_track(track, out, n_checkpoints=args.checkpoints, title=args.title)
    if args.json:
        print(json.dumps({**track_summary(track), "out": str(out)}))
    else:
        print(f"wrote {out} ({track.name}, {track.length:.1f} m)")
    return 0


def cmd_import(args: argparse.Namespace) -> int:
    """``tracks import``: read, validate and write a track as Slipstream JSON."""
    out: Path = args.out
    if out.exists() and not args.force:
        raise TrackError(f"{out} already exists; use --force to overwrite it")
    if out.exists() and not out.is_file():
        raise TrackError(f"{out} is not a file")
    fmt: TrackFormat | None = args.format
    options = ImportOptions(scale=args.scale, width=args.width, max_width=args.max_width)
    track = read_track_file(args.file, fmt, args.name, options)
    if args.raceline is not None:
        track.raceline = read_raceline(args.raceline, scale=args.scale)
    try:  # e.g. a --name longer than the schema allows: refuse before writing anything
        jsonschema.validate(track_to_dict(track), TRACK_SCHEMA)
    except jsonschema.ValidationError as err:
        where = "/".join(str(p) for p in err.absolute_path) or "top level"
        raise TrackError(f"cannot write {out}: {where}: {err.message}") from None
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        write_json(track, out)
    except OSError as err:
        raise TrackError(f"cannot write {out}: {err.strerror or err}") from None

    summary = {**track_summary(track), "points": track.n_points, "source": str(args.file)}
    summary["raceline"] = track.raceline is not None
    summary["notes"] = list(track.import_notes)
    summary["out"] = str(out)
    if args.json:
        print(json.dumps(summary))
    else:
        print(
            f"imported {track.name!r} from {args.file}: {track.length:.1f} m, "
            f"{track.n_points} points, width {summary['min_width_m']:.2f}-"
            f"{summary['max_width_m']:.2f} m, {track.n_corners} corners, "
            f"{track.orientation} -> {out}"
        )
        for note in track.import_notes:
            print(f"  {note}")
    return 0
