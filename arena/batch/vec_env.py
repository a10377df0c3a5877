"""``BatchVecEnv``: a stable-baselines3 ``VecEnv`` whose batch is every car of every race.

One PPO slot per car (parameter sharing, self-play: every car is driven by the policy being
trained), ``num_envs = Σ n_envs × n_cars`` over one :class:`arena.batch.sim.BatchSim` per
training track and direction. Observations, actions and rewards are those of the pybullet
:class:`arena.env.RacingEnv`, so a policy trained here drives there.

Episodes (the semantics of :class:`agents.selfplay.SelfPlayVecEnv`): a race restarts as soon
as any of its cars is done (finished its laps, retired or timed out); every car of that race
reports ``done`` with its ``terminal_observation``. A car that did not end on its own is
marked ``TimeLimit.truncated`` (so PPO bootstraps its value) and ``cut_short``. A car that
retires (stuck, off the track) pays ``dnf_penalty``. Restarts draw a start placement along
the lap and a grid order at random (``random_starts``) from the simulator's start table.

Infos of a done slot: ``terminal_observation``, ``TimeLimit.truncated``, ``episode``
(``r``, ``l``, ``t``), ``laps_completed``, ``cut_short``, ``dnf_reason`` and ``track``;
other slots get one shared empty dict (SB3 only reads them).

>>> venv = BatchVecEnv(["oval"], n_envs=2, n_cars=2)
>>> venv.reset().shape
(4, 100)
>>> venv.close()
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray
from stable_baselines3.common.vec_env import VecEnv
from stable_baselines3.common.vec_env.base_vec_env import VecEnvIndices, VecEnvStepReturn

from arena.batch.sim import BatchSim
from tracks import load_track

_NO_INFO: dict[str, Any] = {}


class BatchVecEnv(VecEnv):
    """Every car of ``n_envs`` races on each of ``tracks`` (and reversed), as SB3 slots.

    Args:
        tracks: track names, files or ``Track`` objects; one :class:`BatchSim` each.
        n_envs: races per track (and per direction).
        n_cars: cars per race.
        laps: laps per episode.
        device: array device (:func:`arena.batch.xp.get_ops`).
        reverse: also race every track the other way round.
        random_starts: random start placement and grid order on every restart.
        reward_scale: multiplies the racing reward.
        dnf_penalty: subtracted when a car retires.
        seed: seeds the restarts.
        sim_kwargs: more :class:`BatchSim` arguments (``lidar_rays``, ``max_cycles`` …).
    """

    def __init__(
        self,
        tracks: Sequence[Any] = ("oval",),
        *,
        n_envs: int = 64,
        n_cars: int = 4,
        laps: int = 1,
        device: str = "numpy",
        reverse: bool = False,
        random_starts: bool = True,
        reward_scale: float = 1.0,
        dnf_penalty: float = 10.0,
        seed: int | None = None,
        sim_kwargs: dict[str, Any] | None = None,
    ) -> None:
        base = [load_track(t) for t in tracks]
        views = base + ([t.reversed() for t in base] if reverse else [])
        ss = np.random.SeedSequence(seed)
        self.sims = [
            BatchSim(
                track,
                n_envs,
                n_cars,
                laps,
                device=device,
                random_starts=random_starts,
                seed=int(child.generate_state(1)[0]),
                **(sim_kwargs or {}),
            )
            for track, child in zip(views, ss.spawn(len(views)), strict=True)
        ]
        first = self.sims[0]
        low, high = first.layout.bounds()
        obs_space = spaces.Box(low, high, dtype=np.float32)
        act_space = spaces.Box(-1.0, 1.0, (2,), dtype=np.float32)
        self.n_cars = n_cars
        self.laps = laps
        self.reward_scale = reward_scale
        self.dnf_penalty = dnf_penalty
        self.render_mode = None
        self._slots = [sim.n_envs * n_cars for sim in self.sims]
        self._bounds = np.cumsum([0, *self._slots])
        super().__init__(int(self._bounds[-1]), obs_space, act_space)
        self._actions: NDArray[np.float32] = np.zeros((self.num_envs, 2), dtype=np.float32)
        self._returns = np.zeros(self.num_envs)
        self._lengths = np.zeros(self.num_envs, dtype=np.int64)
        self._started = time.perf_counter()
        self._seeds = [None] * len(self.sims)

    # ---- VecEnv -------------------------------------------------------------------------------
    def reset(self) -> NDArray[np.float32]:
        """Restart every race; observations (num_envs, D)."""
        out = []
        for seed, sim in zip(self._seeds, self.sims, strict=True):
            out.append(sim.ops.to_numpy(sim.reset(seed=seed)).reshape(-1, sim.layout.size))
        self._seeds = [None] * len(self.sims)
        self._returns[:] = 0.0
        self._lengths[:] = 0
        return np.concatenate(out).astype(np.float32, copy=False)

    def seed(self, seed: int | None = None) -> list[int | None]:
        """Seed the next reset of every track's simulator."""
        ss = np.random.SeedSequence(seed)
        self._seeds = [int(c.generate_state(1)[0]) for c in ss.spawn(len(self.sims))]
        return list(self._seeds)

    _seeds: list[int | None]

    def step_async(self, actions: NDArray[np.float32]) -> None:
        """Store actions (num_envs, 2) for :meth:`step_wait`."""
        self._actions = np.asarray(actions, dtype=np.float32).reshape(self.num_envs, 2)

    def step_wait(self) -> VecEnvStepReturn:
        """Step every simulator; SB3's (obs, rewards, dones, infos)."""
        obs_parts, rew_parts, done_parts = [], [], []
        infos: list[dict[str, Any]] = [_NO_INFO] * self.num_envs
        for k, sim in enumerate(self.sims):
            lo, hi = int(self._bounds[k]), int(self._bounds[k + 1])
            ops, n, d = sim.ops, self.n_cars, sim.layout.size
            acts = ops.asarray(self._actions[lo:hi].reshape(sim.n_envs, n, 2))
            res = sim.step(acts)
            term = ops.to_numpy(res.terminated).reshape(-1)
            trunc = ops.to_numpy(res.truncated).reshape(-1)
            env_done = ops.to_numpy(res.env_done)
            laps = ops.to_numpy(res.laps_completed).reshape(-1)
            retired = term & (laps < self.laps)
            reward = ops.to_numpy(res.reward).reshape(-1).astype(np.float64) * self.reward_scale
            reward -= self.dnf_penalty * retired
            done = np.repeat(env_done, n)
            obs_parts.append(ops.to_numpy(res.obs).reshape(-1, d))
            rew_parts.append(reward)
            done_parts.append(done)
            self._returns[lo:hi] += reward
            self._lengths[lo:hi] += 1
            if env_done.any():
                envs = np.flatnonzero(env_done)
                final = ops.to_numpy(res.final_obs[ops.asarray(envs)]).reshape(-1, d)
                name = sim.track.name
                now = round(time.perf_counter() - self._started, 6)
                for row, slot in enumerate((envs[:, None] * n + np.arange(n)).ravel().tolist()):
                    g = lo + slot
                    ended = bool(term[slot] or trunc[slot])
                    infos[g] = {
                        "terminal_observation": final[row],
                        "TimeLimit.truncated": bool(trunc[slot] or not ended),
                        "episode": {
                            "r": float(self._returns[g]),
                            "l": int(self._lengths[g]),
                            "t": now,
                        },
                        "laps_completed": int(laps[slot]),
                        "cut_short": not ended,
                        "dnf_reason": _dnf_reason(bool(retired[slot]), bool(trunc[slot])),
                        "track": name,
                    }
                self._returns[lo:hi][done] = 0.0
                self._lengths[lo:hi][done] = 0
        return (
            np.concatenate(obs_parts).astype(np.float32, copy=False),
            np.concatenate(rew_parts).astype(np.float32),
            np.concatenate(done_parts),
            infos,
        )

    def close(self) -> None:
        """Nothing to release: the simulators are arrays."""

    def _sim_indices(self, indices: VecEnvIndices) -> list[int]:
        if indices is None:
            slots: list[int] = list(range(self.num_envs))
        elif isinstance(indices, int):
            slots = [indices]
        else:
            slots = [int(i) for i in indices]
        return [int(np.searchsorted(self._bounds, i, side="right") - 1) for i in slots]

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        """Attribute of the simulator behind each slot."""
        if attr_name == "render_mode":
            return [None for _ in self._sim_indices(indices)]
        return [getattr(self.sims[k], attr_name) for k in self._sim_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        """Set an attribute on the simulator behind each slot."""
        for k in self._sim_indices(indices):
            setattr(self.sims[k], attr_name, value)

    def env_method(
        self,
        method_name: str,
        *method_args: Any,
        indices: VecEnvIndices = None,
        **method_kwargs: Any,
    ) -> list[Any]:
        """Call a method of the simulator behind each slot."""
        return [
            getattr(self.sims[k], method_name)(*method_args, **method_kwargs)
            for k in self._sim_indices(indices)
        ]

    def env_is_wrapped(self, wrapper_class: type[Any], indices: VecEnvIndices = None) -> list[bool]:
        """No slot is a Gymnasium wrapper."""
        return [False for _ in self._sim_indices(indices)]


def _dnf_reason(retired: bool, truncated: bool) -> str | None:
    if retired:
        return "retired"
    return "time_limit" if truncated else None
