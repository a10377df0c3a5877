"""``slipstream train --backend batch``: PPO learns on the batched simulator, and the
checkpoint it writes drives on pybullet."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from agents.policy import PolicyError
from agents.train import TrainArgs, main, parse_args


def test_backend_flags_parse_and_bad_combinations_are_user_errors(tmp_path: Path) -> None:
    args = parse_args(["--backend", "batch", "--batch-device", "torch:cpu"])
    assert (args.backend, args.batch_device) == ("batch", "torch:cpu")
    with pytest.raises(PolicyError, match="backend"):
        main(TrainArgs(backend="warp", out=tmp_path))
    with pytest.raises(PolicyError, match="batch"):
        main(TrainArgs(backend="batch", procedural=0.5, out=tmp_path))


def test_tiny_batch_training_run_learns_and_exports_a_bullet_ready_policy(tmp_path: Path) -> None:
    from agents.loading import load_policy
    from arena.env import RacingEnv

    args = TrainArgs(
        backend="batch",
        tracks=["oval"],
        n_cars=2,
        n_envs=16,  # 32 PPO slots
        total_timesteps=4096,
        n_steps=64,
        batch_size=1024,
        n_epochs=2,
        net_arch=[16, 16],
        eval_every=0,
        out=tmp_path,
        run_name="tiny-batch",
        progress_bar=False,
        seed=3,
    )
    summary = main(args)
    run_dir = tmp_path / "tiny-batch"
    assert summary["training"]["steps"] >= 4096
    recorded = json.loads((run_dir / "summary.json").read_text())
    assert recorded["args"]["backend"] == "batch"
    # Episodes ended during training (the batch env reported them to SB3).
    assert any((run_dir / "tb").rglob("events.out.tfevents.*"))
    policy = load_policy(str(run_dir / "policy.zip"))
    env = RacingEnv(track="oval", n_cars=2)  # the pybullet backend
    try:
        obs, _ = env.reset(seed=0)
        policy.reset(0)
        for _ in range(20):
            action = np.asarray(policy.act(obs["car_0"]))
            assert action.shape == (2,) and np.all(np.abs(action) <= 1.0)
            obs, *_ = env.step({"car_0": action, "car_1": np.zeros(2)})
    finally:
        env.close()
