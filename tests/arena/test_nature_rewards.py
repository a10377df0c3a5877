"""The env side of the zero-sum path (:mod:`arena.episode`): nature agents' observations,
rewards and infos, the perturbed reward of each reward mode, on every step of a whole race.

``adversarial`` uncertainty gives car ``k`` a nature ``nature_car_k`` whose reward is exactly
minus the car's *perturbed* reward (Pinto et al. 2017, RARL; Zhang et al. 2020): on every
step the car races, its finishing step and its DNF step included, and 0.0 once it is parked.
Races are short (a 51 m stadium at 10 Hz) so that mutation testing can re-run them.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

import arena
from arena.rewards import RACING_TERMS
from arena.uncertainty import RewardBounds, default_config
from tests.arena.conftest import pursuit_driver
from tests.tracks.builders import stadium

# Every reward weight free (and the additive noise), so perturbed != nominal in every term.
REWARD = RewardBounds(
    noise=0.3,
    progress=(0.8, 1.2),
    off_track=(0.5, 1.5),
    wall=(0.5, 1.5),
    collision=(0.5, 2.0),
    overtake=(0.5, 1.5),
)
CFG = default_config("adversarial", reward=REWARD)
TRACK = stadium(10.0, 5.0, 2.0, 2.0)  # 51 m a lap: two pursuit cars finish in ~12 s


def race(reward: Any) -> Any:
    """Three cars, park_finished: car_0 and car_2 drive pure pursuit and finish, car_1 sits
    on the grid and retires (stuck after 1 s); the natures act at random."""
    return arena.parallel_env(
        track=TRACK,
        n_cars=3,
        control_hz=10,
        stuck_time=1.0,
        reward=reward,
        uncertainty=CFG,
        park_finished=True,
    )


def actions(env: Any, obs: dict[str, Any], rng: np.random.Generator) -> dict[str, Any]:
    """Pursuit for car_0 and car_2, zeros for car_1, uniform [-1, 1] for every nature."""
    drive = pursuit_driver(env)
    out: dict[str, Any] = {}
    for agent in env.agents:
        if agent.startswith("nature_"):
            out[agent] = rng.uniform(-1.0, 1.0, len(CFG.free))
        elif agent == "car_1":
            out[agent] = np.zeros(2)
        else:
            out[agent] = drive(obs[agent])
    return out


def nature_obs(env: Any, k: int) -> np.ndarray:
    """What nature_car_k must see: the env's global state, then a one-hot of car k."""
    return np.concatenate([env.state(), np.eye(env.n_cars, dtype=np.float32)[k]])


def expected_perturbed(
    mode: str, nominal: float, terms: dict[str, float], p: dict[str, float]
) -> float:
    """The perturbed reward from the car's own infos: weights on the terms plus the noise."""
    if mode == "racing":
        base = sum(p[f"w_{name}"] * terms[name] for name in RACING_TERMS)
    elif mode == "progress":
        base = p["w_progress"] * terms["progress"]
    else:
        base = nominal
    return base + p["reward_noise"]


def check_reset(env: Any, obs: dict[str, Any], infos: dict[str, Any]) -> None:
    """Reset: every nature sees state + one-hot; zero rewards and the perturbation in infos."""
    for k, car in enumerate(env.cars):
        nat = f"nature_car_{k}"
        extra = {
            "reward_nominal": 0.0,
            "reward_perturbed": 0.0,
            "perturbation": env.perturbation.car(k),
        }
        assert infos[nat] == {"target": car, **extra}
        assert {key: infos[car][key] for key in extra} == extra
        assert obs[nat].dtype == np.float32 and obs[nat].shape == env.observation_space(nat).shape
        np.testing.assert_array_equal(obs[nat], nature_obs(env, k))


