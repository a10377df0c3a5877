"""Walls of imported tracks: shortened where the full run-off would stand on the road.

The shape comes from the F1TENTH race-track collection: a constant 1.1 m half-width around
bends tighter than that (tests/tracks/test_real_files.py builds such a file). The importer
narrows the road; the walls, 0.4 m of run-off outside each edge on the built-in tracks, must
then stop short of the other leg of the hairpin (``Track.wall_offsets``), on both simulators:
the pybullet wall bodies and lidar (``Walls.around``) and the batched clearance map.
"""

from __future__ import annotations

import numpy as np
import pytest

from arena.batch.maps import TrackMaps
from arena.sim import WALL_THICKNESS
from arena.walls import DEFAULT_RUNOFF, Walls
from tests.tracks.builders import hairpin_points
from tests.tracks.test_real_files import write_f1tenth_centreline
from tracks import Track, list_tracks, load_track
from tracks.formats import read_f1tenth
from tracks.geometry import NEAR_SECTIONS


@pytest.fixture(scope="module")
def hairpin(tmp_path_factory: pytest.TempPathFactory) -> Track:
    folder = tmp_path_factory.mktemp("hairpin")
    csv = write_f1tenth_centreline(folder / "Hairpin_centerline.csv", hairpin_points(0.6))
    return read_f1tenth(csv)


def test_walls_stand_at_the_shortened_offsets(hairpin: Track) -> None:
    walls = Walls.around(hairpin)
    idx = np.arange(0, hairpin.n_points, walls.stride)
    left, right = hairpin.wall_offsets(DEFAULT_RUNOFF)
    assert (left < hairpin.width_left + DEFAULT_RUNOFF - 0.05).any()  # shortened somewhere
    got_left = np.linalg.norm(walls.left - hairpin.centre[idx], axis=1)
    got_right = np.linalg.norm(walls.right - hairpin.centre[idx], axis=1)
    np.testing.assert_allclose(got_left, left[idx], atol=1e-9)
    np.testing.assert_allclose(got_right, right[idx], atol=1e-9)


def test_fewer_wall_points_on_the_road_than_with_the_full_run_off(hairpin: Track) -> None:
    walls = Walls.around(hairpin)
    idx = np.arange(0, hairpin.n_points, walls.stride)
    naive = (
        hairpin.centre[idx]
        + (hairpin.width_left[idx] + DEFAULT_RUNOFF)[:, None] * (hairpin.normals[idx])
    )
    own = {"own_s": hairpin.s[idx], "near": NEAR_SECTIONS}
    on_naive = int(hairpin.on_road(naive, **own).sum())
    on_walls = int(hairpin.on_road(walls.left, **own).sum())
    assert on_naive >= 5 and on_walls <= on_naive // 3


def test_the_batched_clearance_map_uses_the_same_walls(hairpin: Track) -> None:
    maps = TrackMaps.build(hairpin)
    left, right = hairpin.wall_offsets(DEFAULT_RUNOFF)
    # At cells nearest the centre line, clearance is the nearer wall offset (within a cell).
    pts = maps.grid.centres()
    proj = hairpin.project(pts)
    central = np.abs(proj.d) < 0.5 * maps.grid.cell
    seg = proj.segment[central]
    want = np.minimum(left[seg], right[seg])
    close = np.abs(maps.clearance[central] - want) <= maps.grid.cell + 0.05
    assert close.mean() > 0.98  # a cell or two at the hairpin's apex projects ambiguously
    shortened = (
        np.minimum(left, right)
        < np.minimum(hairpin.width_left, hairpin.width_right) + DEFAULT_RUNOFF - 0.05
    )
    assert shortened[seg].any()


def test_builtin_tracks_keep_the_full_run_off() -> None:
    for name in list_tracks():
        track = load_track(name)
        walls = Walls.around(track)
        idx = np.arange(0, track.n_points, walls.stride)
        d_left = np.linalg.norm(walls.left - track.centre[idx], axis=1)
        np.testing.assert_allclose(d_left, track.width_left[idx] + DEFAULT_RUNOFF, atol=1e-9)


