"""The 2D lidar against a brute-force ray cast over every wall segment and car edge."""

from __future__ import annotations

import math

import numpy as np
import pytest

from arena.lidar import DEFAULT_RANGE, Lidar
from arena.sim import PARKING_X, CarParams, car_corners
from arena.walls import Walls
from tests.arena.conftest import FloatArray, drag_strip, pose_at
from tracks import Track, load_track


def brute_force_scan(lidar: Lidar, poses: FloatArray, corners: FloatArray) -> FloatArray:
    """Ranges (n, n_rays): each ray against all wall segments and all other cars' edges."""
    starts, ends = lidar.walls.segments()
    out = np.full((len(poses), lidar.n_rays), lidar.max_range)
    for i, (x, y, yaw) in enumerate(poses):
        others = [j for j in range(len(poses)) if j != i]
        a = np.vstack([starts, *(corners[j] for j in others)])
        b = np.vstack([ends, *(np.roll(corners[j], -1, axis=0) for j in others)])
        e = b - a
        q = a - np.array([x, y])
        for k, angle in enumerate(lidar.angles):
            ux, uy = math.cos(yaw + angle), math.sin(yaw + angle)
            denom = ux * e[:, 1] - uy * e[:, 0]
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (q[:, 0] * e[:, 1] - q[:, 1] * e[:, 0]) / denom  # along the ray
                w = (q[:, 0] * uy - q[:, 1] * ux) / denom  # along the segment
            hit = (np.abs(denom) > 1e-12) & (t > 0) & (w >= 0) & (w <= 1)
            if hit.any():
                out[i, k] = min(lidar.max_range, float(t[hit].min()))
    return out


def random_poses(track: Track, n: int, rng: np.random.Generator) -> FloatArray:
    """``n`` poses on the road within a few metres of each other, headings roughly along it."""
    s0 = rng.uniform(0.0, track.length)
    poses = []
    for s in s0 + rng.uniform(0.0, 6.0, n):
        left, right = (float(w[0]) for w in track.widths_at([s]))
        d = rng.uniform(-0.8 * right, 0.8 * left)
        poses.append(pose_at(track, s, d, rng.normal(0.0, 0.6)))
    return np.array(poses)


@pytest.mark.parametrize("track_name", ["oval", "hairpins", "technical", "monza"])
def test_scan_matches_brute_force(track_name: str) -> None:
    track = load_track(track_name)
    lidar = Lidar(Walls.around(track), n_rays=64)
    params = CarParams()
    rng = np.random.default_rng(len(track_name))
    for _ in range(8):
        poses = random_poses(track, 4, rng)
        corners = car_corners(poses, params.length, params.width)
        segment = track.project(poses[:, :2]).segment
        fast = lidar.scan(poses, segment, corners)
        slow = brute_force_scan(lidar, poses, corners)
        np.testing.assert_allclose(fast, slow, rtol=0, atol=1e-9)
        assert np.any(fast < lidar.max_range)  # walls are always in sight on a road


def test_scan_sees_walls_only_without_cars() -> None:
    track = load_track("oval")
    lidar = Lidar(Walls.around(track), n_rays=32)
    poses = random_poses(track, 3, np.random.default_rng(7))
    segment = track.project(poses[:, :2]).segment
    far = np.full((3, 4, 2), PARKING_X)  # cars nowhere near: walls only
    np.testing.assert_allclose(
        lidar.scan(poses, segment), brute_force_scan(lidar, poses, far), rtol=0, atol=1e-9
    )


def test_car_right_in_front_is_seen_at_its_distance() -> None:
    track = drag_strip()
    lidar = Lidar(Walls.around(track), n_rays=65)  # odd: ray 32 points straight ahead
    assert lidar.angles[32] == pytest.approx(0.0, abs=1e-12)
    params = CarParams()
    poses = np.stack([pose_at(track, -20.0), pose_at(track, -17.0)])  # 3 m between centres
    corners = car_corners(poses, params.length, params.width)
    ranges = lidar.scan(poses, track.project(poses[:, :2]).segment, corners)
    gap = float(np.hypot(*(poses[1, :2] - poses[0, :2])))  # 3 m, to the spline's precision
    assert gap == pytest.approx(3.0, abs=1e-4)
    assert ranges[0, 32] == pytest.approx(gap - params.length / 2, abs=1e-6)
    # The car in front does not see the one behind it (outside its 270° field of view),
    # and a 1.5 m-wide gap each side means nothing else is that close straight ahead.
    assert ranges[1, 32] == pytest.approx(lidar.max_range)
    # Without the other car the ray runs on down the straight.
    alone = lidar.scan(poses[:1], track.project(poses[:1, :2]).segment, corners[:1])
    assert alone[0, 32] == pytest.approx(lidar.max_range)


def test_rays_sweep_from_right_to_left() -> None:
    track = drag_strip()
    lidar = Lidar(Walls.around(track), n_rays=65)
    # Near the right edge: the right wall (ray 0 side) is closer than the left one.
    pose = pose_at(track, -20.0, -1.5)[None]
    ranges = lidar.scan(pose, track.project(pose[:, :2]).segment)[0]
    right = 2.0 - 1.5 + 0.4  # m: to the right road edge, then the run-off
    left = 2.0 + 1.5 + 0.4
    side = int(np.argmin(np.abs(lidar.angles + math.pi / 2)))  # ray pointing right
    expected = right / math.cos(lidar.angles[side] + math.pi / 2)
    assert ranges[side] == pytest.approx(expected, abs=1e-4)
    mirror = int(np.argmin(np.abs(lidar.angles - math.pi / 2)))
    expected = left / math.cos(lidar.angles[mirror] - math.pi / 2)
    assert ranges[mirror] == pytest.approx(expected, abs=1e-4)


def test_nothing_in_range_reads_max_range() -> None:
    track = load_track("oval")
    lidar = Lidar(Walls.around(track), n_rays=64, max_range=DEFAULT_RANGE)
    parked = np.array([[PARKING_X, PARKING_X, 0.3], [PARKING_X + 30.0, PARKING_X, 2.0]])
    corners = car_corners(parked, 0.5, 0.3)
    ranges = lidar.scan(parked, np.zeros(2, dtype=np.int64), corners)
    assert ranges.shape == (2, 64)
    assert np.all(ranges == lidar.max_range)


def test_lidar_rejects_bad_configuration() -> None:
    walls = Walls.around(load_track("oval"))
    for kwargs in ({"n_rays": 0}, {"fov": 0.0}, {"fov": 7.0}, {"max_range": 0.0}):
        with pytest.raises(ValueError):
            Lidar(walls, **kwargs)
