"""The project's stable-baselines3 vector envs: the recommended way to train on Slipstream.

==========================  ===============================================================
class                       what it is, when to use it
==========================  ===============================================================
:class:`BatchVecEnv`        every car of ``n_envs`` races on the batched simulator as one
                            SB3 slot each (parameter sharing, self-play), hundreds of
                            thousands of steps per second; ``slipstream train --backend
                            batch`` uses it. Vector observations, continuous actions.
:class:`SelfPlayVecEnv`     ``n_envs`` pybullet races in-process, ``n_learners`` learner
                            cars each against frozen snapshots and baselines
                            (:class:`OpponentPool`), procedural tracks, model uncertainty
                            and nature agents; ``slipstream train`` (pybullet) uses it.
==========================  ===============================================================

Both are SB3 ``VecEnv`` objects: pass one straight to ``PPO("MlpPolicy", venv)``. Episodes
end per race (a race restarts when one of its learner cars is done; the others are marked
``TimeLimit.truncated`` so PPO bootstraps them), and finished slots carry SB3 Monitor's
``episode`` info, so ``rollout/ep_rew_mean`` is logged without a wrapper. Compared with the
SuperSuit recipe (``examples/sb3_supersuit.py``), they keep every transition real (no padding
for cars that have finished) and drive opponents inside the env.

>>> from agents.vec_env import BatchVecEnv
>>> venv = BatchVecEnv(["oval"], n_envs=2, n_cars=2, seed=0)
>>> venv.reset().shape  # (n_envs × n_cars, observation size)
(4, 100)
>>> venv.close()
"""

from __future__ import annotations

from agents.selfplay import OpponentPool, Procedural, SelfPlayVecEnv
from arena.batch.vec_env import BatchVecEnv

__all__ = ["BatchVecEnv", "OpponentPool", "Procedural", "SelfPlayVecEnv"]
