"""Perturbation-aware observations (``observe_perturbation=True``): each car's observation
ends with its own model-uncertainty values, the same block on both backends, read from the
values the car actually races under (also at the first step of an auto-reset episode)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

from arena import RacingEnv
from arena.batch.parallel import BatchParallelEnv
from arena.batch.sim import BatchSim
from arena.observations import CONTEXT_LIMIT, CONTEXT_SIZE, ObservationLayout
from arena.sim import SimError
from arena.uncertainty import (
    CONTEXT_FEATURES,
    CONTEXT_SCALES,
    Perturbation,
    UncertaintyConfig,
    default_config,
    perturbation_context,
)
from tests.arena.conftest import pursuit_driver

BACKENDS = {"pybullet": RacingEnv, "batch": BatchParallelEnv}
# Every column of the block moved off nominal (a typical grid point, plus the lidar's).
POINT = {
    "friction": 0.7,
    "mass": 1.2,
    "motor": 0.9,
    "steer_gain": 1.1,
    "steer_offset": -0.05,
    "latency": 2,
    "action_noise": 0.05,
    "lidar_noise": 0.02,
    "lidar_dropout": 0.05,
}
WIDE_STEP = default_config("sample", resample="step")


def test_the_block_is_appended_and_every_other_slice_stays_where_it_was() -> None:
    plain, aware = ObservationLayout(64, 3), ObservationLayout(64, 3, context=True)
    assert aware.size == plain.size + len(CONTEXT_FEATURES) == plain.size + CONTEXT_SIZE == 109
    for name in ("lidar", "ego", "track_ahead", "opponents"):
        assert getattr(aware, name) == getattr(plain, name)
    assert plain.perturbation == slice(plain.size, plain.size)  # empty without the option
    low, high = aware.bounds()
    np.testing.assert_array_equal(low[: plain.size], plain.bounds()[0])
    assert (low[aware.perturbation] == -CONTEXT_LIMIT).all()
    assert (high[aware.perturbation] == CONTEXT_LIMIT).all()


def test_the_block_is_each_value_off_nominal_over_a_fixed_scale() -> None:
    values = Perturbation.from_mapping(POINT, 1).values
    block = perturbation_context(values)[0]
    for k, name in enumerate(CONTEXT_FEATURES):
        nominal = 1.0 if name in ("friction", "mass", "motor", "steer_gain") else 0.0
        assert block[k] == pytest.approx((POINT[name] - nominal) / CONTEXT_SCALES[k])
    # The scale does not depend on the set a car is drawn from: friction 0.6 reads the same
    # under the default set and under a wider one.
    assert perturbation_context(Perturbation.from_mapping({"friction": 0.6}, 1).values)[
        0, 0
    ] == pytest.approx(-2 / 3)


@pytest.mark.parametrize("backend", list(BACKENDS))
def test_cars_observe_their_perturbation_and_nothing_else_changes(backend: str) -> None:
    """The same race with and without the option: the first 100 floats agree exactly, and the
    block is the fixed perturbation's, every step."""
    cls = BACKENDS[backend]
    fixed = UncertaintyConfig("fixed")
    aware = cls(track="oval", n_cars=2, uncertainty=fixed, observe_perturbation=True)
    plain = cls(track="oval", n_cars=2, uncertainty=fixed)
    size = plain.layout.size
    assert aware.observation_space("car_0").shape == (size + 9,)
    want = perturbation_context(Perturbation.from_mapping(POINT, 1).values)[0].astype(np.float32)
    obs_a, _ = aware.reset(seed=3, options={"perturbation": POINT})
    obs_p, _ = plain.reset(seed=3, options={"perturbation": POINT})
    drive = pursuit_driver(plain)
    for _ in range(40):
        for agent in plain.agents:
            np.testing.assert_array_equal(obs_a[agent][:size], obs_p[agent])
            np.testing.assert_allclose(obs_a[agent][size:], want, rtol=1e-6)
            assert aware.observation_space(agent).contains(obs_a[agent])
        actions = {a: drive(obs_p[a]) for a in plain.agents}
        obs_a, *_ = aware.step(actions)
        obs_p, *_ = plain.step(actions)
    aware.close()
    plain.close()


def test_both_backends_give_the_same_block() -> None:
    blocks = []
    for cls in BACKENDS.values():
        env = cls(
            track="bean",
            n_cars=1,
            uncertainty=UncertaintyConfig("fixed"),
            observe_perturbation=True,
        )
        obs, _ = env.reset(seed=0, options={"perturbation": POINT})
        blocks.append(obs["car_0"][env.layout.perturbation])
        env.close()
    np.testing.assert_array_equal(blocks[0], blocks[1])


