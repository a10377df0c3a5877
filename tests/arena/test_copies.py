"""Every env copy owns its simulator (issue 15).

The failure this guards against was found by running SuperSuit's
``concat_vec_envs_v1(env, 2)`` recipe: its copies shared one pybullet client, and two copies
stepped in turn silently corrupted each other's physics; a copy sent to a subprocess failed
with "Not connected to physics server".
"""

from __future__ import annotations

import copy
import pickle
import subprocess
import sys
from typing import Any

import cloudpickle
import numpy as np
import pytest
from supersuit import concat_vec_envs_v1, pettingzoo_env_to_vec_env_v1

import arena
from arena.env import RacingEnv
from tests.arena.conftest import pursuit_driver

STEPS = 40


def _trace(env: RacingEnv, obs: dict[str, Any], steps: int) -> list[Any]:
    """Observations, rewards and infos of ``steps`` pursuit steps (bytes: bit for bit)."""
    act = pursuit_driver(env)
    out = []
    for _ in range(steps):
        obs, rew, *_, infos = env.step({a: act(obs[a]) for a in env.agents})
        out.append(
            (
                b"".join(obs[a].tobytes() for a in sorted(obs)),
                sorted(rew.items()),
                sorted((a, i["race_progress"], i["speed"]) for a, i in infos.items()),
            )
        )
    return out


def test_two_copies_stepped_in_turn_match_two_independent_envs_bit_for_bit() -> None:
    base = arena.parallel_env(track="oval", n_cars=3)
    base.reset(seed=5)
    first, second = copy.deepcopy(base), copy.deepcopy(base)
    assert len({base.sim.client, first.sim.client, second.sim.client}) == 3
    obs_1, _ = first.reset(seed=1)
    obs_2, _ = second.reset(seed=2)
    act_1, act_2 = pursuit_driver(first), pursuit_driver(second)
    trace_1, trace_2 = [], []
    for _ in range(STEPS):  # interleaved: one step of each in turn
        obs_1, *_ = first.step({a: act_1(obs_1[a]) for a in first.agents})
        obs_2, *_ = second.step({a: act_2(obs_2[a]) for a in second.agents})
        trace_1.append(b"".join(obs_1[a].tobytes() for a in sorted(obs_1)))
        trace_2.append(b"".join(obs_2[a].tobytes() for a in sorted(obs_2)))
    for seed, trace in ((1, trace_1), (2, trace_2)):
        alone = arena.parallel_env(track="oval", n_cars=3)
        obs, _ = alone.reset(seed=seed)
        assert [t[0] for t in _trace(alone, obs, STEPS)] == trace
        alone.close()


@pytest.mark.parametrize("backend", ["pybullet", "batch"])
def test_a_copy_made_mid_race_continues_exactly_as_the_original(backend: str) -> None:
    # On the batched backend the copy failed outright ("cannot pickle 'module' object": its
    # array namespace held the numpy module).
    env = arena.parallel_env(track="oval", n_cars=2, backend=backend)
    obs, _ = env.reset(seed=0)
    act = pursuit_driver(env)
    for _ in range(15):  # mid-race: cars moving, steering deflected
        obs, *_ = env.step({a: act(obs[a]) for a in env.agents})
    copied = copy.deepcopy(env)
    pickled = pickle.loads(pickle.dumps(env))
    cloudpickled = cloudpickle.loads(cloudpickle.dumps(env))
    ref = _trace(env, obs, 30)
    assert _trace(copied, obs, 30) == ref
    assert _trace(pickled, obs, 30) == ref
    assert _trace(cloudpickled, obs, 30) == ref


def test_a_pickled_env_runs_in_a_fresh_process() -> None:
    """cloudpickle (what SuperSuit and Ray send) into a new interpreter (a spawned process:
    nothing inherited), stepped there, gives the same observations as here."""
    env = arena.parallel_env(track="oval", n_cars=2)
    obs, _ = env.reset(seed=3)
    blob = cloudpickle.dumps(env)
    child = (
        "import sys, cloudpickle, numpy as np\n"
        "env = cloudpickle.loads(sys.stdin.buffer.read())\n"
        "for _ in range(20):\n"
        "    obs, *_ = env.step({a: np.array([0.1, 0.6], dtype=np.float32) for a in env.agents})\n"
        "sys.stdout.buffer.write(b''.join(obs[a].tobytes() for a in sorted(obs)))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", child], input=blob, capture_output=True, check=True, timeout=120
    )
    for _ in range(20):
        obs, *_ = env.step({a: np.array([0.1, 0.6], dtype=np.float32) for a in env.agents})
    assert done.stdout == b"".join(obs[a].tobytes() for a in sorted(obs))


def test_supersuit_subprocess_vector_env_runs() -> None:
    """SuperSuit's multi-process recipe (num_cpus=2: each copy lives in its own worker
    process), which failed with "Not connected to physics server" before copies reconnected."""
    env = arena.parallel_env(track="oval", n_cars=2, park_finished=True, max_cycles=25)
    venv = concat_vec_envs_v1(
        pettingzoo_env_to_vec_env_v1(env), 2, num_cpus=2, base_class="stable_baselines3"
    )
    try:
        obs = venv.reset()
        assert obs.shape == (4, env.layout.size)
        resets = 0
        for _ in range(60):
            obs, rewards, dones, _ = venv.step(np.tile([[0.0, 0.5]], (4, 1)).astype(np.float32))
            resets += int(dones.all())
            assert np.isfinite(obs).all() and np.isfinite(rewards).all()
        assert resets >= 2
    finally:
        venv.close()
