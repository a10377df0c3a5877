"""RARL's nature role on the batched backend (:class:`agents.batch_rarl.BatchNatureVecEnv`).

Slot ``i`` is the nature of car slot ``i`` of a :class:`arena.batch.vec_env.BatchVecEnv`; its
reward is exactly minus that car's (the racer's reward, scaled, less the DNF penalty) on every
step, the DNF step and the truncation step included. The check: a twin ``BatchVecEnv`` seeded
alike, its natures given the same actions and its cars the same commands, is the racer's view.
"""

from __future__ import annotations

from typing import Any
from unittest import mock

import numpy as np
import pytest

from agents.batch_rarl import BatchNatureVecEnv
from agents.policy import PolicyError
from arena.batch.vec_env import BatchVecEnv
from arena.uncertainty import RewardBounds, default_config, normalised
from tests.tracks.builders import stadium

CFG = default_config("adversarial", reward=RewardBounds(noise=0.3, progress=(0.8, 1.2)))
TRACK = stadium(10.0, 5.0, 2.0, 2.0)  # 51 m: a car driving straight on leaves it in ~2 s
N_ENVS, N_CARS = 2, 2
SLOTS = 2 * N_ENVS * N_CARS  # the track both ways round: two simulators


def racers(**changes: Any) -> BatchVecEnv:
    """Two races of two cars each way round the stadium; DNF after 0.5 s off the road,
    truncation after 70 steps; reward x 2, DNF penalty 7."""
    kwargs: dict[str, Any] = {
        "n_envs": N_ENVS,
        "n_cars": N_CARS,
        "reverse": True,
        "random_starts": False,
        "reward_scale": 2.0,
        "dnf_penalty": 7.0,
        "seed": 4,
        "sim_kwargs": {"uncertainty": CFG, "max_cycles": 70, "off_track_limit": 0.5},
    }
    kwargs.update(changes)
    return BatchVecEnv([TRACK], **kwargs)


class Racer:
    """A frozen racer: fixed commands per slot, straight on (slot 0 at full throttle, the
    others at 0.3): the reversed races' first cars leave the road and retire at step 62, the
    others run to the time limit; keeps the observations it was given."""

    def __init__(self) -> None:
        self.actions = np.tile(np.array([0.0, 0.3], np.float32), (SLOTS, 1))
        self.actions[0] = [0.0, 1.0]
        self.seen: list[np.ndarray] = []

    def act_batch(self, obs: np.ndarray) -> np.ndarray:
        self.seen.append(np.array(obs))
        return self.actions


class Given:
    """The twin's nature driver for one simulator: the rows it is told (one step's)."""

    def __init__(self) -> None:
        self.rows = np.zeros((N_ENVS * N_CARS, len(CFG.free)))

    def act_batch(self, obs: np.ndarray) -> np.ndarray:
        return self.rows


def test_refuses_racers_without_adversarial_uncertainty() -> None:
    """Natures need adversarial uncertainty on every simulator: none, ``sample``, or one
    simulator changed behind the env's back are each refused with the same message."""
    message = "the nature role needs adversarial uncertainty on every simulator"
    for kwargs in ({"sim_kwargs": {}}, {"sim_kwargs": {"uncertainty": default_config("sample")}}):
        with pytest.raises(PolicyError, match=f"^{message}$"):
            BatchNatureVecEnv(racers(**kwargs))
    mixed = racers()
    mixed.sims[1].uncertainty = None
    with pytest.raises(PolicyError, match=f"^{message}$"):
        BatchNatureVecEnv(mixed)
    mixed.sims[1].uncertainty = default_config("sample")
    with pytest.raises(PolicyError, match=f"^{message}$"):
        BatchNatureVecEnv(mixed)


