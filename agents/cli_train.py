"""``slipstream train``: PPO self-play training (see :mod:`agents.train`).

Every flag is a field of :class:`agents.train.TrainArgs`, with the field's docstring as its
help text. This module stays cheap to import: torch and stable-baselines3 are imported by the
handler only.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from agents.train import add_train_arguments, args_from_namespace


def register(sub: Any) -> None:
    """Add ``train`` to the ``slipstream`` subcommands."""
    parser = sub.add_parser(
        "train",
        help="train a policy with PPO self-play",
        description=(
            "Train one policy shared by the learner cars with stable-baselines3 PPO, against "
            "frozen snapshots of itself and the baselines; TensorBoard logs, periodic "
            "evaluation races against pursuit, and a safe checkpoint <out>/<run>/policy.zip."
        ),
    )
    add_train_arguments(parser)
    parser.add_argument(
        "--json",
        type=Path,
        default=None,
        metavar="FILE",
        help="also write the run summary as JSON here ('-' for stdout)",
    )
    parser.set_defaults(handler=train_command)


def train_command(args: argparse.Namespace) -> int:
    """Run ``slipstream train``; prints where the run wrote its files."""
    from agents.train import main  # noqa: PLC0415 - the handler's heavy import

    summary = main(args_from_namespace(args))
    text = json.dumps(summary, indent=2)
    if args.json is not None and str(args.json) == "-":
        print(text)
        return 0
    if args.json is not None:
        args.json.write_text(text + "\n", encoding="utf-8")
    training = summary["training"]
    final = summary["reloaded_eval"]
    first = training["first_clean_lap"]
    lines = [
        f"run        {summary['run']} ({training['steps']} steps, "
        f"{training['wall_time_s']:.0f} s, stopped: {training['stop_reason']})",
        f"policy     {summary['policy']} ({summary['policy_bytes'] / 1024:.0f} KiB)",
        f"curve      {summary['curve']}",
        f"tensorboard {summary['tensorboard']}",
        "first clean lap "
        + (f"at {first['timesteps']} steps, {first['wall_s']:.0f} s" if first else "not yet"),
        f"reloaded   {final['completed_laps']}/{final['possible_laps']} laps, best "
        + (f"{final['best_lap']:.2f} s" if final["best_lap"] is not None else "-"),
    ]
    print("\n".join(lines), file=sys.stdout)
    return 0
