"""Model-uncertainty options of ``RacingEnv``: bounds, fixed, latency, nature, determinism."""

from __future__ import annotations

from typing import Any
from unittest import mock

import numpy as np
import pybullet as pb
import pytest
from pettingzoo.test import parallel_api_test

import arena
from arena import RacingEnv
from arena.perception import jitter_image, jitter_lidar
from arena.rewards import RACING_TERMS
from arena.uncertainty import (
    DEFAULT_DYNAMICS,
    INDEX,
    PARAM_NAMES,
    DynamicsBounds,
    EpisodeRandomisation,
    PerceptionBounds,
    Perturbation,
    PerturbationState,
    RewardBounds,
    UncertaintyConfig,
    UncertaintyError,
    default_config,
    nature_values,
    normalised,
    perturbed_reward,
    sample_values,
)
from tests.arena.conftest import pursuit_driver

WIDE = UncertaintyConfig(
    mode="sample",
    resample="step",
    dynamics=DEFAULT_DYNAMICS,
    perception=PerceptionBounds(lidar_noise=(0.0, 0.05), lidar_dropout=(0.0, 0.2)),
    reward=RewardBounds(noise=0.2, collision=(0.5, 2.0), progress=(0.8, 1.2)),
)
IMAGE_JITTER = PerceptionBounds(
    brightness=(-0.2, 0.2),
    contrast=(0.7, 1.3),
    image_noise=(0.0, 8.0),
    shift=(0, 6),
    shadow=(0, 0.5),
)
MODES: dict[str, UncertaintyConfig] = {
    "nominal": UncertaintyConfig(),
    "sample-episode": default_config("sample"),
    "sample-step": WIDE,
    "sample-every-k": UncertaintyConfig(
        mode="sample", resample="every_k", every_k=7, dynamics=DEFAULT_DYNAMICS
    ),
    "fixed": UncertaintyConfig(mode="fixed", perturbation={"friction": 0.7, "latency": 2}),
    "adversarial-reset": default_config("adversarial", nature_acts="reset", nature_rate=None),
    "adversarial-step": default_config("adversarial", reward=RewardBounds(noise=0.1)),
    "episode": UncertaintyConfig(
        mode="sample",
        episode=EpisodeRandomisation(start="random", direction="random", tracks=("oval", "bean")),
    ),
}


def drive(env: RacingEnv, obs: dict[str, Any], rng: np.random.Generator) -> dict[str, Any]:
    """Pursuit for the cars (random wobble), random actions for the natures."""
    act = pursuit_driver(env)
    out: dict[str, Any] = {}
    for agent in env.agents:
        if agent.startswith("nature_"):
            out[agent] = env.action_space(agent).sample()
        else:
            wobble = rng.uniform(-0.2, 0.2, 2)
            out[agent] = np.clip(act(obs[agent]) + wobble, -1, 1).astype(np.float32)
    return out


@pytest.mark.filterwarnings("error")
@pytest.mark.parametrize("name", list(MODES))
def test_parallel_api_every_mode(name: str) -> None:
    env = RacingEnv(track="oval", n_cars=2, uncertainty=MODES[name])
    parallel_api_test(env, num_cycles=150)
    env.close()


@pytest.mark.filterwarnings("error")
def test_parallel_api_image_jitter() -> None:
    cfg = UncertaintyConfig(mode="sample", resample="step", perception=IMAGE_JITTER)
    env = RacingEnv(track="oval", n_cars=2, obs_mode="image", uncertainty=cfg)
    parallel_api_test(env, num_cycles=5)
    env.close()