@pytest.mark.parametrize("backend", list(BACKENDS))
def test_a_nominal_car_reads_zeros(backend: str) -> None:
    env = BACKENDS[backend](track="oval", n_cars=2, observe_perturbation=True)
    obs, _ = env.reset(seed=0)
    for _ in range(3):
        for agent in env.agents:
            assert not obs[agent][env.layout.perturbation].any()
        obs, *_ = env.step({a: np.array([0.0, 1.0], np.float32) for a in env.agents})
    env.close()


def test_a_per_step_draw_is_observed_the_step_it_applies() -> None:
    """``resample="step"``: the values change every step; the observation after a step reads
    the values that step raced under (``infos[...]["perturbation"]``)."""
    env = RacingEnv(track="oval", n_cars=2, uncertainty=WIDE_STEP, observe_perturbation=True)
    obs, infos = env.reset(seed=5)
    seen = set()
    for _ in range(10):
        for agent in env.agents:
            values = Perturbation.from_mapping(infos[agent]["perturbation"], 1).values
            want = perturbation_context(values)[0].astype(np.float32)
            np.testing.assert_allclose(obs[agent][env.layout.perturbation], want, rtol=1e-6)
            seen.add(float(want[0]))
        obs, _, _, _, infos = env.step({a: np.array([0.0, 0.5], np.float32) for a in env.agents})
    assert len(seen) > 5  # the draws did move
    env.close()


def test_an_auto_reset_episode_observes_its_new_values_from_its_first_step() -> None:
    """Training's batched simulator restarts finished races inside ``step``: the observation
    that ends the old race (``final_obs``) reads the old values, the new race's first one the
    values just drawn for it."""
    sim = BatchSim(
        "oval", 4, 2, device="numpy", uncertainty=default_config("sample"), seed=11,
        observe_perturbation=True, max_cycles=30,
    )  # fmt: skip
    block = sim.layout.perturbation
    obs = sim.reset(seed=11)
    np.testing.assert_allclose(obs[..., block], perturbation_context(sim.unc.values), rtol=1e-6)
    before = np.array(sim.unc.values, copy=True)
    restarted = False
    for _ in range(40):
        res = sim.step(np.tile([0.0, 0.3], (4, 2, 1)))
        now = perturbation_context(np.asarray(sim.unc.values))
        np.testing.assert_allclose(res.obs[..., block], now, rtol=1e-6)
        done = np.asarray(res.env_done)
        if done.any():
            restarted = True
            old = perturbation_context(before)
            np.testing.assert_allclose(res.final_obs[done][..., block], old[done], rtol=1e-6)
            assert not np.allclose(now[done], old[done])  # new draws, observed at once
        before = np.array(sim.unc.values, copy=True)
    assert restarted


def test_dict_observations_name_the_block_and_images_refuse_it() -> None:
    env = RacingEnv(track="oval", n_cars=1, obs_mode="dict", observe_perturbation=True)
    obs, _ = env.reset(seed=0, options={})
    assert obs["car_0"]["perturbation"].shape == (9,)
    assert env.observation_space("car_0").contains(obs["car_0"])
    env.close()
    with pytest.raises(SimError, match=r"observe_perturbation.*image"):
        RacingEnv(track="oval", n_cars=1, obs_mode="image", observe_perturbation=True)


@pytest.mark.parametrize("backend", list(BACKENDS))
def test_parallel_api_with_perturbation_aware_observations(backend: str) -> None:
    kwargs: dict[str, Any] = {"uncertainty": WIDE_STEP, "observe_perturbation": True}
    env = BACKENDS[backend](track="oval", n_cars=2, **kwargs)
    parallel_api_test(env, num_cycles=30)
    env.close()


def test_latency_beyond_the_scale_stays_inside_the_bounds() -> None:
    """Latency 10 (the FIFO's bound) reads 3.3 and a 0.3-grip car −1.2: inside ±4."""
    values = Perturbation.from_mapping({"latency": 10, "friction": 0.3}, 1).values
    env = RacingEnv(
        track="oval", n_cars=1, uncertainty=UncertaintyConfig("fixed"), observe_perturbation=True
    )
    obs, _ = env.reset(seed=0, options={"perturbation": {"latency": 10, "friction": 0.3}})
    block = obs["car_0"][env.layout.perturbation]
    assert block[CONTEXT_FEATURES.index("latency")] == pytest.approx(10 / 3, rel=1e-6)
    np.testing.assert_allclose(block, perturbation_context(values)[0], rtol=1e-6)
    assert env.observation_space("car_0").contains(obs["car_0"])
    env.close()