def test_spaces_reset_observations_and_delegation() -> None:
    """One slot per car; observation = the global state then the car's one-hot (float32,
    unbounded), action = Box(-1, 1, (k,)); seed/reset/attributes go to the racing env."""
    env = racers()
    natures = BatchNatureVecEnv(env)
    sim = env.sims[0]
    size = sim.state_size + N_CARS
    assert natures.num_envs == SLOTS and natures.render_mode is None and natures.racer is None
    space = natures.observation_space
    assert space.shape == (size,) and space.dtype == np.float32
    assert np.all(space.low == -np.inf) and np.all(space.high == np.inf)
    act = natures.action_space
    assert act.shape == (len(CFG.free),) and act.dtype == np.float32
    assert np.all(act.low == -1.0) and np.all(act.high == 1.0)

    # One track one way round (the usual training set-up): one simulator, the same spaces.
    single = BatchNatureVecEnv(racers(reverse=False))
    assert single.num_envs == N_ENVS * N_CARS
    assert single.observation_space.shape == (size,) and single.action_space.shape == act.shape
    assert single.reset().shape == (N_ENVS * N_CARS, size)

    twin = racers()
    assert natures.seed(11) == twin.seed(11)
    obs = natures.reset()
    twin_obs = twin.reset()
    assert obs.shape == (SLOTS, size) and obs.dtype == np.float32
    for k, (s, t) in enumerate(zip(env.sims, twin.sims, strict=True)):
        state = t.ops.to_numpy(t.global_state())  # (B, S): seeded alike, the same races
        np.testing.assert_array_equal(s.ops.to_numpy(s.global_state()), state)
        for e in range(N_ENVS):
            for j in range(N_CARS):
                row = obs[(k * N_ENVS + e) * N_CARS + j]
                np.testing.assert_array_equal(row[: sim.state_size], state[e])
                np.testing.assert_array_equal(row[sim.state_size :], np.eye(N_CARS)[j])
    # The racer is handed the cars' observations of that reset.
    racer = Racer()
    natures.racer = racer
    natures.step(np.zeros((SLOTS, len(CFG.free)), np.float32))
    np.testing.assert_array_equal(racer.seen[0], twin_obs)

    natures.set_attr("max_cycles", 33, indices=[0])
    assert natures.get_attr("max_cycles") == [33] * N_ENVS * N_CARS + [70] * N_ENVS * N_CARS
    assert natures.get_attr("max_cycles", indices=[SLOTS - 1]) == [70]
    other = env.sims[0].state
    (called,) = natures.env_method("global_state", indices=[SLOTS - 1], st=other)
    np.testing.assert_array_equal(called, env.sims[1].global_state(st=other))
    (called,) = natures.env_method("global_state", other, indices=[SLOTS - 1])
    np.testing.assert_array_equal(called, env.sims[1].global_state(st=other))
    assert len(natures.env_method("nature_obs")) == SLOTS
    assert natures.env_is_wrapped(object, indices=[0, 1]) == [False, False]
    with mock.patch.object(env, "close") as close:
        natures.close()
    close.assert_called_once_with()


def test_step_without_a_racer_is_refused() -> None:
    """Stepping before a frozen racer is set is a clear error, not an AttributeError."""
    natures = BatchNatureVecEnv(racers())
    natures.reset()
    with pytest.raises(
        PolicyError, match=r"^BatchNatureVecEnv.racer \(a frozen racer driver\) is not set$"
    ):
        natures.step(np.zeros((SLOTS, len(CFG.free)), np.float32))


def test_each_nature_gets_exactly_minus_its_cars_reward_dnf_and_scale_included() -> None:
    """Per slot and per step, the DNF step (penalty 7 included) and the truncation step too:
    the nature's reward is exactly minus the car's scaled reward; slot i's action moves car
    i's perturbation; done slots carry the final nature observation and the negated return;
    the racer sees the cars' latest observations."""
    env, twin = racers(), racers()
    natures = BatchNatureVecEnv(env)
    racer = Racer()
    natures.racer = racer
    drivers = [Given() for _ in twin.sims]
    twin.set_attr("nature", None)
    for sim, driver in zip(twin.sims, drivers, strict=True):
        sim.nature = driver
    obs, twin_obs = natures.reset(), twin.reset()
    rng = np.random.default_rng(0)
    k = len(CFG.free)
    per_sim = N_ENVS * N_CARS
    seen_dnf = seen_trunc = False
    for t in range(75):
        acts = rng.uniform(-1.0, 1.0, (SLOTS, k)).astype(np.float32)
        for s, driver in enumerate(drivers):
            driver.rows = acts[s * per_sim : (s + 1) * per_sim].astype(np.float64)
        obs, rew, done, infos = natures.step(acts)
        np.testing.assert_array_equal(racer.seen[-1], twin_obs)  # the cars' current view
        twin_obs, twin_rew, twin_done, twin_infos = twin.step(racer.actions)
        assert rew.dtype == twin_rew.dtype
        np.testing.assert_array_equal(rew, -twin_rew)  # exactly zero-sum, slot by slot
        np.testing.assert_array_equal(done, twin_done)
        if t == 0:  # nature i's first action puts car i anywhere in the box: its own
            for s, sim in enumerate(env.sims):
                xi = normalised(CFG, sim.unc.raw).reshape(per_sim, k)
                np.testing.assert_allclose(xi, acts[s * per_sim : (s + 1) * per_sim], atol=1e-6)
        for i in range(SLOTS):
            if not done[i]:
                assert infos[i] == twin_infos[i]
                continue
            info, twin_info = infos[i], twin_infos[i]
            s, slot = divmod(i, per_sim)
            final = twin.sims[s].final_nature_obs.reshape(per_sim, -1)[slot]
            assert info["terminal_observation"].dtype == np.float32
            np.testing.assert_array_equal(info["terminal_observation"], final)
            assert not np.array_equal(final, obs[i])  # the next race's first observation
            assert info["episode"]["r"] == -twin_info["episode"]["r"] != 0.0
            assert info["episode"]["l"] == twin_info["episode"]["l"]
            for key in ("laps_completed", "cut_short", "dnf_reason", "TimeLimit.truncated"):
                assert info[key] == twin_info[key]
            if info["dnf_reason"] == "retired":
                seen_dnf = True
                assert twin_rew[i] < -7.0 * 0.5  # the penalty is in the car's reward
                assert rew[i] == -twin_rew[i] > 0.0
            elif info["TimeLimit.truncated"]:
                seen_trunc = True
    assert seen_dnf and seen_trunc
