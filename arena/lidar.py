"""A 2D planar lidar, exact and cheap, vectorised over all cars.

Rays are cast in the plane against the wall polylines near each car (a window of wall
segments around its centre-line position, see :class:`arena.walls.Walls`) and against the
rectangles of the other cars. Nothing goes through pybullet: racecar_gym spends 92% of its
step in pybullet ray tests through car meshes.

The trick that keeps it cheap: rays are fixed in the car frame, so every segment, moved into
the car frame, covers a contiguous interval of ray indices (from the angles of its two ends).
Only those (ray, segment) pairs are intersected — about rays × walls-crossed pairs per car
instead of rays × segments — and each ray keeps its nearest hit (a scatter-min).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

from arena.walls import Walls

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

DEFAULT_FOV = math.radians(270.0)  # rad, as the F1TENTH Hokuyo
DEFAULT_RANGE = 10.0  # m
_NEXT_CORNER = np.array([1, 2, 3, 0])  # each car corner's successor round the rectangle


class Lidar:
    """``n_rays`` evenly spaced rays over ``fov`` radians, centred on the car's heading.

    Args:
        walls: the wall polylines to cast against.
        n_rays: rays per car (ray 0 is the rightmost, ``n_rays - 1`` the leftmost).
        fov: field of view, rad (at most 2π).
        max_range: range reported when nothing is hit, m.
    """

    def __init__(
        self,
        walls: Walls,
        n_rays: int = 64,
        fov: float = DEFAULT_FOV,
        max_range: float = DEFAULT_RANGE,
    ) -> None:
        if n_rays < 1 or not 0 < fov <= 2 * math.pi or max_range <= 0:
            raise ValueError("lidar needs n_rays >= 1, 0 < fov <= 2*pi and max_range > 0")
        self.walls = walls
        self.n_rays = n_rays
        self.fov = fov
        self.max_range = max_range
        self.step = fov / n_rays if fov >= 2 * math.pi else fov / max(n_rays - 1, 1)
        self.first = -0.5 * fov
        self.angles: FloatArray = self.first + self.step * np.arange(n_rays, dtype=np.float64)
        self.dirs: FloatArray = np.stack([np.cos(self.angles), np.sin(self.angles)], axis=1)
        self._shifts = np.array([0.0, -2 * math.pi]) - self.first  # rad, as the first ray
        # A segment's start angle (-2π … π) less the first ray's lies within one turn of 0
        # unless the field of view is (nearly) a full turn: then a sum replaces np.mod.
        self._below_turn = -self.first < 0.9 * math.pi
        spacing = float(np.mean(np.linalg.norm(np.diff(walls.left, axis=0), axis=1)))
        self.half_window = math.ceil(1.5 * max_range / spacing) + 1
        # Per wall point k, both walls' segments k -> k+1 as [x0, y0, x1, y1] (left, right):
        # one gather per scan fetches every windowed segment, ends included.
        left, right = walls.left, walls.right
        self._table: FloatArray = np.hstack(
            [left, np.roll(left, -1, axis=0), right, np.roll(right, -1, axis=0)]
        )  # (W, 8) m
        # The same rows padded round the loop, so that the window of wall point k is rows
        # k … k + 2·half_window, read through a sliding view: one gather per scan, and no
        # index arithmetic (Walls.window's indices, without building them).
        w, hw = len(left), self.half_window
        padded = self._table.take((np.arange(w + 2 * hw) - hw) % w, axis=0)
        self._windows: FloatArray = sliding_window_view(padded, (2 * hw + 1, 8))[:, 0]
        # A segment whose ends both lie farther than this from a car is beyond the range
        # all along (each of its points is within half its length of an end): m², walls.
        ends = self._table.reshape(-1, 2, 2, 2)  # (W, wall, [start, end], xy)
        longest = float(np.max(np.linalg.norm(ends[:, :, 1] - ends[:, :, 0], axis=-1)))
        self._wall_reach = (max_range + 0.5 * longest + 0.01) ** 2
        # Ray directions tiled over cars (flat index car · n_rays + ray), grown on demand.
        self._dir_x: FloatArray = self.dirs[:, 0].copy()
        self._dir_y: FloatArray = self.dirs[:, 1].copy()
        self._layouts: dict[tuple[int, int], _Layout] = {}
        self._halves_tile: IntArray = np.arange(0)
        self._shift_tile: FloatArray = np.empty((0, 2))

    def _shift_rows(self, k: int) -> FloatArray:
        """(2k, 2) rad: rows [shift 0, shift 0], [shift 1, shift 1] of :attr:`_shifts`
        once per segment (grown on demand)."""
        if len(self._shift_tile) < 2 * k:
            self._shift_tile = np.tile(self._shifts.repeat(2).reshape(2, 2), (2 * k, 1))
        return self._shift_tile[: 2 * k]

    def _halves(self, k: int) -> IntArray:
        """(k,) int: 0, 0, 1, 1, 2, 2, … (each pair's segment; grown on demand)."""
        if len(self._halves_tile) < k:
            self._halves_tile = np.arange(2 * k) >> 1
        return self._halves_tile[:k]

    def _layout(self, n: int, n_edges: int) -> _Layout:
        """Constant index arrays for ``n`` scanners and ``n_edges`` car edges (built once)."""
        key = (n, n_edges)
        if key not in self._layouts:
            n_wall = 2 * (2 * self.half_window + 1)
            n_seg = n_wall + n_edges
            usable = np.ones((n, n_seg), dtype=bool)
            if n_edges:  # a car's own four edges are not seen by its lidar
                usable[:, n_wall:] = ~np.repeat(np.eye(n, dtype=bool), 4, axis=1)
            # m² per segment beyond which it cannot be hit: walls from their longest segment;
            # the cars' edges (at most a car long) get a generous 1.5 ranges + 1 m.
            reach = np.full((n, n_seg), (self.max_range * 1.5 + 1.0) ** 2)
            reach[:, :n_wall] = self._wall_reach
            if len(self._dir_x) < n * self.n_rays:
                self._dir_x = np.tile(self.dirs[:, 0], n)
                self._dir_y = np.tile(self.dirs[:, 1], n)
            ray_base = (np.arange(n * n_seg) // n_seg) * self.n_rays
            self._layouts[key] = _Layout(n_seg, usable, reach, ray_base)
        return self._layouts[key]

    def scan(
        self,
        poses: FloatArray,
        segment: IntArray,
        car_corners: FloatArray | None = None,
    ) -> FloatArray:
        """Ranges (n, n_rays) m, capped at ``max_range``.

        Args:
            poses: (n, 3) [x m, y m, yaw rad] of the scanning cars (the lidar at the centre).
            segment: (n,) centre-line segment index of each car (from ``Track.project``).
            car_corners: (n, 4, 2) m, corners of every car's rectangle in order round it; a
                car's own rectangle is skipped. None: walls only.
        """
        n = len(poses)
        # (n, S, 8) → (n, 2S, 4): [x0, y0, x1, y1] of the windowed wall segments.
        windows = self._windows[self.walls.window_start(segment)]
        if car_corners is None or len(car_corners) < 2:
            return self._cast(poses, windows.reshape(n, -1, 4), self._layout(n, 0))
        # Every car's 4 edges after the walls, shared by all scanners (the order of the
        # segments does not matter: each ray keeps its nearest hit). Written in place.
        m = len(car_corners)
        layout = self._layout(n, 4 * m)
        seg = np.empty((n, layout.n_seg, 4))
        n_wall = 2 * windows.shape[1]
        seg[:, :n_wall] = windows.reshape(n, n_wall, 4)
        edges = seg[:, n_wall:].reshape(n, m, 4, 4)  # a view: [start xy, end xy] per edge
        edges[..., :2] = car_corners
        edges[..., 2:] = car_corners.take(_NEXT_CORNER, axis=1)
        return self._cast(poses, seg, layout)

    def _cast(self, poses: FloatArray, seg: FloatArray, layout: _Layout) -> FloatArray:
        """Nearest hit per ray; ``seg`` (n, S, 4) m = start x, start y, end x, end y."""
        n, m = seg.shape[:2]
        # Each car's x, y and heading's cos and sin repeated over both ends of its m
        # segments: numpy buffers a broadcast operand, which costs more than this one repeat
        # on these sizes.
        frame = np.concatenate(
            [poses[:, :2].T, np.cos(poses[None, :, 2]), np.sin(poses[None, :, 2])]
        )
        x, y, cos, sin = frame.repeat(2 * m, axis=1).reshape(4, n, m, 2)
        # Both ends of every segment (last axis: start, end) in each car's frame at once.
        pts = seg.reshape(n, m, 2, 2)
        dx, dy = pts[..., 0] - x, pts[..., 1] - y
        ex, ey = cos * dx + sin * dy, cos * dy - sin * dx
        # Only the segments within reach go on (flat (car, segment) indices): their number,
        # not the window's, sets the cost of what follows.
        r2 = ex * ex + ey * ey
        near = layout.usable & (np.minimum(r2[..., 0], r2[..., 1]) < layout.reach)
        keep = near.ravel().nonzero()[0]
        if len(keep) == 0:
            out = np.empty(n * self.n_rays)
            out.fill(self.max_range)
            return out.reshape(n, self.n_rays)
        ex, ey = ex.reshape(-1, 2).take(keep, axis=0), ey.reshape(-1, 2).take(keep, axis=0)
        ax, bx, ay, by = ex[:, 0], ex[:, 1], ey[:, 0], ey[:, 1]
        span = np.arctan2(ax * by - ay * bx, ax * bx + ay * by)  # signed angle a → b
        # Interval [lo, hi] of angles the segment covers, rotated to start at or after the
        # first ray; its part beyond one turn wraps round to the first rays (shift 1 below).
        bounds = np.empty((len(keep), 2))
        rel = np.arctan2(ay, ax) + np.minimum(span, 0.0) - self.first
        if self._below_turn:  # rel in (-2π, 2π): mod 2π adds a turn to the negative ones
            rel += (rel < 0.0) * (2 * math.pi)  # (-0.0 + 0.0 is +0.0, as mod gives)
        else:
            rel = np.mod(rel, 2 * math.pi)
        lo = np.add(self.first, rel, out=bounds[:, 0])
        np.add(lo, np.abs(span), out=bounds[:, 1])
        # Both shifts of both ends at once: (2K, [lo, hi]) in ray steps, rows [shift 0,
        # shift 1] per segment.
        steps = (bounds.repeat(2, axis=0) + self._shift_rows(len(keep))) / self.step
        k_lo = np.maximum(np.ceil(steps[:, 0] - 1e-9), 0).astype(np.int64)
        k_hi = np.minimum(np.floor(steps[:, 1] + 1e-9), self.n_rays - 1).astype(np.int64)
        # Array methods, not numpy's functions: the same results without the dispatch cost,
        # which dominates on arrays this small.
        counts = np.maximum(k_hi - k_lo + 1, 0)
        out = np.empty(n * self.n_rays)
        out.fill(self.max_range)
        ends = counts.cumsum()
        total = int(ends[-1])
        if total == 0:
            return out.reshape(n, self.n_rays)
        # Every (segment, ray) pair as a flat output index car · n_rays + ray, and its segment.
        first_ray = layout.ray_base.take(keep).repeat(2) + k_lo - (ends - counts)
        flat = first_ray.repeat(counts) + np.arange(total)
        pair_seg = self._halves(2 * len(keep)).repeat(counts)
        pax, pay = ax[pair_seg], ay[pair_seg]
        pex, pey = bx[pair_seg] - pax, by[pair_seg] - pay
        ux, uy = self._dir_x[flat], self._dir_y[flat]
        denom = ux * pey - uy * pex
        hit = np.abs(denom) > 1e-12
        denom = np.where(hit, denom, 1.0)  # the pairs it replaces are rejected: no 0 / 0
        t = (pax * pey - pay * pex) / denom
        w = (pax * uy - pay * ux) / denom
        hit &= (t > 0) & (w >= -1e-9) & (w <= 1 + 1e-9)
        # Each ray keeps its nearest hit (a scatter-min); misses leave max_range.
        np.minimum.at(out, flat[hit], t[hit])
        return out.reshape(n, self.n_rays)


@dataclass(frozen=True)
class _Layout:
    """Index arrays of one scan shape (see :meth:`Lidar._layout`).

    Attributes:
        n_seg: segments per scanner (windowed walls, then every car's edges).
        usable: (n, n_seg) False for a scanner's own edges.
        reach: (n, n_seg) m², squared distance from a scanner beyond which both ends of a
            segment put all of it out of range.
        ray_base: (n · n_seg,) int, per flat (scanner, segment) index the scanner's first
            flat ray index (scanner · n_rays).
    """

    n_seg: int
    usable: NDArray[np.bool_]
    reach: FloatArray
    ray_base: IntArray
