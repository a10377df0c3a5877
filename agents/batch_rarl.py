"""Nature agents on the batched backend: the natures of every car of every race as one batch.

``adversarial`` model uncertainty (:mod:`arena.uncertainty`) gives every car a *nature*
that picks its perturbation inside the box, with reward exactly minus the car's (Zhang et
al. 2020; Pinto et al.'s RARL alternates the two). On the batched backend
(:class:`arena.batch.vec_env.BatchVecEnv` with ``sim_kwargs={"uncertainty": cfg}``):

* **racer role**: the racers learn in the ``BatchVecEnv`` itself; each simulator's natures
  are driven by :attr:`arena.batch.sim.BatchSim.nature` (a frozen nature, ``act_batch`` on
  :meth:`arena.batch.sim.BatchSim.nature_obs`), set on all of them with
  ``venv.set_attr("nature", driver)``; no driver leaves the nominal point;
* **nature role**: :class:`BatchNatureVecEnv` wraps a second ``BatchVecEnv``; its slots are
  the natures of the same cars (observation: the global state and a one-hot of the car,
  as ``nature_car_i`` on pybullet; action: ``Box(-1, 1, (k,))``), the cars are driven by
  :attr:`BatchNatureVecEnv.racer` (a frozen racer), and each nature's reward is exactly
  minus its car's (the racer's reward, scaled, less the DNF penalty) — zero-sum as
  :class:`agents.selfplay.SelfPlayVecEnv` with ``role="nature"``.

>>> from arena.batch.vec_env import BatchVecEnv
>>> from arena.uncertainty import default_config
>>> racers = BatchVecEnv(["oval"], n_envs=2, n_cars=2,
...                      sim_kwargs={"uncertainty": default_config("adversarial")})
>>> natures = BatchNatureVecEnv(racers)
>>> natures.reset().shape  # 2 races x 2 cars; 2 x (10 + 7) state + 2 one-hot
(4, 36)
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray
from stable_baselines3.common.vec_env import VecEnv
from stable_baselines3.common.vec_env.base_vec_env import VecEnvIndices, VecEnvStepReturn

from agents.policy import PolicyError


class _Given:
    """A stand-in nature driver that returns the actions it was given (one step's)."""

    def __init__(self, actions: NDArray[np.float64]) -> None:
        self.actions = actions

    def act_batch(self, obs: NDArray[np.float32]) -> NDArray[np.float64]:
        """The given actions (rows, k), whatever the observations."""
        return self.actions


class BatchNatureVecEnv(VecEnv):
    """The natures of every car of a :class:`arena.batch.vec_env.BatchVecEnv`, as SB3 slots.

    Args:
        racers: the batched racing env (its simulators need ``adversarial`` uncertainty);
            slot ``i`` here is the nature of car slot ``i`` there.
    """

    def __init__(self, racers: Any) -> None:
        cfgs = [sim.uncertainty for sim in racers.sims]
        if any(cfg is None or cfg.mode != "adversarial" for cfg in cfgs):
            raise PolicyError("the nature role needs adversarial uncertainty on every simulator")
        self.racers = racers
        self.racer: Any = None  # drives the cars: something with act_batch(obs (k, d))
        sim = racers.sims[0]
        size = sim.state_size + sim.n_cars
        obs_space = spaces.Box(-np.inf, np.inf, (size,), dtype=np.float32)
        act_space = spaces.Box(-1.0, 1.0, (len(cfgs[0].free),), dtype=np.float32)
        super().__init__(racers.num_envs, obs_space, act_space)
        self.render_mode = None
        self._racer_obs: NDArray[np.float32] = np.zeros((0,), dtype=np.float32)
        self._actions: NDArray[np.float64] = np.zeros((self.num_envs, len(cfgs[0].free)))

    def _nature_obs(self) -> NDArray[np.float32]:
        parts = [sim.ops.to_numpy(sim.nature_obs()) for sim in self.racers.sims]
        return np.concatenate([p.reshape(-1, p.shape[-1]) for p in parts]).astype(np.float32)

    def reset(self) -> NDArray[np.float32]:
        """Restart every race; the natures' observations (num_envs, S + N)."""
        self._racer_obs = self.racers.reset()
        return self._nature_obs()

    def seed(self, seed: int | None = None) -> list[int | None]:
        """Seed the racing env's next reset."""
        return list(self.racers.seed(seed))

    def step_async(self, actions: NDArray[np.float32]) -> None:
        """Store the natures' actions (num_envs, k)."""
        self._actions = np.asarray(actions, dtype=np.float64).reshape(self.num_envs, -1)

    def step_wait(self) -> VecEnvStepReturn:
        """One step of every race: the frozen racer drives, the natures perturb."""
        if self.racer is None:
            raise PolicyError("BatchNatureVecEnv.racer (a frozen racer driver) is not set")
        bounds = self.racers._bounds  # slot ranges of the simulators
        for k, sim in enumerate(self.racers.sims):
            lo, hi = int(bounds[k]), int(bounds[k + 1])
            sim.nature = _Given(self._actions[lo:hi])
        racer_actions = self.racer.act_batch(self._racer_obs)
        obs, rewards, dones, infos = self.racers.step(racer_actions)
        self._racer_obs = obs
        out_infos: list[dict[str, Any]] = list(infos)
        if dones.any():
            size = int(np.prod(self.observation_space.shape or (1,)))
            finals = [
                sim.ops.to_numpy(sim.final_nature_obs).reshape(-1, size) for sim in self.racers.sims
            ]
            final = np.concatenate(finals)
            for i in np.flatnonzero(dones):
                info = dict(infos[i])
                info["terminal_observation"] = final[i].astype(np.float32)
                if "episode" in info:
                    info["episode"] = {**info["episode"], "r": -info["episode"]["r"]}
                out_infos[i] = info
        return self._nature_obs(), -rewards, dones, out_infos  # exactly zero-sum

    def close(self) -> None:
        """Close the racing env."""
        self.racers.close()

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        """As the racing env's."""
        return list(self.racers.get_attr(attr_name, indices))

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        """As the racing env's."""
        self.racers.set_attr(attr_name, value, indices)

    def env_method(
        self,
        method_name: str,
        *method_args: Any,
        indices: VecEnvIndices = None,
        **method_kwargs: Any,
    ) -> list[Any]:
        """As the racing env's."""
        return list(
            self.racers.env_method(method_name, *method_args, indices=indices, **method_kwargs)
        )

    def env_is_wrapped(self, wrapper_class: type[Any], indices: VecEnvIndices = None) -> list[bool]:
        """No slot is a Gymnasium wrapper."""
        return list(self.racers.env_is_wrapped(wrapper_class, indices))
