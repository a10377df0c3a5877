"""Procedural race tracks: a closed, smooth, non-self-intersecting circuit from a seed.

``generate_track(seed, length, difficulty)`` always returns the same track for the same
arguments (it draws only from ``numpy.random.default_rng``), and the library resolves
``random:<seed>[:length=<m>,difficulty=<0..1>]`` to it.

How a circuit is made:

1. Corner points: ``n`` angles spread evenly round a circle with random jitter (kept sorted),
   each at a random radius, so the polygon is star-shaped and cannot cross itself. ``n`` grows
   with the lap length and the difficulty (about one corner every 20 m at difficulty 0, every
   9 m at difficulty 1), and so does the spread of the radii: harder tracks have more and
   tighter corners.
2. Midpoint displacement: a point is added halfway along each edge, pushed sideways by a random
   fraction of the edge (none at difficulty 0). The periodic spline through the points then
   follows the edges as straights and rounds the corners.
3. Scale: the spline is scaled so the lap is ``length`` metres (scaling is exact for a chord-
   length spline, so the lap length matches to a fraction of a millimetre per metre).
4. Checks: the road, made 30% wider than it will be, must pass
   :func:`tracks.validation.validate_track`; that keeps every radius of curvature at least 1.3
   inner half-widths and leaves grass between parts of the road that pass close to each other.
   The start line goes at the end of the straightest 7 m of the lap, and an 8-car grid must
   fit behind it.
5. A shape that fails a check is drawn again from the sub-seed ``(seed, attempt)``, at most
   ``MAX_ATTEMPTS`` times; then :class:`TrackError` is raised.

The total road width falls linearly from 4 m at difficulty 0 to 2 m at difficulty 1.
"""

from __future__ import annotations

import math

import numpy as np

from tracks.errors import TrackError
from tracks.geometry import FloatArray, Track
from tracks.validation import grid_fits, validate_track

MIN_LENGTH = 30.0  # m: shortest lap on offer
MAX_LENGTH = 300.0  # m: longest lap on offer
DEFAULT_LENGTH = 80.0  # m
DEFAULT_DIFFICULTY = 0.5
WIDTH_EASY = 4.0  # m of total road width at difficulty 0
WIDTH_HARD = 2.0  # m of total road width at difficulty 1
CORNER_GAP_EASY = 20.0  # m of lap per corner point at difficulty 0
CORNER_GAP_HARD = 9.0  # m of lap per corner point at difficulty 1
MIN_CORNER_POINTS = 5
RADIUS_SPREAD_EASY = 0.15  # corner radii vary by ±15% of the mean at difficulty 0 ...
RADIUS_SPREAD_HARD = 0.45  # ... and by ±45% at difficulty 1
ANGLE_JITTER = 0.4  # a corner point moves at most this fraction of its sector
MIDPOINT_SHIFT_HARD = 0.2  # sideways midpoint shift, fraction of the edge, at difficulty 1
SAFETY = 1.3  # checks run on a road this much wider (radius and clearance margin)
GRID_CARS = 8  # the start grid that must fit
GRID_WINDOW = (6.0, 1.0)  # m behind / ahead of the start line that should be straight
MAX_SMOOTHING = 12  # smoothing passes before a shape is given up
SMOOTHING_STEP = 0.5  # how far a point moves towards its neighbours' mean per pass
MAX_ATTEMPTS = 100


def _lerp(easy: float, hard: float, difficulty: float) -> float:
    return easy + (hard - easy) * difficulty


def road_width(difficulty: float) -> float:
    """Total road width in metres for a difficulty in [0, 1]: 4 m down to 2 m."""
    return _lerp(WIDTH_EASY, WIDTH_HARD, difficulty)


def random_spec(seed: int, length: float, difficulty: float) -> str:
    """The ``random:`` name that :func:`tracks.load_track` resolves to this track.

    >>> random_spec(7, 60.0, 0.8)
    'random:7:length=60,difficulty=0.8'
    >>> random_spec(7, DEFAULT_LENGTH, DEFAULT_DIFFICULTY)
    'random:7'
    """
    opts = []
    if length != DEFAULT_LENGTH:
        opts.append(f"length={_number(length)}")
    if difficulty != DEFAULT_DIFFICULTY:
        opts.append(f"difficulty={_number(difficulty)}")
    return f"random:{seed}" + (":" + ",".join(opts) if opts else "")


def _number(x: float) -> str:
    """Short text for a number that still reads back as exactly the same float."""
    short = f"{x:g}"
    return short if float(short) == x else repr(float(x))


def _check_arguments(seed: int, length: float, difficulty: float) -> None:
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise TrackError(f"random track seed must be a non-negative integer, got {seed!r}")
    if not MIN_LENGTH <= length <= MAX_LENGTH:  # also rejects NaN
        raise TrackError(
            f"random track length must be between {MIN_LENGTH:g} and {MAX_LENGTH:g} m, "
            f"got {length:g}"
        )
    if not 0.0 <= difficulty <= 1.0:
        raise TrackError(f"random track difficulty must be between 0 and 1, got {difficulty:g}")


