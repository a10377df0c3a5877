"""Track geometry: a closed, smooth centre line with per-point half-widths.

Coordinates are metres in a right-handed x-y plane; angles are radians, counter-clockwise from
+x. Progress ``s`` is metres along the centre line in the driving direction, with ``s = 0`` on
the start/finish line. The lateral offset ``d`` is metres to the *left* of the centre line
(seen in the driving direction); the road spans ``-width_right(s) <= d <= width_left(s)``.

Frenet coordinates use a frame whose normal is interpolated linearly between the (smooth)
vertex normals of the centre line. Unlike "project onto the nearest segment", that frame is
continuous and exactly invertible inside the radius of curvature, so a Cartesian → Frenet →
Cartesian round trip returns the same point to machine precision, and points on the outside of
a bend do not collapse onto a vertex.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tracks.errors import TrackError

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

CAR_LENGTH = 0.5  # m, 1/10-scale car (grid spacing and grid-fit checks use it)
CAR_WIDTH = 0.3  # m
DEFAULT_SPACING = 0.1  # m between resampled centre-line points
DEFAULT_CHECKPOINTS = 10  # ordered gates per lap; gate 0 is the start/finish line
CORNER_CURVATURE = 1.0 / 12.0  # 1/m: bends tighter than a 12 m radius (1/10 scale) are corners
CORNER_MIN_TURN = np.deg2rad(30.0)  # rad of heading change for a bend to count as a corner
_PROJECT_BLOCK = 16384  # points per projection block: keeps the (M, 4) temporaries in cache
# At most this many points are projected in scalar arithmetic (:meth:`Track._project_few`):
# the env's cars, every step. Each numpy call costs about a microsecond whatever its size,
# so on a few points the scalar loop is cheaper than the ~40 calls of a block.
_PROJECT_FEW = 16
# Few-point projections find the two nearest centre-line vertices in a grid of candidates
# (Track._near_grid) instead of the k-d tree, whose per-call overhead dominates for a few
# points: cells of this size, m, and only where every candidate lies within this reach, m.
_NEAR_CELL = 0.5
_NEAR_REACH = 3.0
_NEAR_MARGIN = 1e-6  # m added to each cell's candidate radius: beyond any rounding


@dataclass(frozen=True)
class _NearGrid:
    """Candidates of :meth:`Track._nearest_two`: cell ``(i, j)`` (``i * ny + j``) covers
    ``[x0 + i h, x0 + (i+1) h) × [y0 + j h, …)`` and lists ``flat[a:b]`` for its span
    ``(a, b)`` (None: no candidates kept); ``xs``, ``ys``: the vertices, m."""

    x0: float
    y0: float
    nx: int
    ny: int
    cells: list[tuple[int, int] | None]
    flat: list[int]
    xs: list[float]
    ys: list[float]


@dataclass(frozen=True)
class Projection:
    """Where points lie relative to the track; every field has shape (M,).

    Attributes:
        s: progress along the centre line, metres in ``[0, length)``.
        d: signed lateral offset, metres, positive to the left of the driving direction.
        heading: heading of the centre line at ``s``, radians in ``(-pi, pi]``.
        segment: index ``i`` of the centre-line segment ``i -> i+1`` the point projects onto.
    """

    s: FloatArray
    d: FloatArray
    heading: FloatArray
    segment: IntArray


def short_float(x: float) -> str:
    """Short text for a number that still reads back as exactly the same float.

    >>> short_float(0.52), short_float(80.0), short_float(0.1 + 0.2)
    ('0.52', '80', '0.30000000000000004')
    """
    short = f"{x:g}"
    return short if float(short) == x else repr(float(x))


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """z-component of the 2D cross product over the last axis."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _as_points(points: ArrayLike, what: str = "points") -> FloatArray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise TrackError(f"{what} must have shape (N, 2), got {arr.shape}")
    return arr


