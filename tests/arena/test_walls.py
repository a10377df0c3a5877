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
