"""The env step's shortcuts give exactly what the work they skip would have given.

Each shortcut (bench/env_speed.py measures what it saves) is checked against the path it
replaces, bit for bit, on the built-in tracks with cars placed or driven where the shortcut
must not apply: against walls and each other, across the road edges, on the lidar's window
boundaries.
"""

from __future__ import annotations

import math
import sys
from dataclasses import fields, replace
from typing import Any

import numpy as np
import pytest

from arena import parallel_env
from arena.batch.xp import NUMPY
from arena.core import (
    EpisodeRules,
    EpisodeState,
    Outcome,
    Sensed,
    _quiet_step,
    _rules_step,
    episode_start,
    episode_step,
)
from arena.lidar import Lidar
from arena.sim import CLEARANCE_CAP, CLEARANCE_CELL, CarParams, Simulator
from arena.walls import Clearance, Walls
from tests.arena.conftest import pursuit_driver
from tracks import load_track

env_module = sys.modules["arena.env"]  # ``arena.env`` the attribute is the AEC constructor


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


def assert_same_step(a: tuple[EpisodeState, Outcome], b: tuple[EpisodeState, Outcome]) -> None:
    """Every array of the two steps' states and outcomes (and the terms, in order) alike."""
    for x, y in zip(a, b, strict=True):
        for field in fields(x):
            u, v = getattr(x, field.name), getattr(y, field.name)
            if isinstance(u, dict):
                assert list(u) == list(v), field.name
                pairs = list(zip(u.values(), v.values(), strict=True))
            else:
                pairs = [(u, v)]
            for p, q in pairs:
                assert p.dtype == q.dtype and p.shape == q.shape, field.name
                assert p.tobytes() == q.tobytes(), field.name


@pytest.mark.parametrize(
    ("name", "n_cars", "kwargs", "noise"),
    [
        ("oval", 4, {"laps": 2}, 0.0),  # laps, overtakes, close racing
        ("hairpins", 6, {"max_cycles": 150}, 0.8),  # walls, contacts, edges, truncation
        ("chicanes", 3, {"stuck_time": 0.5, "off_track_limit": 0.2}, 1.5),  # stalls, DNFs
        ("oval", 2, {"preset": "deepracer", "max_cycles": 120}, 0.6),  # ends on a crash
    ],
)
def test_quiet_step_is_the_rules_step(
    monkeypatch: pytest.MonkeyPatch, name: str, n_cars: int, kwargs: dict[str, Any], noise: float
) -> None:
    # Real races (pursuit drivers, some jostled): on every step the Python-float quiet step
    # either declines or gives the array path's state and outcome bit for bit; both happen.
    taken = []

    def checked(ops: Any, rules: EpisodeRules, st: EpisodeState, sensed: Sensed) -> Any:
        full = _rules_step(ops, rules, st, sensed)
        quiet = _quiet_step(rules, st, sensed)
        taken.append(quiet is not None)
        if quiet is not None:
            assert_same_step(quiet, full)
        return full

    monkeypatch.setattr(env_module, "episode_step", checked)
    env = parallel_env(track=name, n_cars=n_cars, **kwargs)
    drive = pursuit_driver(env)
    rng = np.random.default_rng(4)
    obs, _ = env.reset(seed=2)
    for _ in range(400):
        if not env.agents:
            obs, _ = env.reset(seed=len(taken))
        acts = {a: drive(obs[a]) + noise * rng.standard_normal(2).astype(np.float32) for a in obs}
        obs, *_ = env.step(acts)
    env.close()
    assert any(taken) and not all(taken)


def test_quiet_step_declines_what_it_cannot_decide() -> None:
    # One quiet step of a real race, then each thing that makes a step not quiet, alone:
    # the quiet step declines it or agrees with the array path bit for bit.
    env = parallel_env(track="oval", n_cars=3)
    env.reset(seed=0)
    go = {a: np.array([0.0, 0.6], dtype=np.float32) for a in env.agents}
    for _ in range(30):
        env.step(go)
    rules, st = env._rules, env._ep
    frame = env._frame
    assert frame is not None
    s, d = frame.episode.s, frame.d[None]
    left, right = (w[None] for w in env.track.widths_at(s[0]))
    base = Sensed(
        s=s + 0.05,
        d=d,
        heading=np.zeros((1, 3)),
        yaw=np.zeros((1, 3)),
        left=left,
        right=right,
        wall=np.zeros((1, 3), dtype=bool),
        touching=np.zeros((1, 3, 3), dtype=bool),
        upright=np.ones((1, 3)),
        prev_poses=frame.poses[None],
        prev_velocity=frame.velocity[None, :, :2],
    )
    gate = rules.gate_s[st.next_gate]
    touching = np.zeros((1, 3, 3), dtype=bool)
    touching[0, 0, 1] = touching[0, 1, 0] = True
    variants = {
        "quiet": {},
        "gate": {"s": np.where([[True, False, False]], gate + 1e-9, s + 0.05)},
        "lap jump": {"s": s + 4.0},  # a cut: no progress
        "nan s": {"s": np.array([[np.nan, 1.0, 2.0]]) + 0 * s},
        "edge": {"d": d + np.where([[False, True, False]], left, 0.0)},
        "nan d": {"d": np.array([[0.0, np.nan, 0.0]])},
        "touch": {"touching": touching},
        "wall": {"wall": np.array([[False, False, True]])},
        "flip": {"upright": np.array([[1.0, 0.1, 1.0]])},
        "nan upright": {"upright": np.array([[1.0, np.nan, 0.1]])},
    }
    quiet_ones = 0
    for crash in (False, True):
        rules_now = replace(rules, end_on_crash=crash)
        for label, change in variants.items():
            sensed = replace(base, **change)
            quiet = _quiet_step(rules_now, st, sensed)
            if quiet is not None:
                assert_same_step(quiet, _rules_step(NUMPY, rules_now, st, sensed))
                quiet_ones += 1
            else:
                assert label != "quiet", label
    for steps in (rules.max_cycles - 1, rules.window, rules.window - 1):  # limit, stuck test
        later = replace(st, steps=np.array([steps]))
        quiet = _quiet_step(rules, later, base)
        if quiet is not None:
            assert_same_step(quiet, _rules_step(NUMPY, rules, later, base))
    assert quiet_ones >= 4
    env.close()