def _as_widths(width: ArrayLike, n: int, what: str) -> FloatArray:
    arr = np.asarray(width, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.full(n, float(arr))
    if arr.shape != (n,):
        raise TrackError(f"{what} must be a number or have one value per centre-line point ({n})")
    return arr


def signed_area(points: FloatArray) -> float:
    """Shoelace area of a closed polygon (N, 2): positive when anticlockwise."""
    x, y = points[:, 0], points[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def three_point_curvature(points: FloatArray) -> FloatArray:
    """(K,) signed 1/m: curvature of the circle through each point of a closed polyline (K, 2)
    and its two neighbours (Menger curvature; positive turns left, 0 where they are collinear)."""
    a, b, c = np.roll(points, 1, axis=0), points, np.roll(points, -1, axis=0)
    sides = (
        np.linalg.norm(b - a, axis=1)
        * np.linalg.norm(c - b, axis=1)
        * np.linalg.norm(a - c, axis=1)
    )
    return np.asarray(2.0 * _cross(b - a, c - a) / np.maximum(sides, 1e-300), dtype=np.float64)


@dataclass(frozen=True)
class Raceline:
    """An optional reference line of a track: where and how fast to drive (e.g. F1TENTH's
    optimised race lines).

    Attributes:
        points: (M, 2) m, in driving order, the loop open (the last point is not repeated).
        speed: (M,) m/s, the target speed at each point.
    """

    points: FloatArray
    speed: FloatArray

    def __post_init__(self) -> None:
        pts = np.asarray(self.points, dtype=np.float64)
        spd = np.asarray(self.speed, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 4:
            raise TrackError(f"a race line needs at least 4 points (M, 2), got {pts.shape}")
        if spd.shape != (len(pts),):
            raise TrackError(f"a race line needs one speed per point ({len(pts)})")
        if not (np.isfinite(pts).all() and np.isfinite(spd).all()) or (spd < 0).any():
            raise TrackError("race line has NaN, infinite or negative values")
        object.__setattr__(self, "points", pts)
        object.__setattr__(self, "speed", spd)

    def reversed(self) -> Raceline:
        """The same line driven the other way (first point kept first)."""
        order = np.roll(np.arange(len(self.points))[::-1], 1)
        return Raceline(self.points[order], self.speed[order])

    def scaled(self, factor: float) -> Raceline:
        """Coordinates scaled by ``factor``, speeds by its square root (Froude scaling: the
        same lateral acceleration ``v² / r`` in every bend)."""
        return Raceline(self.points * factor, self.speed * float(np.sqrt(factor)))


TIGHTEN_TOLERANCE = 1.1  # a fitted bend may be this much tighter than the file's points
TIGHTEN_RADIUS = 5.0  # m: only bends tighter than this are checked


def tightening(points: FloatArray, centre: FloatArray, curvature: FloatArray) -> FloatArray:
    """(N,) how many times tighter a fitted curve bends than its control points allow.

    The bound at each fitted point is the largest raw three-point curvature
    (:func:`three_point_curvature`) of the nearest control point and its two neighbours;
    points on bends wider than ``TIGHTEN_RADIUS`` score 0.
    """
    raw = np.abs(three_point_curvature(points))
    bound = np.maximum(np.maximum(raw, np.roll(raw, 1)), np.roll(raw, -1))
    from scipy.spatial import cKDTree  # noqa: PLC0415 - scipy loads on first use (CLI start-up)

    _, near = cKDTree(points).query(centre)
    kappa = np.abs(curvature)
    ratio = kappa / np.maximum(bound[np.asarray(near)], 1e-9)
    return np.asarray(np.where(kappa * TIGHTEN_RADIUS > 1.0, ratio, 0.0), dtype=np.float64)


def preload() -> None:
    """Import now the scipy parts this module loads on first use (about 0.7 s on 2 vCPUs):
    for a long-lived process whose first track should not wait for them."""
    import scipy.interpolate  # noqa: PLC0415
    import scipy.spatial  # noqa: F401, PLC0415


def smooth_closed_curve(
    points: FloatArray, widths: FloatArray, spacing: float, shape_preserving: bool = False
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Fit a periodic cubic spline through closed points and resample it at even arc length.

    Args:
        points: (K, 2) control points in order, m; the curve closes from the last to the first.
        widths: (K, 2) left/right half-widths at the control points, m (interpolated linearly).
        spacing: target distance between resampled points, m.
        shape_preserving: where the spline bends more than ``TIGHTEN_TOLERANCE`` times
            tighter than the points (:func:`tightening`), use the arc spline of
            :mod:`tracks.arcspline` instead when it tightens less.

    Returns:
        centre (N, 2) m, widths (N, 2) m, unit tangents (N, 2), curvature (N,) 1/m.
    """
    fitted = _cubic_closed_curve(points, widths, spacing)
    if shape_preserving:
        worst = float(tightening(points, fitted[0], fitted[3]).max())
        if worst > TIGHTEN_TOLERANCE:
            from tracks.arcspline import arc_spline_curve  # noqa: PLC0415 - rarely needed

            arcs = arc_spline_curve(points, widths, spacing)
            if float(tightening(points, arcs[0], arcs[3]).max()) < worst:
                return arcs
    return fitted


def _cubic_closed_curve(
    points: FloatArray, widths: FloatArray, spacing: float
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The periodic cubic spline of :func:`smooth_closed_curve`."""
    closed = np.vstack([points, points[:1]])
    chord = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    u = np.concatenate([[0.0], np.cumsum(chord)])
    from scipy.interpolate import CubicSpline  # noqa: PLC0415 - scipy loads on first use

    spline = CubicSpline(u, closed, bc_type="periodic")
    # Arc length by dense sampling; invert it to place points at even spacing.
    dense_u = np.linspace(0.0, u[-1], max(20 * len(points), int(40 * u[-1] / spacing)) + 1)
    dense = spline(dense_u)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))])
    n = max(8, round(arc[-1] / spacing))
    target = np.linspace(0.0, arc[-1], n, endpoint=False)
    u_even = np.interp(target, arc, dense_u)
    centre = spline(u_even)
    d1 = spline(u_even, 1)
    d2 = spline(u_even, 2)
    speed = np.linalg.norm(d1, axis=1)
    tangents = d1 / speed[:, None]
    curvature = _cross(d1, d2) / speed**3
    closed_w = np.vstack([widths, widths[:1]])
    w = np.stack([np.interp(u_even, u, closed_w[:, k]) for k in range(2)], axis=1)
    return centre, w, tangents, curvature


