"""PettingZoo compliance, spaces, episode structure and reset options of ``RacingEnv``."""

from __future__ import annotations

import re
from typing import Any

import numpy as np
import pytest
from pettingzoo.test import api_test, parallel_api_test

import arena
from arena import ENV_VERSION, RacingEnv, SimError
from arena.env import ActionMode, ObsMode
from arena.observations import EGO_FEATURES
from tests.arena.conftest import pursuit_driver
from tracks import list_tracks

# pettingzoo's advice for Dict observations (the dict mode is one by design).
DICT_ADVICE = [
    "ignore:Observation is not a NumPy array",
    "ignore:Observation space for each agent probably should be",
]
MODES = [(obs, act) for obs in ("vector", "dict", "image") for act in ("continuous", "discrete")]


def cycles(obs_mode: str, normal: int) -> int:
    """Fewer steps for the software-rendered camera."""
    return 6 if obs_mode == "image" else normal


@pytest.mark.filterwarnings("error")
@pytest.mark.parametrize("n_cars", [1, 2, 4, 8])
@pytest.mark.parametrize("track", list_tracks())
def test_parallel_api_every_track_and_car_count(track: str, n_cars: int) -> None:
    env = arena.parallel_env(track=track, n_cars=n_cars)
    parallel_api_test(env, num_cycles=100)
    env.close()


@pytest.mark.filterwarnings("error")
@pytest.mark.parametrize(("obs_mode", "action_mode"), MODES)
@pytest.mark.parametrize("track", ["oval", "technical"])
def test_parallel_api_every_mode(track: str, obs_mode: ObsMode, action_mode: ActionMode) -> None:
    env = arena.parallel_env(track=track, n_cars=2, obs_mode=obs_mode, action_mode=action_mode)
    parallel_api_test(env, num_cycles=cycles(obs_mode, 100))
    env.close()


@pytest.mark.filterwarnings("error", *DICT_ADVICE)
@pytest.mark.parametrize(("obs_mode", "action_mode"), MODES)
def test_aec_api_every_mode(obs_mode: ObsMode, action_mode: ActionMode) -> None:
    env = arena.env(track="oval", n_cars=2, obs_mode=obs_mode, action_mode=action_mode)
    api_test(env, num_cycles=cycles(obs_mode, 60))
    env.close()


@pytest.mark.filterwarnings("error")
def test_aec_api_default_configuration() -> None:
    env = arena.env(track="chicanes")
    api_test(env, num_cycles=60)
    env.close()


@pytest.mark.parametrize(("obs_mode", "action_mode"), MODES)
def test_spaces_are_the_same_object_every_call(obs_mode: ObsMode, action_mode: ActionMode) -> None:
    env = RacingEnv(track="oval", n_cars=3, obs_mode=obs_mode, action_mode=action_mode)
    before = {a: (env.observation_space(a), env.action_space(a)) for a in env.possible_agents}
    obs, _ = env.reset(seed=0)
    env.step({a: env.action_space(a).sample() for a in env.agents})
    env.reset(seed=1)
    for agent in env.possible_agents:
        assert env.observation_space(agent) is before[agent][0]
        assert env.action_space(agent) is before[agent][1]
        assert env.observation_space(agent).contains(obs[agent])
    # Cars have equal spaces (parameter sharing) but each its own object (own seeding).
    assert env.observation_space("car_0") == env.observation_space("car_1")
    assert env.action_space("car_0") is not env.action_space("car_1")
    env.close()


def mixed_actions(env: RacingEnv, obs: dict[str, Any], rng: np.random.Generator) -> dict:
    """Car 0 pursuit, car 1 random, car 2 pursuit veering left, car 3 circling."""
    drive = pursuit_driver(env)
    actions = {}
    for agent in env.agents:
        k = env.agent_index[agent]
        vector = obs[agent] if env.obs_mode == "vector" else _flatten(env, obs[agent])
        act: np.ndarray
        if k == 0:
            act = drive(vector)
        elif k == 1:
            act = rng.uniform(-1.0, 1.0, 2)
        elif k == 2:
            act = drive(vector) + np.array([0.6, 0.4])
        else:
            act = np.array([1.0, 0.6])
        actions[agent] = np.clip(act, -1.0, 1.0).astype(np.float32)
    return actions


def _flatten(env: RacingEnv, named: Any) -> np.ndarray:
    """The vector observation that a dict observation names."""
    lay = env.layout
    flat = np.zeros(lay.size, dtype=np.float32)
    flat[lay.lidar] = named["lidar"]
    flat[lay.ego] = [named[name][0] for name in EGO_FEATURES]
    flat[lay.track_ahead] = named["track_ahead"].ravel()
    flat[lay.opponents] = named["opponents"].ravel()
    return flat


