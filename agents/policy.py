"""The Policy protocol every racer implements: baselines, trained checkpoints, submissions."""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

from tracks.errors import SlipstreamError


class PolicyError(SlipstreamError):
    """A policy could not be built or loaded (unknown name, bad checkpoint)."""


@runtime_checkable
class Policy(Protocol):
    """Something that drives one car from its observations.

    ``reset(seed)`` is called once before each race; ``act(obs)`` once per control step with
    that car's observation, returning an action from the env's action space.
    """

    name: str

    def reset(self, seed: int | None = None) -> None:
        """Prepare for a new race (clear memory, reseed randomness)."""
        ...

    def act(self, obs: Any) -> Any:
        """The action for one observation."""
        ...