def test_every_parameter_stays_inside_its_bounds() -> None:
    env = RacingEnv(track="chicanes", n_cars=3, uncertainty=WIDE, max_cycles=200)
    rng = np.random.default_rng(0)
    lo, hi = WIDE.lows, WIDE.highs
    seen = []
    for seed in range(2):
        obs, infos = env.reset(seed=seed)
        while env.agents:
            obs, _, _, _, infos = env.step(drive(env, obs, rng))
            for agent, info in infos.items():
                values = np.array([info["perturbation"][n] for n in PARAM_NAMES])
                assert np.all(values >= lo - 1e-12), agent
                assert np.all(values <= hi + 1e-12), agent
                assert float(info["perturbation"]["latency"]).is_integer()
                seen.append(values)
    seen_arr = np.array(seen)
    free = WIDE.free
    # The draws fill the box: per-step resampling gets near both ends of every interval.
    span = (seen_arr[:, free].max(axis=0) - seen_arr[:, free].min(axis=0)) / (hi - lo)[free]
    assert np.all(span > 0.8)
    # Lidar observations stay normalised even with noise and dropout.
    lidar = env.layout.lidar
    assert all(v[lidar].min() >= 0.0 and v[lidar].max() <= 1.0 for v in obs.values())
    env.close()


def test_sample_resample_schedule() -> None:
    def friction_track(cfg: UncertaintyConfig) -> list[float]:
        env = RacingEnv(track="oval", n_cars=1, uncertainty=cfg)
        env.reset(seed=3)
        out = []
        for _ in range(30):
            _, _, _, _, infos = env.step({"car_0": np.array([0.0, 0.5], np.float32)})
            out.append(infos["car_0"]["perturbation"]["friction"])
        env.close()
        return out

    dyn = DynamicsBounds(friction=(0.6, 1.2))
    episode = friction_track(UncertaintyConfig(mode="sample", dynamics=dyn))
    assert len(set(episode)) == 1
    step = friction_track(UncertaintyConfig(mode="sample", resample="step", dynamics=dyn))
    assert len(set(step)) == 30
    every = friction_track(
        UncertaintyConfig(mode="sample", resample="every_k", every_k=10, dynamics=dyn)
    )
    # New draws at steps 10 and 20 (0-based step counter before each step).
    assert len(set(every)) == 3 and len(set(every[:10])) == 1 and len(set(every[10:20])) == 1


def test_same_seed_same_draws_other_seed_other_draws() -> None:
    def draws(seed: int) -> np.ndarray:
        env = RacingEnv(track="hairpins", n_cars=2, uncertainty=WIDE)
        rng = np.random.default_rng(0)
        obs, infos = env.reset(seed=seed)
        rows = [[infos[a]["perturbation"][n] for a in env.cars for n in PARAM_NAMES]]
        for _ in range(60):
            obs, rew, _, _, infos = env.step(drive(env, obs, rng))
            rows.append([infos[a]["perturbation"][n] for a in env.cars for n in PARAM_NAMES])
            rows[-1] += [rew[a] for a in env.cars]
        env.close()
        return np.array([np.asarray(r[: 2 * len(PARAM_NAMES)]) for r in rows])

    first, again, other = draws(5), draws(5), draws(6)
    np.testing.assert_array_equal(first, again)
    assert not np.array_equal(first, other)
    # Cars draw independently.
    assert not np.array_equal(first[:, : len(PARAM_NAMES)], first[:, len(PARAM_NAMES) :])


@pytest.mark.parametrize("backend", ["pybullet", "batch"])
def test_corner_weighted_draws_reach_the_cars_on_both_backends(backend: str) -> None:
    """``edge_share=1``: every car of every episode races at a corner of the box (each
    parameter at its low or high end, as the infos report), on either simulator."""
    dyn = DynamicsBounds(friction=(0.5, 1.2), latency=(0, 3), steer_offset=(-0.08, 0.08))
    cfg = UncertaintyConfig(mode="sample", dynamics=dyn, edge_share=1.0)
    env = arena.parallel_env(
        backend=backend, track="oval", n_cars=4, uncertainty=cfg, max_cycles=20
    )
    seen: dict[str, set[float]] = {"friction": set(), "latency": set(), "steer_offset": set()}
    for seed in range(6):
        _, infos = env.reset(seed=seed)
        for car in env.cars:
            for name, values in seen.items():
                values.add(infos[car]["perturbation"][name])
    env.close()
    assert seen == {"friction": {0.5, 1.2}, "latency": {0, 3}, "steer_offset": {-0.08, 0.08}}


