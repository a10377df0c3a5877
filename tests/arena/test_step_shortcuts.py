"""The env step's shortcuts give exactly what the work they skip would have given.

Each shortcut (bench/env_speed.py measures what it saves) is checked against the path it
replaces, bit for bit, on the built-in tracks with cars placed or driven where the shortcut
must not apply: against walls and each other, across the road edges, on the lidar's window
boundaries.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from arena import parallel_env
from arena.batch.xp import NUMPY
from arena.core import EpisodeRules, Sensed, episode_start, episode_step
from arena.lidar import Lidar
from arena.sim import CLEARANCE_CAP, CLEARANCE_CELL, CarParams, Simulator
from arena.walls import Clearance, Walls
from tracks import load_track


@pytest.mark.parametrize("name", ["oval", "hairpins"])
def test_clearance_grid_never_exceeds_the_distance_to_a_wall_box(name: str) -> None:
    # The contact-query skip trusts this bound: brute force over every box of the walls
    # the simulator builds, at random points on, beside and far off the track.
    sim = Simulator(load_track(name), 1)
    try:
        centres, halves, yaws = sim._wall_boxes()
    finally:
        sim.close()
    grid = Clearance.of_boxes(centres, halves, yaws, CLEARANCE_CELL, CLEARANCE_CAP)
    rng = np.random.default_rng(3)
    pts = rng.uniform(centres.min(axis=0) - 3.0, centres.max(axis=0) + 3.0, (4000, 2))
    rel = pts[:, None, :] - centres[None]
    cos, sin = np.cos(yaws), np.sin(yaws)
    along = np.abs(cos * rel[..., 0] + sin * rel[..., 1]) - halves[:, 0]
    across = np.abs(cos * rel[..., 1] - sin * rel[..., 0]) - halves[:, 1]
    exact = np.hypot(np.maximum(along, 0.0), np.maximum(across, 0.0)).min(axis=1)
    bound = np.array([grid.at(x, y) for x, y in pts.tolist()])
    assert (bound <= exact).all()
    assert (bound[exact == 0.0] <= 0.0).all() and (exact == 0.0).any()  # points in walls
    # Not uselessly loose: within a cell's diagonal of the truth below the cap.
    near = exact < CLEARANCE_CAP - CLEARANCE_CELL * math.sqrt(2.0)
    assert (exact[near] - bound[near] <= CLEARANCE_CELL * math.sqrt(2.0)).all()
    assert grid.at(1e9, -1e9) == CLEARANCE_CAP  # far outside the grid
    assert grid.at(math.nan, 0.0) == 0.0  # unknown: never clear


@pytest.mark.parametrize(("name", "n_cars"), [("hairpins", 6), ("chicanes", 3)])
def test_skipping_the_contact_query_changes_no_step(name: str, n_cars: int) -> None:
    # Wild random driving (cars into walls and into each other) on two simulators, one of
    # which always asks pybullet for its contacts: the same poses and contact flags, while
    # the other skipped the query on some steps and contacts did happen.
    track = load_track(name)
    sims = [Simulator(track, n_cars), Simulator(track, n_cars)]
    skipped = []
    fast = sims[0]._kept_apart

    def counted(rows: list[tuple[float, ...]], tyres: list[tuple[float, ...]]) -> bool:
        skipped.append(fast(rows, tyres))
        return skipped[-1]

    sims[0]._kept_apart = counted  # type: ignore[method-assign]
    sims[1]._kept_apart = lambda rows, tyres: False  # type: ignore[method-assign]
    rng = np.random.default_rng(7)
    walls = cars = 0
    try:
        for episode in range(3):
            grid = track.start_grid(n_cars, offset=float(rng.uniform(0.0, track.length)))
            for sim in sims:
                sim.reset(grid)
            for _ in range(120 if episode else 60):
                steer = np.clip(rng.normal(0.0, 0.8, n_cars), -1.0, 1.0)
                throttle = np.clip(rng.normal(0.6, 0.5, n_cars), -1.0, 1.0)
                a, b = (sim.step(steer, throttle) for sim in sims)
                for field in ("poses", "velocity", "wall_contact", "car_contact"):
                    assert getattr(a, field).tobytes() == getattr(b, field).tobytes()
                walls += int(a.wall_contact.sum())
                cars += int(a.car_contact.sum())
    finally:
        for sim in sims:
            sim.close()
    assert walls and cars  # the query was needed on some steps …
    assert any(skipped) and not all(skipped)  # … and skipped on others


def test_off_track_shortcut_matches_the_four_wheel_test() -> None:
    # Cars on both sides of both road edges, at any heading: the rules with the shortcut
    # (every car clear of the edges) and without it (wheel reach infinite) decide the same.
    track = load_track("hairpins")
    params = CarParams()
    rules = EpisodeRules.build(
        track, NUMPY, n_cars=4, laps=2, control_hz=20, params=params, off_track_limit=0.5
    )
    plain = replace(rules, wheel_reach=math.inf)
    rng = np.random.default_rng(1)
    shortcut_taken = 0
    for trial in range(400):
        s = rng.uniform(0.0, track.length, (1, 4))
        left, right = track.widths_at(s[0])
        # Half the trials keep every car well inside (the shortcut's case), half spread
        # them over and beyond the edges.
        spread = 0.3 if trial % 2 else 1.6
        d = rng.uniform(-spread * right, spread * left)[None]
        heading = track.heading_at(s[0])[None]
        state = episode_start(NUMPY, rules, s, np.zeros(1), np.ones(1, dtype=bool))
        state.off_time = rng.uniform(0.0, 1.0, (1, 4)) * (trial % 3 == 0)
        sensed = Sensed(
            s=s,
            d=d,
            heading=heading,
            yaw=heading + rng.uniform(-math.pi, math.pi, (1, 4)),
            left=left[None],
            right=right[None],
            wall=np.zeros((1, 4), dtype=bool),
            touching=np.zeros((1, 4, 4), dtype=bool),
            upright=np.ones((1, 4)),
            prev_poses=np.zeros((1, 4, 3)),
            prev_velocity=np.zeros((1, 4, 2)),
        )
        _, fast = episode_step(NUMPY, rules, state, sensed)
        _, full = episode_step(NUMPY, plain, state, sensed)
        shortcut_taken += bool((np.abs(d) + rules.wheel_reach <= np.minimum(left, right)).all())
        for field in ("off_track", "all_wheels_on", "terminated", "dnf", "reward"):
            x, y = getattr(fast, field), getattr(full, field)
            assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), field
        assert fast.terms["off_track"].tobytes() == full.terms["off_track"].tobytes()
    assert 0 < shortcut_taken < 400
    assert rules.wheel_reach > math.hypot(0.5 * params.wheelbase, 0.5 * params.track_width)


@pytest.mark.parametrize("name", ["oval", "technical"])
def test_lidar_windows_are_the_walls_windows(name: str) -> None:
    # The lidar reads each car's windowed wall segments from a padded sliding table; every
    # centre-line segment must get Walls.window's rows, the loop's seam included.
    track = load_track(name)
    walls = Walls.around(track)
    lidar = Lidar(walls, n_rays=16)
    segment = np.arange(track.n_points)
    expected = lidar._table[walls.window(segment, lidar.half_window)]
    assert np.array_equal(lidar._windows[walls.window_start(segment)], expected)


def test_float_actions_are_read_as_their_float64_values() -> None:
    # A policy's float32 action takes the shortcut; a list, a float64 array, a (1, 2) array
    # and an integer array do not, and all give the same controls for the same numbers.
    env = parallel_env(track="oval", n_cars=4)
    try:
        env.reset(seed=0)
        values = [[0.3, -0.7], [np.nan, 2.0], [-np.inf, 1e-8], [1.0, -1.0]]
        as_f32 = dict(zip(env.agents, np.array(values, dtype=np.float32), strict=True))
        as_list = {a: np.float32(v).tolist() for a, v in as_f32.items()}
        shaped = {a: np.asarray(v, dtype=np.float64).reshape(1, 2) for a, v in as_f32.items()}
        for other in (as_list, shaped):
            for x, y in zip(env._controls(as_f32), env._controls(other), strict=True):
                assert x.dtype == y.dtype and x.tobytes() == y.tobytes()
        ints = {a: np.array([1, -1]) for a in env.agents}
        steer, throttle = env._controls(ints)
        assert steer.tolist() == [1.0] * 4 and throttle.tolist() == [-1.0] * 4
    finally:
        env.close()
