"""The multi-car racing environment: pybullet physics under a PettingZoo parallel API.

>>> from arena import parallel_env
>>> env = parallel_env(track="oval", n_cars=2)
>>> _ = env.reset(seed=1)
>>> sorted(env.agents)
['car_0', 'car_1']
>>> env.close()

``backend="batch"`` gives the same env on the vectorised simulator of :mod:`arena.batch`
(numpy or torch; ``device=...``), which steps many races at once for training.

Importing the package does not load pybullet: it loads when the first simulator is built
(the leaderboard's web process reads :mod:`arena.version` and :mod:`arena.colours`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Literal, overload

from pettingzoo.utils.conversions import parallel_to_aec

from arena.env import RacingEnv
from arena.sim import CarParams, SimError
from arena.version import ENV_VERSION

if TYPE_CHECKING:
    from arena.batch.parallel import BatchParallelEnv


BACKENDS = ("pybullet", "batch")


@overload
def parallel_env(
    *, backend: Literal["pybullet", "bullet"] = "pybullet", **kwargs: Any
) -> RacingEnv: ...
@overload
def parallel_env(*, backend: Literal["batch"], **kwargs: Any) -> BatchParallelEnv: ...
def parallel_env(*, backend: str = "pybullet", **kwargs: Any) -> RacingEnv | BatchParallelEnv:
    """A PettingZoo ``ParallelEnv``; see :class:`RacingEnv` for the arguments.

    Both backends run the same episode code (:mod:`arena.episode` over :mod:`arena.core`).

    Args:
        backend: ``"pybullet"`` (the reference for races; ``"bullet"`` is accepted too) or
            ``"batch"`` (:class:`arena.batch.parallel.BatchParallelEnv`, which also takes
            ``device``).
        kwargs: the env's arguments.
    """
    if backend in ("pybullet", "bullet"):
        return RacingEnv(**kwargs)
    if backend == "batch":
        from arena.batch.parallel import BatchParallelEnv  # noqa: PLC0415 - optional backend

        return BatchParallelEnv(**kwargs)
    raise SimError(f"backend must be one of {', '.join(BACKENDS)}, got {backend!r}")


def env(**kwargs: Any) -> Any:
    """The same environment under PettingZoo's AEC API (``parallel_to_aec``)."""
    return parallel_to_aec(parallel_env(**kwargs))


__all__ = ["BACKENDS", "ENV_VERSION", "CarParams", "RacingEnv", "SimError", "env", "parallel_env"]