@pytest.mark.parametrize("obs_mode", ["vector", "dict"])
def test_observations_stay_inside_the_space(obs_mode: ObsMode) -> None:
    env = RacingEnv(track="chicanes", n_cars=4, obs_mode=obs_mode, max_cycles=300)
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=0)
    steps = 0
    heading = env.layout.ego.start + EGO_FEATURES.index("heading_error")
    turned_round = touched_wall = False
    while env.agents:
        for agent, o in obs.items():
            assert env.observation_space(agent).contains(o), (agent, steps)
            flat: Any = o if obs_mode == "vector" else _flatten(env, o)
            turned_round |= abs(float(flat[heading])) > 0.5
            touched_wall |= bool(np.any(flat[env.layout.lidar] < 0.05))
        obs, rewards, *_ = env.step(mixed_actions(env, obs, rng))
        assert all(np.isfinite(r) for r in rewards.values())
        steps += 1
    assert steps >= 100  # the pursuit car at least drove on
    assert turned_round and touched_wall  # the drivers explored, not only the space's middle
    env.close()


def test_version_history_matches_env_version() -> None:
    doc = RacingEnv.__doc__ or ""
    history = doc.split("**Version History.**")[1]
    versions = re.findall(r"^\s*\*\s*(\d+(?:\.\d+)+):", history, flags=re.MULTILINE)
    assert versions, "no Version History entries"
    newest = max(versions, key=lambda v: tuple(int(part) for part in v.split(".")))
    assert newest == ENV_VERSION


def test_finished_cars_leave_and_the_episode_ends() -> None:
    env = RacingEnv(track="oval", n_cars=3, laps=1)
    drive = pursuit_driver(env)
    obs, _ = env.reset(seed=0)
    finished: dict[str, int] = {}
    while env.agents:
        acting = list(env.agents)
        obs, _, term, trunc, infos = env.step({a: drive(obs[a]) for a in env.agents})
        assert set(obs) == set(term) == set(trunc) == set(infos) == set(acting)
        for agent in acting:
            if term[agent]:
                assert agent not in env.agents
                assert not trunc[agent]
                assert "dnf_reason" not in infos[agent]
                assert infos[agent]["laps_completed"] == 1
                assert len(infos[agent]["lap_times"]) == 1
                finished[agent] = env.steps
            else:
                assert agent in env.agents
    assert set(finished) == set(env.possible_agents)
    assert len(set(finished.values())) > 1  # they did not all cross the line together
    assert env.steps < env.max_cycles
    with pytest.raises(SimError):
        env.step({})
    env.close()


def test_infos_describe_the_state_after_the_step() -> None:
    env = RacingEnv(track="oval", n_cars=2)
    drive = pursuit_driver(env)
    obs, infos = env.reset(seed=0)
    assert all(info["speed"] == 0.0 for info in infos.values())
    for _ in range(20):
        obs, _, _, _, infos = env.step({a: drive(obs[a]) for a in env.agents})
        for agent, info in infos.items():
            k = env.agent_index[agent]
            assert info["speed"] == env.sim_state.v_long[k]
            assert info["s"] == pytest.approx(
                env.track.project(env.sim_state.poses[k : k + 1, :2]).s[0]
            )
            assert info["race_progress"] == env.race_progress[k]
            assert info["rank"] == env.positions[k]
    assert infos["car_0"]["speed"] > 1.0
    env.close()


def test_truncation_at_max_cycles() -> None:
    env = RacingEnv(track="oval", n_cars=2, max_cycles=25)
    drive = pursuit_driver(env)
    obs, _ = env.reset(seed=0)
    for step in range(1, 26):
        obs, _, term, trunc, infos = env.step({a: drive(obs[a]) for a in env.agents})
        assert not any(term.values())
        assert all(trunc.values()) == (step == 25)
    assert env.agents == []
    assert all(info["dnf_reason"] == "time_limit" for info in infos.values())
    env.close()


def test_default_max_cycles_covers_the_race_at_low_speed() -> None:
    env = RacingEnv(track="oval", laps=2)
    expected = (5.0 + 2 * env.base_track.length / 2.5) * env.control_hz
    assert env.max_cycles == pytest.approx(expected, abs=1)
    env.close()


def test_grid_order_places_car_k_at_slot_order_index_k() -> None:
    env = RacingEnv(track="oval", n_cars=4)
    order = [2, 0, 3, 1]
    env.reset(seed=0, options={"grid_order": order})
    slots = env.track.start_grid(4)
    for k in range(4):
        np.testing.assert_allclose(env.sim_state.poses[k], slots[order.index(k)], atol=1e-6)
    env.reset(seed=0)
    np.testing.assert_allclose(env.sim_state.poses, slots, atol=1e-6)
    env.close()


