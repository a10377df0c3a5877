"""Policies that drive cars: the Policy protocol, baselines, checkpoints and loading.

``import agents`` imports neither torch nor pybullet (the command line imports it for every
subcommand); the names below load on first use.
"""

from __future__ import annotations

from typing import Any

__all__ = ["Policy", "PolicyError", "load_policy"]


def __getattr__(name: str) -> Any:
    if name == "load_policy":
        from agents.loading import load_policy  # noqa: PLC0415 - lazy: pulls in the simulator

        return load_policy
    if name in ("Policy", "PolicyError"):
        from agents import policy  # noqa: PLC0415 - lazy, as above

        return getattr(policy, name)
    raise AttributeError(f"module 'agents' has no attribute {name!r}")