def test_fixed_reproduces_the_given_perturbation_exactly() -> None:
    cfg = UncertaintyConfig(mode="fixed")
    env = RacingEnv(track="oval", n_cars=2, uncertainty=cfg)
    given = {
        "friction": [0.7, 1.15],
        "mass": [1.2, 0.85],
        "motor": 0.9,
        "steer_gain": [1.1, 0.95],
        "steer_offset": [0.03, -0.02],
        "latency": [1, 3],
        "w_collision": 1.7,
    }
    _, infos = env.reset(seed=0, options={"perturbation": given})
    for k, agent in enumerate(env.cars):
        for name, value in given.items():
            expected = value[k] if isinstance(value, list) else value
            assert infos[agent]["perturbation"][name] == expected
    sc = env.sim.scales
    np.testing.assert_array_equal(sc.friction, [0.7, 1.15])
    np.testing.assert_array_equal(sc.mass, [1.2, 0.85])
    np.testing.assert_array_equal(sc.steer_offset, [0.03, -0.02])
    for body, m in zip(env.sim.cars, [1.2, 0.85], strict=True):
        mass = pb.getDynamicsInfo(body, -1, physicsClientId=env.sim.client)[0]
        assert mass == pytest.approx(env.params.mass * m)
    # Held through the episode; the next reset without the option is nominal again.
    _, _, _, _, infos = env.step({a: np.zeros(2, np.float32) for a in env.agents})
    assert infos["car_1"]["perturbation"]["latency"] == 3
    _, infos = env.reset(seed=1)
    assert infos["car_0"]["perturbation"] == Perturbation.nominal(1).car(0)
    env.close()


def test_fixed_rejects_bad_perturbations() -> None:
    env = RacingEnv(track="oval", n_cars=2, uncertainty=UncertaintyConfig(mode="fixed"))
    for bad in ({"grip": 1.0}, {"friction": [1.0]}, {"latency": 1.5}, {"mass": 0.0}):
        with pytest.raises(UncertaintyError):
            env.reset(options={"perturbation": bad})
    env.close()
    sample = RacingEnv(track="oval", n_cars=1, uncertainty=default_config("sample"))
    with pytest.raises(UncertaintyError, match="fixed"):
        sample.reset(options={"perturbation": {"friction": 1.0}})
    sample.close()


@pytest.mark.parametrize("latencies", [(0, 2), (1, 3)])
def test_latency_delays_actions_by_exactly_k_steps(latencies: tuple[int, int]) -> None:
    cfg = UncertaintyConfig(mode="fixed", perturbation={"latency": list(latencies)})
    env = RacingEnv(track="oval", n_cars=2, uncertainty=cfg)
    env.reset(seed=0)
    rng = np.random.default_rng(1)
    sent = [rng.uniform(-1, 1, (2, 2)) for _ in range(25)]
    applied: list[np.ndarray] = []
    real_step = env.sim.step

    def spy(steer: np.ndarray, throttle: np.ndarray) -> Any:
        applied.append(np.stack([steer, throttle], axis=1))
        return real_step(steer, throttle)

    with mock.patch.object(env.sim, "step", side_effect=spy):
        for cmd in sent:
            env.step({a: cmd[i].astype(np.float32) for i, a in enumerate(env.cars)})
    for i, k in enumerate(latencies):
        for t in range(len(sent)):
            expected = np.zeros(2) if t < k else sent[t - k][i].astype(np.float32)
            np.testing.assert_allclose(applied[t][i], expected, atol=1e-7)
    env.close()


def test_action_noise_is_bounded() -> None:
    cfg = UncertaintyConfig(mode="fixed", perturbation={"action_noise": [0.0, 0.1]})
    env = RacingEnv(track="oval", n_cars=2, uncertainty=cfg)
    env.reset(seed=0)
    applied: list[np.ndarray] = []
    real_step = env.sim.step

    def spy(steer: np.ndarray, throttle: np.ndarray) -> Any:
        applied.append(np.stack([steer, throttle], axis=1))
        return real_step(steer, throttle)

    cmd = np.array([0.3, 0.5], np.float32)
    with mock.patch.object(env.sim, "step", side_effect=spy):
        for _ in range(50):
            env.step({a: cmd for a in env.cars})
    dev = np.abs(np.array(applied) - cmd)
    assert np.all(dev[:, 0] < 1e-7)  # car 0: no noise
    assert np.all(dev[:, 1] <= 0.1 + 1e-7) and dev[:, 1].max() > 0.05
    env.close()