class Track:
    """A closed race track: smooth centre line, half-widths, start line and driving direction.

    Build one from control points (any orientation is fine: the order of the points is the
    driving direction). The points are smoothed with a periodic cubic spline and resampled at
    ``spacing`` metres, then rotated so that index 0 (``s = 0``) lies on the start line.

    Args:
        centre: (K, 2) control points of the centre line, m, in driving order.
        width_left: half-width to the left border, m; a number or (K,) values.
        width_right: half-width to the right border, m; a number or (K,) values.
        name: short identifier (file name of a built-in track).
        description: one line for people.
        start_s: where the start/finish line is, metres along the smoothed curve from the
            first control point.
        spacing: resampling distance, m. ``smooth=False`` keeps the points as given.
        smooth: fit and resample a spline (True) or use ``centre`` as the polyline itself.
        validate: run :func:`tracks.validation.validate_track` and raise :class:`TrackError`.
        raceline: an optional reference line (:class:`Raceline`), kept as given.
        waypoints: the source file's own centre-line points (K, 2) m, in driving order
            (DeepRacer's ``waypoints``); stored closed (first point repeated at the end).
        shape_preserving: do not let the fit bend much tighter than the points (see
            :func:`smooth_closed_curve`); importers of outside files set it.

    Attributes besides the arrays: ``raceline``, ``waypoints`` (None unless given),
    ``is_reversed`` (True for :meth:`reversed` tracks: driven against the direction their
    file gives) and ``import_notes`` (what an importer changed, one line each).
    """

    def __init__(
        self,
        centre: ArrayLike,
        width_left: ArrayLike,
        width_right: ArrayLike,
        *,
        name: str = "track",
        description: str = "",
        start_s: float = 0.0,
        spacing: float = DEFAULT_SPACING,
        smooth: bool = True,
        validate: bool = True,
        raceline: Raceline | None = None,
        waypoints: ArrayLike | None = None,
        shape_preserving: bool = False,
    ) -> None:
        from tracks.validation import check_raw_inputs, validate_track  # noqa: PLC0415 (cycle)

        pts = _as_points(centre, "centre line")
        if len(pts) > 1 and np.allclose(pts[0], pts[-1]):
            pts = pts[:-1]  # a closing duplicate of the first point
        wl = _as_widths(width_left, len(pts), "width_left")
        wr = _as_widths(width_right, len(pts), "width_right")
        check_raw_inputs(pts, wl, wr)
        self.name = name
        self.description = description
        self.raceline = raceline
        self.waypoints: FloatArray | None = None
        if waypoints is not None:
            wp = _as_points(waypoints, "waypoints")
            if len(wp) > 1 and np.allclose(wp[0], wp[-1]):
                wp = wp[:-1]
            self.waypoints = np.vstack([wp, wp[:1]])
        self.is_reversed = False
        self.import_notes: tuple[str, ...] = ()
        if smooth:
            c, w, tangents, curvature = smooth_closed_curve(
                pts, np.stack([wl, wr], axis=1), spacing, shape_preserving
            )
        else:
            c, w = pts, np.stack([wl, wr], axis=1)
            tangents, curvature = _polyline_tangents_curvature(c)
        seg = np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1)
        s0 = float(start_s) % float(seg.sum())
        shift = int(np.searchsorted(np.cumsum(seg), s0, side="right")) % len(c)
        self._set_arrays(
            np.roll(c, -shift, axis=0),
            np.roll(w, -shift, axis=0),
            np.roll(tangents, -shift, axis=0),
            np.roll(curvature, -shift),
        )
        if validate:
            validate_track(self)

    def _set_arrays(
        self, centre: FloatArray, widths: FloatArray, tangents: FloatArray, curvature: FloatArray
    ) -> None:
        self.centre: FloatArray = np.ascontiguousarray(centre, dtype=np.float64)
        self.width_left: FloatArray = np.ascontiguousarray(widths[:, 0], dtype=np.float64)
        self.width_right: FloatArray = np.ascontiguousarray(widths[:, 1], dtype=np.float64)
        self.tangents: FloatArray = np.ascontiguousarray(tangents, dtype=np.float64)
        self.curvature: FloatArray = np.ascontiguousarray(curvature, dtype=np.float64)
        for arr in (self.centre, self.width_left, self.width_right, self.tangents, self.curvature):
            arr.flags.writeable = False

    # ---- derived arrays -------------------------------------------------------------------

    @property
    def n_points(self) -> int:
        """Number of centre-line points N."""
        return len(self.centre)

    @cached_property
    def segment_lengths(self) -> FloatArray:
        """(N,) m: length of segment ``i -> i+1`` (the last closes the loop)."""
        return np.linalg.norm(np.roll(self.centre, -1, axis=0) - self.centre, axis=1)

    @cached_property
    def s(self) -> FloatArray:
        """(N,) m: progress at each centre-line point; ``s[0] == 0`` is the start line."""
        return np.concatenate([[0.0], np.cumsum(self.segment_lengths)[:-1]])

    @cached_property
    def length(self) -> float:
        """Lap length along the centre line, m."""
        return float(self.segment_lengths.sum())

    @cached_property
    def normals(self) -> FloatArray:
        """(N, 2) unit normals pointing to the left of the driving direction."""
        return np.stack([-self.tangents[:, 1], self.tangents[:, 0]], axis=1)

    @cached_property
    def headings(self) -> FloatArray:
        """(N,) rad: heading of the centre line at each point."""
        return np.arctan2(self.tangents[:, 1], self.tangents[:, 0])

    @cached_property
    def left_border(self) -> FloatArray:
        """(N, 2) m: the left road edge."""
        return self.centre + self.width_left[:, None] * self.normals

    @cached_property
    def right_border(self) -> FloatArray:
        """(N, 2) m: the right road edge."""
        return self.centre - self.width_right[:, None] * self.normals

    def on_road(
        self,
        points: ArrayLike,
        margin: float = 0.0,
        own_s: FloatArray | None = None,
        near: float = 0.0,
    ) -> NDArray[np.bool_]:
        """(M,) True where a point lies within ``margin`` m of the road surface.

        A local test, unlike :meth:`is_inside`: the road is the union of the cross-sections
        ``[-width_right, width_left]`` at every centre point, each a segment long, so a point
        near the centre of a tight bend is not mistaken for one on the road beside it.
        With ``own_s`` (M,) m, cross-sections within ``near`` m of it along the lap count
        without the margin (a point just outside its own edge is not "near the road").
        """
        from scipy.spatial import cKDTree  # noqa: PLC0415 - scipy loads on first use

        p = _as_points(points)
        half = 0.5 * float(self.segment_lengths.max()) + margin
        reach = float(max(self.width_left.max(), self.width_right.max())) + half + margin
        pairs = cKDTree(p).sparse_distance_matrix(self._tree, reach, output_type="ndarray")
        hit = np.zeros(len(p), dtype=bool)
        if len(pairs) == 0:
            return hit
        i, j = pairs["i"], pairs["j"]
        rel = p[i] - self.centre[j]
        along = np.einsum("mk,mk->m", rel, self.tangents[j])
        across = np.einsum("mk,mk->m", rel, self.normals[j])
        m = np.full(len(i), margin)
        if own_s is not None:
            m[np.abs(self.delta_s(self.s[j], np.asarray(own_s)[i])) < near] = 0.0
        inside = (
            (np.abs(along) <= 0.5 * float(self.segment_lengths.max()) + m)
            & (across <= self.width_left[j] + m)
            & (across >= -self.width_right[j] - m)
        )
        hit[i[inside]] = True
        return hit

    def wall_offsets(
        self, runoff: float, steps: int = 8, margin: float = 0.05
    ) -> tuple[FloatArray, FloatArray]:
        """Distances (N,) m from the centre line to walls ``runoff`` m outside each edge.

        Each side's run-off is shortened where the full one would put the wall on (or within
        ``margin`` m of) another part of the road, as in the narrow infield of a hairpin,
        or past the centre of a bend: the largest of ``steps`` even fractions of ``runoff``
        whose wall point, and every nearer one, is off the road.

        Returns:
            left, right offsets (N,) m, both positive.
        """
        fractions = np.linspace(0.0, 1.0, steps + 1)[1:]
        out = []
        for sign, width in ((1.0, self.width_left), (-1.0, self.width_right)):
            ok = np.ones(self.n_points, dtype=bool)
            run = np.zeros(self.n_points)
            limit = 0.98 / np.maximum(np.abs(self.curvature), 1e-9)
            inner = np.sign(self.curvature) == sign
            for f in fractions:
                d = width + f * runoff
                ok &= ~(inner & (d > limit))
                pts = self.centre + (sign * d)[:, None] * self.normals
                ok &= ~self.on_road(pts, margin, own_s=self.s, near=NEAR_SECTIONS)
                run = np.where(ok, f * runoff, run)
            out.append(width + run)
        return out[0], out[1]

    @cached_property
    def width(self) -> FloatArray:
        """(N,) m: full road width."""
        return self.width_left + self.width_right

    @cached_property
    def orientation(self) -> Literal["ccw", "cw"]:
        """Direction of travel seen from above: anticlockwise or clockwise."""
        return "ccw" if signed_area(self.centre) > 0 else "cw"

    @cached_property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) m of both borders."""
        both = np.vstack([self.left_border, self.right_border])
        lo, hi = both.min(axis=0), both.max(axis=0)
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])

    @cached_property
    def _tree(self) -> cKDTree:
        from scipy.spatial import cKDTree  # noqa: PLC0415 - scipy loads on first use

        # Exact either way; on a centre line (points along a curve) queried from a whole grid,
        # as the batched simulator's maps do, leaves of 32 split at the midpoint without
        # shrinking to the data answer k = 2 queries 1.5-1.7x faster than scipy's defaults
        # (bench/map_build.py).
        return cKDTree(self.centre, leafsize=32, balanced_tree=False, compact_nodes=False)

    def __repr__(self) -> str:
        return (
            f"Track({self.name!r}, length={self.length:.1f} m, points={self.n_points}, "
            f"width={self.width.min():.2f}-{self.width.max():.2f} m, {self.orientation})"
        )

    # ---- progress arithmetic --------------------------------------------------------------

    def wrap_s(self, s: ArrayLike) -> FloatArray:
        """Progress folded into ``[0, length)``, m."""
        return np.mod(np.asarray(s, dtype=np.float64), self.length)

    def delta_s(self, s_to: ArrayLike, s_from: ArrayLike) -> FloatArray:
        """Signed shortest progress from ``s_from`` to ``s_to``, m in ``[-L/2, L/2)``."""
        half = 0.5 * self.length
        diff = np.asarray(s_to, dtype=np.float64) - np.asarray(s_from, dtype=np.float64)
        return np.mod(diff + half, self.length) - half

    def _locate(self, s: ArrayLike) -> tuple[IntArray, FloatArray]:
        """Segment index and fraction ``t`` in [0, 1) for progress values."""
        sw = self.wrap_s(s)
        # No clamp needed: ``sw`` lies in [0, L] (or is NaN, sorted last) and ``s`` starts at
        # 0, so the right-side insertion index is 1..N.
        i = self.s.searchsorted(sw, side="right") - 1
        t = (sw - self.s[i]) / self.segment_lengths[i]
        return i.astype(np.int64, copy=False), t

    def widths_at(self, s: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Left and right half-widths at progress ``s`` (linear between points), m."""
        if (  # the env's cars every step
            isinstance(s, np.ndarray)
            and s.dtype == np.float64
            and s.ndim == 1
            and len(s) <= _PROJECT_FEW
        ):
            return self._widths_few(s.tolist())
        i, t = self._locate(s)
        j = (i + 1) % self.n_points
        left = (1 - t) * self.width_left[i] + t * self.width_left[j]
        right = (1 - t) * self.width_right[i] + t * self.width_right[j]
        return left, right

    def _widths_few(self, values: list[float]) -> tuple[FloatArray, FloatArray]:
        """:meth:`widths_at` of a few progress values in Python floats: the same operations
        (``%`` is ``np.mod``'s remainder, ``bisect_right`` the right-side
        ``searchsorted``), so the same bits, without ~15 numpy calls."""
        starts, lengths = self._seg_rows[:2]
        left_w, right_w = self._width_rows
        n, length = self.n_points, self.length
        left: list[float] = []
        right: list[float] = []
        for value in values:
            sw = value % length
            i = bisect_right(starts, sw) - 1
            t = (sw - starts[i]) / lengths[i]
            j = i + 1 if i + 1 < n else 0
            left.append((1 - t) * left_w[i] + t * left_w[j])
            right.append((1 - t) * right_w[i] + t * right_w[j])
        return np.array(left), np.array(right)

    @cached_property
    def _width_rows(self) -> tuple[list[float], list[float]]:
        """The half-widths as Python lists (for :meth:`_widths_few`)."""
        return self.width_left.tolist(), self.width_right.tolist()

    def heading_at(self, s: ArrayLike) -> FloatArray:
        """Heading of the centre line at progress ``s``, rad."""
        i, t = self._locate(s)
        tan = (1 - t)[..., None] * self.tangents[i] + t[..., None] * self.tangents[
            (i + 1) % self.n_points
        ]
        return np.arctan2(tan[..., 1], tan[..., 0])

    def curvature_at(self, s: ArrayLike) -> FloatArray:
        """Signed curvature at progress ``s``, 1/m (positive turns left)."""
        i, t = self._locate(s)
        return (1 - t) * self.curvature[i] + t * self.curvature[(i + 1) % self.n_points]

    # ---- Cartesian <-> Frenet -------------------------------------------------------------

    def to_cartesian(self, frenet: ArrayLike) -> FloatArray:
        """Frenet (M, 2) [s m, d m] → Cartesian (M, 2) [x m, y m]; exact inverse of ``project``."""
        f = _as_points(frenet, "frenet coordinates")
        i, t = self._locate(f[:, 0])
        tt = t[:, None]
        # take(axis=0): fancy indexing's rows, at a fraction of its cost on a few points.
        base = self.centre.take(i, axis=0) + tt * self._centre_steps.take(i, axis=0)
        normal = self.normals.take(i, axis=0) + tt * self._normal_steps.take(i, axis=0)
        return base + f[:, 1:2] * normal

    @cached_property
    def _frame_table(self) -> FloatArray:
        """Per-segment constants of the projection quadratic, (10, N): one gather fetches all
        of a candidate's.

        Rows: ``cx, cy`` segment start; ``nx, ny`` start normal; ``ex, ey`` segment vector;
        ``dnx, dny`` normal change along the segment; ``qa = -e × dn``; ``en = e × n0``.
        """
        c, nrm = self.centre, self.normals
        e = np.roll(c, -1, axis=0) - c
        dn = np.roll(nrm, -1, axis=0) - nrm
        cols = (c[:, 0], c[:, 1], nrm[:, 0], nrm[:, 1], e[:, 0], e[:, 1], dn[:, 0], dn[:, 1])
        return np.stack([*cols, -_cross(e, dn), _cross(e, nrm)])

    @cached_property
    def _centre_steps(self) -> FloatArray:
        """(N, 2) m: segment vectors ``centre[i+1] - centre[i]`` (the last closes the loop)."""
        return np.roll(self.centre, -1, axis=0) - self.centre

    @cached_property
    def _normal_steps(self) -> FloatArray:
        """(N, 2) change of the unit normal along each segment ``i -> i+1``."""
        return np.roll(self.normals, -1, axis=0) - self.normals

    @cached_property
    def _tangent_steps(self) -> FloatArray:
        """(N, 2) change of the unit tangent along each segment ``i -> i+1``."""
        return np.roll(self.tangents, -1, axis=0) - self.tangents

    @cached_property
    def _near_grid(self) -> _NearGrid:
        """Candidate nearest vertices per cell of a square grid around the centre line.

        For a cell with centre q and half-diagonal r, any point p in it has its second
        nearest vertex within ``D2(q) + r`` (``D2``: the second-nearest distance), so both
        of its nearest vertices lie within ``D2(q) + 2r`` of q: those are the cell's
        candidates (plus a margin). Cells whose candidates reach beyond ``_NEAR_REACH`` are
        left out (None: the k-d tree answers there).
        """
        h = _NEAR_CELL
        x0, y0 = self.centre.min(axis=0) - _NEAR_REACH
        x1, y1 = self.centre.max(axis=0) + _NEAR_REACH
        nx, ny = math.ceil((x1 - x0) / h), math.ceil((y1 - y0) / h)
        ix, iy = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
        centres = np.column_stack([x0 + h * (ix.ravel() + 0.5), y0 + h * (iy.ravel() + 0.5)])
        second = self._tree.query(centres, k=2)[0][:, 1]
        radius = second + h * math.sqrt(2.0) + _NEAR_MARGIN
        used = np.flatnonzero(radius <= _NEAR_REACH)
        cells: list[tuple[int, int] | None] = [None] * (nx * ny)
        flat: list[int] = []
        ids = list(range(self.n_points))  # one int object per vertex, shared by the cells
        near = self._tree.query_ball_point(centres[used], radius[used])
        for cell, members in zip(used.tolist(), near, strict=True):
            cells[cell] = (len(flat), len(flat) + len(members))
            flat.extend(ids[v] for v in members)
        return _NearGrid(
            x0=float(x0),
            y0=float(y0),
            nx=nx,
            ny=ny,
            cells=cells,
            flat=flat,
            xs=self.centre[:, 0].tolist(),
            ys=self.centre[:, 1].tolist(),
        )

    def _nearest_two(self, p: FloatArray) -> list[list[int]]:
        """The k-d tree's ``query(p, k=2)`` indices (M, 2) for a few points, nearest first.

        From :attr:`_near_grid` where its answer is certain (distinct distances, every
        candidate's squared distance apart by far more than rounding), else from the tree.
        """
        grid = self._near_grid
        x0, y0, nx, ny, cells, flat = grid.x0, grid.y0, grid.nx, grid.ny, grid.cells, grid.flat
        xs, ys, inv, inf = grid.xs, grid.ys, 1.0 / _NEAR_CELL, math.inf
        out: list[list[int]] = []
        missing: list[int] = []
        for k, (px, py) in enumerate(p.tolist()):
            fx, fy = (px - x0) * inv, (py - y0) * inv
            span = None
            if 0.0 <= fx < nx and 0.0 <= fy < ny:  # False for NaN too
                span = cells[int(fx) * ny + int(fy)]
            if span is None:
                missing.append(k)
                out.append([])
                continue
            d1 = d2 = d3 = inf
            i1 = i2 = -1
            for v in flat[span[0] : span[1]]:
                dx, dy = px - xs[v], py - ys[v]
                d = dx * dx + dy * dy
                if d < d2:
                    if d < d1:
                        d1, d2, d3, i1, i2 = d, d1, d2, v, i1
                    else:
                        d2, d3, i2 = d, d2, v
                elif d < d3:
                    d3 = d
            gap = 1e-9 * d3 + 1e-300
            if i2 < 0 or not (d2 - d1 > gap and d3 - d2 > gap):  # a (near) tie: the tree
                missing.append(k)
            out.append([i1, i2])
        if missing:
            _, nearest = self._tree.query(p[missing], k=2)
            for k, pair in zip(missing, np.reshape(nearest, (-1, 2)).tolist(), strict=True):
                out[k] = pair
        return out

    @cached_property
    def _frame_rows(self) -> list[tuple[float, ...]]:
        """:attr:`_frame_table` as one tuple of 10 Python floats per segment (N,)."""
        return [tuple(row) for row in self._frame_table.T.tolist()]

    def project(self, points: ArrayLike) -> Projection:
        """Project (M, 2) points [x m, y m] onto the centre line.

        Vectorised over points: candidate segments are those next to the two nearest
        centre-line vertices; on each, the interpolated-normal frame gives a quadratic in the
        segment fraction ``t``; the valid solution with the smallest ``|d|`` wins. Points are
        processed in blocks of ``_PROJECT_BLOCK`` so the temporaries stay in the CPU cache.
        """
        p = _as_points(points)
        m = len(p)
        if m <= _PROJECT_FEW:  # the env's cars every step
            return self._project_few(p)
        if m <= _PROJECT_BLOCK:  # one block: no copies
            seg, tb, db = self._project_block(p)
        else:
            seg = np.empty(m, dtype=np.int64)
            tb = np.empty(m)
            db = np.empty(m)
            for lo in range(0, m, _PROJECT_BLOCK):
                hi = min(lo + _PROJECT_BLOCK, m)
                seg[lo:hi], tb[lo:hi], db[lo:hi] = self._project_block(p[lo:hi])
        return self._projection(seg, tb, db)

    def _projection(self, seg: IntArray, tb: FloatArray, db: FloatArray) -> Projection:
        """The projection onto segments ``seg`` (M,) at fractions ``tb`` with offsets ``db``."""
        s = self.wrap_s(self.s[seg] + tb * self.segment_lengths[seg])
        tan = self.tangents.take(seg, axis=0) + tb[:, None] * self._tangent_steps.take(seg, axis=0)
        heading = np.arctan2(tan[:, 1], tan[:, 0])
        return Projection(s=s, d=db, heading=heading, segment=seg)

    def _project_block(self, p: FloatArray) -> tuple[IntArray, FloatArray, FloatArray]:
        """Segment index (M,), fraction ``t`` (M,) in [0, 1] and offset ``d`` (M,) m of points.

        Scalar (x, y) arrays of shape (M, C) over C candidate segments rather than (M, C, 2)
        stacks: no strided last-axis access, and most operations run in place.
        """
        n = self.n_points
        k = min(2, n)
        _, nearest = self._tree.query(p, k=k)
        nearest = np.asarray(nearest).reshape(len(p), k)
        cand = np.concatenate([nearest, nearest - 1], axis=1) % n  # (M, 2k) segment indices
        cx, cy, nx, ny, ex, ey, dnx, dny, qa, en = self._frame_table[:, cand]
        qx = p[:, :1] - cx  # q = p - c0, (M, C)
        qy = p[:, 1:] - cy
        c = qx * ny
        c -= qy * nx  # q × n0
        b = qx * dny
        b -= qy * dnx
        b -= en  # q × dn - e × n0
        disc = b * b
        disc -= 4.0 * qa * c
        root = np.sqrt(np.maximum(disc, 0.0))
        # Root that tends to -c/b as a -> 0 (the other one lies beyond the curvature centre).
        np.negative(root, out=root, where=b < 0)
        denom = np.negative(b, out=b)
        denom -= root
        # 0 where the denominator vanishes (computed only elsewhere: no 0 / 0 warnings).
        t = np.divide(2.0 * c, denom, out=np.zeros(c.shape), where=np.abs(denom) > 1e-300)
        ntx = t * dnx
        ntx += nx  # nt = n0 + t dn
        nty = t * dny
        nty += ny
        qx -= t * ex  # q - t e
        qy -= t * ey
        d = qx * ntx
        d += qy * nty
        ntx *= ntx
        nty *= nty
        ntx += nty
        d /= ntx
        valid = (disc >= 0) & (t >= -1e-9) & (t <= 1 + 1e-9)
        cost = np.where(valid, np.abs(d), np.inf)
        rows = np.arange(len(p))
        best = cost.argmin(axis=1)  # the method: no dispatch cost (a hot path)
        seg = cand[rows, best]
        tb = np.minimum(np.maximum(t[rows, best], 0.0), 1.0)  # np.clip's values, cheaper
        db = d[rows, best]
        # Far off the road on the inside of a bend no frame solution exists: use the vertex.
        none = ~np.isfinite(cost[rows, best])
        if none.any():
            v = nearest[none, 0]
            seg[none] = v
            tb[none] = 0.0
            db[none] = np.einsum("mk,mk->m", p[none] - self.centre[v], self.normals[v])
        return seg, tb, db

    def _project_few(self, p: FloatArray) -> Projection:
        """:meth:`project` of a few points, in Python floats.

        The same candidates, the same operations in the same order (IEEE ``+ - * / sqrt``
        round alike in numpy and Python, and Python's float ``%`` is ``np.mod``'s
        remainder) and the same first-minimum choice give the very same bits (a test holds
        them equal); only the heading's ``arctan2`` stays numpy's. What the block handles by
        its special rules — a point with no frame solution, a degenerate frame, a NaN —
        sends the whole call to the block.
        """
        n = self.n_points
        if n < 3:
            return self._projection(*self._project_block(p))
        rows, sqrt, inf = self._frame_rows, math.sqrt, math.inf
        seg: list[int] = []
        tb: list[float] = []
        db: list[float] = []
        points = zip(p.tolist(), self._nearest_two(p), strict=True)
        for (px, py), (near1, near2) in points:
            best, best_cost, best_t, best_d = -1, inf, 0.0, 0.0
            # The block's candidates in its order (segments v1, v2, v1 - 1, v2 - 1) without
            # repeats: one is usually listed twice, and a repeat can never be a strictly
            # smaller minimum.
            v1, v2 = near1 % n, near2 % n
            cands: tuple[int, ...] = (v1, v2) if v1 != v2 else (v1,)
            for v in ((v1 - 1) % n, (v2 - 1) % n):
                if v not in cands:
                    cands += (v,)
            for j in cands:
                cx, cy, nx, ny, ex, ey, dnx, dny, qa, en = rows[j]
                qx = px - cx
                qy = py - cy
                c = qx * ny - qy * nx
                b = qx * dny - qy * dnx - en
                disc = b * b - 4.0 * qa * c
                # A NaN disc makes the candidate invalid below, whatever its root.
                root = sqrt(disc if disc >= 0.0 else 0.0)
                if b < 0:
                    root = -root
                denom = -b - root
                t = 2.0 * c / denom if abs(denom) > 1e-300 else 0.0
                ntx = t * dnx + nx
                nty = t * dny + ny
                norm2 = ntx * ntx + nty * nty
                if norm2 == 0.0:  # a degenerate frame (x / 0)
                    return self._projection(*self._project_block(p))
                d = ((qx - t * ex) * ntx + (qy - t * ey) * nty) / norm2
                cost = abs(d) if disc >= 0 and -1e-9 <= t <= 1 + 1e-9 else inf
                if not cost <= inf:  # NaN, which the block's argmin would pick
                    return self._projection(*self._project_block(p))
                if cost < best_cost:  # strictly: the first minimum, as argmin
                    best, best_cost, best_t, best_d = j, cost, t, d
            if best < 0:  # no frame solution: the block's nearest-vertex rule
                return self._projection(*self._project_block(p))
            seg.append(best)
            tb.append(min(max(best_t, 0.0), 1.0))
            db.append(best_d)
        # :meth:`_projection`'s arithmetic per point: s wrapped into the lap, the tangent
        # interpolated along the segment.
        starts, lengths, tangents, steps = self._seg_rows
        length = self.length
        s_out: list[float] = []
        tan_x: list[float] = []
        tan_y: list[float] = []
        for j, t in zip(seg, tb, strict=True):
            s_out.append((starts[j] + t * lengths[j]) % length)
            (tx, ty), (sx, sy) = tangents[j], steps[j]
            tan_x.append(tx + t * sx)
            tan_y.append(ty + t * sy)
        return Projection(
            s=np.array(s_out),
            d=np.array(db),
            heading=np.arctan2(np.array(tan_y), np.array(tan_x)),
            segment=np.array(seg, dtype=np.int64),
        )

    @cached_property
    def _seg_rows(
        self,
    ) -> tuple[list[float], list[float], list[list[float]], list[list[float]]]:
        """Per segment as Python lists: start s m, length m, unit tangent and its change
        along the segment (for :meth:`_project_few` and :meth:`widths_at`)."""
        return (
            self.s.tolist(),
            self.segment_lengths.tolist(),
            self.tangents.tolist(),
            self._tangent_steps.tolist(),
        )

    def to_frenet(self, points: ArrayLike) -> FloatArray:
        """Cartesian (M, 2) [x m, y m] → Frenet (M, 2) [s m, d m]."""
        proj = self.project(points)
        return np.stack([proj.s, proj.d], axis=1)

    def signed_distance(self, points: ArrayLike) -> FloatArray:
        """(M,) m to the nearest road edge, measured across the road: negative on the road."""
        proj = self.project(points)
        left, right = self.widths_at(proj.s)
        return np.maximum(proj.d - left, -proj.d - right)

    def is_inside(self, points: ArrayLike) -> NDArray[np.bool_]:
        """(M,) True where a point lies on the road surface."""
        return self.signed_distance(points) <= 0.0

    # ---- race furniture -------------------------------------------------------------------

    def checkpoint_s(self, n: int = DEFAULT_CHECKPOINTS) -> FloatArray:
        """(n,) m: progress of the ordered lap gates; gate 0 is the start/finish line."""
        if n < 2:
            raise TrackError("a lap needs at least 2 checkpoints")
        return np.arange(n, dtype=np.float64) * (self.length / n)

    def gates(self, s: ArrayLike) -> FloatArray:
        """(K, 2, 2) m: the left and right ends of a line across the road at each ``s``."""
        sv = np.atleast_1d(np.asarray(s, dtype=np.float64))
        left, right = self.widths_at(sv)
        ends_l = self.to_cartesian(np.stack([sv, left], axis=1))
        ends_r = self.to_cartesian(np.stack([sv, -right], axis=1))
        return np.stack([ends_l, ends_r], axis=1)

    def start_grid(
        self,
        n_cars: int,
        *,
        gap: float = 2 * CAR_LENGTH,
        setback: float = CAR_LENGTH,
        offset: float = 0.0,
    ) -> FloatArray:
        """Staggered two-wide start grid behind the start line.

        Car 0 (pole) sits on the left half of the road with its front ``setback/2`` m behind
        the line; each next car is ``gap/2`` m further back on the other side, so cars in the
        same column are ``gap`` m (about two car lengths) apart. ``offset`` moves the whole
        grid that many metres along the lap (a start line elsewhere, as DeepRacer trains).

        Returns:
            (n_cars, 3) poses [x m, y m, yaw rad], pole first.
        """
        k = np.arange(n_cars, dtype=np.float64)
        s = offset - (setback + k * 0.5 * gap)
        left, right = self.widths_at(s)
        middle = 0.5 * (left - right)
        quarter = 0.25 * (left + right)
        d = middle + np.where(k % 2 == 0, quarter, -quarter)
        xy = self.to_cartesian(np.stack([self.wrap_s(s), d], axis=1))
        return np.column_stack([xy, self.heading_at(s)])

    @cached_property
    def n_corners(self) -> int:
        """Number of corners: bends tighter than a 12 m radius that turn at least 30 degrees."""
        tight = np.abs(self.curvature) > CORNER_CURVATURE
        if tight.all() or not tight.any():
            return int(tight.all())
        start = int(np.argmin(tight))  # begin scanning on a straight so runs do not wrap
        order = np.roll(np.arange(self.n_points), -start)
        corners, turn = 0, 0.0
        for i in order:
            if tight[i]:
                turn += abs(self.curvature[i]) * self.segment_lengths[i]
            elif turn > 0.0:
                corners += int(turn >= CORNER_MIN_TURN)
                turn = 0.0
        return corners + int(turn >= CORNER_MIN_TURN)

    def with_widths(self, width_left: ArrayLike, width_right: ArrayLike) -> Track:
        """The same centre line with new half-widths (N,) m per point; not validated."""
        out = Track.__new__(Track)
        out.__dict__.update(
            {k: v for k, v in self.__dict__.items() if k not in _DERIVED_FROM_WIDTHS}
        )
        n = self.n_points
        w = np.stack(
            [
                _as_widths(width_left, n, "width_left"),
                _as_widths(width_right, n, "width_right"),
            ],
            axis=1,
        )
        out._set_arrays(self.centre, w, self.tangents, self.curvature)
        return out

    def scaled(self, factor: float) -> Track:
        """The same track with every length multiplied by ``factor``, validated.

        Centre line, half-widths, waypoints and race line scale (race-line speeds by
        ``sqrt(factor)``, :meth:`Raceline.scaled`); headings stay, curvature divides by
        ``factor``. The point count stays too, so the spacing scales with the track. The name
        gets the suffix ``@<factor>``, which :func:`tracks.load_track` reads back
        (``load_track("oval@0.52")``): a track for a car ``factor`` times the size, e.g. the
        1/18 DeepRacer car (0.26 m long) on roads drawn for the 0.5 m F1TENTH car.

        Raises:
            TrackError: ``factor`` is not a positive finite number, or the scaled track
                fails :func:`tracks.validation.validate_track` (shorter than 5 m, say) or has
                implausible half-widths.

        >>> from tracks import load_track
        >>> oval = load_track("oval")
        >>> small = oval.scaled(0.52)
        >>> small.name, round(small.length / oval.length, 6)
        ('oval@0.52', 0.52)
        """
        from tracks.validation import check_raw_inputs, validate_track  # noqa: PLC0415 (cycle)

        try:
            f = float(factor)
        except (TypeError, ValueError):
            f = math.nan
        if not (math.isfinite(f) and f > 0.0):
            raise TrackError(f"a track scale must be a positive number, got {factor!r}")
        out = Track.__new__(Track)
        out.name = f"{self.name}@{short_float(f)}"
        out.description = self.description
        out.raceline = self.raceline.scaled(f) if self.raceline is not None else None
        out.waypoints = self.waypoints * f if self.waypoints is not None else None
        out.is_reversed = self.is_reversed
        out.import_notes = self.import_notes
        widths = np.stack([self.width_left, self.width_right], axis=1) * f
        out._set_arrays(self.centre * f, widths, self.tangents, self.curvature / f)
        try:
            check_raw_inputs(out.centre, out.width_left, out.width_right)
            validate_track(out)
        except TrackError as err:
            raise TrackError(f"{self.name} scaled by {short_float(f)}: {err}") from None
        return out

    def reversed(self) -> Track:
        """The same road driven the other way: start line kept, left and right swapped."""
        order = np.roll(np.arange(self.n_points)[::-1], 1)  # index 0 stays the start line
        rev = Track.__new__(Track)
        rev.name = f"{self.name}-reversed"
        rev.description = self.description
        rev.raceline = self.raceline.reversed() if self.raceline is not None else None
        rev.waypoints = self.waypoints[::-1].copy() if self.waypoints is not None else None
        rev.is_reversed = not self.is_reversed
        rev.import_notes = self.import_notes
        rev._set_arrays(
            self.centre[order],
            np.stack([self.width_right[order], self.width_left[order]], axis=1),
            -self.tangents[order],
            -self.curvature[order],
        )
        return rev


