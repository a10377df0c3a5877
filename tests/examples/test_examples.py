"""Every script in examples/ runs with a tiny budget and trains something.

The scripts are the recipes users copy (SB3 + Gymnasium, SuperSuit + SB3, RLlib, CleanRL);
each is imported from its file and its ``main(Args(...))`` called, as ``python
examples/X.py --flag ...`` does, and one is run exactly that way. Asserted: losses are
finite, the trained policy acts inside the action space, and where it is cheap (the batched
CleanRL script) the deterministic policy's reward on fixed starts improved.
"""

from __future__ import annotations

import importlib.util
import math
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
EXAMPLES = REPO / "examples"


def load(name: str) -> ModuleType:
    """Import ``examples/<name>.py`` as a module (it is a script, not a package)."""
    spec = importlib.util.spec_from_file_location(f"examples_{name}", EXAMPLES / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while building
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
@pytest.mark.component("stable-baselines3")
def test_cleanrl_ppo_on_the_batch_backend_learns_to_drive() -> None:
    ex = load("cleanrl_ppo_batch")
    args = ex.Args(seed=1, n_envs=16, n_cars=2, num_steps=64, total_timesteps=6 * 2048)
    out = ex.main(args)
    history = out["history"]
    assert len(history) == 6
    assert all(math.isfinite(row["losses/value_loss"]) for row in history)
    assert all(math.isfinite(row["losses/policy_loss"]) for row in history)
    # An untrained policy (mean action ≈ 0) stands still; after 12k agent-steps it drives.
    assert abs(out["eval/reward_per_step_before"]) < 0.01
    assert out["eval/reward_per_step_after"] > 0.05  # > 1 m/s of progress on average
    action = out["agent"].act(np.zeros(100, dtype=np.float32))
    assert action.shape == (2,) and np.all(np.abs(action) <= 1.0)


@pytest.mark.slow
@pytest.mark.component("stable-baselines3")
def test_sb3_single_agent_trains_and_exports_a_safe_checkpoint(tmp_path: Path) -> None:
    from agents import load_policy

    ex = load("sb3_single_agent")
    args = ex.Args(backend="batch", total_timesteps=256, n_envs=2, n_steps=64, out=str(tmp_path))
    out = ex.main(args)
    assert out["timesteps"] >= 256
    assert math.isfinite(out["loss"])
    assert math.isfinite(out["eval_return"])
    policy = load_policy(out["policy"])  # our safe format: reloads without unpickling
    obs = out["model"].observation_space.sample()
    action = policy.act(obs)
    expected, _ = out["model"].predict(obs, deterministic=True)
    np.testing.assert_allclose(action, np.clip(expected, -1, 1), atol=1e-5)


@pytest.mark.slow
@pytest.mark.component("stable-baselines3")
@pytest.mark.parametrize(
    ("backend", "num_cpus"),
    [("batch", 0), ("pybullet", 2)],
    ids=["batch-in-process", "pybullet-subprocesses"],
)
def test_supersuit_sb3_parameter_sharing_trains(backend: str, num_cpus: int) -> None:
    """The released SuperSuit 3.11 recipe; with num_cpus=2 the env copies are pickled into
    subprocesses, so each must reconnect its own simulator."""
    ex = load("sb3_supersuit")
    args = ex.Args(backend=backend, n_cars=2, num_vec_envs=2, num_cpus=num_cpus)
    args.total_timesteps, args.n_steps = 256, 64
    out = ex.main(args)
    assert out["slots"] == 4  # 2 copies × 2 cars, one shared policy
    assert out["timesteps"] >= 256
    assert math.isfinite(out["loss"])
    obs = out["model"].observation_space.sample()[None]
    action, _ = out["model"].predict(obs, deterministic=True)
    assert action.shape == (1, 2)


@pytest.mark.slow
@pytest.mark.component("ray")
def test_rllib_shared_policy_trains_one_iteration() -> None:
    pytest.importorskip("ray.rllib", reason="needs the rllib extra: pip install -e '.[rllib]'")
    import ray
    import torch

    ex = load("rllib_multiagent")
    out = ex.main(ex.Args(iterations=1, train_batch_size=128, minibatch_size=64, num_epochs=1))
    algo = out["algo"]
    try:
        assert out["env_steps"] >= 128
        assert math.isfinite(out["total_loss"])
        module = algo.get_module(ex.SHARED)
        obs = torch.zeros((1, 100))
        dist_inputs = module.forward_inference({"obs": obs})["action_dist_inputs"]
        assert dist_inputs.shape == (1, 4)  # mean and log-std of [steer, throttle]
        assert torch.isfinite(dist_inputs).all()
    finally:
        algo.stop()
        ray.shutdown()


@pytest.mark.slow
def test_an_example_runs_from_the_command_line() -> None:
    """Exactly what the README tells users to type."""
    out = subprocess.run(
        [sys.executable, "examples/cleanrl_ppo_batch.py", "--total-timesteps", "1024"],
        check=False,
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert "iter 1/1" in out.stdout
