"""``BatchParallelEnv``: the PettingZoo ``ParallelEnv`` on the batched simulator (B = 1).

``arena.parallel_env(backend="batch", ...)`` returns one. It has the observation and action
spaces, rewards, infos and episode rules of :class:`arena.env.RacingEnv` (see its docstring),
computed by :class:`arena.batch.sim.BatchSim` instead of pybullet, so a policy can be
checked on both backends with the same code. Differences: vector observations only
(``obs_mode="vector"``); rewards ``"racing"`` or ``"progress"`` (no DeepRacer functions);
``start_offset`` is rounded to the nearest of the simulator's ``start_positions``
placements; contacts are soft (:mod:`arena.batch.contact`); no rendering.

>>> env = BatchParallelEnv(track="oval", n_cars=2)
>>> obs, infos = env.reset(seed=0)
>>> obs["car_0"].shape
(100,)
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray
from pettingzoo import ParallelEnv

from arena.actions import DiscreteActions
from arena.batch.sim import BatchSim, StepResult
from arena.env import ActionMode, ObsMode
from arena.rewards import RACING_TERMS
from arena.sim import SimError
from arena.version import ENV_VERSION
from tracks import Track, load_track

START_POSITIONS = 64  # placements along the lap that ``start_offset`` rounds to


class BatchParallelEnv(ParallelEnv):
    """Several Ackermann cars racing on one track, on the batched backend.

    Arguments as :class:`arena.env.RacingEnv` (``track``, ``n_cars``, ``laps``,
    ``control_hz``, ``physics_hz``, ``obs_mode``, ``action_mode``, ``lidar_rays``,
    ``k_opponents``, ``discrete_actions``, ``reward``, ``reward_weights``, ``max_cycles``,
    ``off_track_limit``, ``stuck_time``, ``runoff``, ``car_params``), plus ``device``.
    """

    metadata = {  # noqa: RUF012 - PettingZoo reads this class attribute
        "name": "slipstream_racing_batch_v0",
        "render_modes": [],
        "is_parallelizable": True,
        "render_fps": 20,
    }

    def __init__(
        self,
        track: str | Path | Track = "oval",
        n_cars: int = 4,
        laps: int = 1,
        *,
        obs_mode: ObsMode = "vector",
        action_mode: ActionMode = "continuous",
        discrete_actions: tuple[int, int] = (5, 2),
        reward: str = "racing",
        render_mode: str | None = None,
        device: str = "numpy",
        **sim_kwargs: Any,
    ) -> None:
        if obs_mode != "vector":
            raise SimError("backend='batch' has vector observations only (obs_mode='vector')")
        if action_mode not in ("continuous", "discrete"):
            raise SimError(f"action_mode must be 'continuous' or 'discrete', got {action_mode!r}")
        if reward not in ("racing", "progress"):
            raise SimError("backend='batch' supports reward='racing' or 'progress'")
        if render_mode is not None:
            raise SimError("backend='batch' does not render; use the pybullet backend")
        self.base_track = load_track(track)
        self.n_cars, self.laps = n_cars, laps
        self.action_mode: ActionMode = action_mode
        self.reward_mode = reward
        self.render_mode = render_mode
        self._kwargs = {"device": device, **sim_kwargs}
        self._sims: dict[bool, BatchSim] = {}
        self.sim = self._sim(False)
        self.params, self.layout = self.sim.params, self.sim.layout
        self.dt, self.max_cycles = self.sim.dt, self.sim.max_cycles
        self.discrete = DiscreteActions(*discrete_actions, top_speed=self.params.top_speed)
        self.possible_agents = [f"car_{i}" for i in range(n_cars)]
        self.agent_index = {a: i for i, a in enumerate(self.possible_agents)}
        self.agents: list[str] = []
        low, high = self.layout.bounds()
        obs_space = spaces.Box(low, high, dtype=np.float32)
        act_space: spaces.Space[Any] = (
            spaces.Discrete(self.discrete.n)
            if action_mode == "discrete"
            else spaces.Box(-1.0, 1.0, (2,), dtype=np.float32)
        )
        self._observation_spaces = {a: obs_space for a in self.possible_agents}
        self._action_spaces = {a: act_space for a in self.possible_agents}
        self.np_random = np.random.default_rng()
        self.track = self.base_track
        self.env_version = ENV_VERSION

    def _sim(self, reverse: bool) -> BatchSim:
        if reverse not in self._sims:
            track = self.base_track.reversed() if reverse else self.base_track
            self._sims[reverse] = BatchSim(
                track,
                1,
                self.n_cars,
                self.laps,
                auto_reset=False,
                start_positions=START_POSITIONS,
                **self._kwargs,
            )
        return self._sims[reverse]

    def observation_space(self, agent: str) -> spaces.Space[Any]:
        """The (cached) observation space of ``agent``."""
        return self._observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Space[Any]:
        """The (cached) action space of ``agent``."""
        return self._action_spaces[agent]

    # ---- reset ------------------------------------------------------------------------------
    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, NDArray[np.float32]], dict[str, dict[str, Any]]]:
        """Start a new race; ``options`` as :meth:`arena.env.RacingEnv.reset`."""
        if seed is not None:
            self.np_random = np.random.default_rng(seed)
        opts = options or {}
        n = self.n_cars
        direction = opts.get("direction", "forward")
        if direction == "random":
            direction = "reverse" if self.np_random.random() < 0.5 else "forward"
        if direction not in ("forward", "reverse"):
            raise SimError(f"direction must be forward, reverse or random, got {direction!r}")
        self.sim = self._sim(direction == "reverse")
        self.track = self.sim.track
        order = opts.get("grid_order")
        if order == "random":
            order = self.np_random.permutation(n)
        order = np.arange(n) if order is None else np.asarray(order, dtype=np.int64)
        if sorted(order.tolist()) != list(range(n)):
            raise SimError(f"grid_order must be a permutation of 0..{n - 1}")
        offset = opts.get("start_offset", 0.0)
        if offset == "random":
            offset = float(self.np_random.uniform(0.0, self.track.length))
        k = round(float(offset) / self.track.length * self.sim.n_starts) % self.sim.n_starts
        slot_of_car = np.empty(n, dtype=np.int64)
        slot_of_car[order] = np.arange(n)  # order[p] is the car in slot p
        ops = self.sim.ops
        obs = ops.to_numpy(self.sim.reset(start=np.array([k]), slot_of_car=slot_of_car[None]))[0]
        self.agents = list(self.possible_agents)
        self.steps = 0
        self.lap_times: list[list[float]] = [[] for _ in range(n)]
        self.dnf_reason: list[str | None] = [None] * n
        self.collision_count = np.zeros(n, dtype=np.int64)
        self.at_fault_count = np.zeros(n, dtype=np.int64)
        self.off_track_count = np.zeros(n, dtype=np.int64)
        self._was_off = np.zeros(n, dtype=bool)
        self.active = np.ones(n, dtype=bool)
        zero = dict.fromkeys(RACING_TERMS, 0.0)
        cars = self._host_cars()
        infos = {a: self._info(i, cars, [], False, False, zero) for i, a in enumerate(self.agents)}
        return {a: obs[i] for i, a in enumerate(self.agents)}, infos

    # ---- step -------------------------------------------------------------------------------
    def _controls(self, actions: dict[str, Any]) -> NDArray[np.float64]:
        n = self.n_cars
        cmd = np.zeros((n, 2))
        if self.action_mode == "discrete":
            idx = np.zeros(n, dtype=np.int64)
            for agent, act in actions.items():
                idx[self.agent_index[agent]] = int(np.asarray(act).reshape(()))
            st = self.sim.state.car
            ops = self.sim.ops
            yaw, vx, vy = (ops.to_numpy(a)[0] for a in (st.yaw, st.vx, st.vy))
            v_long = np.cos(yaw) * vx + np.sin(yaw) * vy
            steer, throttle = self.discrete.to_controls(idx, v_long)
            cmd[:, 0], cmd[:, 1] = steer, throttle
        else:
            for agent, act in actions.items():
                a = np.asarray(act, dtype=np.float64).reshape(-1)
                if a.shape != (2,):
                    raise SimError(f"action for {agent} must have shape (2,), got {a.shape}")
                cmd[self.agent_index[agent]] = a
        return cmd * self.active[:, None]

    def step(
        self, actions: dict[str, Any]
    ) -> tuple[
        dict[str, NDArray[np.float32]],
        dict[str, float],
        dict[str, bool],
        dict[str, bool],
        dict[str, dict[str, Any]],
    ]:
        """Advance every car one control step; PettingZoo parallel semantics."""
        if not self.agents:
            raise SimError("step() called on a finished episode; call reset() first")
        res = self.sim.step(self._controls(actions)[None])
        self.steps += 1
        h = _Host(res, self.sim)
        off, new_contact = h.off_track, h.new_contact
        self.off_track_count += off & ~self._was_off
        self._was_off = off
        self.collision_count += new_contact.any(axis=1)
        self.at_fault_count += (h.at_fault & new_contact).any(axis=1)
        for i in np.flatnonzero(h.lap_done):
            self.lap_times[i].append(round(float(h.lap_time[i]), 10))
        for i in np.flatnonzero(h.terminated & (h.laps < self.laps)):
            self.dnf_reason[i] = (
                "off_track" if h.off_time[i] > self.sim.off_track_limit else "stuck"
            )
        for i in np.flatnonzero(h.truncated):
            self.dnf_reason[i] = "timeout"
        reward = h.terms["progress"] if self.reward_mode == "progress" else h.reward
        obs, rew, term, trunc, infos = {}, {}, {}, {}, {}
        cars = self._host_cars()
        for agent in self.agents:
            k = self.agent_index[agent]
            obs[agent] = h.obs[k]
            rew[agent] = float(reward[k])
            term[agent] = bool(h.terminated[k])
            trunc[agent] = bool(h.truncated[k])
            events = [
                {
                    "with": self.possible_agents[j],
                    "at_fault": bool(h.at_fault[k, j]),
                    "closing_speed": float(h.closing[k, j]),
                    "new": bool(new_contact[k, j]),
                }
                for j in np.flatnonzero(h.contact[k])
            ]
            terms = {name: float(v[k]) for name, v in h.terms.items()}
            infos[agent] = self._info(k, cars, events, bool(off[k]), bool(h.wall[k]), terms)
        done = h.terminated | h.truncated
        self.active &= ~done
        self.agents = [a for a in self.agents if not done[self.agent_index[a]]]
        return obs, rew, term, trunc, infos

    @property
    def laps_completed(self) -> NDArray[np.int64]:
        """(n_cars,) laps each car has completed in this episode."""
        return np.maximum(self.sim.ops.to_numpy(self.sim.state.laps)[0], 0)

    def _host_cars(self) -> dict[str, list[Any]]:
        """Environment 0's per-car state for the infos, as Python lists (n_cars,): one
        device-to-host copy per quantity and step, not one per car."""
        st, ops = self.sim.state, self.sim.ops

        def row(a: Any) -> list[Any]:
            return list(ops.to_numpy(a)[0].tolist())

        yaw, vx, vy = row(st.car.yaw), row(st.car.vx), row(st.car.vy)
        return {
            "laps": [max(k, 0) for k in row(st.laps)],
            "speed": [
                math.cos(y) * u + math.sin(y) * v for y, u, v in zip(yaw, vx, vy, strict=True)
            ],
            "s": row(st.s),
            "race_progress": row(st.race_progress),
            "rank": row(st.positions),
        }

    def _info(
        self,
        i: int,
        cars: dict[str, list[Any]],
        collisions: list[dict[str, Any]],
        off: bool,
        wall: bool,
        terms: dict[str, float],
    ) -> dict[str, Any]:
        done_laps = cars["laps"][i]
        info: dict[str, Any] = {
            "lap": min(done_laps + 1, self.laps),
            "laps_completed": done_laps,
            "lap_times": list(self.lap_times[i]),
            "s": cars["s"][i],
            "race_progress": cars["race_progress"][i],
            "rank": cars["rank"][i],
            "collisions": collisions,
            "off_track": off,
            "wall_contact": wall,
            "speed": cars["speed"][i],
            "reward_terms": terms,
        }
        if self.dnf_reason[i] is not None:
            info["dnf_reason"] = self.dnf_reason[i]
        return info

    def render(self) -> None:
        """No rendering on this backend."""
        return None

    def close(self) -> None:
        """Nothing to release."""


class _Host:
    """One step's results for environment 0, as numpy on the host."""

    def __init__(self, res: StepResult, sim: BatchSim) -> None:
        def get(a: Any) -> Any:
            return sim.ops.to_numpy(a)[0]

        self.obs = get(res.obs)
        self.reward = get(res.reward).astype(np.float64)
        self.terms = {k: get(v).astype(np.float64) for k, v in res.terms.items()}
        self.terminated, self.truncated = get(res.terminated), get(res.truncated)
        self.lap_done, self.lap_time = get(res.lap_done), get(res.lap_time)
        self.laps = get(res.laps_completed)
        self.off_track, self.wall = get(res.off_track), get(res.wall)
        self.contact, self.new_contact = get(res.contact), get(res.new_contact)
        self.at_fault, self.closing = get(res.at_fault), get(res.closing)
        self.off_time = get(sim.state.off_time)