def test_start_offset_moves_the_grid() -> None:
    env = RacingEnv(track="oval", n_cars=2)
    env.reset(seed=0, options={"start_offset": 20.0})
    np.testing.assert_allclose(env.sim_state.poses, env.track.start_grid(2, offset=20.0), atol=1e-6)
    s = env.track.project(env.sim_state.poses[:, :2]).s
    assert np.all((s > 17.0) & (s < 20.0))  # just behind the moved start line
    env.close()


@pytest.mark.parametrize("offset", [20.0, 60.0])
def test_mid_lap_start_counts_race_progress_from_the_start_line(offset: float) -> None:
    env = RacingEnv(track="oval", n_cars=2)  # 94 m long: 60 m is 34 m before the line
    _, infos = env.reset(seed=0, options={"start_offset": offset})
    s = env.track.project(env.sim_state.poses[:, :2]).s
    expected = env.track.delta_s(s, 0.0)  # the offset once, not twice
    got = [infos[a]["race_progress"] for a in env.agents]
    np.testing.assert_allclose(got, expected, atol=1e-9)
    length = env.track.length
    ahead = offset if offset < length / 2 else offset - length  # signed, from the line
    assert ahead - 1.0 < got[0] < ahead  # the pole sits just behind its grid line
    _, _, _, _, infos = env.step({a: np.array([0.0, 1.0]) for a in env.agents})
    assert abs(infos["car_0"]["race_progress"] - got[0]) < 0.2  # one step's progress
    env.close()


def test_reverse_direction_drives_the_track_the_other_way() -> None:
    env = RacingEnv(track="oval", n_cars=1, laps=1)
    drive = pursuit_driver(env)
    obs, _ = env.reset(seed=0, options={"direction": "reverse"})
    assert env.track is not env.base_track
    yaw = env.sim_state.poses[0, 2]
    base_heading = env.base_track.project(env.sim_state.poses[:, :2]).heading[0]
    assert np.cos(yaw - base_heading) < -0.99  # facing against the base track's direction
    while env.agents:
        obs, _, term, _, infos = env.step({"car_0": drive(obs["car_0"])})
    assert term["car_0"]
    assert "dnf_reason" not in infos["car_0"]
    assert len(infos["car_0"]["lap_times"]) == 1
    env.close()


def test_random_direction_and_offset_follow_the_seed() -> None:
    env = RacingEnv(track="oval", n_cars=2)
    options = {"direction": "random", "start_offset": "random"}
    seen = set()
    for seed in range(8):
        env.reset(seed=seed, options=options)
        first = (env.track.name, env.sim_state.poses.tobytes())
        env.reset(seed=seed, options=options)
        assert (env.track.name, env.sim_state.poses.tobytes()) == first
        seen.add(first[0])
    assert seen == {"oval", "oval-reversed"}
    env.close()


@pytest.mark.parametrize(
    "kwargs",
    [
        {"obs_mode": "x"},
        {"action_mode": "x"},
        {"render_mode": "human"},
        {"reward": "fastest"},
        {"laps": 0},
        {"n_cars": 0},
        {"n_cars": 17},
        {"physics_hz": 50, "control_hz": 20},
    ],
)
def test_bad_arguments_raise_sim_error(kwargs: dict[str, Any]) -> None:
    with pytest.raises(SimError):
        RacingEnv(track="oval", **kwargs)


@pytest.mark.parametrize(
    "options",
    [{"grid_order": [0, 0]}, {"grid_order": [0, 1, 2]}, {"direction": "sideways"}],
)
def test_bad_reset_options_raise_sim_error(options: dict[str, Any]) -> None:
    env = RacingEnv(track="oval", n_cars=2)
    with pytest.raises(SimError):
        env.reset(seed=0, options=options)
    env.close()


def test_bad_actions_raise_or_are_sanitised() -> None:
    env = RacingEnv(track="oval", n_cars=2)
    env.reset(seed=0)
    with pytest.raises(SimError):
        env.step({"car_0": np.zeros(3), "car_1": np.zeros(2)})
    # NaN is "no input" and infinities saturate: the physics never sees them.
    obs, rewards, *_ = env.step({"car_0": np.array([np.nan, np.inf]), "car_1": np.zeros(2)})
    assert all(np.all(np.isfinite(np.asarray(o))) for o in obs.values())
    assert all(np.isfinite(r) for r in rewards.values())
    env.close()


def test_render_returns_a_top_down_image() -> None:
    env = RacingEnv(track="oval", n_cars=2, render_mode="rgb_array")
    env.reset(seed=0)
    image = env.render()
    assert image is not None and image.dtype == np.uint8
    assert image.ndim == 3 and image.shape[2] == 3
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 4  # road, grass, walls, cars
    env.close()
    quiet = RacingEnv(track="oval", n_cars=2)
    quiet.reset(seed=0)
    assert quiet.render() is None
    quiet.close()
