"""Precomputed track fields for the batched simulator: grids it can read with one gather.

The pybullet env projects cars onto the centre line with a k-d tree and casts lidar rays
against the wall polylines. Neither runs branch-free on a GPU, so :class:`TrackMaps` turns
them into arrays once per track (cached per process):

* ``segment``: a grid (``cell`` m) of the nearest centre-line segment of each cell, refined
  per car by an exact point-to-segment projection onto its neighbours;
* ``clearance`` and ``wall_normal``: the signed distance from each cell to the nearer wall,
  measured across the road (positive between the walls), and the unit normal pointing back
  between the walls — the walls of :class:`arena.walls.Walls`, ``runoff`` m off the road;
* ``ranges``: a lidar range table (range_libc's "giant lookup table"): for every cell of a
  coarser grid (``lidar_cell`` m) on or near the corridor between the walls, the exact range
  to the walls along ``lidar_bins`` directions, cast with :class:`arena.lidar.Lidar`. A scan
  is then a gather per ray (interpolated between the two nearest directions and corrected for
  the car's offset from the cell centre along the ray).

Cells far from the corridor read "inside the wall" (range 0, clearance negative).
"""

from __future__ import annotations

import hashlib
import math
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from arena.lidar import DEFAULT_RANGE, Lidar
from arena.walls import DEFAULT_RUNOFF, Walls, wall_offsets
from tracks import Projection, Track

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

GRID_CELL = 0.1  # m: segment and clearance grid
LIDAR_CELL = 0.2  # m: lidar table grid
LIDAR_BINS = 180  # directions of the lidar table (2° apart)
MARGIN = 1.5  # m of grid beyond the walls
LIDAR_REACH = 0.6  # m beyond the walls where the lidar table still has rows
CACHE_BYTES = 256 << 20  # maps a process keeps for reuse, bytes (10–40 MB a track)
# Least recently used first, the newest always kept. Bounded: training on generated tracks
# draws a new one every few rollouts, and an unbounded cache held every map ever built (a
# 4 M-step run grew by ~5 GB, 1.2 KB a step; 20 M steps would not fit 24 GiB). A simulator
# keeps its own maps alive whatever the cache drops.
_CACHE: OrderedDict[tuple[object, ...], TrackMaps] = OrderedDict()


@dataclass(frozen=True)
class Grid:
    """A regular grid: cell ``(iy, ix)`` has its centre at ``origin + (ix, iy) · cell``."""

    origin: tuple[float, float]
    cell: float
    shape: tuple[int, int]  # (rows H, columns W)

    @classmethod
    def covering(cls, lo: FloatArray, hi: FloatArray, cell: float) -> Grid:
        """The grid of ``cell`` m whose cells cover the box ``lo``–``hi`` (2,) m."""
        cols, rows = np.ceil((hi - lo) / cell).astype(int) + 1
        return cls((float(lo[0]), float(lo[1])), cell, (int(rows), int(cols)))

    def centres(self) -> FloatArray:
        """(H·W, 2) m: cell centres, row-major."""
        h, w = self.shape
        ys, xs = np.mgrid[0:h, 0:w]
        return np.stack([xs.ravel(), ys.ravel()], axis=1) * self.cell + np.asarray(self.origin)


