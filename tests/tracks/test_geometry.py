"""Track geometry: arc length, Frenet projection, signed distance, start grid, reversal."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import ArrayLike

from tests.tracks.builders import circle_points, stadium, stadium_points, wavy_stadium
from tracks import Track, TrackError, list_tracks, load_track
from tracks.geometry import FloatArray
from tracks.validation import grid_fits

STRAIGHT, RADIUS, SPACING = 30.0, 10.0, 0.05  # the hand-made polyline stadium, m
WL, WR = 2.0, 1.5  # its half-widths, m


def angle_diff(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """Smallest signed difference of angles, rad."""
    return np.angle(np.exp(1j * (np.asarray(a) - np.asarray(b))))


def frenet_samples(track: Track, n: int, seed: int, inside: float = 0.95) -> FloatArray:
    """(n, 2) [s, d] uniform over the lap and across ``inside`` of the road width."""
    rng = np.random.default_rng(seed)
    s = rng.uniform(0.0, track.length, n)
    left, right = track.widths_at(s)
    return np.column_stack([s, rng.uniform(-inside * right, inside * left)])


def assert_round_trip(track: Track, n: int = 20_000, seed: int = 0) -> None:
    """Frenet → Cartesian → Frenet → Cartesian returns every point within 1 mm."""
    frenet = frenet_samples(track, n, seed)
    xy = track.to_cartesian(frenet)
    back = track.project(xy)
    ds = np.abs(track.delta_s(back.s, frenet[:, 0]))
    dd = np.abs(back.d - frenet[:, 1])
    dxy = np.linalg.norm(track.to_cartesian(np.column_stack([back.s, back.d])) - xy, axis=1)
    assert ds.max() < 1e-3, f"{track.name}: s off by {ds.max():.2e} m"
    assert dd.max() < 1e-3, f"{track.name}: d off by {dd.max():.2e} m"
    assert dxy.max() < 1e-3, f"{track.name}: point moved {dxy.max():.2e} m"
    assert ((back.s >= 0) & (back.s < track.length)).all()


@pytest.fixture(scope="module")
def polyline() -> Track:
    """The dense stadium polyline used as it is (no smoothing): exact straights."""
    return Track(stadium_points(STRAIGHT, RADIUS, SPACING), WL, WR, smooth=False, name="poly")


def test_stadium_length_matches_formula() -> None:
    expected = 2 * STRAIGHT + 2 * np.pi * RADIUS
    smooth = Track(stadium_points(STRAIGHT, RADIUS, SPACING), 1.5, 1.5)
    raw = Track(stadium_points(STRAIGHT, RADIUS, SPACING), 1.5, 1.5, smooth=False)
    assert smooth.length == pytest.approx(expected, rel=1e-3)
    assert raw.length == pytest.approx(expected, rel=1e-3)
    assert smooth.orientation == "ccw"
    assert smooth.n_corners == 2


def test_round_trip_on_every_builtin_track() -> None:
    names = list_tracks()
    assert names, "the built-in track library is empty"
    for i, name in enumerate(names):
        assert_round_trip(load_track(name), n=5_000, seed=i)


def test_round_trip_on_built_stadiums() -> None:
    assert_round_trip(stadium())
    assert_round_trip(wavy_stadium())
    assert_round_trip(stadium().reversed())


def test_projection_on_straights_is_exact(polyline: Track) -> None:
    rng = np.random.default_rng(1)
    n_seg = round(STRAIGHT / SPACING)  # segments per straight
    seg = rng.integers(5, n_seg - 5, 200)  # stay clear of the bend junctions
    frac = rng.uniform(0.01, 0.99, 200)
    along = (seg + frac) * SPACING  # m from the start of the straight
    d = rng.uniform(-WR - 1.0, WL + 1.0, 200)  # on and off the road

    # Bottom straight: starts the lap at (-15, -10), driven towards +x, left is +y.
    bottom = np.column_stack([-STRAIGHT / 2 + along, -RADIUS + d])
    proj = polyline.project(bottom)
    np.testing.assert_allclose(proj.s, along, atol=1e-9)
    np.testing.assert_allclose(proj.d, d, atol=1e-9)
    np.testing.assert_allclose(angle_diff(proj.heading, 0.0), 0.0, atol=1e-12)
    np.testing.assert_array_equal(proj.segment, seg)

    # Top straight: driven towards -x after a bend of n_arc chords, so left is -y.
    n_arc = round(np.pi * RADIUS / SPACING)
    s_top = STRAIGHT + n_arc * 2 * RADIUS * np.sin(np.pi / (2 * n_arc))
    top = np.column_stack([STRAIGHT / 2 - along, RADIUS - d])
    proj = polyline.project(top)
    np.testing.assert_allclose(proj.s, s_top + along, atol=1e-9)
    np.testing.assert_allclose(proj.d, d, atol=1e-9)
    np.testing.assert_allclose(angle_diff(proj.heading, np.pi), 0.0, atol=1e-12)
    np.testing.assert_array_equal(proj.segment, n_seg + n_arc + seg)


def test_projection_on_a_circle_gives_radial_offset() -> None:
    radius = 8.0
    track = Track(circle_points(radius), 1.0, 1.0)
    rng = np.random.default_rng(2)
    r = rng.uniform(radius - 0.9, radius + 2.0, 500)
    th = rng.uniform(-np.pi, np.pi, 500)
    proj = track.project(np.column_stack([r * np.cos(th), r * np.sin(th)]))
    # Anticlockwise: the left is the inside, so d = radius - r; heading is th + 90 degrees.
    np.testing.assert_allclose(proj.d, radius - r, atol=2e-3)
    np.testing.assert_allclose(angle_diff(proj.heading, th + np.pi / 2), 0.0, atol=2e-3)
    arc = np.mod(th - np.arctan2(track.centre[0, 1], track.centre[0, 0]), 2 * np.pi)
    np.testing.assert_allclose(track.delta_s(proj.s, arc * radius), 0.0, atol=2e-2)


def test_projection_is_finite_everywhere_and_blockwise_consistent() -> None:
    track = wavy_stadium()
    rng = np.random.default_rng(3)
    xmin, ymin, xmax, ymax = track.bounds
    pts = rng.uniform([2 * xmin, 2 * ymin], [2 * xmax, 2 * ymax], (40_000, 2))
    whole = track.project(pts)
    for field in (whole.s, whole.d, whole.heading):
        assert np.isfinite(field).all()
    assert ((whole.s >= 0) & (whole.s < track.length)).all()
    assert ((whole.segment >= 0) & (whole.segment < track.n_points)).all()
    # Points are projected in blocks: the answer must not depend on where a block starts.
    idx = rng.choice(len(pts), 300, replace=False)
    part = track.project(pts[idx])
    np.testing.assert_array_equal(part.s, whole.s[idx])
    np.testing.assert_array_equal(part.d, whole.d[idx])
    np.testing.assert_array_equal(part.segment, whole.segment[idx])


def assert_same_bits(a: tuple[FloatArray, ...], b: tuple[FloatArray, ...]) -> None:
    for x, y in zip(a, b, strict=True):
        assert x.dtype == y.dtype and x.shape == y.shape
        assert x.tobytes() == y.tobytes()


def few_and_block(track: Track, pts: FloatArray) -> tuple[tuple[FloatArray, ...], ...]:
    """The few-point projection's fields and the block path's (numpy throughout)."""
    few, block = track._project_few(pts), track._projection(*track._project_block(pts))
    return tuple((p.segment, p.s, p.d, p.heading) for p in (few, block))


@pytest.mark.parametrize("name", ["oval", "monza", "hairpins", "chicanes"])
def test_projection_of_a_few_points_is_the_block_projection_bit_for_bit(name: str) -> None:
    # The env projects its cars (<= 16) in Python floats; a race must not depend on which
    # path ran: cars on the road, off it, and far beyond the walls.
    track = load_track(name)
    rng = np.random.default_rng(5)
    xmin, ymin, xmax, ymax = track.bounds
    for trial in range(150):
        m = int(rng.integers(1, 17))
        if trial % 2:
            pts = rng.uniform([xmin - 10, ymin - 10], [xmax + 10, ymax + 10], (m, 2))
        else:
            pts = track.centre[rng.integers(0, track.n_points, m)] + rng.normal(0, 0.7, (m, 2))
        assert_same_bits(*few_and_block(track, pts))
        proj = track.project(pts)
        assert proj.s.shape == proj.d.shape == proj.heading.shape == proj.segment.shape == (m,)


@pytest.mark.parametrize("name", ["oval", "monza", "hairpins"])
def test_widths_at_a_few_points_are_the_array_path_bit_for_bit(name: str) -> None:
    # The env asks the widths at its cars' s (<= 16 values) in Python floats: the same bits
    # as numpy's path (many values), in the lap, beyond it, negative, at the vertices, NaN.
    track = load_track(name)
    rng = np.random.default_rng(3)
    special = np.array([0.0, -0.0, track.length, -1e-300, track.s[1], track.s[-1], np.nan])
    many = np.concatenate(
        [rng.uniform(-2 * track.length, 3 * track.length, 2000), track.s, special]
    )
    expected = track.widths_at(many)  # > 16 values: numpy's path
    for lo in range(0, len(many), 16):
        few = track.widths_at(many[lo : lo + 16])
        assert_same_bits(few, tuple(side[lo : lo + 16] for side in expected))


@pytest.mark.parametrize("name", ["oval", "monza", "hairpins", "bean"])
def test_nearest_two_vertices_are_the_kd_trees(name: str) -> None:
    # The few-point projection looks its candidate segments up in a grid instead of the k-d
    # tree: the same two vertices, nearest first, on the road, off it and beyond the grid.
    track = load_track(name)
    rng = np.random.default_rng(11)
    xmin, ymin, xmax, ymax = track.bounds
    pts = np.vstack(
        [
            rng.uniform([xmin - 6, ymin - 6], [xmax + 6, ymax + 6], (3000, 2)),
            track.centre[rng.integers(0, track.n_points, 3000)] + rng.normal(0, 0.8, (3000, 2)),
            # Exactly between two vertices: a tie the grid must leave to the tree.
            0.5 * (track.centre[:50] + track.centre[1:51]),
        ]
    )
    _, expected = track._tree.query(pts, k=2)
    np.testing.assert_array_equal(np.array(track._nearest_two(pts)), expected)


def test_projection_of_a_few_points_without_a_frame_solution_uses_the_vertex() -> None:
    # A concave notch (5 corners, no smoothing): inside it some points have no solution on
    # the candidate segments' frames, and the nearest vertex is used, as for many points.
    notch = Track(
        np.array([[0.0, 0.0], [6.0, 0.0], [6.0, 6.0], [3.0, 1.0], [0.0, 6.0]]),
        0.5,
        0.5,
        smooth=False,
        name="notch",
    )
    pts = np.array([[0.20328112, 2.58220763], [0.28163639, 0.33265804], [3.0, 3.0]])
    seg, t, d = notch._project_block(pts[:1])
    assert t[0] == 0.0  # the vertex rule ran
    np.testing.assert_allclose(d, (pts[0] - notch.centre[seg[0]]) @ notch.normals[seg[0]])
    for k in range(1, 4):
        assert_same_bits(*few_and_block(notch, pts[:k]))


def test_signed_distance_and_is_inside(polyline: Track) -> None:
    x = np.linspace(-10.0, 10.0, 9)  # along the bottom straight, y = -RADIUS
    on_centre = np.column_stack([x, np.full_like(x, -RADIUS)])
    np.testing.assert_allclose(polyline.signed_distance(on_centre), -min(WL, WR), atol=1e-9)
    assert polyline.is_inside(on_centre).all()

    beyond_left = on_centre + np.array([0.0, WL + 0.3])
    beyond_right = on_centre - np.array([0.0, WR + 0.2])
    just_inside = on_centre + np.array([0.0, WL - 1e-6])
    np.testing.assert_allclose(polyline.signed_distance(beyond_left), 0.3, atol=1e-9)
    np.testing.assert_allclose(polyline.signed_distance(beyond_right), 0.2, atol=1e-9)
    assert not polyline.is_inside(beyond_left).any()
    assert not polyline.is_inside(beyond_right).any()
    assert polyline.is_inside(just_inside).all()

    # Deep in the infield and far outside: off the road, by about the right amount.
    far = np.array([[0.0, 0.0], [0.0, -RADIUS - 6.0]])
    sd = polyline.signed_distance(far)
    np.testing.assert_allclose(sd, [RADIUS - WL, 6.0 - WR], atol=1e-9)
    assert not polyline.is_inside(far).any()


def test_signed_distance_on_a_bend() -> None:
    track = stadium()
    s = np.linspace(40.0, 50.0, 20)  # on the first half circle
    left, right = track.widths_at(s)
    outside = track.to_cartesian(np.column_stack([s, -right - 0.4]))
    inside = track.to_cartesian(np.column_stack([s, left - 0.1]))
    np.testing.assert_allclose(track.signed_distance(outside), 0.4, atol=1e-6)
    np.testing.assert_allclose(track.signed_distance(inside), -0.1, atol=1e-6)


@pytest.mark.parametrize("n_cars", [1, 4, 7])
def test_start_grid(n_cars: int) -> None:
    track = stadium(width_left=1.6, width_right=1.6)
    poses = track.start_grid(n_cars)
    assert poses.shape == (n_cars, 3)
    proj = track.project(poses[:, :2])
    behind = track.delta_s(proj.s, 0.0)
    assert (behind < 0).all(), "every car starts behind the line"
    assert (proj.s > track.length - 0.5 * n_cars - 1.0).all(), "s wraps to just below length"
    # Pole 0.5 m behind the line, each next car 0.5 m further back, same column 1 m apart.
    np.testing.assert_allclose(behind, -0.5 - 0.5 * np.arange(n_cars), atol=1e-9)
    np.testing.assert_allclose(np.diff(behind[::2]), -1.0, atol=1e-9)
    # Two wide, alternating sides: even cars on the left half, odd on the right.
    side = np.where(np.arange(n_cars) % 2 == 0, 1.0, -1.0)
    np.testing.assert_allclose(proj.d, side * 0.8, atol=1e-9)
    np.testing.assert_allclose(angle_diff(poses[:, 2], track.heading_at(proj.s)), 0.0, atol=1e-9)
    assert grid_fits(track, n_cars)


def test_reversed_track() -> None:
    track = wavy_stadium()
    rev = track.reversed()
    assert rev.length == pytest.approx(track.length, abs=1e-9)
    assert rev.orientation == "cw" and track.orientation == "ccw"
    np.testing.assert_array_equal(rev.centre[0], track.centre[0])  # same start line
    np.testing.assert_allclose(rev.curvature.sum(), -track.curvature.sum())
    # The same physical points: progress runs the other way, left and right swap.
    frenet = frenet_samples(track, 2_000, seed=4)
    xy = track.to_cartesian(frenet)
    back = rev.project(xy)
    np.testing.assert_allclose(rev.delta_s(back.s, -frenet[:, 0]), 0.0, atol=1e-6)
    np.testing.assert_allclose(back.d, -frenet[:, 1], atol=1e-6)
    left, right = track.widths_at(frenet[:, 0])
    rev_left, rev_right = rev.widths_at(back.s)
    np.testing.assert_allclose(rev_left, right, atol=1e-6)
    np.testing.assert_allclose(rev_right, left, atol=1e-6)
    np.testing.assert_allclose(
        angle_diff(back.heading, track.heading_at(frenet[:, 0]) + np.pi), 0.0, atol=1e-6
    )
    again = rev.reversed()
    np.testing.assert_array_equal(again.centre, track.centre)
    np.testing.assert_array_equal(again.width_left, track.width_left)


@pytest.mark.parametrize("radius", [5.0, 8.0, 20.0])
def test_curvature_of_a_circle(radius: float) -> None:
    ccw = Track(circle_points(radius), 1.0, 1.0)
    np.testing.assert_allclose(ccw.curvature, 1 / radius, rtol=1e-2)
    np.testing.assert_allclose(ccw.curvature_at([0.0, 3.3, 17.0]), 1 / radius, rtol=1e-2)
    cw = Track(circle_points(radius)[::-1], 1.0, 1.0)
    np.testing.assert_allclose(cw.curvature, -1 / radius, rtol=1e-2)
    assert ccw.n_corners == (1 if radius < 12.0 else 0)


def test_checkpoints_and_gates() -> None:
    track = stadium()
    s = track.checkpoint_s(8)
    np.testing.assert_allclose(s, np.arange(8) * track.length / 8)
    gates = track.gates(s)
    assert gates.shape == (8, 2, 2)
    left = track.project(gates[:, 0])
    right = track.project(gates[:, 1])
    np.testing.assert_allclose(track.delta_s(left.s, s), 0.0, atol=1e-9)
    np.testing.assert_allclose(track.delta_s(right.s, s), 0.0, atol=1e-9)
    np.testing.assert_allclose(left.d, 2.0, atol=1e-9)
    np.testing.assert_allclose(right.d, -1.5, atol=1e-9)
    with pytest.raises(TrackError, match="at least 2 checkpoints"):
        track.checkpoint_s(1)
