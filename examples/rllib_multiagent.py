"""RLlib multi-agent PPO: one policy shared by every car, through ``ParallelPettingZooEnv``.

RLlib's own PettingZoo wrapper (``ray.rllib.env.wrappers.pettingzoo_env``) takes the parallel
env as it is (cars that finish leave the race; RLlib handles agents that leave), and a
policy-mapping function sends every car to the one module ``"shared"``. Needs the ``rllib``
extra: ``pip install 'slipstream[rllib]'`` (``ray[rllib]``).

    python examples/rllib_multiagent.py --iterations 20 --n-cars 4 --num-env-runners 2

Every env runner builds its own env (``register_env``'s creator runs in each), so runners
never share a simulator; ``--num-env-runners 0`` samples in this process.
"""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass
from typing import Any, TypeVar

import ray
from ray.rllib.algorithms.ppo import PPOConfig
from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv
from ray.tune.registry import register_env

import arena

ENV_NAME = "slipstream_race"
SHARED = "shared"

_T = TypeVar("_T")


def flag(default: _T, help: str) -> _T:
    """An :class:`Args` field; ``help`` is its ``--help`` text."""
    return dataclasses.field(default=default, metadata={"help": help})


@dataclass
class Args:
    """Command-line arguments (``--iterations 1`` etc.)."""

    seed: int = flag(1, "seeds python, numpy, torch and the races")
    track: str = flag("oval", "built-in name, track file or random:<seed>")
    backend: str = flag("pybullet", "simulator: pybullet, or batch (the vectorised one, B = 1)")
    n_cars: int = flag(2, "cars per race, every one driven by the shared policy")
    iterations: int = flag(1, "training iterations (algo.train() calls)")
    total_timesteps: int = flag(0, "if > 0: train until this many env steps (overrides iterations)")
    num_env_runners: int = flag(0, "remote env runners; 0 samples in this process")
    train_batch_size: int = flag(256, "agent-steps per iteration")
    minibatch_size: int = flag(64, "agent-steps per SGD minibatch")
    num_epochs: int = flag(2, "passes over each train batch")
    rollout_fragment_length: int = flag(64, "agent-steps each env runner samples at a time")
    learning_rate: float = flag(3e-4, "Adam step size")


def parse_args(argv: list[str] | None = None) -> Args:
    """``--flag value`` for every :class:`Args` field."""
    parser = argparse.ArgumentParser(
        description=(__doc__ or "").splitlines()[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    for f in dataclasses.fields(Args):
        parser.add_argument(
            "--" + f.name.replace("_", "-"),
            type=type(f.default),
            default=f.default,
            help=f.metadata["help"],
        )
    return Args(**vars(parser.parse_args(argv)))


def make_env(config: dict[str, Any]) -> ParallelPettingZooEnv:
    """One env per call (RLlib calls it in every env runner)."""
    return ParallelPettingZooEnv(arena.parallel_env(**config))


def main(args: Args) -> dict[str, Any]:
    """Train; returns the last iteration's metrics and the ``algo`` (call ``algo.stop()``)."""
    register_env(ENV_NAME, make_env)
    env_config = {"track": args.track, "n_cars": args.n_cars, "backend": args.backend}
    config = (
        PPOConfig()
        .environment(ENV_NAME, env_config=env_config)
        .framework("torch")
        .env_runners(
            num_env_runners=args.num_env_runners,
            rollout_fragment_length=args.rollout_fragment_length,
        )
        .training(
            train_batch_size_per_learner=args.train_batch_size,
            minibatch_size=args.minibatch_size,
            num_epochs=args.num_epochs,
            lr=args.learning_rate,
        )
        .multi_agent(policies={SHARED}, policy_mapping_fn=lambda agent_id, *a, **k: SHARED)
        .debugging(seed=args.seed)
    )
    algo = config.build_algo()
    result: dict[str, Any] = {}
    steps = 0
    i = 0
    while (args.total_timesteps > 0 and steps < args.total_timesteps) or (
        args.total_timesteps <= 0 and i < args.iterations
    ):
        result = algo.train()
        i += 1
        steps = int(result.get("num_env_steps_sampled_lifetime", 0))
        learner = result.get("learners", {}).get(SHARED, {})
        runners = result.get("env_runners", {})
        loss = learner.get("total_loss", float("nan"))
        ret = runners.get("episode_return_mean", float("nan"))
        print(f"iter {i}: env steps {steps}, total_loss {loss:.4f}, episode_return_mean {ret:.2f}")
    learner = result.get("learners", {}).get(SHARED, {})
    return {
        "iterations": i,
        "env_steps": steps,
        "total_loss": float(learner.get("total_loss", float("nan"))),
        "episode_return_mean": float(
            result.get("env_runners", {}).get("episode_return_mean", float("nan"))
        ),
        "algo": algo,
    }


if __name__ == "__main__":
    out = main(parse_args())
    out["algo"].stop()
    ray.shutdown()
