"""Every ``slipstream`` subcommand's help, as a newcomer reads it first."""

from __future__ import annotations

import argparse
from collections.abc import Iterator

from leaderboard.cli import build_parser


def commands(
    parser: argparse.ArgumentParser, path: str = "slipstream"
) -> Iterator[tuple[str, argparse.ArgumentParser]]:
    """Every parser under ``parser`` (itself included), nested subcommands too, by its path."""
    yield path, parser
    for action in parser._actions:  # argparse keeps subcommands only here
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from commands(sub, f"{path} {name}")


def test_every_subcommand_help_renders_without_format_escapes() -> None:
    # argparse %-formats help texts but not descriptions (without "%(prog)"), so a "%%" in
    # a description was printed as is: `slipstream robustness --help` said "worst-10%% mean";
    # and a lone "%" in a help text crashes --help (`slipstream train --help`, stop 26).
    found = dict(commands(build_parser()))
    assert {"slipstream robustness", "slipstream train", "slipstream tracks import"} <= set(found)
    for path, parser in found.items():
        text = parser.format_help()
        assert "%%" not in text, path
        assert text.startswith(f"usage: {path}"), path
