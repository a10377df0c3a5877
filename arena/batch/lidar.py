"""The batched lidar: walls from a precomputed range table, cars as exact rectangles.

Same rays as :class:`arena.lidar.Lidar` (``n_rays`` over ``fov``, ray 0 rightmost, capped at
``max_range``) and the same targets (the walls and the other cars' rectangles), computed
without any per-car branch:

* walls: the range stored in :attr:`arena.batch.maps.TrackMaps.ranges` for the car's lidar
  cell, linearly interpolated between the two nearest table directions, minus the car's
  offset from the cell centre along the ray (exact for a wall square to the ray);
* cars: a slab test of every ray against every other car's rectangle.
"""

from __future__ import annotations

import math

import numpy as np

from arena.batch.xp import Array, NumpyOps
from arena.lidar import DEFAULT_FOV

CAR_WINDOW = 16  # rays tested against each other car, centred on its bearing


def ray_angles(n_rays: int, fov: float = DEFAULT_FOV) -> np.ndarray:
    """(n_rays,) ray angles in the car frame, rad, as :class:`arena.lidar.Lidar` lays them."""
    step = fov / n_rays if fov >= 2 * math.pi else fov / max(n_rays - 1, 1)
    return -0.5 * fov + step * np.arange(n_rays, dtype=np.float64)


def wall_ranges(
    x: Array,
    y: Array,
    yaw: Array,
    ray_bins: Array,
    ux: Array,
    uy: Array,
    table: Array,
    rows: Array,
    origin: tuple[float, float],
    cell: float,
    shape: tuple[int, int],
    max_range: float,
    ops: NumpyOps,
) -> Array:
    """Ranges (..., R) m to the walls from poses (...,).

    Args:
        x, y, yaw: (...,) lidar poses [m, m, rad].
        ray_bins: (R,) ray angles in the car frame as fractional table bins
            (``(angle + π) · bins / 2π``).
        ux, uy: (R,) ray directions in the car frame.
        table: (rows, bins + 1) ranges by absolute direction ``-π + k · 2π / bins`` (the
            last column repeats the first).
        rows: (H·W,) flat offset ``row · (bins + 1)`` of each lidar-grid cell's table row.
        origin, cell, shape: the lidar grid.
        max_range: m.
        ops: array namespace.
    """
    h, w = shape
    bins = table.shape[1] - 1  # the last column repeats the first: no wrap when interpolating
    ix = ops.clip(ops.floor((x - origin[0]) * (1.0 / cell) + 0.5), 0, w - 1)
    iy = ops.clip(ops.floor((y - origin[1]) * (1.0 / cell) + 0.5), 0, h - 1)
    base = rows[ops.cast(iy * w + ix, ops.int)][..., None]  # (..., 1) flat offset of the row
    # The car's offset from the cell centre, in the car frame (rays are fixed in it).
    cos, sin = ops.cos(yaw), ops.sin(yaw)
    dx, dy = x - (origin[0] + ix * cell), y - (origin[1] + iy * cell)
    ox, oy = (cos * dx + sin * dy)[..., None], (cos * dy - sin * dx)[..., None]
    f = (ops.wrap(yaw, 2 * math.pi) * (bins / (2 * math.pi)))[..., None] + ray_bins
    f = ops.where(f >= bins, f - bins, f)  # both terms lie in [0, bins)
    k0f = ops.minimum(ops.floor(f), bins - 1.0)  # f may round up to ``bins`` in float32
    frac = f - k0f
    idx = base + ops.cast(k0f, ops.int)
    flat = table.reshape(-1)
    r0 = ops.cast(flat[idx], x.dtype)
    r1 = ops.cast(flat[idx + 1], x.dtype)
    rng = r0 + frac * (r1 - r0) - (ox * ux + oy * uy)
    hit = ops.maximum(r0, r1) < max_range - 1e-3
    return ops.where(hit, ops.clip(rng, 0.0, max_range), max_range)