def run_race(mode: str, reward: Any) -> dict[str, Any]:
    """Run a whole race, checking the zero-sum contract on every step; returns what it saw."""
    env = race(reward)
    rng = np.random.default_rng(1)
    obs, infos = env.reset(seed=0)
    check_reset(env, obs, infos)
    last_nature_obs = {nat: obs[nat] for nat in env.natures}
    seen: dict[str, Any] = {"finish": [], "dnf": [], "parked": 0, "steps": 0}
    out: set[str] = set()  # cars that finished or retired on an earlier step
    while env.agents:
        racing = [c for c in env.cars if c not in out]
        obs, rew, term, trunc, infos = env.step(actions(env, obs, rng))
        out |= {c for c in racing if term[c] or trunc[c]}
        seen["steps"] += 1
        for k, car in enumerate(env.cars):
            nat = f"nature_car_{k}"
            if car not in racing:  # parked: both read 0.0 and keep their last observation
                assert rew[car] == 0.0 and rew[nat] == 0.0
                np.testing.assert_array_equal(obs[nat], last_nature_obs[nat])
                seen["parked"] += 1
                continue
            p = env.perturbation.car(k)
            nominal = infos[car]["reward_nominal"]
            perturbed = infos[car]["reward_perturbed"]
            # Zero-sum, exactly: the nature's reward is minus the car's perturbed reward.
            assert rew[car] == perturbed
            assert rew[nat] == -perturbed
            assert infos[car]["perturbation"] == p
            assert infos[nat] == {
                "target": car,
                "reward_nominal": nominal,
                "reward_perturbed": perturbed,
                "perturbation": p,
            }
            terms = infos[car]["reward_terms"]
            assert perturbed == pytest.approx(
                expected_perturbed(mode, nominal, terms, p), rel=1e-12, abs=1e-12
            )
            assert perturbed != nominal  # the perturbation is not a no-op
            assert (term[nat], trunc[nat]) == (term[car], trunc[car])
            assert obs[nat].dtype == np.float32
            np.testing.assert_array_equal(obs[nat], nature_obs(env, k))
            last_nature_obs[nat] = obs[nat]
            if term[car] and env.finished[k]:
                seen["finish"].append((car, rew[car], nominal, terms))
            elif term[car]:
                seen["dnf"].append((car, rew[car], infos[car]["dnf_reason"]))
    env.close()
    # car_0 and car_2 finished, car_1 retired: the contract held on those very steps.
    assert sorted(c for c, *_ in seen["finish"]) == ["car_0", "car_2"]
    assert [(c, reason) for c, _, reason in seen["dnf"]] == [("car_1", "stuck")]
    assert seen["parked"] > 0
    return seen


def test_nature_reward_is_minus_the_perturbed_progress_reward_on_every_step() -> None:
    """reward="progress": the perturbed reward is w_progress x progress + noise; each nature
    gets exactly its negation on every step, the finishing and the DNF step included, and
    sees the global state with its car's one-hot."""
    seen = run_race("progress", "progress")
    for _, reward, nominal, terms in seen["finish"]:
        assert nominal == terms["progress"] > 0.0  # the nominal reward is the progress term
        assert reward != 0.0


def test_nature_reward_is_minus_the_perturbed_racing_reward_on_every_step() -> None:
    """reward="racing": the nominal reward is the sum of the (weighted) racing terms, the
    perturbed one puts each term's interval weight on it; the nature gets exactly minus it."""
    seen = run_race("racing", "racing")
    for _, _, nominal, terms in seen["finish"]:
        assert nominal == pytest.approx(sum(terms[name] for name in RACING_TERMS), abs=1e-12)


class Recorder:
    """A DeepRacer reward function (the developer guide's ``reward_function(params)``) that
    keeps the params it was given and rewards speed plus progress."""

    def __init__(self) -> None:
        self.params: list[dict[str, Any]] = []

    def __call__(self, params: dict[str, Any]) -> float:
        self.params.append(params)
        return 1.0 + float(params["speed"]) + 0.01 * float(params["progress"])