@pytest.mark.parametrize("acts", ["reset", "step"])
@pytest.mark.parametrize("backend", ["pybullet", "batch"])
def test_nature_and_its_car_sum_to_zero_every_step(acts: str, backend: str) -> None:
    cfg = default_config("adversarial", nature_acts=acts, reward=RewardBounds(noise=0.3))
    env = arena.parallel_env(
        backend=backend, track="chicanes", n_cars=3, uncertainty=cfg, max_cycles=300
    )
    assert env.possible_agents[3:] == ["nature_car_0", "nature_car_1", "nature_car_2"]
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=0)
    state_size = env.state_space.shape[0]
    for nat in env.natures:
        assert env.observation_space(nat).shape == (state_size + 3,)
        assert env.action_space(nat).shape == (len(cfg.free),)
    steps = 0
    while env.agents:
        before = list(env.agents)
        obs, rew, term, trunc, infos = env.step(drive(env, obs, rng))
        steps += 1
        for k, car in enumerate(env.cars):
            nat = f"nature_car_{k}"
            if car in before:
                assert rew[nat] + rew[car] == 0.0
                assert rew[car] == infos[car]["reward_perturbed"]
                assert infos[nat]["target"] == car
                assert (term[nat], trunc[nat]) == (term[car], trunc[car])
                assert (car in env.agents) == (nat in env.agents)
    assert steps > 50
    env.close()


def test_nature_action_maps_affinely_into_the_bounds() -> None:
    cfg = UncertaintyConfig(
        mode="adversarial",
        dynamics=DynamicsBounds(friction=(0.6, 1.2), latency=(0, 3)),
        reward=RewardBounds(noise=0.5, noise_clip=2.0),
    )
    assert cfg.free_names == ("friction", "latency", "reward_noise")
    start = np.tile(cfg.nominal, (1, 1))
    lo = nature_values(cfg, np.array([-1.0, -1.0, -1.0]), start)[0]
    hi = nature_values(cfg, np.array([1.0, 1.0, 1.0]), start)[0]
    mid = nature_values(cfg, np.array([0.0, 0.0, 0.0]), start)[0]
    clipped = nature_values(cfg, np.array([-7.0, 9.0, np.nan]), start)[0]
    f, lat, noise = INDEX["friction"], INDEX["latency"], INDEX["reward_noise"]
    assert (lo[f], lo[lat], lo[noise]) == (0.6, 0.0, -1.0)
    assert (hi[f], hi[lat], hi[noise]) == (1.2, 3.0, 1.0)
    assert mid[f] == pytest.approx(0.9) and mid[lat] == 1.5 and mid[noise] == 0.0
    assert (clipped[f], clipped[lat], clipped[noise]) == (0.6, 3.0, 0.0)
    # Every other parameter keeps its current value; the inverse map gives the action back.
    others = [k for k in range(len(PARAM_NAMES)) if k not in cfg.free]
    np.testing.assert_array_equal(hi[others], start[0, others])
    np.testing.assert_allclose(normalised(cfg, mid[None]), [[0.0, 0.0, 0.0]], atol=1e-12)
    # Rate limit: at most 10 % of each interval per call.
    moved = nature_values(cfg, np.array([1.0, 1.0, 1.0]), lo[None], rate=0.1)[0]
    np.testing.assert_allclose(moved[[f, lat, noise]], [0.66, 0.3, -0.8])


