"""Checks that a track is a usable closed road, each failing with a :class:`TrackError`
whose message says what is wrong and where."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree

from tracks.errors import TrackError

if TYPE_CHECKING:
    from tracks.geometry import FloatArray, Track

MIN_POINTS = 4  # a periodic cubic spline needs at least 4 distinct control points
MIN_LENGTH = 5.0  # m: shorter than this is not a race track for a 0.5 m car
MAX_WIDTH = 50.0  # m: half-widths beyond this are a unit mistake (mm? cm?)


def check_raw_inputs(points: FloatArray, width_left: FloatArray, width_right: FloatArray) -> None:
    """Reject control points and widths that no smoothing could turn into a track."""
    if len(points) < MIN_POINTS:
        raise TrackError(f"too few centre-line points: {len(points)} (need at least {MIN_POINTS})")
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise TrackError(f"centre line has NaN or infinite coordinates at point {_first(bad)}")
    for side, w in (("left", width_left), ("right", width_right)):
        if not np.isfinite(w).all():
            raise TrackError(f"{side} width is NaN or infinite at point {_first(~np.isfinite(w))}")
        if (w <= 0).any():
            i = _first(w <= 0)
            raise TrackError(f"{side} width must be positive, got {w[i]:g} m at point {i}")
        if (w > MAX_WIDTH).any():
            i = _first(w > MAX_WIDTH)
            raise TrackError(
                f"{side} width {w[i]:g} m at point {i} is implausible (over {MAX_WIDTH:g} m)"
            )
    steps = np.linalg.norm(np.diff(np.vstack([points, points[:1]]), axis=0), axis=1)
    if (steps < 1e-9).any():
        raise TrackError(f"centre line repeats point {_first(steps < 1e-9)}")
    if steps.sum() < MIN_LENGTH:
        raise TrackError(f"track is only {steps.sum():.2f} m long (need at least {MIN_LENGTH} m)")


def _first(mask: ArrayLike) -> int:
    return int(np.flatnonzero(mask)[0])


def segment_crossings(points: FloatArray) -> list[tuple[int, int]]:
    """Pairs (i, j) of non-adjacent segments of a closed polyline (N, 2) that intersect."""
    n = len(points)
    a, b = points, np.roll(points, -1, axis=0)
    mid = 0.5 * (a + b)
    reach = float(np.linalg.norm(b - a, axis=1).max())
    pairs = cKDTree(mid).query_pairs(r=reach, output_type="ndarray")
    if len(pairs) == 0:
        return []
    i, j = pairs[:, 0], pairs[:, 1]
    adjacent = (np.abs(i - j) <= 1) | (np.abs(i - j) == n - 1)
    i, j = i[~adjacent], j[~adjacent]

    def side(p: FloatArray, q: FloatArray, r: FloatArray) -> FloatArray:
        return (q[:, 0] - p[:, 0]) * (r[:, 1] - p[:, 1]) - (q[:, 1] - p[:, 1]) * (r[:, 0] - p[:, 0])

    d1 = side(a[i], b[i], a[j])
    d2 = side(a[i], b[i], b[j])
    d3 = side(a[j], b[j], a[i])
    d4 = side(a[j], b[j], b[i])
    hit = (d1 * d2 <= 0) & (d3 * d4 <= 0)
    return [(int(x), int(y)) for x, y in zip(i[hit], j[hit], strict=True)]


def validate_track(track: Track) -> None:
    """Check a built track: long enough, centre line simple, borders do not fold or touch.

    Raises:
        TrackError: naming the first problem found and where (progress ``s`` in metres).
    """
    if track.length < MIN_LENGTH:
        raise TrackError(f"track is only {track.length:.2f} m long (need at least {MIN_LENGTH} m)")
    crossings = segment_crossings(track.centre)
    if crossings:
        i, j = crossings[0]
        raise TrackError(
            f"centre line intersects itself (near s={track.s[i]:.1f} m and s={track.s[j]:.1f} m)"
        )
    # A border folds over when the inner half-width exceeds the radius of curvature.
    inner = np.where(track.curvature > 0, track.width_left, track.width_right)
    fold = np.abs(track.curvature) * inner >= 1.0
    if fold.any():
        i = _first(fold)
        raise TrackError(
            f"bend at s={track.s[i]:.1f} m is too tight for its width: radius "
            f"{1 / abs(track.curvature[i]):.2f} m < inner half-width {inner[i]:.2f} m"
        )
    _check_clearance(track)


def _check_clearance(track: Track) -> None:
    """Parts of the road that are far apart along the lap must not overlap in the plane."""
    c = track.centre
    wmax = float(max(track.width_left.max(), track.width_right.max()))
    window = 4.0 * wmax + 1.0  # m along the lap inside which nearness is just the bend itself
    pairs = cKDTree(c).query_pairs(r=2.0 * wmax, output_type="ndarray")
    if len(pairs) == 0:
        return
    i, j = pairs[:, 0], pairs[:, 1]
    sep = np.abs(track.delta_s(track.s[j], track.s[i]))
    i, j = i[sep > window], j[sep > window]
    if len(i) == 0:
        return
    delta = c[j] - c[i]
    left_of_i = (track.tangents[i, 0] * delta[:, 1] - track.tangents[i, 1] * delta[:, 0]) > 0
    left_of_j = (track.tangents[j, 0] * -delta[:, 1] - track.tangents[j, 1] * -delta[:, 0]) > 0
    need = np.where(left_of_i, track.width_left[i], track.width_right[i]) + np.where(
        left_of_j, track.width_left[j], track.width_right[j]
    )
    overlap = np.linalg.norm(delta, axis=1) < need
    if overlap.any():
        k = _first(overlap)
        raise TrackError(
            "road overlaps itself (the surface near "
            f"s={track.s[i[k]]:.1f} m touches the surface near s={track.s[j[k]]:.1f} m)"
        )


def grid_fits(track: Track, n_cars: int, margin: float = 0.05) -> bool:
    """True when every car of an ``n_cars`` start grid lies on the road with ``margin`` m spare."""
    from tracks.geometry import CAR_LENGTH, CAR_WIDTH  # noqa: PLC0415 (geometry imports us)

    poses = track.start_grid(n_cars)
    hl, hw = 0.5 * CAR_LENGTH + margin, 0.5 * CAR_WIDTH + margin
    local = np.array([[hl, hw], [hl, -hw], [-hl, hw], [-hl, -hw]])
    cos, sin = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    rot = np.stack([np.stack([cos, -sin], -1), np.stack([sin, cos], -1)], -2)  # (n, 2, 2)
    corners = poses[:, None, :2] + np.einsum("nij,kj->nki", rot, local)
    return bool(track.is_inside(corners.reshape(-1, 2)).all())
