"""CVaR training: PPO updates on the worst share of every rollout (the ``cvar`` arm).

Issue 17's experiment asks, when domain randomisation and RARL do not reach the goal, for
other robust objectives, a CVaR objective among them. This is the EPOpt recipe (Rajeswaran
et al., "EPOpt: Learning Robust Neural Network Policies Using Model Ensembles", 2017) on
the batched backend: the racers see perturbed cars and tracks drawn from a wide set (the
``wide`` arm's domain randomisation, :func:`agents.robustness.wide_dynamics`, plus the
generated tracks), and each PPO update uses only the *worst* ``share`` of the rollout — the
slots (one learner car each) whose summed reward over the rollout is lowest — so the policy
gradient follows the lower tail of the return distribution (the CVaR at level ``share``)
rather than its mean. As in EPOpt, the first ``warmup`` rollouts use every slot (a policy
that cannot drive yet has no meaningful tail).

What a slot's rollout return measures is the joint draw of everything the slot's car met in
those ``n_steps`` steps (its perturbation, its track, its place on the lap, the other cars),
not the perturbation alone: the tail it trains on is that of the whole training
distribution, generated hairpin tracks included, which is what the evaluation's worst-10 %
mean scores.

The selection lives in the rollout buffer (:class:`WorstShareRolloutBuffer`), given to SB3's
PPO as ``rollout_buffer_class``: the collected data, the advantages (GAE over every step,
the value function's bootstrap included) and the update rule are PPO's own; only the rows
that the update's minibatches are drawn from change.
"""

from __future__ import annotations

import math
from collections.abc import Generator
from typing import Any

import numpy as np
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.type_aliases import RolloutBufferSamples

CVAR_SHARE = 0.5  # the share of slots each update trains on, after the warm-up
CVAR_WARMUP = 0.2  # the share of the budget trained on every slot first (EPOpt's warm-up)


class WorstShareRolloutBuffer(RolloutBuffer):
    """A :class:`~stable_baselines3.common.buffers.RolloutBuffer` whose minibatches come
    from the worst ``share`` of its slots (see the module docstring).

    Args:
        *args: :class:`RolloutBuffer`'s (``buffer_size`` = PPO's ``n_steps``, the spaces…).
        share: the share of slots kept, 0 < share ≤ 1 (at least one slot is kept).
        warmup_rollouts: rollouts that keep every slot before the selection starts.
        **kwargs: :class:`RolloutBuffer`'s.

    Attributes:
        rollouts: rollouts handed to updates so far.
        kept: the slots (env indices) the latest update trains on, ascending.
    """

    def __init__(
        self, *args: Any, share: float = CVAR_SHARE, warmup_rollouts: int = 0, **kwargs: Any
    ) -> None:
        if not 0.0 < share <= 1.0:
            raise ValueError(f"share must be within (0, 1], not {share}")
        super().__init__(*args, **kwargs)
        self.share = share
        self.warmup_rollouts = warmup_rollouts
        self.rollouts = 0
        self.kept: np.ndarray = np.arange(self.n_envs)
        self._rows: np.ndarray = np.arange(self.buffer_size * self.n_envs)

    def select(self) -> np.ndarray:
        """The slots the update trains on: during the warm-up every one, then the
        ``ceil(share · n_envs)`` with the lowest summed reward over the rollout (ties: the
        lower index), ascending."""
        if self.rollouts <= self.warmup_rollouts:
            return np.arange(self.n_envs)
        returns = self.rewards.sum(axis=0)  # (n_envs,): rewards are (n_steps, n_envs)
        n = max(1, math.ceil(self.share * self.n_envs))
        return np.sort(np.argsort(returns, kind="stable")[:n])

    def get(self, batch_size: int | None = None) -> Generator[RolloutBufferSamples, None, None]:
        """Minibatches of ``batch_size`` rows drawn, in a fresh random order each call (each
        epoch), from the kept slots' rows only (see :meth:`select`)."""
        assert self.full, "the rollout buffer is not full"
        if not self.generator_ready:
            self.rollouts += 1
            self.kept = self.select()
            for name in ("observations", "actions", "values", "log_probs", "advantages", "returns"):
                self.__dict__[name] = self.swap_and_flatten(self.__dict__[name])
            self.generator_ready = True
            # swap_and_flatten puts slot e's step t at row e · n_steps + t
            steps = np.arange(self.buffer_size)
            self._rows = (self.kept[:, None] * self.buffer_size + steps[None, :]).ravel()
        indices = np.random.permutation(self._rows)  # noqa: NPY002 - seeded by SB3, as its own
        size = len(indices) if batch_size is None else batch_size
        for start in range(0, len(indices), size):
            yield self._get_samples(indices[start : start + size])


def cvar_buffer(
    total_timesteps: int,
    n_steps: int,
    n_envs: int,
    share: float = CVAR_SHARE,
    warmup: float = CVAR_WARMUP,
) -> dict[str, Any]:
    """PPO's ``rollout_buffer_class`` and ``rollout_buffer_kwargs`` for the ``cvar`` arm:
    ``share`` of the slots (``slipstream train --cvar-share``) after a warm-up of ``warmup``
    of the budget (``--cvar-warmup``; ``total_timesteps`` agent-steps, ``n_steps × n_envs``
    per rollout)."""
    per_rollout = max(1, n_steps * n_envs)
    rollouts = math.floor(warmup * total_timesteps / per_rollout)
    return {
        "rollout_buffer_class": WorstShareRolloutBuffer,
        "rollout_buffer_kwargs": {"share": share, "warmup_rollouts": rollouts},
    }