def test_reward_function_nominal_and_perturbed_with_natures() -> None:
    """A reward function: its value is the nominal reward (and the ``deepracer`` term), the
    perturbation only adds the noise, and the nature gets exactly minus the sum, on the
    finishing and the DNF steps too (the function is called for every car still racing)."""
    fn = Recorder()
    seen = run_race("function", fn)
    for _, _, nominal, terms in seen["finish"]:
        assert terms["deepracer"] == nominal > 1.0
    # Called once per racing car per step: the steps the cars raced, DNF/finish included.
    assert len(fn.params) > 2 * 100


def test_reward_function_params_describe_the_car_of_this_step() -> None:
    """The params a reward function gets are the car's of this step: speed, progress (% of the
    race), steps, off-track and crash flags (its own wall or car contact, not another car's)
    match the env's infos; a reversed race builds reversed params (one cached builder per
    track and direction)."""
    fn = Recorder()
    env = arena.parallel_env(track=TRACK, n_cars=3, control_hz=10, reward=fn)
    drive = pursuit_driver(env)
    flags: set[tuple[bool, bool]] = set()
    crashes: set[tuple[bool, ...]] = set()
    for direction in ("forward", "reverse"):
        obs, _ = env.reset(seed=0, options={"direction": direction})
        for step in range(1, 26):
            fn.params.clear()
            acts = {a: drive(obs[a]) for a in env.agents}
            acts["car_1"] = np.array([0.0, 1.0])  # straight on: off the road, into the wall
            acts["car_2"] = np.zeros(2)  # stays on the grid, touching nothing
            obs, rew, _, _, infos = env.step(acts)
            assert len(fn.params) == 3
            crashes.add(tuple(p["is_crashed"] for p in fn.params))
            for car, p in zip(env.cars, fn.params, strict=True):
                info = infos[car]
                assert rew[car] == info["reward_terms"]["deepracer"]
                assert rew[car] == 1.0 + p["speed"] + 0.01 * p["progress"]
                assert p["is_reversed"] == (direction == "reverse")
                assert p["steps"] == step
                assert p["speed"] == pytest.approx(info["speed"], abs=1e-9)
                expected = 100.0 * info["race_progress"] / env.race_distance
                assert p["progress"] == pytest.approx(np.clip(expected, 0.0, 100.0), abs=1e-6)
                assert p["is_offtrack"] == info["off_track"]
                crashed = info["wall_contact"] or bool(info["collisions"])
                assert p["is_crashed"] == crashed
                flags.add((p["is_offtrack"], p["is_crashed"]))
    env.close()
    # On the road, off it, off it against the wall, and back on the road against it.
    assert flags == {(False, False), (True, False), (True, True), (False, True)}
    assert (True, True, False) in crashes  # reversed: car_0 and car_1 touch, car_2 does not


def test_sampled_uncertainty_has_infos_but_no_natures() -> None:
    """``sample`` mode: the cars' infos carry nominal/perturbed rewards and the perturbation,
    the reward is the perturbed one, and there is no nature agent."""
    cfg = default_config("sample", reward=RewardBounds(noise=0.3))
    env = arena.parallel_env(
        track=TRACK, n_cars=2, control_hz=10, reward="progress", uncertainty=cfg
    )
    assert env.possible_agents == ["car_0", "car_1"]
    obs, infos = env.reset(seed=2)
    assert set(obs) == {"car_0", "car_1"}
    for k, car in enumerate(env.cars):
        assert infos[car]["reward_perturbed"] == 0.0 and infos[car]["reward_nominal"] == 0.0
        assert infos[car]["perturbation"] == env.perturbation.car(k)
    drive = pursuit_driver(env)
    for _ in range(10):
        obs, rew, _, _, infos = env.step({a: drive(obs[a]) for a in env.agents})
        assert set(rew) == {"car_0", "car_1"}
        for k, car in enumerate(env.cars):
            p = env.perturbation.car(k)
            nominal = infos[car]["reward_nominal"]
            assert nominal == infos[car]["reward_terms"]["progress"]
            assert rew[car] == infos[car]["reward_perturbed"]
            assert rew[car] == pytest.approx(p["w_progress"] * nominal + p["reward_noise"])
            assert rew[car] != nominal
    env.close()