def _control_points(rng: np.random.Generator, length: float, difficulty: float) -> FloatArray:
    """(2n, 2) control points of a star-shaped circuit, anticlockwise, about unit size."""
    n = max(MIN_CORNER_POINTS, round(length / _lerp(CORNER_GAP_EASY, CORNER_GAP_HARD, difficulty)))
    sector = 2.0 * math.pi / n
    angles = (np.arange(n) + rng.uniform(-ANGLE_JITTER, ANGLE_JITTER, n)) * sector
    spread = _lerp(RADIUS_SPREAD_EASY, RADIUS_SPREAD_HARD, difficulty)
    radii = 1.0 + spread * rng.uniform(-1.0, 1.0, n)
    corners = radii[:, None] * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    edges = np.roll(corners, -1, axis=0) - corners
    normals = np.stack([-edges[:, 1], edges[:, 0]], axis=1)  # edge-length long
    shift = MIDPOINT_SHIFT_HARD * difficulty * rng.uniform(-1.0, 1.0, n)
    middles = corners + 0.5 * edges + shift[:, None] * normals
    return np.stack([corners, middles], axis=1).reshape(-1, 2)


def _straightest_start(track: Track) -> float:
    """Progress (m) whose window ``GRID_WINDOW`` behind/ahead has the least peak curvature."""
    spacing = track.length / track.n_points
    behind = math.ceil(GRID_WINDOW[0] / spacing)
    ahead = math.ceil(GRID_WINDOW[1] / spacing)
    offsets = np.arange(-behind, ahead + 1)
    windows = (np.arange(track.n_points)[:, None] + offsets[None, :]) % track.n_points
    peak = np.abs(track.curvature)[windows].max(axis=1)
    return float(track.s[int(np.argmin(peak))])


def _smoothed(points: FloatArray) -> FloatArray:
    """One pass of Laplacian smoothing of a closed polygon (N, 2): rounds its sharpest corners."""
    neighbours = 0.5 * (np.roll(points, 1, axis=0) + np.roll(points, -1, axis=0))
    return points + SMOOTHING_STEP * (neighbours - points)


def _attempt(
    rng: np.random.Generator, seed: int, length: float, difficulty: float
) -> Track | None:
    """One candidate circuit, or None when it fails a check even after smoothing."""
    half = 0.5 * road_width(difficulty)
    raw = _control_points(rng, length, difficulty)
    for _ in range(MAX_SMOOTHING + 1):
        raw *= length / (2.0 * math.pi * np.linalg.norm(raw, axis=1).mean())
        probe = Track(raw, half, half, validate=False)
        points = raw * (length / probe.length)
        # Checks on a wider road keep radius and clearance margins; the centre line is the same.
        wide = Track(points, SAFETY * half, SAFETY * half, validate=False)
        try:
            validate_track(wide)
        except TrackError:
            raw = _smoothed(points)  # a bend too tight or two parts too close: round it off
            continue
        track = Track(
            points,
            half,
            half,
            name=random_spec(seed, length, difficulty),
            description=(
                f"Procedurally generated circuit: seed {seed}, length {length:g} m, "
                f"difficulty {difficulty:g}, road {2 * half:g} m wide."
            ),
            start_s=_straightest_start(wide),
        )
        return track if grid_fits(track, GRID_CARS) else None
    return None


def generate_track(
    seed: int, length: float = DEFAULT_LENGTH, difficulty: float = DEFAULT_DIFFICULTY
) -> Track:
    """A random closed circuit, the same one for the same arguments.

    Args:
        seed: non-negative integer; the only source of randomness.
        length: lap length along the centre line, m, in ``[30, 300]``.
        difficulty: ``0`` (few gentle corners, 4 m road) to ``1`` (many tight corners, 2 m road).

    Returns:
        A validated :class:`Track` named ``random:<seed>[:options]`` with its start line on the
        straightest stretch and room for an 8-car grid behind it.

    Raises:
        TrackError: an argument is out of range, or no valid circuit was found.

    >>> track = generate_track(3, length=60.0, difficulty=0.2)
    >>> track.name, round(track.length)
    ('random:3:length=60,difficulty=0.2', 60)
    """
    _check_arguments(seed, length, difficulty)
    length, difficulty = float(length), float(difficulty)
    for attempt in range(MAX_ATTEMPTS):
        rng = np.random.default_rng(seed if attempt == 0 else (int(seed), attempt))
        track = _attempt(rng, int(seed), length, difficulty)
        if track is not None:
            return track
    raise TrackError(
        f"no valid circuit for seed {seed}, length {length:g} m, difficulty {difficulty:g} "
        f"after {MAX_ATTEMPTS} attempts; try another seed, a longer lap or a lower difficulty"
    )
