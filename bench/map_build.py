"""Map build time: seconds of ``TrackMaps`` for the batched simulator, per track.

Training with ``--backend batch --procedural P`` draws a generated track at the end of
(nearly) every rollout and builds its maps twice (the track and, with ``--randomise``, its
reversed twin): the segment and clearance grids (0.1 m) and the lidar range table (0.2 m,
180 directions). A profile of a 20 M-step run of ``bench/robust_experiment.py`` put about
40 % of its wall time there. This script times ``TrackMaps._build`` (the cache bypassed) on
tracks drawn like the experiment's (``--tracks`` for others), both directions, best of
``--repeats``, and prints a digest of every map so that two checkouts can be held to the
same bits.

``--baseline-tree DIR`` times another checkout too (e.g. ``git worktree add /tmp/old HEAD~1``)
in a child process, alternating with this tree's runs so that both see the same machine load;
the table and the JSON get both, their ratio and whether the maps are equal. ``--clock cpu``
times this process's CPU time (a machine busy with trainings mostly adds waiting to the wall
clock).

Usage::

    python bench/map_build.py [--tracks NAME ...] [--repeats 3] [--clock wall|cpu]
                              [--baseline-tree DIR] [--json]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

# Drawn like bench/robust_experiment.py's generated training tracks (100-250 m, difficulty
# 0.1-1.0, hairpins of 0.45-0.9 m radius), plus the longest built-in.
TRACKS = (
    "random:101:length=100,difficulty=0.2,hairpin=0.9",
    "random:102:length=150,difficulty=0.5,hairpin=0.7",
    "random:103:length=200,difficulty=0.8,hairpin=0.55",
    "random:104:length=250,difficulty=1.0,hairpin=0.45",
    "monza",
)


def time_builds(names: list[str], repeats: int, clock: str) -> list[dict[str, Any]]:
    """Per track and direction: best seconds of ``repeats`` builds and the maps' digest."""
    from arena.batch.maps import TrackMaps  # this tree's, or the baseline's (PYTHONPATH)
    from arena.lidar import DEFAULT_RANGE
    from arena.walls import DEFAULT_RUNOFF
    from tracks import load_track

    tick = time.process_time if clock == "cpu" else time.perf_counter
    rows = []
    for name in names:
        forward = load_track(name)
        for direction, track in (("forward", forward), ("reversed", forward.reversed())):
            best, maps = float("inf"), None
            for _ in range(repeats):
                t0 = tick()
                maps = TrackMaps._build(track, DEFAULT_RUNOFF, DEFAULT_RANGE, 0.1, 0.2, 180)
                best = min(best, tick() - t0)
            assert maps is not None
            digest = hashlib.sha1()
            for a in (maps.segment, maps.clearance, maps.wall_normal, maps.lidar_row, maps.ranges):
                digest.update(a.tobytes())
            rows.append(
                {
                    "track": name,
                    "direction": direction,
                    "seconds": best,
                    "cells": int(maps.segment.size),
                    "lidar_rows": int(maps.ranges.shape[0]),
                    "digest": digest.hexdigest()[:16],
                }
            )
    return rows


def time_tree(tree: Path, names: list[str], clock: str) -> list[dict[str, Any]]:
    """One repeat of this script on ``tree``'s packages, in a child process."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--repeats", "1", "--clock", clock]
    cmd += ["--json", "--tracks", *names]
    env = {**os.environ, "PYTHONPATH": str(tree)}
    done = subprocess.run(cmd, env=env, cwd=tree, capture_output=True, text=True, check=True)
    rows: list[dict[str, Any]] = json.loads(done.stdout)["results"]
    return rows


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Time every track (and the baseline's, alternating) and return the JSON document."""
    if args.baseline_tree is None:
        rows = time_builds(args.tracks, args.repeats, args.clock)
    else:
        rows = []
        for _ in range(args.repeats):
            theirs = time_tree(args.baseline_tree, args.tracks, args.clock)
            ours = time_builds(args.tracks, 1, args.clock)
            if not rows:
                rows = [
                    {**o, "baseline_seconds": t["seconds"]}
                    for o, t in zip(ours, theirs, strict=True)
                ]
            for row, o, t in zip(rows, ours, theirs, strict=True):
                row["seconds"] = min(row["seconds"], o["seconds"])
                row["baseline_seconds"] = min(row["baseline_seconds"], t["seconds"])
                row["same_maps"] = o["digest"] == t["digest"]
        for row in rows:
            row["speedup"] = row["baseline_seconds"] / row["seconds"]
    total = sum(r["seconds"] for r in rows)
    doc: dict[str, Any] = {
        "command": "python bench/map_build.py " + " ".join(sys.argv[1:]),
        "machine": f"{os.cpu_count()} CPU cores ({platform.machine()}), {platform.system()}",
        "clock": args.clock,
        "repeats": args.repeats,
        "results": rows,
        "total_seconds": total,
    }
    if args.baseline_tree is not None:
        base = sum(r["baseline_seconds"] for r in rows)
        doc["baseline"] = {"tree": str(args.baseline_tree), "total_seconds": base}
        doc["speedup"] = base / total
    return doc


def print_table(doc: dict[str, Any]) -> None:
    """The figures as a table (rich)."""
    from rich.console import Console
    from rich.table import Table

    base = "baseline" in doc
    table = Table(title=f"TrackMaps build, best of {doc['repeats']} ({doc['clock']} clock)")
    for col in ("track", "direction", "cells", "lidar rows", "s"):
        table.add_column(col, justify="left" if col in ("track", "direction") else "right")
    if base:
        for col in ("baseline s", "×", "same maps"):
            table.add_column(col, justify="right")
    for r in doc["results"]:
        cells = [r["track"], r["direction"], f"{r['cells']:,}", f"{r['lidar_rows']:,}"]
        cells.append(f"{r['seconds']:.2f}")
        if base:
            cells += [f"{r['baseline_seconds']:.2f}", f"{r['speedup']:.2f}", str(r["same_maps"])]
        table.add_row(*cells)
    console = Console()
    console.print(table)
    line = f"total {doc['total_seconds']:.2f} s"
    if base:
        line += (
            f" against {doc['baseline']['total_seconds']:.2f} s in {doc['baseline']['tree']}"
            f" (×{doc['speedup']:.2f}, same run)"
        )
    console.print(line)


def main(argv: list[str] | None = None) -> int:
    """Parse the arguments, time, print the table (or the JSON)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tracks", nargs="+", default=list(TRACKS), help="track names")
    parser.add_argument("--repeats", type=int, default=3, help="builds per track (best kept)")
    parser.add_argument("--clock", choices=("wall", "cpu"), default="wall")
    parser.add_argument("--baseline-tree", type=Path, default=None, help="another checkout")
    parser.add_argument("--json", action="store_true", help="print a JSON object")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    if args.baseline_tree is not None and not (args.baseline_tree / "arena").is_dir():
        parser.error(f"--baseline-tree {args.baseline_tree}: no arena/ package there")
    doc = run(args)
    if not args.json:
        print_table(doc)
        return 0
    print(json.dumps(doc, indent=2))  # also how a --baseline-tree child answers its parent
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