def car_ranges(
    x: Array,
    y: Array,
    cos: Array,
    sin: Array,
    pairs: tuple[Array, Array],
    ux: Array,
    uy: Array,
    fan: tuple[float, float],
    active: Array,
    half_length: float,
    half_width: float,
    max_range: float,
    ops: NumpyOps,
    window: int = CAR_WINDOW,
) -> Array:
    """Ranges (..., N, R) m from each car to the other cars' rectangles.

    Only the ``window`` rays centred on the bearing to each other car are tested (a slab
    test against its rectangle): 16 rays span 69°, what a car subtends from 0.45 m away
    (closer, the cars overlap), so nothing is lost in a race, for a quarter of the work.

    Args:
        x, y: (..., N) positions m; cos, sin: (..., N) of the yaw.
        pairs: ``(i, j)`` index arrays (N·(N−1),): scanner i, target j, grouped by i.
        ux, uy: (R,) ray directions in the car frame.
        fan: (first ray angle, angle between rays), rad.
        active: (..., N) cars still racing (the others are invisible).
    """
    n = x.shape[-1]
    n_rays = ux.shape[0]
    first, step = fan
    pi, pj = pairs
    dx = x[..., pj] - x[..., pi]
    dy = y[..., pj] - y[..., pi]
    ci, si, cj, sj = cos[..., pi], sin[..., pi], cos[..., pj], sin[..., pj]
    # The target's bearing in the scanner's frame picks the window of rays.
    bx, by = ci * dx + si * dy, ci * dy - si * dx
    centre = ops.floor((ops.atan2(by, bx) - first) * (1.0 / step) + 0.5)
    k = ops.cast(centre, ops.int)[..., None] + ops.arange(window) - window // 2  # (..., P, W)
    valid = (k >= 0) & (k < n_rays)
    kc = ops.clip(k, 0, n_rays - 1)
    # Ray directions and the scanner's origin in the target's frame.
    c_rel = (ci * cj + si * sj)[..., None]  # cos(yaw_i − yaw_j)
    s_rel = (si * cj - ci * sj)[..., None]
    u, v = ux[kc], uy[kc]
    dxj, dyj = c_rel * u - s_rel * v, s_rel * u + c_rel * v
    ox = (-(cj * dx + sj * dy))[..., None]
    oy = (-(cj * dy - sj * dx))[..., None]
    with ops.quiet():  # a ray parallel to a side: ±inf slab bounds, as IEEE intends
        inv_x, inv_y = 1.0 / dxj, 1.0 / dyj
        ax, bx_ = (-half_length - ox) * inv_x, (half_length - ox) * inv_x
        ay, by_ = (-half_width - oy) * inv_y, (half_width - oy) * inv_y
        t_near = ops.maximum(ops.minimum(ax, bx_), ops.minimum(ay, by_))
        t_far = ops.minimum(ops.maximum(ax, bx_), ops.maximum(ay, by_))
    seen = (active[..., pj] & active[..., pi])[..., None]
    ok = seen & valid & (t_near <= t_far) & (t_near > 0.0)
    dist = ops.where(ok, ops.minimum(t_near, max_range), max_range)
    # Scatter each opponent's window into the scan (invalid rays into a spare column).
    lead = tuple(x.shape[:-1])
    idx = ops.where(valid, kc, n_rays).reshape(*lead, n, n - 1, window)
    dist = dist.reshape(*lead, n, n - 1, window)
    out = None
    for m in range(n - 1):  # opponent slots: a static count, not data
        scan = ops.full((*lead, n, n_rays + 1), max_range, dtype=dist.dtype)
        scan = ops.put_along(scan, idx[..., m, :], dist[..., m, :], axis=-1)[..., :n_rays]
        out = scan if out is None else ops.minimum(out, scan)
    return out


def car_pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Ordered pairs (i, j), i ≠ j, of ``n`` cars, grouped by i: two (n·(n−1),) arrays."""
    i, j = np.nonzero(~np.eye(n, dtype=bool))
    return i.astype(np.int64), j.astype(np.int64)
