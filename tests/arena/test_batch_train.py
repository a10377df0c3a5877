"""``slipstream train --backend batch``: PPO learns on the batched simulator, and the
checkpoint it writes drives on pybullet."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from agents.policy import PolicyError
from agents.train import TrainArgs, main, parse_args, procedural_groups


def test_backend_flags_parse_and_bad_combinations_are_user_errors(tmp_path: Path) -> None:
    args = parse_args(["--backend", "batch", "--batch-device", "torch:cpu"])
    assert (args.backend, args.batch_device) == ("batch", "torch:cpu")
    with pytest.raises(PolicyError, match="backend"):
        main(TrainArgs(backend="warp", out=tmp_path))
    with pytest.raises(PolicyError, match="procedural"):
        main(TrainArgs(backend="batch", procedural=1.5, out=tmp_path))
    with pytest.raises(PolicyError, match="uncertainty"):
        main(TrainArgs(backend="batch", uncertainty="chaos", out=tmp_path))
    # The share of generated tracks is a share of race groups (one track per group).
    assert procedural_groups(TrainArgs(tracks=["oval", "bean"], procedural=0.5)) == 2
    assert procedural_groups(TrainArgs(tracks=["oval"], procedural=0.2)) == 1
    assert procedural_groups(TrainArgs(tracks=["oval"], procedural=0.0)) == 0


def test_tiny_batch_training_run_learns_and_exports_a_bullet_ready_policy(tmp_path: Path) -> None:
    from stable_baselines3 import PPO

    from agents.checkpoint import export_sb3
    from agents.loading import load_policy
    from arena.batch.vec_env import BatchVecEnv
    from arena.env import RacingEnv

    args = TrainArgs(
        backend="batch",
        tracks=["oval"],
        n_cars=2,
        n_envs=16,  # 64 PPO slots (both directions): one rollout of 4,096 steps
        total_timesteps=4096,
        n_steps=64,
        batch_size=1024,
        n_epochs=4,
        learning_rate=3e-3,
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
    # It learned, on a fixed seed: against the untrained policy (PPO's initial weights for the
    # same seed and architecture), whose near-zero actions let the car roll backwards, the
    # trained one makes net forward progress. Measured on oval, 200 steps: untrained -0.100,
    # trained +0.018 (seeds 1, 2, 5: +0.034, +0.025, +0.011). With the learning rate annealed
    # to 0 on the last update (the bug this test found) the single update changed nothing.
    untrained = PPO(
        "MlpPolicy", BatchVecEnv(["oval"], n_envs=1, n_cars=2), seed=3, device="cpu",
        policy_kwargs={"net_arch": {"pi": [16, 16], "vf": [16, 16]}},
    )  # fmt: skip
    before_path = export_sb3(untrained, tmp_path / "untrained.zip", name="untrained", env_config={})
    before = _mean_reward(str(before_path), "oval", randomised=False, steps=200)
    after = _mean_reward(summary["policy"], "oval", randomised=False, steps=200)
    assert before < -0.05 < 0.0 < after, (before, after)
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


def _mean_reward(
    policy_path: str, track: str = "bean", *, randomised: bool = True, steps: int = 300
) -> float:
    """Mean per-step reward of a checkpoint's deterministic actions over 8 races of 2 cars on
    ``track`` (default: bean, held out), under the default domain-randomisation set unless
    ``randomised`` is False, fixed seed."""
    from agents.loading import load_policy
    from arena.batch.vec_env import BatchVecEnv
    from arena.uncertainty import default_config

    policy = load_policy(policy_path)
    sim_kwargs = {"uncertainty": default_config("sample")} if randomised else None
    env = BatchVecEnv([track], n_envs=8, n_cars=2, seed=0, sim_kwargs=sim_kwargs)
    obs, total = env.reset(), 0.0
    for _ in range(steps):
        obs, reward, _, _ = env.step(policy.act_batch(obs))
        total += float(reward.mean())
    return total / steps


@pytest.mark.slow
def test_domain_randomised_batch_training_on_generated_tracks_improves_the_reward(
    tmp_path: Path,
) -> None:
    def run(steps: int) -> dict:
        return main(
            TrainArgs(
                backend="batch", tracks=["oval"], n_cars=2, n_envs=8, total_timesteps=steps,
                n_steps=32, batch_size=512, n_epochs=4, net_arch=[32, 32], learning_rate=1e-3,
                eval_every=0, out=tmp_path, run_name=f"dr-{steps}", progress_bar=False, seed=3,
                uncertainty="sample", procedural=0.5,
            )
        )  # fmt: skip

    before, after = run(1024), run(16384)  # one rollout vs sixteen, the same seed
    training = after["training"]
    assert training["steps"] >= 16384
    # One generated group (and its reversed twin), redrawn every 8,192 rollout steps.
    assert len(training["generated_tracks"]) == 2
    assert training["generated_tracks_drawn"] >= 2  # every 4 rollouts of 2,048 steps
    recorded = after["args"]
    assert (recorded["backend"], recorded["uncertainty"]) == ("batch", "sample")
    assert _mean_reward(after["policy"]) > _mean_reward(before["policy"]) + 0.05


@pytest.mark.slow
def test_adversarial_batch_training_alternates_racer_and_batched_natures(tmp_path: Path) -> None:
    summary = main(
        TrainArgs(
            backend="batch", tracks=["oval"], n_cars=2, n_envs=4, total_timesteps=2048,
            n_steps=32, batch_size=256, n_epochs=2, net_arch=[16, 16], eval_every=0,
            out=tmp_path, run_name="rarl", progress_bar=False, seed=1,
            uncertainty="adversarial", nature_every=512, nature_steps=512,
        )
    )  # fmt: skip
    run_dir = tmp_path / "rarl"
    assert summary["training"]["steps"] >= 2048
    assert (run_dir / "nature_sb3.zip").is_file()  # the nature that was trained alongside
    assert any((run_dir / "tb_nature").rglob("events.out.tfevents.*"))


@pytest.mark.slow
def test_a_population_of_natures_trains_each_in_turn_and_spreads_them_over_the_groups(
    tmp_path: Path,
) -> None:
    # Vinitsky et al.'s adversarial population on the batched backend: two natures, one
    # trained per phase in turn; each race group of the racers' env meets one of those
    # trained so far, drawn anew each phase.
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback

    from agents.robustness import rarl_callback, training_uncertainty
    from agents.train import _batch_vec_env

    args = TrainArgs(
        backend="batch", tracks=["oval", "bean", "chicanes"], n_cars=2, n_envs=2,
        uncertainty="adversarial", natures=2, nature_every=192, nature_steps=128, seed=0,
        randomise=False, out=tmp_path,
    )  # fmt: skip
    cfg = training_uncertainty("adversarial")
    env = _batch_vec_env(args, cfg)
    seen: list[list[str | None]] = []

    class Watch(BaseCallback):
        def _on_step(self) -> bool:
            return True

        def _on_rollout_start(self) -> None:
            seen.append([getattr(sim.nature, "name", None) for sim in env.sims])

    racers = PPO("MlpPolicy", env, n_steps=16, batch_size=64, n_epochs=1, seed=0, device="cpu")
    racers.learn(1152, callback=rarl_callback(args, env, {"uncertainty": cfg}, tmp_path, Watch()))
    env.close()
    assert seen[0] == [None] * len(env.sims)  # no nature trained yet: nominal cars
    # A phase after each rollout of 3 groups x 2 races x 2 cars x 16 steps = 192 steps.
    assert seen[1] == ["nature_0"] * len(env.sims)  # the first phase trained the first nature
    later = {name for names in seen[2:] for name in names}
    assert later == {"nature_0", "nature_1"}  # both met, the groups spread over them
    assert any(len(set(names)) == 2 for names in seen[2:])  # in one rollout, too
    for name in ("nature_sb3.zip", "nature_sb3_1.zip"):  # each trained, each saved
        assert PPO.load(tmp_path / name, device="cpu").num_timesteps >= 128
    with pytest.raises(PolicyError, match="population"):
        main(TrainArgs(backend="batch", uncertainty="sample", natures=2, out=tmp_path))
