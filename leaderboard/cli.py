"""The ``slipstream`` console script: one entry point, a subcommand per capability.

Each package contributes its subcommands through a ``register(subparsers)`` function in its
own ``cli`` module, which must stay cheap to import (heavy imports go inside the handlers). A
user error (:class:`tracks.SlipstreamError`) prints one line on stderr, with no traceback, and
exits with status 2.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from tracks.errors import SlipstreamError

EXIT_USER_ERROR = 2

# Modules with a ``register(subparsers)`` function, in the order ``--help`` lists them.
COMMAND_MODULES = (
    "tracks.cli",
    "agents.cli",
    "agents.cli_train",
    "agents.cli_robustness",
    "submissions.cli",
    "submissions.cli_bundle",
    "leaderboard.demo",
    "leaderboard.cli_server",
    "leaderboard.cli_participant",
    "leaderboard.cli_tournament",
)


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser with every package's subcommands."""
    parser = argparse.ArgumentParser(
        prog="slipstream",
        description="Multi-agent autonomous racing: tracks, races, training, evaluation.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the process exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        result = args.handler(args)
    except SlipstreamError as err:
        print(f"slipstream: error: {err}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print("slipstream: interrupted", file=sys.stderr)
        return 130
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
