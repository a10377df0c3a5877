"""The walls around a track, as closed polylines shared by the physics and the lidar.

The walls stand ``runoff`` metres outside each road edge, so a car can run wide (off the
track, as DeepRacer counts it) before it hits a wall, as on a real circuit. The physics builds
its wall boxes from these polylines and the lidar casts against the very same lines, so what
a car sees is what it can hit.
"""

from __future__ import annotations

import math
import weakref
from array import array
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tracks import Track

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

DEFAULT_RUNOFF = 0.4  # m of run-off between the road edge and the wall

# Track → run-off → (left, right) wall offsets: computing them projects thousands of points.
_OFFSETS: weakref.WeakKeyDictionary[Track, dict[float, tuple[FloatArray, FloatArray]]] = (
    weakref.WeakKeyDictionary()
)


def wall_offsets(track: Track, runoff: float) -> tuple[FloatArray, FloatArray]:
    """Distances (N,) m from the centre line to the left and right walls (cached per track).

    ``width + runoff`` wherever that is clear of the road, shorter where it is not
    (:meth:`tracks.Track.wall_offsets`); identical to ``width + runoff`` on the built-in tracks.
    """
    per_track = _OFFSETS.setdefault(track, {})
    if runoff not in per_track:
        per_track[runoff] = track.wall_offsets(runoff)
    return per_track[runoff]


TURN_EPS = 1e-9  # m²: a cross product of two wall segments below this is a straight run
MIN_THICKNESS = 0.025  # m: thinnest wall box (thinner ones let a fast car tunnel through)
THINNING_STEPS = 4  # halvings of a wall box that would reach the road (0.2 m -> 0.025 m)
BOX_TOLERANCE = -0.03  # m: a box may touch the road's edge by this much (round-off)
WALL_SPACING = 0.5  # m between wall polyline points (chord error < 2 cm at 1.5 m radius)


