"""``BatchParallelEnv``: the PettingZoo ``ParallelEnv`` on the batched simulator (B = 1).

``arena.parallel_env(backend="batch", ...)`` returns one. Everything about the episode —
reset options, rules, rewards (racing, progress, DeepRacer functions), infos, model
uncertainty and nature agents, ``park_finished``, ``state()`` — is the same code as the
pybullet :class:`arena.env.RacingEnv` (:mod:`arena.episode` over :mod:`arena.core`); this
module only hands it :class:`arena.batch.sim.BatchSim` as the simulator. Differences, all
from the simulator: vector observations only (``obs_mode="vector"``); ``start_offset`` is
rounded to the nearest of the simulator's ``start_positions`` placements; contacts are soft
(:mod:`arena.batch.contact`); a car cannot flip; no rendering, no camera (the image jitter
parameters have nothing to act on).

>>> env = BatchParallelEnv(track="oval", n_cars=2)
>>> obs, infos = env.reset(seed=0)
>>> obs["car_0"].shape, env.state().shape
((100,), (20,))
"""

from __future__ import annotations

from dataclasses import fields, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from arena.batch.sim import BatchSim
from arena.core import EpisodeState, Outcome
from arena.episode import Frame, RaceEpisodeEnv
from arena.observations import wrap_angle
from arena.uncertainty import Perturbation
from arena.version import ENV_VERSION
from arena.walls import DEFAULT_RUNOFF
from tracks import Track

START_POSITIONS = 64  # placements along the lap that ``start_offset`` rounds to


class BatchParallelEnv(RaceEpisodeEnv):
    """Several Ackermann cars racing on one track, on the batched backend.

    Arguments as :class:`arena.env.RacingEnv`, plus ``device`` (``"numpy"``,
    ``"torch:cpu"``, ``"cuda"``, see :func:`arena.batch.xp.get_ops`).
    """

    metadata = {  # noqa: RUF012 - PettingZoo reads this class attribute
        "name": "slipstream_racing_batch_v0",
        "render_modes": [],
        "is_parallelizable": True,
        "render_fps": 20,
    }
    obs_modes = ("vector",)
    render_modes_supported = (None,)
    backend = "batch"

    def __init__(
        self,
        track: str | Path | Track = "oval",
        n_cars: int = 4,
        laps: int = 1,
        *,
        device: str = "numpy",
        runoff: float = DEFAULT_RUNOFF,
        **kwargs: Any,
    ) -> None:
        super().__init__(track, n_cars, laps, **kwargs)
        self.runoff = runoff
        self._device = device
        self._sims: dict[tuple[str, bool], BatchSim] = {}
        self.sim = self._sim(False)
        self._values = Perturbation.nominal(n_cars).values
        self.env_version = ENV_VERSION

    def _sim(self, reverse: bool) -> BatchSim:
        key = (self._track_key, reverse)
        if key not in self._sims:
            track = self.base_track.reversed() if reverse else self.base_track
            self._sims[key] = BatchSim(
                track,
                1,
                self.n_cars,
                self.laps,
                device=self._device,
                control_hz=self.control_hz,
                physics_hz=self.physics_hz,
                lidar_rays=self.layout.n_rays,
                k_opponents=self.layout.k_opponents,
                observe_perturbation=self.layout.context,
                runoff=self.runoff,
                car_params=self.params,
                reward_weights=self.weights,
                max_cycles=self.max_cycles,
                off_track_limit=self.off_track_limit,
                stuck_time=self.stuck_time,
                auto_reset=False,
                start_positions=START_POSITIONS,
            )
            if self.end_on_crash:
                sim = self._sims[key]
                sim.rules = replace(sim.rules, end_on_crash=True)
        return self._sims[key]

    # ---- the batched pipeline ------------------------------------------------------------------

    def _pipeline_view(self, reverse: bool) -> Track:
        self.sim = self._sim(reverse)
        return self.sim.track

    def _pipeline_use_track(self, name: str) -> None:
        """Nothing to do: :meth:`_pipeline_view` builds the new track's simulator."""

    def _pipeline_perturb(self, values: NDArray[np.float64]) -> None:
        self._values = values.copy()
        self.sim.set_perturbation(self._values[None])

    def _pipeline_park(self, i: int) -> None:
        self.sim.state.active[0, i] = False

    def _pipeline_reset(self, order: NDArray[np.int64], offset: float) -> Frame:
        sim, n = self.sim, self.n_cars
        k = round(offset / self.track.length * sim.n_starts) % sim.n_starts
        slot_of_car = np.empty(n, dtype=np.int64)
        slot_of_car[order] = np.arange(n)  # order[p] is the car in slot p
        # The simulator's own draws (action noise, lidar noise) follow the env's seed.
        sim.reset(
            seed=int(self.np_random.integers(2**62)),
            start=np.array([k]),
            slot_of_car=slot_of_car[None],
        )
        if self._unc is not None:
            sim.set_perturbation(self._values[None])
        return self._frame_of(sim.obs, None)

    def _pipeline_step(self, steer: NDArray[np.float64], throttle: NDArray[np.float64]) -> Frame:
        sim = self.sim
        if sim.max_cycles != self.max_cycles:  # a caller changed env.max_cycles
            sim.max_cycles = self.max_cycles
            sim.rules = type(sim.rules)(**{**sim.rules.__dict__, "max_cycles": self.max_cycles})
        res = sim.step(np.stack([steer, throttle], axis=1)[None])
        ops = sim.ops
        out = sim.outcome
        arrays: dict[str, Any] = {
            f.name: ops.to_numpy(getattr(out, f.name)) for f in fields(Outcome) if f.name != "terms"
        }
        terms = {k: ops.to_numpy(v).astype(np.float64) for k, v in out.terms.items()}
        host = Outcome(terms=terms, **arrays)
        host.reward = host.reward.astype(np.float64)
        return self._frame_of(res.obs, host)

    def _frame_of(self, obs: Any, outcome: Outcome | None) -> Frame:
        sim, ops = self.sim, self.sim.ops
        st = sim.state
        episode = EpisodeState(
            **{f.name: ops.to_numpy(getattr(st, f.name)) for f in fields(EpisodeState)}
        )
        car = st.car
        x, y, yaw, vx, vy, r, steering = (
            ops.to_numpy(getattr(car, name))[0].astype(np.float64)
            for name in ("x", "y", "yaw", "vx", "vy", "r", "steering")
        )
        heading = ops.to_numpy(st.heading)[0].astype(np.float64)
        return Frame(
            episode=episode,
            outcome=outcome,
            poses=np.stack([x, y, yaw], axis=1),
            velocity=np.stack([vx, vy, r], axis=1),
            v_long=np.cos(yaw) * vx + np.sin(yaw) * vy,
            steering=steering,
            d=ops.to_numpy(st.d)[0].astype(np.float64),
            segment=ops.to_numpy(st.segment)[0].astype(np.int64),
            heading_error=wrap_angle(yaw - heading),
            obs=ops.to_numpy(obs)[0],
            time=float(ops.to_numpy(st.steps)[0]) / self.control_hz,
        )

    def render(self) -> None:
        """No rendering on this backend."""
        return None

    def close(self) -> None:
        """Nothing to release: the simulator is arrays."""