def test_nature_reset_latch_and_rate_limit_in_the_env() -> None:
    latch = default_config("adversarial", nature_acts="reset", nature_rate=None)
    env = RacingEnv(track="oval", n_cars=1, uncertainty=latch)
    env.reset(seed=0)
    k = len(latch.free)
    _, _, _, _, infos = env.step({"car_0": np.zeros(2), "nature_car_0": -np.ones(k)})
    first = infos["car_0"]["perturbation"]
    assert first["friction"] == 0.6 and first["latency"] == 0
    for _ in range(5):
        _, _, _, _, infos = env.step({"car_0": np.zeros(2), "nature_car_0": np.ones(k)})
        assert infos["car_0"]["perturbation"] == first  # held after the first step
    assert env.sim.scales.friction[0] == 0.6
    env.close()

    rated = default_config("adversarial", nature_acts="step", nature_rate=0.1)
    env = RacingEnv(track="oval", n_cars=1, uncertainty=rated)
    env.reset(seed=0)
    env.step({"car_0": np.zeros(2), "nature_car_0": -np.ones(k)})
    frictions = []
    for _ in range(12):
        _, _, _, _, infos = env.step({"car_0": np.zeros(2), "nature_car_0": np.ones(k)})
        frictions.append(infos["car_0"]["perturbation"]["friction"])
    np.testing.assert_allclose(np.diff([0.6, *frictions])[:10], 0.06)
    assert frictions[-1] == pytest.approx(1.2)
    env.close()


def test_reward_perturbation_weights_and_bounded_noise() -> None:
    cfg = UncertaintyConfig(
        mode="sample",
        reward=RewardBounds(noise=0.05, noise_clip=2.0, progress=(0.5, 1.5), collision=(0.5, 2.0)),
    )
    env = RacingEnv(track="oval", n_cars=2, uncertainty=cfg)
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=0)
    noise = []
    for _ in range(150):
        obs, rew, _, _, infos = env.step(drive(env, obs, rng))
        for agent in env.cars:
            info = infos.get(agent)
            if info is None:
                continue
            p, terms = info["perturbation"], info["reward_terms"]
            assert info["reward_nominal"] == pytest.approx(sum(terms.values()))
            weighted = sum(p["w_" + t] * terms[t] for t in RACING_TERMS)
            delta = info["reward_perturbed"] - weighted
            assert delta == pytest.approx(p["reward_noise"], abs=1e-12)
            assert abs(delta) <= 0.1 + 1e-12
            assert rew[agent] == info["reward_perturbed"]
            noise.append(delta)
    # Redrawn every step, centred, and about λ wide (a 2λ-truncated normal: std ≈ 0.88 λ).
    assert len(set(noise)) == len(noise)
    assert abs(np.mean(noise)) < 0.01
    assert 0.035 < np.std(noise) < 0.05
    env.close()


def test_nominal_config_changes_nothing() -> None:
    def trajectory(uncertainty: UncertaintyConfig | None) -> list[np.ndarray]:
        env = RacingEnv(track="bean", n_cars=2, uncertainty=uncertainty)
        obs, infos = env.reset(seed=4)
        assert "perturbation" not in infos["car_0"]
        rng = np.random.default_rng(2)
        out = []
        for _ in range(80):
            obs, _, _, _, _ = env.step(drive(env, obs, rng))
            out += [obs[a] for a in env.agents]
        env.close()
        return out

    for a, b in zip(trajectory(None), trajectory(UncertaintyConfig()), strict=True):
        np.testing.assert_array_equal(a, b)


def test_episode_randomisation() -> None:
    ep = EpisodeRandomisation(start="round_robin", start_step=0.05, direction="alternate")
    env = RacingEnv(track="oval", n_cars=1, uncertainty=UncertaintyConfig("sample", episode=ep))
    starts, directions = [], []
    for seed in range(5):
        _, infos = env.reset(seed=seed)
        starts.append(infos["car_0"]["s"])
        directions.append(env._reversed)
    length = env.base_track.length
    assert directions == [False, True, False, True, False]
    # The grid moves 5 % of a lap further along each episode (compare forward episodes).
    forward = np.array(starts[::2])
    np.testing.assert_allclose(np.diff(forward) % length, 0.1 * length, atol=0.01)
    env.close()

    tracks = EpisodeRandomisation(tracks=("oval", "bean", "hairpins"))
    env = RacingEnv(track="oval", n_cars=2, uncertainty=UncertaintyConfig("sample", episode=tracks))
    names = set()
    for seed in range(16):
        env.reset(seed=seed)
        names.add(env.base_track.name)
        env.step({a: np.array([0.0, 1.0], np.float32) for a in env.agents})
        assert env.max_cycles > 0
    assert names == {"oval", "bean", "hairpins"}
    env.close()


