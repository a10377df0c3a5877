"""Top-down pictures of a track: road, borders, start line, direction, gates and start grid.

Rendered with matplotlib's Agg canvas straight to a file (no display, no ``pyplot`` global
state), so it works on a headless server and inside tests.

>>> import tempfile
>>> from pathlib import Path
>>> from tracks import load_track
>>> with tempfile.TemporaryDirectory() as tmp:
...     out = plot_track(load_track("oval"), Path(tmp) / "oval.png")
...     out.stat().st_size > 10_000
True
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.figure import Figure
from matplotlib.patches import PathPatch
from matplotlib.path import Path as MplPath

from tracks.errors import TrackError
from tracks.geometry import CAR_LENGTH, CAR_WIDTH, DEFAULT_CHECKPOINTS, FloatArray, Track

GRID_CARS = 4  # cars drawn on the start grid
ROAD_COLOUR = "#9a9a9a"
GRASS_COLOUR = "#e8f0e0"
LEFT_COLOUR = "#c0392b"  # left border (seen in the driving direction)
RIGHT_COLOUR = "#1f4e9c"
GATE_COLOUR = "#e67e22"
CENTRE_COLOUR = "#2b2b2b"
RACELINE_CMAP = "viridis"  # race line, coloured by its target speed
CAR_COLOURS = ("#d62728", "#2ca02c", "#9467bd", "#17becf", "#8c564b", "#e377c2")
FIG_WIDTH = 10.0  # inches
DPI = 120


def _ring(points: FloatArray) -> tuple[FloatArray, list[np.uint8]]:
    """Vertices (N+1, 2) and path codes of one closed ring."""
    verts = np.vstack([points, points[:1]])
    codes = [MplPath.MOVETO] + [MplPath.LINETO] * (len(points) - 1) + [MplPath.CLOSEPOLY]
    return verts, codes


def _road_path(track: Track) -> MplPath:
    """The road surface as one path: left border ring plus the right border ring reversed.

    The two rings wind in opposite senses, so the non-zero fill rule leaves the infield empty.
    """
    v1, c1 = _ring(track.left_border)
    v2, c2 = _ring(track.right_border[::-1])
    return MplPath(np.vstack([v1, v2]), c1 + c2)


def _chequers(track: Track, rows: int = 2, cols: int = 8) -> tuple[list[FloatArray], list[str]]:
    """Squares (each (4, 2) m) of a chequered start/finish line and their colours."""
    left, right = float(track.width_left[0]), float(track.width_right[0])  # s = 0 is point 0
    depth = (left + right) / cols  # square side along the road, m
    polys: list[FloatArray] = []
    colours: list[str] = []
    d_edges = np.linspace(-right, left, cols + 1)
    for r in range(rows):
        s0, s1 = (r - rows / 2) * depth, (r + 1 - rows / 2) * depth
        for c in range(cols):
            frenet = np.array(
                [
                    [s0, d_edges[c]],
                    [s1, d_edges[c]],
                    [s1, d_edges[c + 1]],
                    [s0, d_edges[c + 1]],
                ]
            )
            frenet[:, 0] = track.wrap_s(frenet[:, 0])
            polys.append(track.to_cartesian(frenet))
            colours.append("black" if (r + c) % 2 == 0 else "white")
    return polys, colours


def _car_outlines(poses: FloatArray) -> list[FloatArray]:
    """Rectangles (4, 2) m of cars at poses (n, 3) [x m, y m, yaw rad]."""
    hl, hw = 0.5 * CAR_LENGTH, 0.5 * CAR_WIDTH
    local = np.array([[hl, hw], [-hl, hw], [-hl, -hw], [hl, -hw]])
    outlines = []
    for x, y, yaw in poses:
        rot = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
        outlines.append(local @ rot.T + np.array([x, y]))
    return outlines


def raceline_collection(track: Track) -> LineCollection | None:
    """The track's race line as a closed chain of segments coloured by target speed (m/s),
    or None when the track has no race line."""
    if track.raceline is None:
        return None
    pts = track.raceline.points
    segments = np.stack([pts, np.roll(pts, -1, axis=0)], axis=1)  # (M, 2, 2), closed
    speed = track.raceline.speed
    lines = LineCollection(list(segments), cmap=RACELINE_CMAP, linewidths=2.2, zorder=4)
    lines.set_array(0.5 * (speed + np.roll(speed, -1)))
    lines.set_label("race line")
    return lines


def default_title(track: Track) -> str:
    """Name, lap length, width range, corners and direction in one line."""
    direction = "anticlockwise" if track.orientation == "ccw" else "clockwise"
    return (
        f"{track.name}: {track.length:.1f} m, width {track.width.min():.2f}–"
        f"{track.width.max():.2f} m, {track.n_corners} corners, {direction}"
    )


def plot_track(
    track: Track,
    out: Path,
    *,
    n_checkpoints: int = DEFAULT_CHECKPOINTS,
    title: str | None = None,
) -> Path:
    """Draw a track seen from above and save it as an image (format from the suffix).

    Shows the road surface, the left (red) and right (blue) borders, the dashed centre line,
    the race line coloured by its speed (when the track has one), the chequered start/finish
    line, an arrow for the driving direction just after the start,
    the numbered checkpoint gates and a start grid of four cars.

    Args:
        track: the track to draw.
        out: image file to write (``.png``, ``.svg``, ``.pdf``); parent folders are created.
        n_checkpoints: number of lap gates to draw (gate 0 is the start/finish line).
        title: figure title; defaults to name, length, width range, corners and direction.

    Returns:
        ``out``.

    Raises:
        TrackError: the file cannot be written.
    """
    xmin, ymin, xmax, ymax = track.bounds
    extent = max(xmax - xmin, ymax - ymin)
    margin = 0.06 * extent
    aspect = (ymax - ymin + 2 * margin) / (xmax - xmin + 2 * margin)
    fig = Figure(figsize=(FIG_WIDTH, float(np.clip(FIG_WIDTH * aspect, 4.0, 14.0)) + 0.6))
    ax = fig.add_subplot()
    ax.set_facecolor(GRASS_COLOUR)

    ax.add_patch(PathPatch(_road_path(track), facecolor=ROAD_COLOUR, edgecolor="none", zorder=1))
    closed = np.vstack([track.centre, track.centre[:1]])
    ax.plot(*closed.T, color=CENTRE_COLOUR, lw=0.9, ls=(0, (6, 5)), zorder=2, label="centre line")
    for border, colour, label in (
        (track.left_border, LEFT_COLOUR, "left border"),
        (track.right_border, RIGHT_COLOUR, "right border"),
    ):
        ring = np.vstack([border, border[:1]])
        ax.plot(*ring.T, color=colour, lw=1.6, zorder=3, label=label)

    race = raceline_collection(track)
    if race is not None:
        ax.add_collection(race)
        fig.colorbar(race, ax=ax, shrink=0.6, pad=0.01, label="race line speed [m/s]")

    # Checkpoint gates 1..n-1 (gate 0 is the chequered line), numbered beside the left end.
    gate_s = track.checkpoint_s(n_checkpoints)
    gates = track.gates(gate_s)
    ax.add_collection(LineCollection(list(gates[1:]), colors=GATE_COLOUR, linewidths=2.0, zorder=4))
    ax.plot([], [], color=GATE_COLOUR, lw=2.0, label="checkpoint gates")
    label_off = 0.025 * extent
    across = gates[:, 0] - gates[:, 1]  # (n, 2) right end -> left end
    across /= np.linalg.norm(across, axis=1, keepdims=True)
    for k, (gate, out_dir) in enumerate(zip(gates, across, strict=True)):
        x, y = gate[0] + label_off * out_dir
        ax.text(
            x,
            y,
            "S/F" if k == 0 else str(k),
            ha="center",
            va="center",
            fontsize=8,
            fontweight="bold",
            zorder=7,
            bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": GATE_COLOUR, "lw": 0.8},
        )

    polys, colours = _chequers(track)
    ax.add_collection(
        PolyCollection(polys, facecolors=colours, edgecolors="black", linewidths=0.3, zorder=5)
    )

    # Driving direction: an arrow that follows the centre line for a stretch after the start.
    s_arrow = np.linspace(1.0, 1.0 + min(0.12 * extent, 0.12 * track.length), 40)
    body = track.to_cartesian(np.column_stack([s_arrow, np.zeros_like(s_arrow)]))
    ax.plot(*body[:-2].T, color="black", lw=5, solid_capstyle="butt", zorder=6)
    ax.annotate(
        "",
        xy=tuple(body[-1]),
        xytext=tuple(body[-3]),
        arrowprops={"arrowstyle": "-|>", "mutation_scale": 32, "color": "black", "lw": 0},
        zorder=6,
    )
    ax.plot([], [], color="black", lw=3.5, marker=">", markersize=7, label="direction")

    cars = _car_outlines(track.start_grid(GRID_CARS))
    ax.add_collection(
        PolyCollection(
            cars,
            facecolors=[CAR_COLOURS[i % len(CAR_COLOURS)] for i in range(len(cars))],
            edgecolors="black",
            linewidths=0.6,
            zorder=6,
        )
    )

    ax.set_aspect("equal")
    ax.set_xlim(xmin - margin, xmax + margin)
    ax.set_ylim(ymin - margin, ymax + margin)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(True, color="white", lw=0.5, alpha=0.6)
    ax.set_axisbelow(True)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.09), ncol=5, fontsize=8, frameon=False)
    ax.set_title(title if title is not None else default_title(track), fontsize=11)
    fig.tight_layout()

    out = Path(out)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(out, dpi=DPI)
    except (OSError, ValueError) as err:
        raise TrackError(f"cannot write {out}: {err}") from None
    return out
