"""Reward modes: DeepRacer compatibility, the racing terms, progress and overtaking."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from arena import RacingEnv
from arena.deepracer import follow_centre_line
from arena.rewards import RACING_TERMS, collision_blame, race_positions
from tests.arena.conftest import drag_strip, grid_at, pose_at, pursuit_driver, speed_throttle

# Every key of the DeepRacer reward-function params dict, with its type.
DEEPRACER_KEYS: dict[str, type | tuple[type, ...]] = {
    "all_wheels_on_track": bool,
    "x": float,
    "y": float,
    "heading": float,
    "distance_from_center": float,
    "is_left_of_center": bool,
    "is_offtrack": bool,
    "is_crashed": bool,
    "is_reversed": bool,
    "progress": float,
    "steps": int,
    "speed": float,
    "steering_angle": float,
    "track_width": float,
    "track_length": float,
    "waypoints": list,
    "closest_waypoints": list,
    "closest_objects": list,
    "objects_location": list,
    "objects_left_of_center": list,
    "objects_speed": list,
    "objects_heading": list,
    "objects_distance": list,
    "objects_distance_from_center": list,
    "object_in_camera": bool,
    "projection_distance": float,
}


def test_deepracer_example_runs_unchanged_as_the_reward() -> None:
    env = RacingEnv(track="oval", n_cars=2, reward=follow_centre_line)
    drive = pursuit_driver(env)
    obs, _ = env.reset(seed=0)
    rewards_seen = []
    for _ in range(150):
        obs, rewards, _, _, infos = env.step({a: drive(obs[a]) for a in env.agents})
        for agent, r in rewards.items():
            assert r in (1.0, 0.5, 0.1, 1e-3)
            assert infos[agent]["reward_terms"]["deepracer"] == r
            rewards_seen.append(r)
    assert np.mean(np.array(rewards_seen) == 1.0) > 0.5  # pursuit keeps near the centre
    env.close()


@pytest.fixture(scope="module")
def deepracer_params() -> tuple[RacingEnv, list[tuple[int, dict[str, Any]]]]:
    """(env step, params) seen by a reward function over 200 steps of 3 pursuit cars."""
    calls: list[dict[str, Any]] = []

    def spy(params: dict[str, Any]) -> float:
        calls.append(params)
        return follow_centre_line(params)

    env = RacingEnv(track="hairpins", n_cars=3, laps=2, reward=spy)
    drive = pursuit_driver(env)
    obs, _ = env.reset(seed=0)
    seen: list[tuple[int, dict[str, Any]]] = []
    for _ in range(200):
        obs, _, _, _, _ = env.step({a: drive(obs[a]) for a in env.agents})
        seen.extend((env.steps, params) for params in calls)
        calls.clear()
    env.close()
    return env, seen


def test_deepracer_params_have_every_key_with_its_type(deepracer_params: Any) -> None:
    _, seen = deepracer_params
    assert len(seen) == 3 * 200  # once per car and step
    for _, params in seen:
        for key, kind in DEEPRACER_KEYS.items():
            assert isinstance(params[key], kind), key


def test_deepracer_params_values_are_in_range(deepracer_params: Any) -> None:
    env, seen = deepracer_params
    track = env.track
    waypoints = seen[0][1]["waypoints"]
    assert all(
        isinstance(w, tuple) and len(w) == 2 and all(isinstance(c, float) for c in w)
        for w in waypoints
    )
    spacing = np.linalg.norm(np.diff(np.array(waypoints), axis=0), axis=1)
    assert np.all((spacing > 0.3) & (spacing < 0.7))  # about every 0.5 m
    max_steer = math.degrees(env.params.max_steer)
    for steps, p in seen:
        assert p["steps"] == steps
        assert 0.0 <= p["progress"] <= 100.0
        assert -180.0 <= p["heading"] <= 180.0
        assert abs(p["steering_angle"]) <= max_steer + 1e-9
        here = np.array([p["x"], p["y"]])
        where = track.project(here[None])
        assert p["projection_distance"] == pytest.approx(where.s[0])
        assert p["distance_from_center"] == pytest.approx(abs(where.d[0]))
        assert p["is_left_of_center"] == (where.d[0] > 0)
        assert p["track_length"] == pytest.approx(track.length)
        left, right = track.widths_at(where.s)
        assert p["track_width"] == pytest.approx(float(left[0] + right[0]))
        i, j = p["closest_waypoints"]
        assert isinstance(i, int) and isinstance(j, int)
        assert j == (i + 1) % len(waypoints)
        assert np.linalg.norm(here - np.array(waypoints[i])) < 1.5
        assert len(p["objects_location"]) == len(p["objects_speed"]) == 2
        assert all(isinstance(k, int) and 0 <= k < 2 for k in p["closest_objects"])
        assert not p["is_reversed"] and not p["is_offtrack"]
    # Progress is the share of the race distance (2 laps) covered: about 0 % at the start.
    first, last = seen[0][1], seen[-1][1]
    assert first["progress"] < 1.0
    covered = float(track.delta_s(last["projection_distance"], 0.0))  # < half a lap so far
    assert last["progress"] == pytest.approx(100.0 * covered / (2 * track.length), abs=1.0)


def test_progress_reward_is_the_progress_term() -> None:
    env = RacingEnv(track="oval", n_cars=2, reward="progress")
    drive = pursuit_driver(env)
    obs, infos = env.reset(seed=0)
    start = {a: infos[a]["race_progress"] for a in env.agents}
    total = dict.fromkeys(env.agents, 0.0)
    for _ in range(60):
        obs, rewards, _, _, infos = env.step({a: drive(obs[a]) for a in env.agents})
        for agent, r in rewards.items():
            assert r == infos[agent]["reward_terms"]["progress"]
            total[agent] += r
    # Summed progress is the distance covered along the centre line.
    for agent in env.agents:
        assert total[agent] == pytest.approx(infos[agent]["race_progress"] - start[agent])
        assert total[agent] > 5.0
    env.close()


def test_racing_reward_is_the_sum_of_its_terms() -> None:
    env = RacingEnv(track="chicanes", n_cars=4)
    drive = pursuit_driver(env)
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=0)
    nonzero = dict.fromkeys(RACING_TERMS, False)
    while env.agents and env.steps < 300:
        actions = {a: drive(obs[a]) + rng.normal(0.0, 0.4, 2) for a in env.agents}
        obs, rewards, _, _, infos = env.step(actions)
        for agent, r in rewards.items():
            terms = infos[agent]["reward_terms"]
            assert set(terms) == set(RACING_TERMS)
            assert r == pytest.approx(sum(terms.values()), abs=1e-12)
            for name, value in terms.items():
                nonzero[name] |= value != 0.0
    assert nonzero["progress"] and nonzero["off_track"] and nonzero["wall"]
    env.close()


def test_driving_backwards_gives_negative_progress() -> None:
    env = RacingEnv(track="oval", n_cars=1)
    _, infos = env.reset(seed=0)
    start = infos["car_0"]["race_progress"]
    progress = []
    for _ in range(30):
        _, rewards, _, _, infos = env.step({"car_0": np.array([0.0, -1.0])})  # reverse gear
        progress.append(infos["car_0"]["reward_terms"]["progress"])
        assert rewards["car_0"] == pytest.approx(sum(infos["car_0"]["reward_terms"].values()))
    assert infos["car_0"]["speed"] < -0.5
    assert all(p <= 0.0 for p in progress) and sum(progress) < -0.5
    assert infos["car_0"]["race_progress"] == pytest.approx(start + sum(progress))
    env.close()


def test_overtaking_earns_a_place_and_costs_the_other_car_one() -> None:
    env = RacingEnv(track=drag_strip(), n_cars=2)
    track = env.base_track
    # car_0 ahead in the left lane, car_1 behind in the right lane: 2 m apart sideways.
    with grid_at(env, np.stack([pose_at(track, -25.0, 1.0), pose_at(track, -27.0, -1.0)])):
        env.reset(seed=0)
    overtakes, ranks = [], []
    v0 = 0.0
    for _ in range(60):
        actions = {"car_0": np.array([0.0, speed_throttle(v0, 1.0)]), "car_1": np.array([0, 1.0])}
        infos = env.step(actions)[4]
        v0 = infos["car_0"]["speed"]
        overtakes.append([infos[a]["reward_terms"]["overtake"] for a in ("car_0", "car_1")])
        ranks.append([infos[a]["rank"] for a in ("car_0", "car_1")])
        assert not infos["car_0"]["collisions"]
    overtakes_arr = np.array(overtakes)
    (when,) = np.flatnonzero(overtakes_arr.any(axis=1))  # exactly one step with a pass
    assert overtakes_arr[when].tolist() == [-1.0, 1.0]
    assert ranks[0] == [1, 2] and ranks[-1] == [2, 1]
    assert ranks[when] == [2, 1] and ranks[when - 1] == [1, 2]
    env.close()


def test_race_positions_rank_by_progress() -> None:
    assert race_positions(np.array([3.0, 10.0, -1.0, 5.0])).tolist() == [3, 1, 4, 2]


def test_collision_blame_is_geometric() -> None:
    # i behind j, closing: i to blame; j not. Side by side: nobody. Head-on: both.
    poses = np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.4, 0.0], [1.0, 0.0, math.pi]])
    vel = np.array([[3.0, 0.0], [1.0, 0.0], [3.0, 0.0], [-2.0, 0.0]])
    pair = np.zeros((4, 4), dtype=bool)
    pair[0, 1] = pair[1, 0] = True
    at_fault, closing = collision_blame(poses, vel, pair)
    assert at_fault[0, 1] and not at_fault[1, 0]
    assert closing[0, 1] == pytest.approx(2.0)
    side = np.zeros((4, 4), dtype=bool)
    side[0, 2] = side[2, 0] = True
    assert not collision_blame(poses, vel, side)[0].any()
    head_on = np.zeros((4, 4), dtype=bool)
    head_on[1, 3] = head_on[3, 1] = True
    at_fault, _ = collision_blame(poses, vel, head_on)
    assert at_fault[1, 3] and at_fault[3, 1]
    # Without a contact nobody is to blame, however fast they close.
    assert not collision_blame(poses, vel, np.zeros((4, 4), dtype=bool))[0].any()