def test_scaled_config_shrinks_about_nominal() -> None:
    cfg = default_config("sample")
    zero, full = cfg.scaled(0.0), cfg.scaled(1.0)
    np.testing.assert_array_equal(zero.lows, zero.nominal)
    np.testing.assert_array_equal(zero.highs, zero.nominal)
    np.testing.assert_allclose(full.lows, cfg.lows)
    np.testing.assert_allclose(full.highs, cfg.highs)
    half = cfg.scaled(0.5)
    assert half.dynamics.friction == pytest.approx((0.8, 1.1))
    assert half.dynamics.latency == (0, 1)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"mode": "robust"},
        {"resample": "lap"},
        {"every_k": 0},
        {"dynamics": DynamicsBounds(friction=(1.2, 0.6))},
        {"dynamics": DynamicsBounds(friction=(0.0, 1.0))},
        {"dynamics": DynamicsBounds(latency=(0, 99))},
        {"perception": PerceptionBounds(lidar_dropout=(0.0, 1.5))},
        {"mode": "adversarial"},  # nothing for nature to choose
        {"nature_rate": 0.0},
        {"perturbation": {"grip": 1.0}},
    ],
)
def test_bad_configs_raise_a_clear_error(kwargs: dict[str, Any]) -> None:
    with pytest.raises(UncertaintyError):
        UncertaintyConfig(**kwargs)


def test_lidar_jitter() -> None:
    rng = np.random.default_rng(0)
    ranges = np.full((2, 2000), 0.5)
    out = jitter_lidar(ranges, np.array([0.0, 0.05]), np.array([0.3, 0.0]), rng)
    assert out.dtype == np.float32 and out.min() >= 0.0 and out.max() <= 1.0
    assert np.mean(out[0] == 1.0) == pytest.approx(0.3, abs=0.04)
    assert np.all((out[0] == 1.0) | (out[0] == 0.5))
    assert np.std(out[1]) == pytest.approx(0.05, rel=0.1)


def test_image_jitter() -> None:
    rng = np.random.default_rng(0)
    grey = np.full((120, 160, 1), 100, np.uint8)
    same = jitter_image(
        grey, brightness=0, contrast=1, hue=0.3, noise_std=0, shift=0, shadow=0, rng=rng
    )
    np.testing.assert_array_equal(same, grey)  # hue means nothing to a grey image
    brighter = jitter_image(
        grey, brightness=0.1, contrast=1, hue=0, noise_std=0, shift=0, shadow=0, rng=rng
    )
    assert np.all(brighter == 126)
    shaded = jitter_image(
        grey, brightness=0, contrast=1, hue=0, noise_std=0, shift=0, shadow=0.5, rng=rng
    )
    assert np.sum(shaded[0, :, 0] == 50) == 40 and np.sum(shaded[0, :, 0] == 100) == 120
    ramp = np.tile(np.arange(160, dtype=np.uint8), (120, 1))[..., None]
    shifted = jitter_image(
        ramp, brightness=0, contrast=1, hue=0, noise_std=0, shift=3, shadow=0, rng=rng
    )
    np.testing.assert_array_equal(shifted[:, 3:], ramp[:, :-3])
    red = np.zeros((4, 4, 3), np.uint8)
    red[..., 0] = 200
    turned = jitter_image(
        red, brightness=0, contrast=1, hue=1 / 3, noise_std=0, shift=0, shadow=0, rng=rng
    )
    assert turned[0, 0, 1] > 150 and turned[0, 0, 0] < 50  # a third of a turn: red to green


# ---- the array-shaped implementation shared by both backends ---------------------------------


def test_batched_draws_have_a_batch_axis_and_stay_in_the_box() -> None:
    values = sample_values(WIDE, np.random.default_rng(0), (64, 4))
    assert values.shape == (64, 4, len(PARAM_NAMES))
    flat = values.reshape(-1, len(PARAM_NAMES))
    assert np.all(flat >= WIDE.lows) and np.all(flat <= WIDE.highs)
    assert set(np.unique(flat[:, INDEX["latency"]])) == {0.0, 1.0, 2.0}
    # One race (an int) draws exactly what it drew before the batch axis existed.
    one = sample_values(WIDE, np.random.default_rng(1), 4)
    assert one.shape == (4, len(PARAM_NAMES))


