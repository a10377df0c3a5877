"""SuperSuit + Stable-Baselines3: PPO with one policy shared by every car (PettingZoo recipe).

PettingZoo's documented recipe for parameter sharing: each car of the parallel env becomes
one slot of a vector env (``supersuit.pettingzoo_env_to_vec_env_v1``), several env copies are
concatenated (``supersuit.concat_vec_envs_v1``; ``--num-cpus N`` runs them in N
subprocesses), and SB3's PPO trains one policy on all slots. SuperSuit needs every car to
stay in ``env.agents`` until the race ends, which is what ``park_finished=True`` does: a car
that finishes or retires is parked (terminated every later step, reward 0, its last
observation repeated) until every car is done.

    python examples/sb3_supersuit.py --total-timesteps 100000 --n-cars 4 --num-cpus 2

The project's own vector envs (:mod:`agents.vec_env`, what ``slipstream train`` uses) do the
same job faster and without parked cars' padding; this script is for users who already
train their PettingZoo envs this way.
"""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass
from typing import Any, TypeVar

import supersuit as ss
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.logger import KVWriter, Logger
from stable_baselines3.common.utils import set_random_seed
from stable_baselines3.common.vec_env import VecMonitor

import arena

_T = TypeVar("_T")


def flag(default: _T, help: str) -> _T:
    """An :class:`Args` field; ``help`` is its ``--help`` text."""
    return dataclasses.field(default=default, metadata={"help": help})


@dataclass
class Args:
    """Command-line arguments (``--total-timesteps 2048`` etc.)."""

    seed: int = flag(1, "seeds python, numpy, torch and the races")
    track: str = flag("oval", "built-in name, track file or random:<seed>")
    backend: str = flag("pybullet", "simulator: pybullet, or batch (the vectorised one, B = 1)")
    n_cars: int = flag(2, "cars per race, all driven by the shared policy")
    num_vec_envs: int = flag(2, "env copies (each one its own simulator)")
    num_cpus: int = flag(0, "subprocesses for the copies; 0 steps them in this process")
    total_timesteps: int = flag(512, "agent-steps to train for")
    n_steps: int = flag(64, "control steps per slot and rollout")
    batch_size: int = flag(64, "minibatch size, samples")
    n_epochs: int = flag(4, "passes over each rollout")
    learning_rate: float = flag(3e-4, "Adam step size")
    threads: int = flag(1, "torch CPU threads: one is fastest for networks this small")


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


class Capture(KVWriter):
    """Keeps every row SB3 logs (``train/loss`` …), so the script can report them."""

    def __init__(self) -> None:
        self.rows: list[dict[str, Any]] = []

    def write(self, key_values: dict[str, Any], key_excluded: Any, step: int = 0) -> None:
        self.rows.append(dict(key_values))

    def close(self) -> None:
        """Nothing to release."""


def main(args: Args) -> dict[str, Any]:
    """Train; returns the metrics and the ``model``."""
    torch.set_num_threads(args.threads)
    # SuperSuit 3.11's SB3 wrapper has no seed(), and PPO(seed=...) calls it: seed torch and
    # numpy here, and the env before it is copied (each copy then continues its own stream).
    set_random_seed(args.seed)
    env_kwargs: dict[str, Any] = {"backend": args.backend, "track": args.track}
    env = arena.parallel_env(**env_kwargs, n_cars=args.n_cars, park_finished=True)
    env.reset(seed=args.seed)
    venv = ss.pettingzoo_env_to_vec_env_v1(env)
    venv = ss.concat_vec_envs_v1(
        venv, args.num_vec_envs, num_cpus=args.num_cpus, base_class="stable_baselines3"
    )
    venv = VecMonitor(venv)  # episode returns per slot, for rollout/ep_rew_mean
    model = PPO(
        "MlpPolicy",
        venv,
        n_steps=args.n_steps,
        batch_size=args.batch_size,
        n_epochs=args.n_epochs,
        learning_rate=args.learning_rate,
    )
    capture = Capture()
    model.set_logger(Logger(folder=None, output_formats=[capture]))
    model.learn(total_timesteps=args.total_timesteps)
    model.logger.dump(model.num_timesteps)  # SB3 dumps before training: flush the last update
    venv.close()
    losses = [row["train/loss"] for row in capture.rows if "train/loss" in row]
    returns = [row["rollout/ep_rew_mean"] for row in capture.rows if "rollout/ep_rew_mean" in row]
    result = {
        "timesteps": model.num_timesteps,
        "slots": venv.num_envs,
        "loss": losses[-1] if losses else float("nan"),
        "ep_rew_mean": returns[-1] if returns else float("nan"),
        "model": model,
    }
    print(
        f"{result['timesteps']} steps over {result['slots']} slots, "
        f"last loss {result['loss']:.4f}, ep_rew_mean {result['ep_rew_mean']:.2f}"
    )
    return result


if __name__ == "__main__":
    main(parse_args())
