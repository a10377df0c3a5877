"""Stable-Baselines3 PPO on the single-agent Gymnasium env ``slipstream/Race-v0``.

One learning car (``car_0``) races the opponents you name (baselines, checkpoints) inside the
env, so SB3 sees an ordinary Gymnasium env. ``--opponents ""`` is a solo time trial.

    python examples/sb3_single_agent.py --total-timesteps 50000 --opponents pursuit

Afterwards the model is evaluated on a fixed seed and, with ``--out``, saved as an SB3 zip
(to resume training) and exported to Slipstream's safe checkpoint format (``policy.zip``:
loads anywhere with ``agents.load_policy``; ``slipstream race --agents policy.zip,pursuit``).
"""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import gymnasium
import numpy as np
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.logger import KVWriter, Logger

import agents  # registers slipstream/Race-v0
from agents.checkpoint import export_sb3

_T = TypeVar("_T")


def flag(default: _T, help: str) -> _T:
    """An :class:`Args` field; ``help`` is its ``--help`` text."""
    return dataclasses.field(default=default, metadata={"help": help})


@dataclass
class Args:
    """Command-line arguments (``--total-timesteps 2048`` etc.)."""

    seed: int = flag(1, "seeds python, numpy, torch and the races")
    track: str = flag("oval", "built-in name, track file or random:<seed>")
    opponents: str = flag(
        "pursuit", "comma-separated baselines or checkpoint paths; '' = time trial"
    )
    backend: str = flag("pybullet", "simulator: pybullet, or batch (the vectorised one, B = 1)")
    n_envs: int = flag(2, "env copies in SB3's DummyVecEnv")
    total_timesteps: int = flag(512, "agent-steps to train for")
    n_steps: int = flag(128, "control steps per env copy and rollout")
    batch_size: int = flag(64, "minibatch size, samples")
    n_epochs: int = flag(4, "passes over each rollout")
    learning_rate: float = flag(3e-4, "Adam step size")
    threads: int = flag(1, "torch CPU threads: one is fastest for networks this small")
    out: str = flag("", "folder for model.zip and policy.zip; '' saves nothing")


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
    """Train, evaluate, optionally save; returns the metrics and the ``model``."""
    torch.set_num_threads(args.threads)
    env_kwargs: dict[str, Any] = {
        "track": args.track,
        "opponents": [o for o in args.opponents.split(",") if o],
        "backend": args.backend,
    }
    venv = make_vec_env(
        agents.GYM_ENV_ID, n_envs=args.n_envs, seed=args.seed, env_kwargs=env_kwargs
    )
    model = PPO(
        "MlpPolicy",
        venv,
        n_steps=args.n_steps,
        batch_size=args.batch_size,
        n_epochs=args.n_epochs,
        learning_rate=args.learning_rate,
        seed=args.seed,
    )
    capture = Capture()
    model.set_logger(Logger(folder=None, output_formats=[capture]))
    model.learn(total_timesteps=args.total_timesteps, progress_bar=False)
    model.logger.dump(model.num_timesteps)  # SB3 dumps before training: flush the last update
    losses = [row["train/loss"] for row in capture.rows if "train/loss" in row]

    eval_env = gymnasium.make(agents.GYM_ENV_ID, **env_kwargs)
    eval_env.reset(seed=args.seed)
    mean_return, _ = evaluate_policy(model, eval_env, n_eval_episodes=1, deterministic=True)
    eval_env.close()
    venv.close()
    result: dict[str, Any] = {
        "timesteps": model.num_timesteps,
        "loss": losses[-1] if losses else float("nan"),
        "eval_return": float(np.mean(mean_return)),
        "model": model,
    }
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        model.save(out / "model.zip")  # SB3's own zip: a pickle, for resuming only
        result["policy"] = export_sb3(
            model, out / "policy.zip", name="sb3-single-agent", env_config={"track": args.track}
        )
    print(
        f"{result['timesteps']} steps, last loss {result['loss']:.4f}, "
        f"eval return {result['eval_return']:.2f}"
    )
    return result


if __name__ == "__main__":
    main(parse_args())