def test_nature_map_is_the_same_row_by_row_and_as_a_batch() -> None:
    cfg = default_config("adversarial")
    rng = np.random.default_rng(2)
    act = rng.uniform(-1.5, 1.5, (8, 3, len(cfg.free)))
    current = sample_values(default_config("sample"), rng, (8, 3))
    batch = nature_values(cfg, act, current, rate=0.1)
    rows = np.stack([nature_values(cfg, act[b], current[b], rate=0.1) for b in range(8)])
    np.testing.assert_array_equal(batch, rows)
    np.testing.assert_allclose(
        normalised(cfg, nature_values(cfg, act, current)), np.clip(act, -1, 1)
    )


def test_perturbation_state_schedules_per_race() -> None:
    dyn = DynamicsBounds(friction=(0.6, 1.2))
    rng = np.random.default_rng(0)
    every = PerturbationState(UncertaintyConfig("sample", "every_k", 5, dynamics=dyn), (3, 2))
    every.start(rng)
    first = every.values.copy()
    # Race 1 is at step 5 (a redraw), races 0 and 2 are not.
    assert every.advance(rng, np.array([3, 5, 0])) is True
    fric = INDEX["friction"]
    assert np.array_equal(every.values[[0, 2], :, fric], first[[0, 2], :, fric])
    assert not np.array_equal(every.values[1, :, fric], first[1, :, fric])
    # A new episode in race 2 only.
    before = every.values.copy()
    every.start(rng, envs=np.array([False, False, True]))
    assert np.array_equal(every.values[:2], before[:2])
    assert not np.array_equal(every.values[2, :, fric], before[2, :, fric])

    fixed = PerturbationState(UncertaintyConfig("fixed"), (2, 2))
    fixed.start(rng, given={"latency": [1, 3], "friction": 0.7})
    assert fixed.values[:, :, INDEX["latency"]].tolist() == [[1, 3], [1, 3]]
    with pytest.raises(UncertaintyError, match="fixed"):
        every.start(rng, given={"friction": 0.7})


def test_perturbation_state_nature_moves_freely_first_then_rate_limited() -> None:
    cfg = default_config("adversarial")  # acts every step, 10 % of each interval per step
    state = PerturbationState(cfg, (2, 1))
    state.start(np.random.default_rng(0))
    low = -np.ones((2, 1, len(cfg.free)))
    state.advance(np.random.default_rng(0), np.array([0, 0]), low)
    fric = INDEX["friction"]
    assert state.values[:, 0, fric].tolist() == [0.6, 0.6]  # the first choice is free
    acting = np.array([[True], [False]])  # race 1's car is out: its nature does not act
    state.advance(np.random.default_rng(0), np.array([1, 1]), -low, acting)
    assert state.values[0, 0, fric] == pytest.approx(0.6 + 0.1 * 0.6)
    assert state.values[1, 0, fric] == 0.6
    with pytest.raises(UncertaintyError, match="shape"):
        state.advance(np.random.default_rng(0), 2, np.zeros((2, 1, 1)))


def test_perturbed_reward_weights_each_term_and_adds_the_noise() -> None:
    values = Perturbation.from_mapping(
        {"w_progress": 2.0, "w_collision": 0.5, "reward_noise": [0.1, -0.1]}, 2
    ).values
    terms = {name: np.array([1.0, 2.0]) for name in RACING_TERMS}
    racing = perturbed_reward(values, terms, "racing", np.zeros(2))
    np.testing.assert_allclose(racing, [2 + 1 + 1 + 0.5 + 1 + 0.1, 4 + 2 + 2 + 1 + 2 - 0.1])
    np.testing.assert_allclose(perturbed_reward(values, terms, "progress", np.zeros(2)), [2.1, 3.9])
    np.testing.assert_allclose(perturbed_reward(values, terms, "fn", np.ones(2)), [1.1, 0.9])
