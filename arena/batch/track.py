"""Track queries of the batched simulator: projection, centre-line points, widths, clearance.

The device-side counterpart of :class:`tracks.Track`'s queries, on :class:`TrackMaps`
arrays converted once to the array library of the simulation. A car is projected onto the
centre line by reading the nearest segment from a grid and refining over that segment's
neighbours (±2) with an exact point-to-segment projection: a fixed amount of work per car.
"""

from __future__ import annotations

import numpy as np

from arena.batch.maps import TrackMaps
from arena.batch.xp import Array, NumpyOps

NEIGHBOURS = 2  # segments either side of the grid's guess that the projection tries


class DeviceTrack:
    """A :class:`TrackMaps` on the simulation's device, with vectorised queries."""

    def __init__(self, maps: TrackMaps, ops: NumpyOps) -> None:
        self.maps = maps
        self.ops = ops
        track = maps.track
        self.length = float(track.length)
        self.n = track.n_points
        c = maps.centre
        e = np.roll(c, -1, axis=0) - c
        normals = np.stack([-maps.tangents[:, 1], maps.tangents[:, 0]], axis=1)
        a = ops.asarray
        self.cx, self.cy = a(c[:, 0]), a(c[:, 1])
        self.ex, self.ey = a(e[:, 0]), a(e[:, 1])
        self.inv_len2 = a(1.0 / np.maximum((e * e).sum(axis=1), 1e-12))
        self.inv_len = a(1.0 / np.maximum(np.hypot(e[:, 0], e[:, 1]), 1e-12))
        self.tx, self.ty = a(maps.tangents[:, 0]), a(maps.tangents[:, 1])
        self.nx, self.ny = a(normals[:, 0]), a(normals[:, 1])
        self.s = a(maps.s)
        self.seg_len = a(maps.seg_len)
        self.width_left, self.width_right = a(maps.width_left), a(maps.width_right)
        self.segment = a(maps.segment)
        self.clear = a(maps.clearance)
        self.wnx, self.wny = a(maps.wall_normal[:, 0]), a(maps.wall_normal[:, 1])
        padded = np.concatenate([maps.ranges, maps.ranges[:, :1]], axis=1)  # wrap column
        self.lidar_rows = a(maps.lidar_row * padded.shape[1])
        self.ranges = a(padded, dtype=ops.float32)
        self.offsets = a(np.arange(-NEIGHBOURS, NEIGHBOURS + 1), dtype=ops.int)

    # ---- progress arithmetic ----------------------------------------------------------------
    def wrap_s(self, s: Array) -> Array:
        """Progress folded into [0, L), m."""
        return self.ops.wrap(s, self.length)

    def delta_s(self, s_to: Array, s_from: Array) -> Array:
        """Signed shortest progress from ``s_from`` to ``s_to``, m in [-L/2, L/2)."""
        half = 0.5 * self.length
        return self.ops.wrap(s_to - s_from + half, self.length) - half

    def _locate(self, s: Array) -> tuple[Array, Array, Array]:
        ops = self.ops
        sw = self.wrap_s(s)
        i = ops.clip(ops.searchsorted(self.s, sw) - 1, 0, self.n - 1)
        t = (sw - self.s[i]) / self.seg_len[i]
        j = ops.where(i + 1 >= self.n, 0, i + 1)
        return i, j, t

    def centre_at(self, s: Array) -> tuple[Array, Array]:
        """Centre-line points (x, y) m at progress ``s`` (any shape)."""
        i, j, t = self._locate(s)
        return (
            self.cx[i] + t * (self.cx[j] - self.cx[i]),
            self.cy[i] + t * (self.cy[j] - self.cy[i]),
        )

    def widths_at(self, s: Array) -> tuple[Array, Array]:
        """Left and right half-widths m at progress ``s`` (linear between points)."""
        i, j, t = self._locate(s)
        wl, wr = self.width_left, self.width_right
        return wl[i] + t * (wl[j] - wl[i]), wr[i] + t * (wr[j] - wr[i])

    # ---- projection -------------------------------------------------------------------------
    def _cell(self, x: Array, y: Array) -> Array:
        ops, g = self.ops, self.maps.grid
        h, w = g.shape
        ix = ops.cast(ops.clip(ops.floor((x - g.origin[0]) / g.cell + 0.5), 0, w - 1), ops.int)
        iy = ops.cast(ops.clip(ops.floor((y - g.origin[1]) / g.cell + 0.5), 0, h - 1), ops.int)
        return iy * w + ix

    def project(self, x: Array, y: Array) -> tuple[Array, Array, Array, Array]:
        """Progress ``s`` m, lateral offset ``d`` m (+ left), centre-line heading rad and
        segment index of points (x, y) (any shape)."""
        ops = self.ops
        guess = self.segment[self._cell(x, y)]
        cand = ops.mod(guess[..., None] + self.offsets, self.n)  # (..., 5)
        qx = x[..., None] - self.cx[cand]
        qy = y[..., None] - self.cy[cand]
        ex, ey = self.ex[cand], self.ey[cand]
        t = ops.clip((qx * ex + qy * ey) * self.inv_len2[cand], 0.0, 1.0)
        fx, fy = qx - t * ex, qy - t * ey
        best = ops.argmin(fx * fx + fy * fy, axis=-1)[..., None]
        seg = ops.take_along(cand, best, -1)[..., 0]
        tb = ops.take_along(t, best, -1)[..., 0]
        qxb = ops.take_along(qx, best, -1)[..., 0]
        qyb = ops.take_along(qy, best, -1)[..., 0]
        d = (self.ex[seg] * qyb - self.ey[seg] * qxb) * self.inv_len[seg]
        s = self.wrap_s(self.s[seg] + tb * self.seg_len[seg])
        nxt = ops.where(seg + 1 >= self.n, 0, seg + 1)
        hx = self.tx[seg] + tb * (self.tx[nxt] - self.tx[seg])
        hy = self.ty[seg] + tb * (self.ty[nxt] - self.ty[seg])
        return s, d, ops.atan2(hy, hx), seg

    # ---- walls ------------------------------------------------------------------------------
    def clearance(self, x: Array, y: Array) -> tuple[Array, Array, Array]:
        """Distance m to the walls (bilinear; negative inside a wall) and the unit normal
        (x, y) pointing away from the nearer wall, at points of any shape."""
        ops, g = self.ops, self.maps.grid
        h, w = g.shape
        fx = (x - g.origin[0]) / g.cell
        fy = (y - g.origin[1]) / g.cell
        x0 = ops.clip(ops.floor(fx), 0, w - 2)
        y0 = ops.clip(ops.floor(fy), 0, h - 2)
        ax = ops.clip(fx - x0, 0.0, 1.0)
        ay = ops.clip(fy - y0, 0.0, 1.0)
        k = ops.cast(y0, ops.int) * w + ops.cast(x0, ops.int)
        c = self.clear
        top = c[k] + ax * (c[k + 1] - c[k])
        bottom = c[k + w] + ax * (c[k + w + 1] - c[k + w])
        value = top + ay * (bottom - top)
        near = self._cell(x, y)
        return value, self.wnx[near], self.wny[near]
