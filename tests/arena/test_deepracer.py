# mypy: disable-error-code="assignment"
# (AWS example 1, kept verbatim, assigns an int and then floats to ``reward``.)
"""DeepRacer fidelity: the AWS examples run unchanged for whole races, params mean what the
developer guide says, and the ``deepracer`` preset's action spaces parse as DeepRacer writes them.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from arena import RacingEnv, parallel_env
from arena.cars import car_params
from arena.deepracer import (
    DEEPRACER_PRESET,
    DeepRacerError,
    DeepRacerParams,
    action_table,
    find_prev_next,
    read_model_metadata,
)
from tests.arena.conftest import pursuit_driver
from tests.tracks.builders import chicane_points, stadium_points
from tests.tracks.test_real_files import deepracer_rows, save_npy
from tracks import Track

# ---- the AWS DeepRacer Developer Guide's reward functions, verbatim -------------------------------
# Examples 1-4: https://docs.aws.amazon.com/deepracer/latest/developerguide/deepracer-reward-function-examples.html
# The waypoints/heading example: the ``waypoints`` entry of
# https://docs.aws.amazon.com/deepracer/latest/developerguide/deepracer-reward-function-input.html
# ruff: noqa: E501


def example_1(params):
    """
    Example of rewarding the agent to follow center line
    """

    # Read input parameters
    track_width = params["track_width"]
    distance_from_center = params["distance_from_center"]

    # Calculate 3 markers that are increasingly further away from the center line
    marker_1 = 0.1 * track_width
    marker_2 = 0.25 * track_width
    marker_3 = 0.5 * track_width

    # Give higher reward if the car is closer to center line and vice versa
    if distance_from_center <= marker_1:
        reward = 1
    elif distance_from_center <= marker_2:
        reward = 0.5
    elif distance_from_center <= marker_3:
        reward = 0.1
    else:
        reward = 1e-3  # likely crashed/ close to off track

    return reward


def example_2(params):
    """
    Example of rewarding the agent to stay inside the two borders of the track
    """

    # Read input parameters
    all_wheels_on_track = params["all_wheels_on_track"]
    distance_from_center = params["distance_from_center"]
    track_width = params["track_width"]

    # Give a very low reward by default
    reward = 1e-3

    # Give a high reward if no wheels go off the track and
    # the car is somewhere in between the track borders
    if all_wheels_on_track and (0.5 * track_width - distance_from_center) >= 0.05:
        reward = 1.0

    # Always return a float value
    return reward


def example_3(params):
    """
    Example of penalize steering, which helps mitigate zig-zag behaviors
    """

    # Read input parameters
    distance_from_center = params["distance_from_center"]
    track_width = params["track_width"]
    abs_steering = abs(params["steering_angle"])  # Only need the absolute steering angle

    # Calculate 3 marks that are farther and father away from the center line
    marker_1 = 0.1 * track_width
    marker_2 = 0.25 * track_width
    marker_3 = 0.5 * track_width

    # Give higher reward if the car is closer to center line and vice versa
    if distance_from_center <= marker_1:
        reward = 1.0
    elif distance_from_center <= marker_2:
        reward = 0.5
    elif distance_from_center <= marker_3:
        reward = 0.1
    else:
        reward = 1e-3  # likely crashed/ close to off track

    # Steering penality threshold, change the number based on your action space setting
    ABS_STEERING_THRESHOLD = 15

    # Penalize reward if the car is steering too much
    if abs_steering > ABS_STEERING_THRESHOLD:
        reward *= 0.8

    return float(reward)


def example_4(params):
    """
    Example of rewarding the agent to stay inside two borders
    and penalizing getting too close to the objects in front
    """

    all_wheels_on_track = params["all_wheels_on_track"]
    distance_from_center = params["distance_from_center"]
    track_width = params["track_width"]
    objects_location = params["objects_location"]
    agent_x = params["x"]
    agent_y = params["y"]
    _, next_object_index = params["closest_objects"]
    objects_left_of_center = params["objects_left_of_center"]
    is_left_of_center = params["is_left_of_center"]

    # Initialize reward with a small number but not zero
    # because zero means off-track or crashed
    reward = 1e-3

    # Reward if the agent stays inside the two borders of the track
    if all_wheels_on_track and (0.5 * track_width - distance_from_center) >= 0.05:
        reward_lane = 1.0
    else:
        reward_lane = 1e-3

    # Penalize if the agent is too close to the next object
    reward_avoid = 1.0

    # Distance to the next object
    next_object_loc = objects_location[next_object_index]
    distance_closest_object = math.sqrt(
        (agent_x - next_object_loc[0]) ** 2 + (agent_y - next_object_loc[1]) ** 2
    )

    # Decide if the agent and the next object is on the same lane
    is_same_lane = objects_left_of_center[next_object_index] == is_left_of_center

    if is_same_lane:
        if 0.5 <= distance_closest_object < 0.8:
            reward_avoid *= 0.5
        elif 0.3 <= distance_closest_object < 0.5:
            reward_avoid *= 0.2
        elif distance_closest_object < 0.3:
            reward_avoid = 1e-3  # Likely crashed

    # Calculate reward by putting different weights on
    # the two aspects above
    reward += 1.0 * reward_lane + 4.0 * reward_avoid

    return reward


def waypoints_heading(params):
    ###############################################################################
    """
    Example of using waypoints and heading to make the car point in the right direction
    """

    import math

    # Read input variables
    waypoints = params["waypoints"]
    closest_waypoints = params["closest_waypoints"]
    heading = params["heading"]

    # Initialize the reward with typical value
    reward = 1.0

    # Calculate the direction of the centerline based on the closest waypoints
    next_point = waypoints[closest_waypoints[1]]
    prev_point = waypoints[closest_waypoints[0]]

    # Calculate the direction in radius, arctan2(dy, dx), the result is (-pi, pi) in radians
    track_direction = math.atan2(next_point[1] - prev_point[1], next_point[0] - prev_point[0])
    # Convert to degree
    track_direction = math.degrees(track_direction)

    # Calculate the difference between the track direction and the heading direction of the car
    direction_diff = abs(track_direction - heading)
    if direction_diff > 180:
        direction_diff = 360 - direction_diff

    # Penalize the reward if the difference is too large
    DIRECTION_THRESHOLD = 10.0
    if direction_diff > DIRECTION_THRESHOLD:
        reward *= 0.5

    return float(reward)


AWS_EXAMPLES = (example_1, example_2, example_3, example_4, waypoints_heading)


# ---- whole races with every example ----------------------------------------------------------


class AllExamples:
    """A reward function that runs every AWS example on the same params and records them."""

    def __init__(self) -> None:
        self.calls = 0
        self.heading_rewards: list[float] = []
        self.seen: list[dict[str, Any]] = []

    def __call__(self, params: dict[str, Any]) -> float:
        values = [float(fn(params)) for fn in AWS_EXAMPLES]
        assert all(math.isfinite(v) and v > 0 for v in values)
        self.calls += 1
        self.heading_rewards.append(values[-1])
        self.seen.append(params)
        return sum(values)


@pytest.mark.parametrize("direction", ["forward", "reverse"])
def test_aws_examples_run_whole_races_where_others_finish_or_retire(direction: str) -> None:
    # Three cars, one lap: two pursuit drivers finish (one a little later), the third sits
    # still on the grid and retires (stuck). Every example, AWS example 4 included, runs for
    # every step of every car until the race is over.
    reward = AllExamples()
    env = RacingEnv(track="oval", n_cars=3, laps=1, reward=reward)
    drive = pursuit_driver(env)
    obs, _ = env.reset(seed=3, options={"direction": direction})
    finished: set[str] = set()
    steps = 0
    while env.agents:
        actions = {a: drive(obs[a]) for a in env.agents}
        if "car_2" in actions:
            actions["car_2"] = np.zeros(2, dtype=np.float32)  # parked: retires
        if "car_1" in actions and steps < 30:
            actions["car_1"] = np.zeros(2, dtype=np.float32)  # a late start: finishes last
        obs, _, term, trunc, _ = env.step(actions)
        finished |= {a for a in term if term[a] or trunc[a]}
        steps += 1
        assert steps < 5000
    env.close()
    assert finished == {"car_0", "car_1", "car_2"}
    assert reward.calls > 300
    for p in reward.seen:  # including every step after car_0 finished and car_2 retired
        assert p["is_reversed"] == (direction == "reverse")
        assert len(p["objects_location"]) == 2 and len(p["closest_objects"]) == 2
    # Waypoints follow the driving direction: pursuit keeps its heading within 10° of them.
    assert np.mean(np.array(reward.heading_rewards) == 1.0) > 0.8


def test_deepracer_track_waypoints_are_the_files_points(tmp_path: Path) -> None:
    # A DeepRacer-shaped .npy (closed, (N, 6) centre/inner/outer rows 0.5 m apart).
    pts = stadium_points(10.0, 4.0, 0.5)
    tan = np.roll(pts, -1, axis=0) - np.roll(pts, 1, axis=0)
    n = np.column_stack([-tan[:, 1], tan[:, 0]]) / np.linalg.norm(tan, axis=1)[:, None]
    rows = np.column_stack([pts, pts + 1.2 * n, pts - 1.2 * n])
    rows = np.insert(rows, 9, rows[9], axis=0)  # a repeated row, as in Fumiaki's file
    path = tmp_path / "Oval_track.npy"
    np.save(path, np.vstack([rows, rows[:1]]))
    fn = AllExamples()
    env = RacingEnv(track=str(path), n_cars=2, reward=fn)
    drive = pursuit_driver(env)
    for direction in ("forward", "reverse"):
        obs, _ = env.reset(seed=0, options={"direction": direction})
        fn.seen.clear()
        for _ in range(60):
            obs, *_ = env.step({a: drive(obs[a]) for a in env.agents})
        wp = np.array(fn.seen[-1]["waypoints"])
        # every row of the file, the repeat included: DeepRacer's indices
        expected = np.vstack([rows, rows[:1]])[:, :2]
        np.testing.assert_allclose(wp, expected if direction == "forward" else expected[::-1])
        for p in fn.seen:
            prev, nxt = p["closest_waypoints"]
            assert nxt == prev + 1 < len(wp)
            # The car lies between its two closest waypoints along the lap.
            here = np.array([p["x"], p["y"]])
            seg = wp[nxt] - wp[prev]
            t = float(np.dot(here - wp[prev], seg) / np.dot(seg, seg))
            assert -0.3 < t < 1.3
            assert p["is_reversed"] == (direction == "reverse")
    env.close()


# ---- params without a simulator ----------------------------------------------------------------


def params_for(n_cars: int, s: list[float], present: list[bool] | None = None) -> dict[str, Any]:
    track = Track(stadium_points(10.0, 4.0, 0.5), 1.0, 1.0)
    poses = np.column_stack(
        [track.to_cartesian(np.column_stack([s, np.zeros(n_cars)])), np.zeros(n_cars)]
    )
    z = np.zeros(n_cars)
    builder = DeepRacerParams(track, track.length)
    return builder.build(
        0,
        poses=poses,
        speed=z,
        steering=z,
        s=np.array(s),
        d=z,
        segment=np.zeros(n_cars, dtype=np.int64),
        heading_error=z,
        race_progress=z,
        all_wheels_on=np.ones(n_cars, dtype=bool),
        off_track=np.zeros(n_cars, dtype=bool),
        crashed=np.zeros(n_cars, dtype=bool),
        present=np.array(present if present is not None else [True] * n_cars),
        steps=1,
    )


def test_closest_objects_follow_deepracer() -> None:
    assert params_for(1, [5.0])["closest_objects"] == [0, 0]  # no other car: never []
    assert params_for(2, [5.0, 9.0])["closest_objects"] == [0, 0]  # one object
    # Objects at s = 9, 2, 20 (indices 0, 1, 2); the car at 5: behind is 1 (s=2), ahead 0 (s=9).
    assert params_for(4, [5.0, 9.0, 2.0, 20.0])["closest_objects"] == [1, 0]
    # A car that retired stays an object (example 4 keeps running after the others leave).
    gone = params_for(3, [5.0, 9.0, 2.0], present=[True, False, False])
    assert len(gone["objects_location"]) == 2 and gone["closest_objects"] == [1, 0]
    assert example_4(gone) > 0
    assert find_prev_next(np.array([1.0, 4.0]), 5.0) == (1, 0)  # wraps round


# ---- model_metadata.json action spaces ----------------------------------------------------------

# The shape DeepRacer writes (its console's default 5 x 2 discrete action space).
MODEL_METADATA: dict[str, Any] = {
    "action_space": [
        {"steering_angle": -30, "speed": 0.6, "index": 0},
        {"steering_angle": -15, "speed": 0.6, "index": 1},
        {"steering_angle": 0, "speed": 0.6, "index": 2},
        {"steering_angle": 15, "speed": 0.6, "index": 3},
        {"steering_angle": 30, "speed": 0.6, "index": 4},
        {"steering_angle": -30, "speed": 1.2, "index": 5},
        {"steering_angle": -15, "speed": 1.2, "index": 6},
        {"steering_angle": 0, "speed": 1.2, "index": 7},
        {"steering_angle": 15, "speed": 1.2, "index": 8},
        {"steering_angle": 30, "speed": 1.2, "index": 9},
    ],
    "sensor": ["FRONT_FACING_CAMERA"],
    "neural_network": "DEEP_CONVOLUTIONAL_NETWORK_SHALLOW",
    "training_algorithm": "clipped_ppo",
    "action_space_type": "discrete",
    "version": "5",
}


def test_model_metadata_becomes_an_action_table(tmp_path: Path) -> None:
    path = tmp_path / "model_metadata.json"
    path.write_text(json.dumps(MODEL_METADATA))
    table = read_model_metadata(path)
    assert table.n == 10
    menu = table.menu()
    np.testing.assert_allclose(menu[:5, 0], [-1.0, -0.5, 0.0, 0.5, 1.0])
    np.testing.assert_allclose(menu[5:, 1], 1.2)
    steer, throttle = table.to_controls(np.array([4, 7]), np.array([0.6, 2.0]))
    np.testing.assert_allclose(steer, [1.0, 0.0])
    assert throttle[0] == pytest.approx(0.0) and throttle[1] < 0  # hold 0.6, brake to 1.2
    assert action_table(MODEL_METADATA["action_space"]).n == 10  # the bare list works too
    # saved by a Windows editor (Notepad's "UTF-8 with BOM"): was "not valid JSON"
    path.write_bytes(b"\xef\xbb\xbf" + json.dumps(MODEL_METADATA).encode())
    assert read_model_metadata(path).n == 10
    assert DEEPRACER_PRESET.control_hz == 15.0 and DEEPRACER_PRESET.car == "deepracer"


@pytest.mark.parametrize(
    ("space", "message"),
    [
        ([], "non-empty list"),
        ([{"steering_angle": 45, "speed": 1.0}], "beyond the car's ±30°"),
        ([{"steering_angle": 0, "speed": 5.0}], "outside 0.5-4 m/s"),
        ([{"steering_angle": "left", "speed": 1.0}], "'steering_angle' must be a finite number"),
        ([{"steering_angle": 0, "speed": float("nan")}], "'speed' must be a finite number"),
        ([{"steering_angle": 0, "speed": 1.0, "index": 3}], "index 3 is not its position 0"),
        ([[0, 1.0]], "expected an object"),
        ({"action_space_type": "continuous", "action_space": {}}, "only discrete"),
    ],
)
def test_bad_action_spaces_are_clear_errors(space: Any, message: str) -> None:
    with pytest.raises(DeepRacerError, match=message):
        action_table(space)


def test_model_metadata_file_errors(tmp_path: Path) -> None:
    with pytest.raises(DeepRacerError, match="not found"):
        read_model_metadata(tmp_path / "missing.json")
    bad = tmp_path / "model_metadata.json"
    bad.write_text("{not json")
    with pytest.raises(DeepRacerError, match="not valid JSON"):
        read_model_metadata(bad)


@pytest.mark.parametrize("backend", ["bullet", pytest.param("batch", marks=pytest.mark.slow)])
def test_deepracer_preset_with_a_model_metadata_action_space(tmp_path: Path, backend: str) -> None:
    # DeepRacer's rules end a car's episode the step it leaves the track: always "straight
    # ahead at 1.2 m/s" (action 7 of the console's default menu) runs off at the first bend.
    path = tmp_path / "model_metadata.json"
    path.write_text(json.dumps(MODEL_METADATA))
    kwargs: dict[str, Any] = {"backend": backend, "preset": "deepracer", "n_cars": 2}
    kwargs.update(action_table=str(path), track="oval")
    if backend == "bullet":  # the batched backend takes no reward functions
        kwargs["reward"] = example_4
    env = parallel_env(**kwargs)
    assert env.action_space("car_0").n == 10
    assert env.params == car_params("deepracer")
    env.reset(seed=0)
    steps, infos = 0, {}
    while env.agents and steps < 1000:
        _, _, _, _, infos = env.step({a: 7 for a in env.agents})
        steps += 1
    assert not env.agents
    assert {info.get("dnf_reason") for info in infos.values()} == {"off_track"}
    # 15 Hz: the ~16 m to the first bend at 1.2 m/s take about 13 s, about 200 steps.
    assert 100 < steps < 400


def test_pursuit_keeps_the_deepracer_car_on_a_deepracer_chicane(tmp_path: Path) -> None:
    # The AWS DeepRacer "Carrera" track (0.66 m wide) has an S-bend of 0.62-0.70 m radii after
    # a short straight. Pure pursuit with the F1TENTH car's 1.6 m look-ahead at 3 m/s cut it,
    # ran off the inside and stuck on the wall there; scaled to the DeepRacer car's wheelbase
    # it keeps all four wheels on the road for the whole lap, as DeepRacer's own
    # ``all_wheels_on_track`` says.
    pts = chicane_points(radius=0.62, angle=math.pi / 3)
    path = save_npy(tmp_path / "chicane.npy", deepracer_rows(pts, 0.33, 0.33))
    wheels: list[bool] = []

    def record(params: dict[str, Any]) -> float:
        wheels.append(params["all_wheels_on_track"])
        return 1.0

    env = RacingEnv(track=str(path), n_cars=1, laps=1, car="deepracer", reward=record)
    drive = pursuit_driver(env)
    obs, _ = env.reset(seed=0)
    infos: dict[str, Any] = {}
    wall = 0
    while env.agents:
        obs, _, _, _, infos = env.step({a: drive(obs[a]) for a in env.agents})
        wall += bool(infos["car_0"]["wall_contact"])
    env.close()
    assert infos["car_0"]["laps_completed"] == 1
    assert wall == 0
    assert len(wheels) > 100 and all(wheels)
