"""One episode core over two simulators: the same names and numbers on both backends.

The rules (arena.core) are pure functions of (B, N) arrays, so what is a function of the
same state is checked exactly; what depends on the two simulators' physics (positions,
hence progress and rewards) is checked within the parity bounds of
tests/arena/test_batch_parity.py (the same tyre model: positions within millimetres over
seconds; lidar from a range table, so observations only loosely).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test
from supersuit import concat_vec_envs_v1, pettingzoo_env_to_vec_env_v1

import arena
from arena.batch.xp import get_ops
from arena.cars import CAR_PRESETS, CarError
from arena.core import (
    DNF_REASONS,
    STATE_FEATURES,
    EpisodeRules,
    Sensed,
    episode_start,
    episode_step,
)
from arena.sim import CarParams
from arena.uncertainty import default_config
from tests.arena.conftest import pursuit_driver
from tracks import LapCounter, load_track

BACKENDS = ("pybullet", "batch")
NP = get_ops("numpy")


def test_both_backends_give_the_same_infos_and_rewards_step_by_step() -> None:
    """Two cars, pure pursuit driving both backends with the same actions (those chosen on
    pybullet), a whole lap of the oval: names identical; ranks, laps and flags equal; progress,
    rewards and lap times within the physics difference (the tyre model is shared)."""
    bullet = arena.parallel_env(track="oval", n_cars=2, backend="pybullet")
    batch = arena.parallel_env(track="oval", n_cars=2, backend="batch")
    obs, info_a = bullet.reset(seed=0)
    _, info_b = batch.reset(seed=0)
    assert info_a.keys() == info_b.keys()
    for agent in info_a:
        assert info_a[agent].keys() == info_b[agent].keys()
        assert info_a[agent]["rank"] == info_b[agent]["rank"]
        assert info_a[agent]["race_progress"] == pytest.approx(
            info_b[agent]["race_progress"], abs=1e-3
        )
    act = pursuit_driver(bullet)
    steps = 0
    while bullet.agents:
        actions = {a: act(obs[a]) for a in bullet.agents}
        obs, rew_a, term_a, trunc_a, info_a = bullet.step(actions)
        _, rew_b, term_b, trunc_b, info_b = batch.step(actions)
        steps += 1
        assert rew_a.keys() == rew_b.keys() and term_a == term_b and trunc_a == trunc_b
        for agent in rew_a:
            a, b = info_a[agent], info_b[agent]
            assert a.keys() == b.keys()
            assert a["reward_terms"].keys() == b["reward_terms"].keys()
            assert (a["lap"], a["laps_completed"], a["rank"]) == (
                b["lap"],
                b["laps_completed"],
                b["rank"],
            )
            assert (a["off_track"], a["wall_contact"]) == (b["off_track"], b["wall_contact"])
            assert a["race_progress"] == pytest.approx(b["race_progress"], abs=0.05)
            assert rew_a[agent] == pytest.approx(rew_b[agent], abs=0.01)
            assert a["speed"] == pytest.approx(b["speed"], abs=0.05)
            assert len(a["lap_times"]) == len(b["lap_times"])
            np.testing.assert_allclose(a["lap_times"], b["lap_times"], atol=0.051)
    assert not batch.agents  # both episodes ended on the same step
    assert steps > 300 and all(len(info_a[a]["lap_times"]) == 1 for a in info_a)


@pytest.mark.parametrize("backend", BACKENDS)
def test_step_limit_dnf_is_time_limit_on_both_backends(backend: str) -> None:
    env = arena.parallel_env(track="oval", n_cars=2, backend=backend, max_cycles=5)
    env.reset(seed=0)
    for _ in range(5):
        *_, trunc, infos = env.step({a: np.array([0.0, 0.3]) for a in env.agents})
    assert trunc == {"car_0": True, "car_1": True}
    assert {info["dnf_reason"] for info in infos.values()} == {"time_limit"}
    assert "time_limit" in DNF_REASONS


@pytest.mark.parametrize("backend", BACKENDS)
def test_mid_lap_start_counts_race_progress_from_the_line_on_both(backend: str) -> None:
    """A start 3/4 of the way round (a placement the batch start table has exactly): the cars
    are about a quarter lap *behind* the line, as pybullet env 0.2 counts it."""
    env = arena.parallel_env(track="oval", n_cars=2, backend=backend)
    length = env.base_track.length
    _, infos = env.reset(seed=0, options={"start_offset": 0.75 * length})
    for info in infos.values():
        assert -0.3 * length < info["race_progress"] < -0.2 * length


def test_lap_gates_are_exactly_tracks_lap_counter() -> None:
    """The core's gates over a random walk of progress (forward, backward, cuts) count the
    same laps, gate by gate, as tracks.LapCounter — exactly: both are pure functions of s."""
    track = load_track("oval")
    rng = np.random.default_rng(4)
    n = 5
    params = CarParams()
    rules = EpisodeRules.build(track, NP, n_cars=n, laps=99, control_hz=20, params=params)
    s0 = rng.uniform(0.0, track.length, n)
    counter = LapCounter(track, s0, max_jump=3.0)
    st = episode_start(NP, rules, s0[None], np.zeros(1), np.array([True]))
    np.testing.assert_array_equal(st.next_gate[0], counter.next_gate)
    s = s0.copy()
    for _ in range(2000):
        s = track.wrap_s(s + rng.normal(0.4, 0.6, n) + (rng.random(n) < 0.01) * 20.0)
        sensed = Sensed(
            s=s[None],
            d=np.zeros((1, n)),
            heading=np.zeros((1, n)),
            yaw=np.zeros((1, n)),
            left=np.ones((1, n)),
            right=np.ones((1, n)),
            wall=np.zeros((1, n), bool),
            touching=np.zeros((1, n, n), bool),
            upright=None,
            prev_poses=np.zeros((1, n, 3)),
            prev_velocity=np.zeros((1, n, 2)),
        )
        st, out = episode_step(NP, rules, st, sensed)
        done = counter.update(s)
        np.testing.assert_array_equal(out.lap_done[0], done)
        np.testing.assert_array_equal(st.laps[0], counter.laps)
        np.testing.assert_array_equal(st.next_gate[0], counter.next_gate)
    assert counter.laps.min() >= 1  # every car did go round


def test_the_rules_on_a_batch_equal_the_rules_on_each_race() -> None:
    """B = 3 races stepped together give, race by race, exactly what B = 1 gives."""
    track = load_track("oval")
    rng = np.random.default_rng(1)
    n, b = 3, 3
    rules = EpisodeRules.build(
        track, NP, n_cars=n, laps=1, control_hz=20, params=CarParams(), max_cycles=40
    )
    s0 = rng.uniform(0.0, track.length, (b, n))
    grid = np.array([True, False, True])
    batched = episode_start(NP, rules, s0, np.zeros(b), grid)
    singles = [
        episode_start(NP, rules, s0[k : k + 1], np.zeros(1), grid[k : k + 1]) for k in range(b)
    ]
    s = s0
    for _ in range(60):
        s = track.wrap_s(s + rng.normal(0.3, 0.3, (b, n)))
        touching = rng.random((b, n, n)) < 0.05
        touching = touching | touching.transpose(0, 2, 1)
        fields: dict[str, Any] = {
            "s": s,
            "d": rng.normal(0.0, 1.5, (b, n)),
            "heading": rng.normal(0.0, 0.1, (b, n)),
            "yaw": rng.normal(0.0, 0.1, (b, n)),
            "left": np.full((b, n), 1.2),
            "right": np.full((b, n), 1.2),
            "wall": rng.random((b, n)) < 0.1,
            "touching": touching,
            "upright": np.ones((b, n)),
            "prev_poses": rng.normal(0.0, 5.0, (b, n, 3)),
            "prev_velocity": rng.normal(0.0, 2.0, (b, n, 2)),
        }
        batched, out = episode_step(NP, rules, batched, Sensed(**fields))
        for k in range(b):
            one = Sensed(
                **{name: v[k : k + 1] if v is not None else None for name, v in fields.items()}
            )
            singles[k], out_k = episode_step(NP, rules, singles[k], one)
            np.testing.assert_array_equal(out.reward[k], out_k.reward[0])
            np.testing.assert_array_equal(out.dnf[k], out_k.dnf[0])
            np.testing.assert_array_equal(batched.positions[k], singles[k].positions[0])
            np.testing.assert_array_equal(batched.active[k], singles[k].active[0])


@pytest.mark.parametrize("backend", BACKENDS)
def test_state_is_pettingzoo_global_state_on_both_backends(backend: str) -> None:
    env = arena.parallel_env(track="oval", n_cars=3, backend=backend)
    assert env.state_space.shape == (3 * STATE_FEATURES,)
    env.reset(seed=2)
    state = env.state()
    assert state.dtype == np.float32 and state.shape == env.state_space.shape
    assert env.state_space.contains(state)
    per_car = state.reshape(3, STATE_FEATURES)
    np.testing.assert_array_equal(per_car[:, -1], 1.0)  # everyone racing
    env.retire("car_1", "test")
    np.testing.assert_array_equal(env.state().reshape(3, STATE_FEATURES)[1], 0.0)


def test_state_holds_the_perturbation_with_uncertainty() -> None:
    cfg = default_config("sample")
    env = arena.parallel_env(track="oval", n_cars=2, uncertainty=cfg)
    env.reset(seed=0)
    n_free = len(cfg.free)
    assert env.state().shape == (2 * (STATE_FEATURES + n_free),) == env.state_space.shape


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("mode", ["sample", "adversarial"])
def test_uncertainty_runs_the_same_code_on_both_backends(backend: str, mode: str) -> None:
    env = arena.parallel_env(
        track="oval", n_cars=2, backend=backend, uncertainty=default_config(mode), max_cycles=40
    )
    parallel_api_test(env, num_cycles=50)
    env.reset(seed=0)
    _, rew, _, _, infos = env.step({a: env.action_space(a).sample() for a in env.agents})
    for car in env.cars:
        assert infos[car]["reward_perturbed"] == rew[car]
        if mode == "adversarial":
            assert rew["nature_" + car] == -rew[car]


@pytest.mark.parametrize("backend", BACKENDS)
def test_park_finished_keeps_done_cars_until_everyone_is_done(backend: str) -> None:
    env = arena.parallel_env(track="oval", n_cars=3, backend=backend, park_finished=True)
    obs, _ = env.reset(seed=0)
    go = {a: np.array([0.0, 0.5], dtype=np.float32) for a in env.agents}
    obs, *_ = env.step(go)
    env.retire("car_1", "test")
    assert env.agents == ["car_0", "car_1", "car_2"]
    parked_obs = obs["car_1"]
    for _ in range(3):
        obs, rew, term, trunc, infos = env.step(go)  # car_1's action is ignored
        assert list(obs) == ["car_0", "car_1", "car_2"]
        assert term["car_1"] is True and trunc["car_1"] is False and rew["car_1"] == 0.0
        np.testing.assert_array_equal(obs["car_1"], parked_obs)
        assert infos["car_1"]["dnf_reason"] == "test"
        assert not term["car_0"] and rew["car_0"] != 0.0
    env.retire("car_0", "test")
    env.retire("car_2", "test")
    assert env.agents == []


@pytest.mark.parametrize("backend", BACKENDS)
def test_park_finished_runs_supersuits_released_vector_recipe(backend: str) -> None:
    """The recipe from SuperSuit's README (pettingzoo_env_to_vec_env_v1 + concat_vec_envs_v1,
    SB3 base class), which refuses envs whose agents leave, over several episodes."""
    env = arena.parallel_env(
        track="oval", n_cars=2, backend=backend, park_finished=True, max_cycles=30
    )
    venv = concat_vec_envs_v1(
        pettingzoo_env_to_vec_env_v1(env), 2, num_cpus=0, base_class="stable_baselines3"
    )
    obs = venv.reset()
    assert obs.shape == (4, env.layout.size)
    episodes = 0
    for _ in range(70):
        obs, rewards, dones, _ = venv.step(np.tile([[0.0, 0.4]], (4, 1)).astype(np.float32))
        episodes += int(dones.all())
        assert obs.shape == (4, env.layout.size) and np.isfinite(rewards).all()
    assert episodes >= 2
    venv.close()


@pytest.mark.parametrize("backend", BACKENDS)
def test_car_presets_on_both_backends(backend: str) -> None:
    env = arena.parallel_env(track="oval", n_cars=1, backend=backend, car="deepracer")
    assert env.params == CAR_PRESETS["deepracer"]
    obs, _ = env.reset(seed=0)
    assert env.observation_space("car_0").contains(obs["car_0"])
    with pytest.raises(CarError):
        arena.parallel_env(track="oval", n_cars=1, backend=backend, car="monster-truck")


@pytest.mark.parametrize("backend", BACKENDS)
def test_deepracer_preset_ends_a_car_that_leaves_the_road_at_once(backend: str) -> None:
    """preset="deepracer": the 1/18 car at 15 Hz, and DeepRacer's episode rules — all four
    wheels off the road ends the car's episode that very step (no grace period)."""
    env = arena.parallel_env(track="oval", n_cars=1, backend=backend, preset="deepracer")
    assert env.params == CAR_PRESETS["deepracer"] and env.control_hz == 15
    env.reset(seed=0)
    ends = []
    for _ in range(300):  # straight on at full throttle: off the road at the first bend
        *_, term, _, infos = env.step({"car_0": np.array([0.0, 1.0], dtype=np.float32)})
        ends.append(term["car_0"])
        if term["car_0"]:
            break
    assert ends[-1] and infos["car_0"]["dnf_reason"] == "off_track"
    assert infos["car_0"]["off_track"]  # it ended on the step it left the road


@pytest.mark.parametrize("backend", BACKENDS)
def test_deepracer_action_table_drives_the_discrete_space(backend: str, tmp_path: Any) -> None:
    """An action space in the shape DeepRacer's console writes to model_metadata.json (its
    default 5 × 2 menu, as in tests/arena/test_deepracer.py)."""
    import json

    menu = [
        {"steering_angle": angle, "speed": speed, "index": 5 * k + j}
        for k, speed in enumerate((0.6, 1.2))
        for j, angle in enumerate((-30, -15, 0, 15, 30))
    ]
    path = tmp_path / "model_metadata.json"
    path.write_text(json.dumps({"action_space": menu, "action_space_type": "discrete"}))
    env = arena.parallel_env(
        track="oval", n_cars=1, backend=backend, car="deepracer", action_table=path
    )
    assert env.action_space("car_0").n == 10  # type: ignore[attr-defined]
    env.reset(seed=0)
    for _ in range(40):  # straight ahead at 1.2 m/s
        *_, infos = env.step({"car_0": 7})
    assert infos["car_0"]["speed"] == pytest.approx(1.2, abs=0.15)
