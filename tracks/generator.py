"""Procedural race tracks: a closed, non-self-intersecting circuit from a seed.

``generate_track(seed, length, difficulty)`` always returns the same track for the same
arguments (it draws only from ``numpy.random.default_rng``), and the library resolves
``random:<seed>[:length=<m>,difficulty=<0..1>]`` to it.

How a circuit is made:

1. Corner points: ``n`` angles spread evenly round a circle with random jitter (so they stay
   sorted), each at a random radius: a star-shaped polygon, which cannot cross itself.
2. Midpoint displacement: a vertex is added halfway along each edge and pushed sideways by a
   random fraction of the edge, which makes kinks, esses and concave bends.
3. Straights and bends: every vertex is rounded with a circular arc of random radius, entered
   and left along the polygon edges, so the lap is straights joined by constant-radius bends.
   The polygon is scaled so that the lap is ``length`` metres long, and driven anticlockwise
   or clockwise at random.
4. The path is sampled every metre or so and handed to :class:`Track` (periodic spline).
5. Checks: the road, made 30% wider than it will be, must pass
   :func:`tracks.validation.validate_track` (so every radius of curvature is at least 1.3
   inner half-widths, and parts of the road that pass close to each other keep grass between
   them). The start line goes where the 6 m behind it and the 1 m after it are straightest,
   and an 8-car grid must fit behind it.
6. A shape that fails is first calmed: blended step by step into a regular polygon with wide
   bends (short laps need it: a 30 m lap has no room for many corners). If even that fails, a
   new shape is drawn from the sub-seed ``(seed, attempt)``, at most ``MAX_ATTEMPTS`` times,
   and then :class:`TrackError` is raised.

Difficulty, from 0 to 1, sets how twisty the lap is and how narrow the road:

================  ====================  ====================
quantity          difficulty 0          difficulty 1
================  ====================  ====================
corner points     one per 28 m of lap   one per 12 m of lap
radial spread     up to 25% inwards     up to 55% inwards
midpoint shift    ±5% of the edge       ±35% of the edge
bend radii        1.7 half-widths–15 m  1.7 half-widths–4 m
road width        4 m                   2 m
================  ====================  ====================
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tracks.errors import TrackError
from tracks.geometry import FloatArray, Track, short_float
from tracks.validation import fit_widths, grid_fits, validate_track

MIN_LENGTH = 30.0  # m: shortest lap on offer
MAX_LENGTH = 300.0  # m: longest lap on offer
DEFAULT_LENGTH = 80.0  # m
DEFAULT_DIFFICULTY = 0.5
WIDTH_EASY = 4.0  # m of total road width at difficulty 0
WIDTH_HARD = 2.0  # m of total road width at difficulty 1
CORNER_GAP = (28.0, 12.0)  # m of lap per corner point (difficulty 0, difficulty 1)
MIN_CORNERS = 4  # fewest corner points (before midpoints are added)
ANGLE_JITTER = 0.35  # a corner point moves at most this fraction of its sector
RADIAL_SPREAD = (0.25, 0.55)  # corner points lie at (1 - spread .. 1) x the mean radius
MIDPOINT_SHIFT = (0.05, 0.35)  # sideways midpoint shift, fraction of the edge
BEND_RADIUS_MAX = (15.0, 4.0)  # m: largest bend radius drawn
BEND_RADIUS_MIN = 1.7  # half-widths: smallest bend radius (the spline tightens it by ~15%)
SAFETY = 1.3  # checks run on a road this much wider (radius and clearance margin)
ARC_STEP = 0.5  # m between samples on a bend
STRAIGHT_STEP = 1.0  # m between samples on a straight
CALMING = (0.0, 0.25, 0.5, 0.75, 1.0)  # blends towards a regular polygon, tried in turn
GRID_CARS = 8  # the start grid that must fit
GRID_WINDOW = (6.0, 1.0)  # m behind / ahead of the start line that should be straight
MAX_ATTEMPTS = 20  # fresh shapes (each tried at every calming level) before giving up
# Real-track-like tightness (``hairpin=R``): the F1TENTH race tracks (1/10 scale, a constant
# 1.1 m half-width) have hairpins of 0.4-1.1 m centre-line radius, tighter than their
# half-width and than the car's 0.74 m full-lock radius; their importer narrows the inside.
HAIRPIN_RANGE = (0.3, 5.0)  # m: the smallest bend radius a hairpin track may ask for
HAIRPIN_SHARE = 0.35  # share of a hairpin track's bends drawn near the hairpin radius
HAIRPIN_HALF_WIDTH = 1.1  # m: the F1TENTH race tracks' half-width, before narrowing
WIDTH_RANGE = (1.0, 6.0)  # m: total road widths ``width=`` may ask for


def _lerp(range_: tuple[float, float], difficulty: float) -> float:
    """The value for ``difficulty`` between the (easy, hard) ends of a range."""
    easy, hard = range_
    return easy + (hard - easy) * difficulty


def road_width(difficulty: float) -> float:
    """Total road width in metres for a difficulty in [0, 1]: 4 m down to 2 m."""
    return _lerp((WIDTH_EASY, WIDTH_HARD), difficulty)


def random_spec(
    seed: int,
    length: float,
    difficulty: float,
    hairpin: float | None = None,
    width: float | None = None,
) -> str:
    """The ``random:`` name that :func:`tracks.load_track` resolves to this track.

    >>> random_spec(7, 60.0, 0.8)
    'random:7:length=60,difficulty=0.8'
    >>> random_spec(7, DEFAULT_LENGTH, DEFAULT_DIFFICULTY)
    'random:7'
    >>> random_spec(7, 200.0, 0.8, hairpin=0.6)
    'random:7:length=200,difficulty=0.8,hairpin=0.6'
    >>> random_spec(7, 120.0, 0.5, hairpin=0.6, width=1.5)
    'random:7:length=120,hairpin=0.6,width=1.5'
    """
    opts = []
    if length != DEFAULT_LENGTH:
        opts.append(f"length={short_float(length)}")
    if difficulty != DEFAULT_DIFFICULTY:
        opts.append(f"difficulty={short_float(difficulty)}")
    if hairpin is not None:
        opts.append(f"hairpin={short_float(hairpin)}")
    if width is not None:
        opts.append(f"width={short_float(width)}")
    return f"random:{seed}" + (":" + ",".join(opts) if opts else "")


def _check_arguments(
    seed: int, length: float, difficulty: float, hairpin: float | None, width: float | None
) -> None:
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise TrackError(f"random track seed must be a non-negative integer, got {seed!r}")
    if not MIN_LENGTH <= length <= MAX_LENGTH:  # also rejects NaN
        raise TrackError(
            f"random track length must be between {MIN_LENGTH:g} and {MAX_LENGTH:g} m, "
            f"got {length:g}"
        )
    if not 0.0 <= difficulty <= 1.0:
        raise TrackError(f"random track difficulty must be between 0 and 1, got {difficulty:g}")
    if width is not None and not WIDTH_RANGE[0] <= width <= WIDTH_RANGE[1]:
        raise TrackError(
            f"random track width must be between {WIDTH_RANGE[0]:g} and {WIDTH_RANGE[1]:g} m, "
            f"got {width:g}"
        )
    if hairpin is not None and not HAIRPIN_RANGE[0] <= hairpin <= HAIRPIN_RANGE[1]:
        raise TrackError(
            f"random track hairpin radius must be between {HAIRPIN_RANGE[0]:g} and "
            f"{HAIRPIN_RANGE[1]:g} m, got {hairpin:g}"
        )


@dataclass(frozen=True)
class _Shape:
    """The random draws behind one circuit polygon (each array has shape (n,)).

    Attributes:
        jitter: angle of each corner point, fraction of its sector off the even spacing.
        spread: how far in each corner point lies, fraction of the unit radius.
        shift: sideways shift of each edge midpoint, fraction of the edge length.
        bends: (2n,) where each vertex's bend radius lies between the smallest and largest.
        clockwise: drive the circuit clockwise.
    """

    jitter: FloatArray
    spread: FloatArray
    shift: FloatArray
    bends: FloatArray
    clockwise: bool

    @classmethod
    def draw(cls, rng: np.random.Generator, length: float, difficulty: float) -> _Shape:
        n = max(MIN_CORNERS, round(length / _lerp(CORNER_GAP, difficulty)))
        return cls(
            jitter=rng.uniform(-ANGLE_JITTER, ANGLE_JITTER, n),
            spread=_lerp(RADIAL_SPREAD, difficulty) * rng.uniform(0.0, 1.0, n),
            shift=_lerp(MIDPOINT_SHIFT, difficulty) * rng.uniform(-1.0, 1.0, n),
            bends=rng.uniform(0.0, 1.0, 2 * n),
            clockwise=bool(rng.integers(2)),
        )

    def polygon(self, calm: float) -> FloatArray:
        """(2n, 2) vertices, anticlockwise, about unit radius; ``calm`` in [0, 1] blends the
        random shape into a regular polygon (which always has room for its bends)."""
        n = len(self.jitter)
        keep = 1.0 - calm
        angles = (np.arange(n) + keep * self.jitter) * (2.0 * math.pi / n)
        radii = 1.0 - keep * self.spread
        corners = radii[:, None] * np.stack([np.cos(angles), np.sin(angles)], axis=1)
        edges = np.roll(corners, -1, axis=0) - corners
        normals = np.stack([-edges[:, 1], edges[:, 0]], axis=1)  # edge-length long, leftwards
        middles = corners + 0.5 * edges + (keep * self.shift)[:, None] * normals
        return np.stack([corners, middles], axis=1).reshape(-1, 2)


def _fit_bends(
    vertices: FloatArray, radii: FloatArray, length: float, min_radius: float
) -> tuple[float, FloatArray] | None:
    """Scale for the polygon and bend radii (m) so the rounded lap is ``length`` m long.

    Rounding a vertex that turns by ``theta`` with radius ``R`` cuts ``t = R tan(theta/2)``
    off both edges and shortens the lap by ``2t - R theta``, so for fixed radii the lap length
    is linear in the scale. Radii whose cuts do not fit on an edge are reduced (not below
    ``min_radius``); None when the polygon is too sharp for that.
    """
    incoming = vertices - np.roll(vertices, 1, axis=0)
    outgoing = np.roll(incoming, -1, axis=0)  # edge i runs from vertex i to vertex i+1
    turn = np.abs(np.arctan2(_cross(incoming, outgoing), np.einsum("ij,ij->i", incoming, outgoing)))
    edge = np.linalg.norm(outgoing, axis=1)
    perimeter = float(edge.sum())
    radii = radii.copy()
    for _ in range(20):
        cut = radii * np.tan(0.5 * turn)
        scale = (length + float(np.sum(2.0 * cut - radii * turn))) / perimeter
        need = cut + np.roll(cut, -1)  # metres taken off edge i by its two bends
        room = 0.98 * scale * edge / np.maximum(need, 1e-12)
        if (room >= 1.0).all():
            return scale, radii
        shrink = np.minimum(room, np.roll(room, 1))  # a vertex has two edges
        # Overshoot a little: shrinking exactly to fit only approaches the fit.
        radii = np.maximum(min_radius, radii * np.where(shrink < 1.0, 0.95 * shrink, 1.0))
    return None


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _rounded_path(vertices: FloatArray, radii: FloatArray) -> FloatArray:
    """(M, 2) points along the polygon (m) with each vertex rounded by a circular arc."""
    incoming = vertices - np.roll(vertices, 1, axis=0)
    u_in = incoming / np.linalg.norm(incoming, axis=1)[:, None]
    u_out = np.roll(u_in, -1, axis=0)
    turn = np.arctan2(_cross(u_in, u_out), np.einsum("ij,ij->i", u_in, u_out))
    cut = radii * np.tan(0.5 * np.abs(turn))
    arc_start = vertices - cut[:, None] * u_in
    arc_end = vertices + cut[:, None] * u_out
    pieces = []
    for i in range(len(vertices)):
        # Bend: from arc_start round the centre on the inside of the turn.
        to_centre = np.array([-u_in[i, 1], u_in[i, 0]]) * math.copysign(radii[i], turn[i])
        spoke = -to_centre  # centre -> arc_start, rotated by the turn as the bend goes round
        arc = radii[i] * abs(turn[i])
        steps = math.ceil(arc / ARC_STEP) if arc > 0.01 * ARC_STEP else 0  # none if no turn
        phi = turn[i] * np.arange(steps) / steps
        cos, sin = np.cos(phi)[:, None], np.sin(phi)[:, None]
        perp = np.array([-spoke[1], spoke[0]])
        pieces.append(arc_start[i] + to_centre + cos * spoke + sin * perp)
        # Straight: from the end of this bend to the start of the next.
        nxt = arc_start[(i + 1) % len(vertices)]
        run = float(np.linalg.norm(nxt - arc_end[i]))
        steps = math.ceil(run / STRAIGHT_STEP) if run > 0.1 * ARC_STEP else 0
        pieces.append(arc_end[i] + np.outer(np.arange(steps) / max(steps, 1), nxt - arc_end[i]))
    return np.vstack(pieces)


def _straightest_start(track: Track) -> float:
    """Progress (m) whose window ``GRID_WINDOW`` behind/ahead has the least peak curvature."""
    spacing = track.length / track.n_points
    behind = math.ceil(GRID_WINDOW[0] / spacing)
    ahead = math.ceil(GRID_WINDOW[1] / spacing)
    offsets = np.arange(-behind, ahead + 1)
    windows = (np.arange(track.n_points)[:, None] + offsets[None, :]) % track.n_points
    peak = np.abs(track.curvature)[windows].max(axis=1)
    return float(track.s[int(np.argmin(peak))])


def _attempt(
    rng: np.random.Generator,
    seed: int,
    length: float,
    difficulty: float,
    hairpin: float | None,
    width: float | None,
) -> Track | None:
    """One candidate circuit, or None when it fails a check even when calmed down."""
    # Hairpin tracks have the F1TENTH tracks' road; difficulty then sets only the corners, so
    # an easy one has long straights into its hairpins, as real circuits do.
    half = 0.5 * road_width(difficulty) if hairpin is None else HAIRPIN_HALF_WIDTH
    if width is not None:
        half = 0.5 * width
    shape = _Shape.draw(rng, length, difficulty)
    min_radius = BEND_RADIUS_MIN * half if hairpin is None else hairpin
    max_radius = max(_lerp(BEND_RADIUS_MAX, difficulty), 1.2 * min_radius)
    bends = shape.bends
    if hairpin is not None:  # a share of the bends squeezed towards the hairpin radius
        bends = np.where(bends < HAIRPIN_SHARE, 0.1 * bends / HAIRPIN_SHARE, bends)
    for calm in CALMING:
        vertices = shape.polygon(calm)
        spread = bends + calm * (1.0 - bends)  # calmer: wider bends
        fit = _fit_bends(
            vertices, min_radius + (max_radius - min_radius) * spread, length, min_radius
        )
        if fit is None:
            continue
        points = _rounded_path(fit[0] * vertices, fit[1])
        if shape.clockwise:
            points = points[::-1]
        points *= length / Track(points, half, half, validate=False).length  # spline vs arcs
        description = (
            f"Procedurally generated circuit: seed {seed}, length {length:g} m, "
            f"difficulty {difficulty:g}, road {2 * half:g} m wide"
        )
        name = random_spec(seed, length, difficulty, hairpin, width)
        if hairpin is None:
            # Checks on a wider road keep radius and clearance margins; same centre line.
            wide = Track(points, SAFETY * half, SAFETY * half, validate=False)
            try:
                validate_track(wide)
            except TrackError:
                continue
            track = Track(
                points,
                half,
                half,
                name=name,
                description=description + ".",
                start_s=_straightest_start(wide),
            )
        else:
            found = _hairpin_track(points, half, name, description, hairpin)
            if found is None:
                continue
            track = found
        if grid_fits(track, GRID_CARS):
            return track
    return None


def _hairpin_track(
    points: FloatArray, half: float, name: str, description: str, hairpin: float
) -> Track | None:
    """The road around ``points`` built as a real track file is imported, or None.

    A constant half-width, narrowed by :func:`tracks.validation.fit_widths` where a bend or
    a facing stretch of road leaves no room (as the F1TENTH importer does), then checked as
    it is: no safety margin, since the narrowing already keeps 10 % of each bend's radius.
    """
    fitted, _ = fit_widths(Track(points, half, half, validate=False))
    try:
        return Track(
            fitted.centre,
            fitted.width_left,
            fitted.width_right,
            smooth=False,
            name=name,
            description=f"{description}, hairpins down to {hairpin:g} m (inside narrowed).",
            start_s=_straightest_start(fitted),
        )
    except TrackError:
        return None


def generate_track(
    seed: int,
    length: float = DEFAULT_LENGTH,
    difficulty: float = DEFAULT_DIFFICULTY,
    hairpin: float | None = None,
    width: float | None = None,
) -> Track:
    """A random closed circuit, the same one for the same arguments.

    Args:
        seed: non-negative integer; the only source of randomness.
        length: lap length along the centre line, m, in ``[30, 300]``.
        difficulty: ``0`` (few gentle corners, 4 m road) to ``1`` (many tight corners, 2 m road).
        hairpin: real-track-like tightness: the F1TENTH race tracks' 2.2 m road (difficulty
            then sets only how many corners and how twisty), about a third of the bends drawn
            down to this radius (m), tighter than the half-width (those tracks' hairpins are
            0.4-1.1 m), and the inside of the road narrowed there as the importers narrow
            real files (:func:`tracks.validation.fit_widths`). None: every bend is at least
            1.7 half-widths and the road keeps its width.
        width: total road width, m (before any narrowing), instead of the one that
            ``difficulty`` or ``hairpin`` gives: e.g. 1.5 for a road that, scaled for the
            DeepRacer car (``@0.52``), is as narrow as DeepRacer's 0.76 m tracks.

    Returns:
        A validated :class:`Track` named ``random:<seed>[:options]`` with its start line on the
        straightest stretch and room for an 8-car grid behind it.

    Raises:
        TrackError: an argument is out of range, or no valid circuit was found.

    >>> track = generate_track(3, length=60.0, difficulty=0.2)
    >>> track.name, round(track.length)
    ('random:3:length=60,difficulty=0.2', 60)
    """
    _check_arguments(seed, length, difficulty, hairpin, width)
    length, difficulty = float(length), float(difficulty)
    hairpin = None if hairpin is None else float(hairpin)
    width = None if width is None else float(width)
    for attempt in range(MAX_ATTEMPTS):
        rng = np.random.default_rng(seed if attempt == 0 else (int(seed), attempt))
        track = _attempt(rng, int(seed), length, difficulty, hairpin, width)
        if track is not None:
            return track
    raise TrackError(
        f"no valid circuit for seed {seed}, length {length:g} m, difficulty {difficulty:g} "
        f"after {MAX_ATTEMPTS} attempts; try another seed, a longer lap or a lower difficulty"
    )