def _control_interval(track: Track, points: FloatArray) -> IntArray:
    """(N,) index ``m`` of the control segment ``points[m] -> points[m+1]`` that each of the
    track's points lies on (control points (K, 2) m in driving order, on the centre line)."""
    s_ctrl = track.project(points).s
    rel = np.mod(s_ctrl - s_ctrl[0], track.length)
    rel = np.maximum.accumulate(rel)  # tolerate a tiny backwards step from projection noise
    here = np.mod(track.s - s_ctrl[0], track.length)
    m = np.searchsorted(rel, here, side="right") - 1
    return np.clip(m, 0, len(points) - 1).astype(np.int64)


def border_widths(
    track: Track, points: FloatArray, borders: tuple[FloatArray, FloatArray], reach: int = 3
) -> tuple[FloatArray, FloatArray]:
    """Half-widths (N,) m from the track's centre points to a file's own border polylines.

    Args:
        track: the smoothed track.
        points: (K, 2) m the file's centre points the track was fitted through.
        borders: left and right border points (K, 2) m, one per centre point, closed loops.
        reach: border segments searched on each side of the matching centre segment.

    Returns:
        left, right (N,): the distance from each centre point to the nearest point of that
        border polyline near it along the lap.
    """
    k = len(points)
    m = _control_interval(track, points)
    idx = (m[:, None] + np.arange(-reach, reach + 1)[None, :]) % k  # (N, C) segments
    out = []
    for border in borders:
        a, b = border[idx], border[(idx + 1) % k]  # (N, C, 2)
        ab = b - a
        ap = track.centre[:, None, :] - a
        t = np.clip(
            np.einsum("ncj,ncj->nc", ap, ab) / np.maximum(np.einsum("ncj,ncj->nc", ab, ab), 1e-18),
            0.0,
            1.0,
        )
        gap = np.linalg.norm(ap - t[..., None] * ab, axis=-1)
        out.append(gap.min(axis=1))
    return out[0], out[1]


