"""The multi-car racing environment: pybullet physics under a PettingZoo parallel API.

>>> from arena import parallel_env
>>> env = parallel_env(track="oval", n_cars=2)
>>> _ = env.reset(seed=1)
>>> sorted(env.agents)
['car_0', 'car_1']
>>> env.close()
"""

from __future__ import annotations

from typing import Any

from pettingzoo.utils.conversions import parallel_to_aec

from arena.env import ENV_VERSION, RacingEnv
from arena.sim import CarParams, SimError


def parallel_env(**kwargs: Any) -> RacingEnv:
    """A :class:`RacingEnv` (PettingZoo ``ParallelEnv``); see its docstring for arguments."""
    return RacingEnv(**kwargs)


def env(**kwargs: Any) -> Any:
    """The same environment under PettingZoo's AEC API (``parallel_to_aec``)."""
    return parallel_to_aec(RacingEnv(**kwargs))


__all__ = ["ENV_VERSION", "CarParams", "RacingEnv", "SimError", "env", "parallel_env"]
