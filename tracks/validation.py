"""Checks that a track is a usable closed road, each failing with a :class:`TrackError`
whose message says what is wrong and where."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from tracks.errors import TrackError

if TYPE_CHECKING:
    from tracks.geometry import FloatArray, IntArray, Track

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
    from scipy.spatial import cKDTree  # noqa: PLC0415 - scipy loads on first use (CLI start-up)

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


def _near_pairs(
    track: Track, folds_back: bool = False
) -> tuple[IntArray, IntArray, FloatArray, FloatArray, FloatArray]:
    """Pairs of centre points far apart along the lap but near in the plane.

    ``folds_back`` also takes pairs closer along the lap whose road has turned back on
    itself between them (lap distance over ``FOLD_BACK`` times the distance in the plane),
    such as the two legs of a hairpin.

    Returns:
        ``i``, ``j`` (P,) point indices; ``gap`` (P,) m between them; ``side_i``, ``side_j``
        (P,) +1 where the other point lies to the left of that point's direction, -1 right.
    """
    c = track.centre
    wmax = float(max(track.width_left.max(), track.width_right.max()))
    window = 4.0 * wmax + 1.0  # m along the lap inside which nearness is just the bend itself
    from scipy.spatial import cKDTree  # noqa: PLC0415 - scipy loads on first use

    pairs = cKDTree(c).query_pairs(r=2.0 * wmax, output_type="ndarray")
    empty = np.zeros(0, dtype=np.int64)
    if len(pairs) == 0:
        return empty, empty, np.zeros(0), np.zeros(0), np.zeros(0)
    i, j = pairs[:, 0], pairs[:, 1]
    sep = np.abs(track.delta_s(track.s[j], track.s[i]))
    keep = sep > window
    if folds_back:
        keep |= sep > FOLD_BACK * np.linalg.norm(c[j] - c[i], axis=1)
    i, j = i[keep], j[keep]
    delta = c[j] - c[i]
    left_of_i = (track.tangents[i, 0] * delta[:, 1] - track.tangents[i, 1] * delta[:, 0]) > 0
    left_of_j = (track.tangents[j, 0] * -delta[:, 1] - track.tangents[j, 1] * -delta[:, 0]) > 0
    side_i = np.where(left_of_i, 1.0, -1.0)
    side_j = np.where(left_of_j, 1.0, -1.0)
    return i, j, np.linalg.norm(delta, axis=1), side_i, side_j


def _check_clearance(track: Track) -> None:
    """Parts of the road that are far apart along the lap must not overlap in the plane."""
    i, j, gap, side_i, side_j = _near_pairs(track)
    need = np.where(side_i > 0, track.width_left[i], track.width_right[i]) + np.where(
        side_j > 0, track.width_left[j], track.width_right[j]
    )
    overlap = gap < need
    if overlap.any():
        k = _first(overlap)
        raise TrackError(
            "road overlaps itself (the surface near "
            f"s={track.s[i[k]]:.1f} m touches the surface near s={track.s[j[k]]:.1f} m)"
        )


FOLD_FRACTION = 0.9  # a narrowed inner edge keeps 10 % of the bend's radius
FOLD_BACK = 1.7  # lap distance / plane distance past which two stretches face each other
# (a semicircle gives π/2 ≈ 1.57 between its ends: those are left to the fold rule)
OVERLAP_FRACTION = 0.45  # each of two facing roads keeps under half of the gap between them
TAPER = 0.3  # m of width change per m along the lap where a narrowed stretch begins and ends


def fit_widths(track: Track, max_width: float | None = None) -> tuple[Track, tuple[str, ...]]:
    """Narrow the half-widths locally so the road neither folds nor overlaps itself.

    Real track files often give a constant half-width (F1TENTH: 1.1 m) that is wider than
    the radius of their tightest bends. Rather than refuse them, the inner half-width is cut
    to ``FOLD_FRACTION`` of the bend's radius, facing stretches of road that would touch
    (across an infield, or the two legs of a hairpin) are cut to under half the gap between
    them, and every cut tapers in and out at ``TAPER`` m/m. Widths never grow.

    Args:
        track: a built track (its widths may fold; it need not be validated).
        max_width: also cap every half-width at this many metres.

    Returns:
        The track with fitted widths (not validated) and one note per narrowed stretch,
        saying where (progress ``s``), which side and by how much.
    """
    if max_width is not None:  # asked for: not reported as a narrowing
        track = track.with_widths(
            np.minimum(track.width_left, max_width), np.minimum(track.width_right, max_width)
        )
    kappa = track.curvature
    caps = np.stack([track.width_left.copy(), track.width_right.copy()], axis=1)  # (N, 2)
    radius = FOLD_FRACTION / np.maximum(np.abs(kappa), 1e-9)
    caps[:, 0] = np.where(kappa > 0, np.minimum(caps[:, 0], radius), caps[:, 0])
    caps[:, 1] = np.where(kappa < 0, np.minimum(caps[:, 1], radius), caps[:, 1])
    i, j, gap, side_i, side_j = _near_pairs(
        track.with_widths(caps[:, 0], caps[:, 1]), folds_back=True
    )
    col_i, col_j = (side_i < 0).astype(np.int64), (side_j < 0).astype(np.int64)
    need = caps[i, col_i] + caps[j, col_j]
    over = need > OVERLAP_FRACTION * 2 * gap
    if over.any():
        scale = np.ones(len(i))
        scale[over] = OVERLAP_FRACTION * 2 * gap[over] / need[over]
        np.minimum.at(caps, (i, col_i), caps[i, col_i] * scale)
        np.minimum.at(caps, (j, col_j), caps[j, col_j] * scale)
    fitted = np.stack([_taper(caps[:, k], track.s, track.length) for k in range(2)], axis=1)
    notes: list[str] = []
    for k, side in enumerate(("left", "right")):
        before = track.width_left if k == 0 else track.width_right
        notes += _narrowing_notes(track, side, before, fitted[:, k])
    return track.with_widths(fitted[:, 0], fitted[:, 1]), tuple(notes)


def _taper(caps: FloatArray, s: FloatArray, length: float) -> FloatArray:
    """The largest widths (N,) under ``caps`` that change by at most ``TAPER`` m per m.

    A lower envelope of cones ``caps[j] + TAPER * |s - s[j]|`` around the closed lap: two
    sweeps each way (twice round, so the loop's seam is covered).
    """
    n = len(caps)
    out = caps.copy()
    ds = np.diff(np.concatenate([s, [length]]))  # (N,) m from point k to k+1
    for _ in range(2):
        for k in range(1, n + 1):  # forward
            a, b = (k - 1) % n, k % n
            out[b] = min(out[b], out[a] + TAPER * ds[a])
        for k in range(n - 1, -1, -1):  # backward
            a, b = (k + 1) % n, k
            out[b] = min(out[b], out[a] + TAPER * ds[b])
    return out


NOTE_CUT = 0.005  # m: a stretch cut by less than this is counted, not listed (0.00 m)


def _narrowing_notes(
    track: Track, side: str, before: FloatArray, after: FloatArray, tol: float = 1e-3
) -> list[str]:
    """One line per contiguous stretch where a side was narrowed by more than ``tol`` m; the
    stretches whose largest cut is under :data:`NOTE_CUT` (dense, slightly noisy centre
    lines such as MapZoo's 0.1 m files give a few 1-4 mm cuts each) share one line."""
    cut = before - after > tol
    if not cut.any():
        return []
    if cut.all():
        runs = [np.arange(len(cut))]
    else:
        start = int(np.argmin(cut))  # begin on an uncut point so no run wraps the seam
        order = np.roll(np.arange(len(cut)), -start)
        flags = cut[order]
        edges = np.flatnonzero(np.diff(np.concatenate([[0], flags.astype(np.int8), [0]])))
        runs = [order[a:b] for a, b in zip(edges[::2], edges[1::2], strict=True)]
    notes = []
    small = 0
    for run in runs:
        k = run[int(np.argmax(before[run] - after[run]))]
        if before[k] - after[k] < NOTE_CUT:
            small += 1
            continue
        radius = 1.0 / max(abs(float(track.curvature[k])), 1e-9)
        why = f", bend radius {radius:.2f} m" if radius < 1e3 else ""
        notes.append(
            f"narrowed the {side} half-width at s={track.s[run[0]]:.1f}-{track.s[run[-1]]:.1f} m"
            f" by up to {before[k] - after[k]:.2f} m ({before[k]:.2f} -> {after[k]:.2f} m{why})"
        )
    if small:
        notes.append(f"narrowed the {side} half-width by under 5 mm at {small} more stretch(es)")
    return notes


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