@dataclass(frozen=True)
class Walls:
    """Inner faces of the left and right walls.

    Attributes:
        left: (W, 2) m, closed polyline on the left of the driving direction.
        right: (W, 2) m, closed polyline on the right.
        stride: centre-line points per wall point: wall point ``k`` sits beside centre point
            ``k * stride``, so a car's centre-line segment index locates nearby walls.
        left_out, right_out: (W, 2) unit vectors from each wall point away from the road (the
            centre line's normal it was placed along).
    """

    left: FloatArray
    right: FloatArray
    stride: int
    left_out: FloatArray
    right_out: FloatArray

    @classmethod
    def around(cls, track: Track, runoff: float = DEFAULT_RUNOFF) -> Walls:
        """Walls ``runoff`` m outside both road edges of ``track`` (less where that is road).

        Where the full run-off would put a wall on another part of the road (the infield of
        a tight hairpin on an imported track) it is shortened: see :func:`wall_offsets`.
        """
        stride = max(1, round(WALL_SPACING / float(np.mean(track.segment_lengths))))
        idx = np.arange(0, track.n_points, stride)
        c, n = track.centre[idx], track.normals[idx]
        to_left, to_right = wall_offsets(track, runoff)
        left = c + to_left[idx, None] * n
        right = c - to_right[idx, None] * n
        return cls(left=left, right=right, stride=stride, left_out=n, right_out=-n)

    @property
    def n_points(self) -> int:
        """Points W per wall polyline."""
        return len(self.left)

    def window_start(self, segment: IntArray) -> IntArray:
        """The wall point (n,) at the middle of each window: the one at the start of the
        stride that holds each centre-line segment index (n,)."""
        return np.asarray(segment, dtype=np.int64) // self.stride

    def window(self, segment: IntArray, half_width: int) -> IntArray:
        """Wall-point indices (n, 2*half_width+1) around centre-line segment indices (n,)."""
        base = self.window_start(segment)
        return (base[:, None] + np.arange(-half_width, half_width + 1)) % self.n_points

    def segments(self) -> tuple[FloatArray, FloatArray]:
        """All wall segments: starts and ends (2W, 2) m, left wall first."""
        starts = np.vstack([self.left, self.right])
        ends = np.vstack([np.roll(self.left, -1, axis=0), np.roll(self.right, -1, axis=0)])
        return starts, ends

    def boxes(
        self, thickness: float, track: Track | None = None
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Boxes up to ``thickness`` m thick whose inner faces are the wall segments.

        Each box lies on the far side of its segment from the road (the side its two wall
        points were pushed out to), so its face towards the road is the wall line itself.
        Each box reaches ``thickness / 2`` past its segment's ends so no gap opens behind a
        vertex, except at a vertex where the wall turns towards the road: there it stops at
        the vertex (reaching past it would push a box corner onto the road). With ``track``,
        a box whose far side would reach the road (the inside of a hairpin tighter than the
        run-off, where the road wraps round the bend's centre: 0.3 m onto the road on the
        real F1TENTH tracks) is made thinner, down to ``MIN_THICKNESS``.

        Returns:
            centres (2W, 2) m, half-extents (2W, 2) m along and across the segment, yaws
            (2W,) rad of the segments; left wall first.
        """
        starts, ends = self.segments()
        delta = ends - starts
        length = np.linalg.norm(delta, axis=1)
        yaw = np.arctan2(delta[:, 1], delta[:, 0])
        unit = np.stack([np.cos(yaw), np.sin(yaw)], axis=1)
        out = np.vstack([self.left_out, self.right_out])
        w = self.n_points
        nxt_of = np.concatenate([np.roll(np.arange(w), -1), w + np.roll(np.arange(w), -1)])
        prv_of = np.concatenate([np.roll(np.arange(w), 1), w + np.roll(np.arange(w), 1)])
        normal = np.stack([-unit[:, 1], unit[:, 0]], axis=1)
        away = out + out[nxt_of]  # the road is on the other side of the segment
        flip = np.where(np.einsum("ij,ij->i", normal, away) >= 0.0, 1.0, -1.0)
        normal = normal * flip[:, None]
        # Negative turn at a vertex: the wall bends towards the road there.
        turn_end = _cross(delta, delta[nxt_of]) * flip
        turn_start = _cross(delta[prv_of], delta) * flip
        thick = np.full(len(length), thickness)
        if track is not None:
            for k in range(THINNING_STEPS):
                reach = self._box_points(starts, unit, normal, length, thick, turn_start, turn_end)
                bad = track.on_road(reach.reshape(-1, 2), BOX_TOLERANCE).reshape(len(thick), -1)
                hit = bad.any(axis=1)
                if not hit.any() or k == THINNING_STEPS - 1:
                    break
                thick = np.where(hit, np.maximum(0.5 * thick, MIN_THICKNESS), thick)
        ext_start = np.where(turn_start < -TURN_EPS, 0.0, 0.5 * thick)
        ext_end = np.where(turn_end < -TURN_EPS, 0.0, 0.5 * thick)
        centres = (
            starts
            + (0.5 * (length + ext_end - ext_start))[:, None] * unit
            + (0.5 * thick)[:, None] * normal
        )
        halves = np.stack([0.5 * (length + ext_start + ext_end), 0.5 * thick], axis=1)
        return centres, halves, yaw

    @staticmethod
    def _box_points(
        starts: FloatArray,
        unit: FloatArray,
        normal: FloatArray,
        length: FloatArray,
        thick: FloatArray,
        turn_start: FloatArray,
        turn_end: FloatArray,
    ) -> FloatArray:
        """(S, 18, 2) points on the far and end faces of each box (for the road check)."""
        ext_start = np.where(turn_start < -TURN_EPS, 0.0, 0.5 * thick)
        ext_end = np.where(turn_end < -TURN_EPS, 0.0, 0.5 * thick)
        a = np.linspace(0.0, 1.0, 9)[None, :]
        along = -ext_start[:, None] + a * (length + ext_start + ext_end)[:, None]  # (S, 9)
        far = (
            starts[:, None, :]
            + along[..., None] * unit[:, None, :]
            + thick[:, None, None] * normal[:, None, :]
        )
        across = a * thick[:, None]  # the two end faces
        first = (
            starts[:, None, :]
            - ext_start[:, None, None] * unit[:, None, :]
            + across[..., None] * normal[:, None, :]
        )
        last = (
            starts[:, None, :]
            + (length + ext_end)[:, None, None] * unit[:, None, :]
            + across[..., None] * normal[:, None, :]
        )
        return np.concatenate([far, first[:, :4], last[:, :5]], axis=1)


@dataclass(frozen=True)
class Clearance:
    """A lower bound on the distance from any point to a set of wall boxes, on a grid.

    Each cell holds the exact distance from its centre to the nearest box, less the cell's
    half-diagonal (so no point of the cell is nearer), capped at ``cap``; a point outside the
    grid is at least ``cap`` from every box. The simulator uses it to know, without asking
    pybullet, that no car can reach a wall within a control step.

    Attributes:
        x0, y0: m, the grid's lower-left corner; cell: m, its cell size.
        nx, ny: cells along x and y; cap: m, the largest value held.
        table: (nx · ny,) m, row-major (index ``ix · ny + iy``); an ``array`` of doubles,
            whose items read as Python floats.
    """

    x0: float
    y0: float
    cell: float
    nx: int
    ny: int
    cap: float
    table: array[float]

    @classmethod
    def of_boxes(
        cls, centres: FloatArray, halves: FloatArray, yaws: FloatArray, cell: float, cap: float
    ) -> Clearance:
        """The grid for boxes: centres (B, 2) m, half-extents (B, 2) m along and across each
        box's axis at yaw (B,) rad (those of :meth:`Walls.boxes`)."""
        radius = np.hypot(halves[:, 0], halves[:, 1])
        lo = (centres - radius[:, None]).min(axis=0) - cap - cell
        hi = (centres + radius[:, None]).max(axis=0) + cap + cell
        nx, ny = (int(v) for v in np.ceil((hi - lo) / cell))
        half_diag = 0.5 * cell * math.sqrt(2.0)
        # Every cell within cap of a box lies in the square of cells round it (w each side).
        w = math.ceil((cap + float(radius.max()) + half_diag) / cell) + 1
        offsets = np.arange(-w, w + 1)
        home = np.floor((centres - lo) / cell).astype(np.int64)  # (B, 2) the centres' cells
        ix = home[:, 0, None, None] + offsets[None, :, None]  # (B, K, 1)
        iy = home[:, 1, None, None] + offsets[None, None, :]  # (B, 1, K)
        dx = lo[0] + (ix + 0.5) * cell - centres[:, 0, None, None]
        dy = lo[1] + (iy + 0.5) * cell - centres[:, 1, None, None]
        cos, sin = np.cos(yaws)[:, None, None], np.sin(yaws)[:, None, None]
        along = np.maximum(np.abs(cos * dx + sin * dy) - halves[:, 0, None, None], 0.0)
        across = np.maximum(np.abs(cos * dy - sin * dx) - halves[:, 1, None, None], 0.0)
        # The distance from the cell's centre to the box, less its half-diagonal and a hair
        # for rounding: a bound for the whole cell.
        bound = np.hypot(along, across) - half_diag - 1e-9
        inside = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        grid = np.full(nx * ny, cap)
        np.minimum.at(grid, (ix * ny + iy)[inside], bound[inside])
        table = array("d")
        table.frombytes(grid.tobytes())
        return cls(float(lo[0]), float(lo[1]), cell, nx, ny, cap, table)

    def at(self, x: float, y: float) -> float:
        """m: no wall box is nearer to the point (x, y) than this (0.0 for NaN)."""
        fx, fy = (x - self.x0) / self.cell, (y - self.y0) / self.cell
        if 0.0 <= fx < self.nx and 0.0 <= fy < self.ny:
            return self.table[int(fx) * self.ny + int(fy)]
        return 0.0 if math.isnan(fx) or math.isnan(fy) else self.cap  # NaN, or outside


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """z of the 2D cross product of (..., 2) vectors."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