@dataclass(frozen=True)
class TrackMaps:
    """Everything the batched simulator reads about one track (numpy, host memory).

    Attributes:
        track: the track.
        walls: its walls.
        centre, tangents: (N, 2) centre-line points m and unit tangents.
        s: (N + 1,) m progress of each point, closed with the lap length.
        seg_len: (N,) m segment lengths.
        width_left, width_right: (N,) m half-widths.
        grid: the segment / clearance grid.
        segment: (H·W,) nearest centre-line segment per cell.
        clearance: (H·W,) m to the nearer wall, positive between the walls.
        wall_normal: (H·W, 2) unit normal away from that wall.
        lidar_grid: the lidar table grid.
        lidar_row: (H'·W',) row of the range table per cell (the last row: inside a wall).
        ranges: (rows, bins) float32 m, ranges to the walls by absolute direction
            ``-π + k · 2π / bins``.
        max_range: lidar range, m.
    """

    track: Track
    walls: Walls
    centre: FloatArray
    tangents: FloatArray
    s: FloatArray
    seg_len: FloatArray
    width_left: FloatArray
    width_right: FloatArray
    grid: Grid
    segment: IntArray
    clearance: FloatArray
    wall_normal: FloatArray
    lidar_grid: Grid
    lidar_row: IntArray
    ranges: NDArray[np.float32]
    max_range: float

    @classmethod
    def build(
        cls,
        track: Track,
        runoff: float = DEFAULT_RUNOFF,
        max_range: float = DEFAULT_RANGE,
        *,
        cell: float = GRID_CELL,
        lidar_cell: float = LIDAR_CELL,
        lidar_bins: int = LIDAR_BINS,
    ) -> TrackMaps:
        """The maps of ``track`` (cached per process by the track's geometry: the most
        recently used, up to :data:`CACHE_BYTES`)."""
        digest = hashlib.sha1(track.centre.tobytes() + track.width_left.tobytes()).hexdigest()
        key = (digest, track.width_right.tobytes(), runoff, max_range, cell, lidar_cell, lidar_bins)
        maps = _CACHE.get(key)
        if maps is None:
            maps = cls._build(track, runoff, max_range, cell, lidar_cell, lidar_bins)
            _CACHE[key] = maps
            held = sum(m.nbytes for m in _CACHE.values())
            while held > CACHE_BYTES and len(_CACHE) > 1:
                held -= _CACHE.popitem(last=False)[1].nbytes
        else:
            _CACHE.move_to_end(key)
        return maps

    @classmethod
    def _build(
        cls,
        track: Track,
        runoff: float,
        max_range: float,
        cell: float,
        lidar_cell: float,
        lidar_bins: int,
    ) -> TrackMaps:
        walls = Walls.around(track, runoff)
        both = np.vstack([walls.left, walls.right])
        lo, hi = both.min(axis=0) - MARGIN, both.max(axis=0) + MARGIN
        grid = Grid.covering(lo, hi, cell)
        pts = grid.centres()
        proj = track.project(pts)
        wall_left, wall_right = _wall_offsets_at(track, runoff, proj.s)
        to_left = wall_left - proj.d  # m to the left wall, across the road
        to_right = wall_right + proj.d
        clearance = np.minimum(to_left, to_right)
        normal = np.stack([-np.sin(proj.heading), np.cos(proj.heading)], axis=1)
        wall_normal = np.where((to_left < to_right)[:, None], -normal, normal)

        lgrid = Grid.covering(lo, hi, lidar_cell)
        lpts = lgrid.centres()
        l_s, l_d, l_segment = _project_cells(track, lgrid, lpts, grid, pts, proj)
        lleft, lright = _wall_offsets_at(track, runoff, l_s)
        near = np.minimum(lleft - l_d, lright + l_d) > -LIDAR_REACH
        rows = np.flatnonzero(near)
        lidar = Lidar(walls, lidar_bins, 2 * math.pi, max_range)
        ranges = np.zeros((len(rows) + 1, lidar_bins), dtype=np.float32)  # last row: blind
        block = 4096
        for start in range(0, len(rows), block):
            part = rows[start : start + block]
            poses = np.column_stack([lpts[part], np.zeros(len(part))])
            ranges[start : start + len(part)] = lidar.scan(poses, l_segment[part])
        lidar_row = np.full(len(lpts), len(rows), dtype=np.int64)
        lidar_row[rows] = np.arange(len(rows))
        n = track.n_points
        return cls(
            track=track,
            walls=walls,
            centre=np.asarray(track.centre),
            tangents=np.asarray(track.tangents),
            s=np.append(track.s, track.length),
            seg_len=np.asarray(track.segment_lengths),
            width_left=np.asarray(track.width_left),
            width_right=np.asarray(track.width_right),
            grid=grid,
            segment=proj.segment.astype(np.int64) % n,
            clearance=clearance,
            wall_normal=wall_normal,
            lidar_grid=lgrid,
            lidar_row=lidar_row,
            ranges=ranges,
            max_range=max_range,
        )

    @property
    def nbytes(self) -> int:
        """Bytes of the grids and the range table."""
        arrays = (self.segment, self.clearance, self.wall_normal, self.lidar_row, self.ranges)
        return sum(a.nbytes for a in arrays)


def _project_cells(
    track: Track,
    coarse: Grid,
    points: FloatArray,
    fine: Grid,
    fine_points: FloatArray,
    fine_proj: Projection,
) -> tuple[FloatArray, FloatArray, IntArray]:
    """Progress ``s`` (M,) m, offset ``d`` (M,) m and segment (M,) of the ``coarse`` grid's
    cell centres ``points`` (M, 2) m.

    Projection is point by point, so a coarse centre that is, bit for bit, a centre of the
    ``fine`` grid already projected (``fine_points``, ``fine_proj``) takes that answer: with
    the same origin and a cell twice as large (the default 0.2 and 0.1 m: ``ix · 0.2`` and
    ``2 ix · 0.1`` round alike) every centre but the last row and column does, and the k-d
    tree is asked about the rest only. The result equals ``track.project(points)``.
    """
    h, w = coarse.shape
    ratio = max(1, round(coarse.cell / fine.cell))
    iy, ix = np.divmod(np.arange(h * w), w)
    fy, fx = iy * ratio, ix * ratio
    idx = np.flatnonzero((fy < fine.shape[0]) & (fx < fine.shape[1]))
    at = fy[idx] * fine.shape[1] + fx[idx]
    same = (fine_points[at] == points[idx]).all(axis=1)
    idx, at = idx[same], at[same]
    s = np.empty(len(points))
    d = np.empty(len(points))
    segment = np.empty(len(points), dtype=np.int64)
    s[idx], d[idx], segment[idx] = fine_proj.s[at], fine_proj.d[at], fine_proj.segment[at]
    rest = np.ones(len(points), dtype=bool)
    rest[idx] = False
    if rest.any():
        proj = track.project(points[rest])
        s[rest], d[rest], segment[rest] = proj.s, proj.d, proj.segment
    return s, d, segment


def _wall_offsets_at(track: Track, runoff: float, s: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Left and right wall offsets (M,) m at progress ``s`` (M,) m, linearly interpolated."""
    left, right = wall_offsets(track, runoff)
    at = track.wrap_s(s)
    knots = np.append(track.s, track.length)
    return (
        np.interp(at, knots, np.append(left, left[0])),
        np.interp(at, knots, np.append(right, right[0])),
    )
