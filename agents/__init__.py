"""Policies that drive cars: the Policy protocol, baselines, checkpoints and loading.

``import agents`` imports neither torch nor pybullet (the command line imports it for every
subcommand); the names below load on first use. It registers the single-agent Gymnasium env
``slipstream/Race-v0`` (:mod:`agents.gym_env`), which costs only Gymnasium's own import.
"""

from __future__ import annotations

from typing import Any

import gymnasium

GYM_ENV_ID = "slipstream/Race-v0"

__all__ = ["GYM_ENV_ID", "Policy", "PolicyError", "RaceEnv", "load_policy"]

# Gymnasium >= 1.0 reads no plugin entry points: registering here, on import, is what makes
# ``import agents; gymnasium.make("slipstream/Race-v0")`` and ``"agents:slipstream/Race-v0"``
# work. The entry point is a string, so nothing heavy loads until the env is made.
if GYM_ENV_ID not in gymnasium.registry:
    gymnasium.register(id=GYM_ENV_ID, entry_point="agents.gym_env:RaceEnv")


def __getattr__(name: str) -> Any:
    if name == "load_policy":
        from agents.loading import load_policy  # noqa: PLC0415 - lazy: pulls in the simulator

        return load_policy
    if name in ("Policy", "PolicyError"):
        from agents import policy  # noqa: PLC0415 - lazy, as above

        return getattr(policy, name)
    if name == "RaceEnv":
        from agents.gym_env import RaceEnv  # noqa: PLC0415 - lazy, as above

        return RaceEnv
    raise AttributeError(f"module 'agents' has no attribute {name!r}")
