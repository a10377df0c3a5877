"""Track projection speed: Cartesian → Frenet (``Track.project``) and back, points per second.

Draws ``--points`` random points on and near the road (uniform progress ``s``, lateral offset
``d`` uniform within the half-widths ± 0.5 m) on the longest built-in track, or on a stadium
built here when the library is not installed, and times ``track.project`` and
``track.to_cartesian`` on all of them at once: best and median of ``--repeats`` runs.

Usage::

    python bench/track_speed.py [--points 1000000] [--repeats 3] [--track NAME] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from tracks import SlipstreamError, Track, list_tracks, load_track
from tracks.geometry import FloatArray


def stadium(straight: float = 40.0, radius: float = 12.0, width: float = 3.0) -> Track:
    """A stadium (two straights of ``straight`` m, two half circles of ``radius`` m)."""
    n_s, n_c = 40, 60
    xs = np.linspace(-straight / 2, straight / 2, n_s, endpoint=False)
    th = np.linspace(-np.pi / 2, np.pi / 2, n_c, endpoint=False)
    pts = np.vstack(
        [
            np.column_stack([xs, np.full(n_s, -radius)]),
            np.column_stack([straight / 2 + radius * np.cos(th), radius * np.sin(th)]),
            np.column_stack([-xs, np.full(n_s, radius)]),
            np.column_stack([-straight / 2 - radius * np.cos(th), -radius * np.sin(th)]),
        ]
    )
    return Track(pts, width / 2, width / 2, name="stadium", description="bench fallback")


def pick_track(name: str | None) -> Track:
    """The named track, else the longest built-in one, else a stadium."""
    if name is not None:
        return load_track(name)
    tracks = [load_track(n) for n in list_tracks()]
    return max(tracks, key=lambda t: t.length) if tracks else stadium()


def sample_points(track: Track, n: int, seed: int = 0) -> tuple[FloatArray, FloatArray]:
    """Frenet (n, 2) [s m, d m] near the road and the same points in Cartesian (n, 2) m."""
    rng = np.random.default_rng(seed)
    s = rng.uniform(0.0, track.length, n)
    left, right = track.widths_at(s)
    d = rng.uniform(-right - 0.5, left + 0.5)
    frenet = np.column_stack([s, d])
    return frenet, track.to_cartesian(frenet)


def time_runs(fn: Callable[[], object], repeats: int) -> list[float]:
    """Wall-clock seconds of ``repeats`` calls of ``fn``."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return times


def run(n_points: int, repeats: int, track_name: str | None) -> dict[str, Any]:
    """Measure both directions and return the figures as a JSON-ready dict."""
    track = pick_track(track_name)
    frenet, xy = sample_points(track, n_points)
    track.project(xy[:1000])  # build the k-d tree and cached frames outside the timing
    proj = time_runs(lambda: track.project(xy), repeats)
    cart = time_runs(lambda: track.to_cartesian(frenet), repeats)
    back = track.project(xy)
    return {
        "track": track.name,
        "track_length_m": round(track.length, 2),
        "track_points": track.n_points,
        "n_points": n_points,
        "repeats": repeats,
        "project_points_per_s": n_points / min(proj),
        "project_points_per_s_median": n_points / statistics.median(proj),
        "to_cartesian_points_per_s": n_points / min(cart),
        "to_cartesian_points_per_s_median": n_points / statistics.median(cart),
        "round_trip_max_error_m": float(
            max(
                np.abs(track.delta_s(back.s, frenet[:, 0])).max(),
                np.abs(back.d - frenet[:, 1]).max(),
            )
        ),
        "machine": {
            "cpu_count": os.cpu_count(),
            "processor": platform.processor() or platform.machine(),
            "python": platform.python_version(),
            "numpy": np.__version__,
            "platform": platform.platform(),
        },
    }


def main(argv: list[str] | None = None) -> int:
    """Command line entry point; prints one human line or, with ``--json``, a JSON object."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--points", type=int, default=1_000_000, help="points per call")
    parser.add_argument("--repeats", type=int, default=3, help="timed calls per function")
    parser.add_argument("--track", default=None, help="track (default: longest built-in)")
    parser.add_argument("--json", action="store_true", help="print a JSON object")
    args = parser.parse_args(argv)
    if args.points < 1 or args.repeats < 1:
        parser.error("--points and --repeats must be positive")
    try:
        res = run(args.points, args.repeats, args.track)
    except SlipstreamError as err:
        print(f"track_speed: error: {err}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(res, indent=2))
    else:
        m = res["machine"]
        print(
            f"{res['track']} ({res['track_length_m']:.0f} m, {res['track_points']} pts): "
            f"project {res['project_points_per_s'] / 1e6:.2f} M points/s "
            f"(median {res['project_points_per_s_median'] / 1e6:.2f}), "
            f"to_cartesian {res['to_cartesian_points_per_s'] / 1e6:.2f} M points/s "
            f"(median {res['to_cartesian_points_per_s_median'] / 1e6:.2f}); "
            f"{res['n_points']:,} points, best of {res['repeats']}, round trip "
            f"{res['round_trip_max_error_m']:.1e} m; {m['cpu_count']} CPUs, "
            f"Python {m['python']}, numpy {m['numpy']}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
