"""Shared helpers for the arena tests: a drag strip, grid placement and simple drivers."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from functools import lru_cache
from typing import Any
from unittest import mock

import numpy as np
from numpy.typing import NDArray

from arena.env import RacingEnv
from tracks import Track

FloatArray = NDArray[np.float64]

STRIP_STRAIGHT = 150.0  # m, each straight of the drag strip
STRIP_RADIUS = 12.0  # m, its bends
STRIP_HALF_WIDTH = 2.0  # m, each side of the centre line
STRIP_START = 40.0  # m into the lower straight: the start line


@lru_cache(maxsize=1)
def drag_strip() -> Track:
    """A stadium with 150 m straights, 4 m wide, start line 40 m into the lower straight.

    The lower straight runs along ``y = -12`` in +x; progress ``s`` from -40 m to +110 m
    (mod the lap) lies on it, so tests can accelerate, brake and collide far from any bend.
    """
    half = STRIP_STRAIGHT / 2
    xs = np.linspace(-half, half, 31)[:-1]
    arc = np.linspace(-np.pi / 2, np.pi / 2, 25)[:-1]
    r = STRIP_RADIUS
    pts = np.vstack(
        [
            np.column_stack([xs, np.full_like(xs, -r)]),
            np.column_stack([half + r * np.cos(arc), r * np.sin(arc)]),
            np.column_stack([-xs, np.full_like(xs, r)]),
            np.column_stack([-half - r * np.cos(arc), -r * np.sin(arc)]),
        ]
    )
    return Track(pts, STRIP_HALF_WIDTH, STRIP_HALF_WIDTH, name="drag-strip", start_s=STRIP_START)


def pose_at(track: Track, s: float, d: float = 0.0, yaw_offset: float = 0.0) -> FloatArray:
    """Pose (3,) [x m, y m, yaw rad] at progress ``s`` m, offset ``d`` m, heading + offset."""
    xy = track.to_cartesian(np.array([[track.wrap_s(s), d]]))[0]
    return np.array([xy[0], xy[1], float(track.heading_at(track.wrap_s(s))) + yaw_offset])


@contextmanager
def grid_at(env: RacingEnv, poses: FloatArray) -> Iterator[None]:
    """Within the block, ``env.reset`` puts car ``i`` at ``poses[i]`` instead of the grid."""
    poses = np.asarray(poses, dtype=np.float64)
    track = env.base_track

    def start_grid(n_cars: int, **_: Any) -> FloatArray:
        assert n_cars == len(poses)
        return poses.copy()

    with mock.patch.object(track, "start_grid", side_effect=start_grid):
        yield


def pursuit_driver(env: RacingEnv) -> Callable[[Any], NDArray[np.float32]]:
    """The pure-pursuit baseline's ``act`` for this env's observation layout."""
    from agents.baselines import PursuitPolicy

    return PursuitPolicy(env.layout, env.params).act


def speed_throttle(v_long: float, target: float, gain: float = 2.0) -> float:
    """A proportional throttle that holds ``target`` m/s."""
    return float(np.clip(gain * (target - v_long), -1.0, 1.0))