def _box_intrusion(track: Track) -> float:
    """How far (m) the deepest point of a pybullet wall box lies on the road (0: none)."""
    walls = Walls.around(track)
    centres, halves, yaws = walls.boxes(WALL_THICKNESS, track)
    g = np.linspace(-1.0, 1.0, 9)
    a, b = np.meshgrid(g, g)
    local = np.stack([a.ravel(), b.ravel()], axis=1)  # (81, 2) over the box
    u = np.stack([np.cos(yaws), np.sin(yaws)], axis=1)
    v = np.stack([-u[:, 1], u[:, 0]], axis=1)
    pts = (
        centres[:, None, :]
        + (local[None, :, 0] * halves[:, 0, None])[..., None] * u[:, None, :]
        + (local[None, :, 1] * halves[:, 1, None])[..., None] * v[:, None, :]
    ).reshape(-1, 2)
    on = track.on_road(pts, margin=-0.005)
    if not on.any():
        return 0.0
    proj = track.project(pts[on])
    seg = proj.segment % track.n_points
    width = np.where(proj.d > 0, track.width_left[seg], track.width_right[seg])
    return float((width - np.abs(proj.d)).max())


@pytest.mark.parametrize(
    "make",
    [
        # The F1TENTH shape: 1.1 m half-width narrowed around a 0.6 m hairpin.
        pytest.param("hairpin", id="f1tenth-hairpin-0.6"),
        # Real-track-like generated circuits (0.5-0.6 m hairpins entered from straights).
        pytest.param("random:2:length=200,difficulty=0.8,hairpin=0.6", id="generated-0.6"),
        pytest.param("random:4:length=200,difficulty=0.8,hairpin=0.5", id="generated-0.5"),
    ],
)
def test_wall_boxes_stay_off_the_road_inside_tight_hairpins(make: str, hairpin: Track) -> None:
    """Inside a hairpin tighter than the run-off the road wraps round the bend's centre, so a
    0.2 m box behind the inner wall came out on the road on the bend's far side: 0.26-0.29 m
    onto the road on every published F1TENTH layout tried (Spielberg, Monza, Austin, Catalunya,
    Silverstone), where pybullet cars then crashed into it while batch cars drove on."""
    track = hairpin if make == "hairpin" else load_track(make)
    assert _box_intrusion(track) < 0.08


def test_builtin_wall_boxes_keep_their_full_thickness_off_the_road() -> None:
    for name in list_tracks():
        track = load_track(name)
        _, halves, _ = Walls.around(track).boxes(WALL_THICKNESS, track)
        np.testing.assert_allclose(halves[:, 1], WALL_THICKNESS / 2)
        assert _box_intrusion(track) == 0.0


@pytest.mark.slow
def test_pursuit_drives_through_real_track_hairpins_on_pybullet() -> None:
    """random:0 with 0.6 m hairpins: pursuit got stuck on a wall box inside the first one."""
    from agents.baselines import make_baseline
    from arena.env import RacingEnv
    from arena.race import run_race

    env = RacingEnv(track="random:0:length=200,difficulty=0.8,hairpin=0.6", n_cars=1)
    result, _ = run_race(
        [make_baseline("pursuit", env.layout, env.params)],
        track=env.base_track,
        laps=1,
        record=False,
    )
    env.close()
    assert result.cars[0].status == "finished", result.cars[0].dnf_reason


def test_the_maps_cache_is_bounded_and_keeps_the_most_recent(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # Training on generated tracks (`--procedural`) builds maps for a new track every few
    # rollouts; an unbounded cache kept every one (10–40 MB each): a 4 M-step run grew by
    # ~5 GB and was killed for memory. The cache now drops the least recently used maps
    # past its byte budget; what it drops is rebuilt when asked for again.
    from arena.batch import maps as maps_module
    from tracks import load_track

    monkeypatch.setattr(maps_module, "_CACHE", maps_module.OrderedDict())
    tracks = [load_track(f"random:{seed}:length=100") for seed in (11, 12, 13, 14)]
    first = TrackMaps.build(tracks[0])
    monkeypatch.setattr(maps_module, "CACHE_BYTES", int(2.5 * first.nbytes))
    built = [first] + [TrackMaps.build(t) for t in tracks[1:]]
    cache = maps_module._CACHE
    assert sum(m.nbytes for m in cache.values()) <= maps_module.CACHE_BYTES
    assert built[-1] in cache.values() and first not in cache.values()
    assert TrackMaps.build(tracks[-1]) is built[-1]  # still cached: the same maps
    again = TrackMaps.build(tracks[0])  # dropped: built anew, equal
    assert again is not first and np.array_equal(again.ranges, first.ranges)
    # Asking for cached maps makes them the most recent: the next eviction spares them.
    TrackMaps.build(tracks[-1])
    TrackMaps.build(tracks[1])
    assert built[-1] in cache.values()