def tightened_bends(track: Track, points: FloatArray) -> list[str]:
    """Where the track bends tighter than its control points (K, 2) allow (:func:`tightening`
    over ``TIGHTEN_TOLERANCE``): one line naming the worst place and both radii, or none."""
    ratio = tightening(points, track.centre, track.curvature)
    k = int(np.argmax(ratio))
    if ratio[k] <= TIGHTEN_TOLERANCE:
        return []
    radius = 1.0 / abs(float(track.curvature[k]))
    return [
        f"the centre line bends tighter than the file's points at "
        f"{int((ratio > TIGHTEN_TOLERANCE).sum())} point(s); worst at s={track.s[k]:.1f} m: "
        f"radius {radius:.2f} m where the points give {radius * ratio[k]:.2f} m"
    ]


NEAR_SECTIONS = 0.5  # m along the lap: a wall's own stretch of road, checked without margin

# Cached properties that depend on the widths (dropped by :meth:`Track.with_widths`).
_DERIVED_FROM_WIDTHS = ("left_border", "right_border", "width", "bounds")


def _polyline_tangents_curvature(c: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Unit tangents (central differences) and curvature (turning angle / length) of a polyline."""
    fwd = np.roll(c, -1, axis=0) - c
    back = c - np.roll(c, 1, axis=0)
    tan = fwd / np.linalg.norm(fwd, axis=1)[:, None] + back / np.linalg.norm(back, axis=1)[:, None]
    tan /= np.linalg.norm(tan, axis=1)[:, None]
    turn = np.arctan2(_cross(back, fwd), np.einsum("ij,ij->i", back, fwd))
    ds = 0.5 * (np.linalg.norm(fwd, axis=1) + np.linalg.norm(back, axis=1))
    return tan, turn / ds
