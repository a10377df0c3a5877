"""``RaceEpisodeEnv``: the PettingZoo side of a race, written once for both simulators.

Brax's ``PipelineEnv`` model: this class writes ``reset`` and ``step`` — the reset options,
agents and spaces, actions, model uncertainty (perturbations and nature agents), rewards
(racing, progress or a DeepRacer function, perturbed), infos, lap times, DNF reasons,
``park_finished``, PettingZoo's ``state()`` — against a small *pipeline* that a backend
provides: :class:`arena.env.RacingEnv` (pybullet, the reference for races) and
:class:`arena.batch.parallel.BatchParallelEnv` (the batched simulator, ``B = 1``). The race
rules themselves (laps, termination, blame, reward terms) are :mod:`arena.core`'s, which the
pipelines call on ``(B, N)`` arrays. See :class:`arena.env.RacingEnv` for the full spec.

A pipeline implements :meth:`RaceEpisodeEnv._pipeline_reset`,
:meth:`RaceEpisodeEnv._pipeline_step`, :meth:`RaceEpisodeEnv._pipeline_view`,
:meth:`RaceEpisodeEnv._pipeline_park` and :meth:`RaceEpisodeEnv._pipeline_perturb`; each
reset and step returns a :class:`Frame` of host numpy arrays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray
from pettingzoo import ParallelEnv

from arena.actions import DiscreteActions
from arena.batch.xp import count_true
from arena.cars import car_params as resolve_car
from arena.core import (
    DNF_REASONS,
    STATE_FEATURES,
    EpisodeState,
    Outcome,
    StartSpec,
    default_max_cycles,
    global_state,
    start_offset,
    start_spec,
)
from arena.deepracer import (
    DEEPRACER_PRESET,
    ActionTable,
    DeepRacerParams,
    RewardFunction,
    read_model_metadata,
)
from arena.observations import (
    CONTEXT_LIMIT,
    CONTEXT_SIZE,
    EGO_FEATURES,
    EGO_HIGH,
    EGO_LOW,
    LOOKAHEAD,
    OPP_HIGH,
    OPP_LOW,
    TRACK_LIMIT,
    ObservationLayout,
)
from arena.rewards import RACING_TERMS, RewardWeights
from arena.sim import CarParams, SimError
from arena.uncertainty import (
    PARAM_NAMES,
    Perturbation,
    PerturbationState,
    UncertaintyConfig,
    UncertaintyError,
    normalised,
    perturbed_reward,
)
from tracks import Track, load_track

ObsMode = Literal["vector", "dict", "image"]
ActionMode = Literal["continuous", "discrete"]
IMAGE_SHAPE = (120, 160, 1)  # rows, columns, channels: DeepRacer's 160×120 grayscale camera
NATURE_PREFIX = "nature_"
Obs = NDArray[np.float32] | NDArray[np.uint8] | dict[str, NDArray[np.float32]]


@dataclass
class Frame:
    """One reset or step of race 0, as host numpy arrays.

    Attributes:
        episode: the rules' state after the step (arrays (1, N)).
        outcome: what the rules decided this step (None after a reset).
        poses: (N, 3) [x m, y m, yaw rad]; velocity: (N, 3) [vx, vy m/s world, yaw rate].
        v_long: (N,) forward speed, m/s; steering: (N,) road-wheel angle, rad.
        d: (N,) m left of the centre line; segment: (N,) centre-line segment index;
        heading_error: (N,) rad.
        obs: (N, D) float32 vector observations, or per-car images (image mode).
        time: s since the start.
    """

    episode: EpisodeState
    outcome: Outcome | None
    poses: NDArray[np.float64]
    velocity: NDArray[np.float64]
    v_long: NDArray[np.float64]
    steering: NDArray[np.float64]
    d: NDArray[np.float64]
    segment: NDArray[np.int64]
    heading_error: NDArray[np.float64]
    obs: Any
    time: float


def _race_zero(name: str, doc: str) -> Any:
    """A read-only property: field ``name`` of race 0's episode state, (N,)."""

    def get(self: RaceEpisodeEnv) -> Any:
        return getattr(self._ep, name)[0]

    return property(get, doc=doc)


class RaceEpisodeEnv(ParallelEnv):
    """The episode core's PettingZoo env; a backend subclass provides the pipeline.

    Arguments and behaviour: :class:`arena.env.RacingEnv`.
    """

    obs_modes: tuple[str, ...] = ("vector", "dict", "image")
    render_modes_supported: tuple[str | None, ...] = (None, "rgb_array")
    backend = "pybullet"

    def __init__(
        self,
        track: str | Path | Track = "oval",
        n_cars: int = 4,
        laps: int = 1,
        *,
        control_hz: int = 20,
        physics_hz: int = 60,
        obs_mode: ObsMode = "vector",
        action_mode: ActionMode = "continuous",
        lidar_rays: int = 64,
        k_opponents: int = 3,
        discrete_actions: tuple[int, int] = (5, 2),
        reward: str | RewardFunction = "racing",
        reward_weights: RewardWeights | None = None,
        max_cycles: int | None = None,
        render_mode: str | None = None,
        off_track_limit: float = 3.0,
        stuck_time: float = 4.0,
        car_params: CarParams | None = None,
        car: str | CarParams | None = None,
        uncertainty: UncertaintyConfig | None = None,
        park_finished: bool = False,
        preset: str | None = None,
        action_table: ActionTable | str | Path | None = None,
        observe_perturbation: bool = False,
    ) -> None:
        self.end_on_crash = False
        if preset is not None:
            if preset != "deepracer":
                raise SimError(f"preset must be 'deepracer' or None, got {preset!r}")
            rules = DEEPRACER_PRESET
            car = car if car is not None or car_params is not None else rules.car
            control_hz = int(rules.control_hz)
            if rules.end_on_off_track:
                off_track_limit = 0.0
            self.end_on_crash = rules.end_on_crash
        if action_table is not None:
            if isinstance(action_table, str | Path):
                action_table = read_model_metadata(Path(action_table))
            action_mode = "discrete"
        if obs_mode not in self.obs_modes:
            allowed = ", ".join(repr(m) for m in self.obs_modes)
            raise SimError(f"obs_mode must be one of {allowed} on this backend, got {obs_mode!r}")
        if action_mode not in ("continuous", "discrete"):
            raise SimError(f"action_mode must be 'continuous' or 'discrete', got {action_mode!r}")
        if observe_perturbation and obs_mode == "image":
            raise SimError("observe_perturbation needs obs_mode 'vector' or 'dict', not 'image'")
        if render_mode not in self.render_modes_supported:
            raise SimError(f"render_mode {render_mode!r} is not supported by this backend")
        if not (isinstance(reward, str) and reward in ("racing", "progress")) and not callable(
            reward
        ):
            raise SimError("reward must be 'racing', 'progress' or a reward_function(params)")
        if laps < 1:
            raise SimError(f"laps must be at least 1, got {laps}")
        if uncertainty is not None and not isinstance(uncertainty, UncertaintyConfig):
            raise UncertaintyError("uncertainty must be an arena.uncertainty.UncertaintyConfig")
        if car is not None and car_params is not None:
            raise SimError("give either car= (a preset name or CarParams) or car_params=, not both")
        params = resolve_car(car) if car is not None else (car_params or CarParams())
        # Python ``if`` on this static config only: nominal costs nothing per step.
        self.uncertainty = uncertainty
        self._unc = (
            uncertainty if uncertainty is not None and uncertainty.mode != "nominal" else None
        )
        self.base_track = load_track(track)
        self._track_key = track if isinstance(track, str) else self.base_track.name
        self._fixed_max_cycles = max_cycles
        self.n_cars = n_cars
        self.laps = laps
        self.obs_mode: ObsMode = obs_mode
        self.action_mode: ActionMode = action_mode
        self.reward_mode = reward
        self.weights = reward_weights or RewardWeights()
        self.render_mode = render_mode
        self.off_track_limit = off_track_limit
        self.stuck_time = stuck_time
        self.park_finished = park_finished
        self.params = params
        self.control_hz = control_hz
        self.physics_hz = physics_hz
        self.dt = 1.0 / control_hz
        self.layout = ObservationLayout(lidar_rays, k_opponents, bool(observe_perturbation))
        self.discrete: DiscreteActions | ActionTable = (
            action_table
            if action_table is not None
            else DiscreteActions(*discrete_actions, top_speed=params.top_speed)
        )
        self.preset = preset
        self._set_race_distance()
        self.cars = [f"car_{i}" for i in range(n_cars)]
        adversarial = self._unc is not None and self._unc.mode == "adversarial"
        self.natures = [NATURE_PREFIX + a for a in self.cars] if adversarial else []
        self.possible_agents = self.cars + self.natures
        # A nature agent shares its car's index: it acts on, and leaves with, that car.
        self.agent_index = {a: i for i, a in enumerate(self.cars)}
        self.agent_index.update({a: i for i, a in enumerate(self.natures)})
        self.agents: list[str] = []
        self._observation_spaces = {a: self._make_obs_space() for a in self.cars}
        self._action_spaces = {a: self._make_action_space() for a in self.cars}
        n_free = len(self._unc.free) if self._unc is not None else 0
        self.state_space = spaces.Box(
            -np.inf, np.inf, (n_cars * (STATE_FEATURES + n_free),), dtype=np.float32
        )
        for a in self.natures:
            self._observation_spaces[a] = spaces.Box(
                -np.inf, np.inf, (self.state_space.shape[0] + n_cars,), dtype=np.float32
            )
            self._action_spaces[a] = spaces.Box(-1.0, 1.0, (n_free,), dtype=np.float32)
        self.perturbation = Perturbation.nominal(n_cars)
        if self._unc is not None:
            self._pert = PerturbationState(self._unc, (1, n_cars))
            self._episodes = 0
        self.np_random = np.random.default_rng()
        self._reversed = False
        self.track = self.base_track
        self._deepracer: dict[tuple[str, bool], DeepRacerParams] = {}
        self._frame: Frame | None = None

    def _set_race_distance(self) -> None:
        self.race_distance = self.laps * self.base_track.length
        self.max_cycles = self._fixed_max_cycles or default_max_cycles(
            self.race_distance, self.control_hz
        )

    # ---- the pipeline a backend provides -------------------------------------------------------

    def _pipeline_view(self, reverse: bool) -> Track:
        """Make the simulator race ``self.base_track`` in a direction; returns that track."""
        raise NotImplementedError

    def _pipeline_reset(self, order: NDArray[np.int64], offset: float) -> Frame:
        """Place car ``order[p]`` in grid slot ``p``, the grid ``offset`` m along the lap."""
        raise NotImplementedError

    def _pipeline_step(self, steer: NDArray[np.float64], throttle: NDArray[np.float64]) -> Frame:
        """One control step with commands (N,) in [-1, 1] (parked cars get zeros)."""
        raise NotImplementedError

    def _pipeline_park(self, i: int) -> None:
        """Take car ``i`` out of the race (its episode state's ``active`` is already False)."""
        raise NotImplementedError

    def _pipeline_perturb(self, values: NDArray[np.float64]) -> None:
        """Hand the simulator this episode's perturbation values (N, n_params)."""
        raise NotImplementedError

    def _pipeline_use_track(self, name: str) -> None:
        """Race on track ``name`` from now on (episode randomisation over a track set)."""
        raise NotImplementedError

    # ---- spaces --------------------------------------------------------------------------------

    def _make_obs_space(self) -> spaces.Space[Any]:
        if self.obs_mode == "image":
            return spaces.Box(0, 255, IMAGE_SHAPE, dtype=np.uint8)
        low, high = self.layout.bounds()
        if self.obs_mode == "vector":
            return spaces.Box(low, high, dtype=np.float32)
        named: dict[str, spaces.Space[Any]] = {
            "lidar": spaces.Box(0.0, 1.0, (self.layout.n_rays,), dtype=np.float32)
        }
        for k, name in enumerate(EGO_FEATURES):
            named[name] = spaces.Box(
                np.float32(EGO_LOW[k]), np.float32(EGO_HIGH[k]), (1,), dtype=np.float32
            )
        named["track_ahead"] = spaces.Box(
            -TRACK_LIMIT, TRACK_LIMIT, (len(LOOKAHEAD), 2), dtype=np.float32
        )
        k_opp = self.layout.k_opponents
        named["opponents"] = spaces.Box(
            np.tile(OPP_LOW, (k_opp, 1)).astype(np.float32),
            np.tile(OPP_HIGH, (k_opp, 1)).astype(np.float32),
            dtype=np.float32,
        )
        if self.layout.context:
            named["perturbation"] = spaces.Box(
                -CONTEXT_LIMIT, CONTEXT_LIMIT, (CONTEXT_SIZE,), dtype=np.float32
            )
        return spaces.Dict(named)

    def _make_action_space(self) -> spaces.Space[Any]:
        if self.action_mode == "discrete":
            return spaces.Discrete(self.discrete.n)
        return spaces.Box(-1.0, 1.0, (2,), dtype=np.float32)

    def observation_space(self, agent: str) -> spaces.Space[Any]:
        """The (cached, identical every call) observation space of ``agent``."""
        return self._observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Space[Any]:
        """The (cached, identical every call) action space of ``agent``."""
        return self._action_spaces[agent]

    # ---- the episode state, by name (race 0 of the pipeline's arrays) --------------------------

    @property
    def _ep(self) -> EpisodeState:
        if self._frame is None:
            raise SimError("call reset() first")
        return self._frame.episode

    race_progress = _race_zero("race_progress", "(N,) m from the start line (negative behind).")
    positions = _race_zero("positions", "(N,) 1-based race positions.")
    active = _race_zero("active", "(N,) cars still racing.")
    finished = _race_zero("finished", "(N,) cars that completed the race distance.")
    off_time = _race_zero("off_time", "(N,) s each car has spent off the road without a break.")

    @property
    def finish_time(self) -> NDArray[np.float64]:
        """(N,) s at which each car finished (inf if it has not)."""
        return np.where(self.finished, self._ep.finish_time[0], np.inf)

    @property
    def laps_completed(self) -> NDArray[np.int64]:
        """(N,) laps each car has completed in this episode."""
        return np.maximum(self._ep.laps[0], 0)

    @property
    def steps(self) -> int:
        """Control steps since the reset."""
        return int(self._ep.steps[0]) if self._frame is not None else 0

    # ---- reset ---------------------------------------------------------------------------------

    def _episode_options(self, opts: dict[str, Any]) -> dict[str, Any]:
        """``opts`` with the config's episode randomisation filled in (explicit ones win)."""
        assert self._unc is not None
        ep = self._unc.episode
        k = self._episodes
        self._episodes += 1
        if ep.tracks:
            name = ep.tracks[int(self.np_random.integers(len(ep.tracks)))]
            if name != self._track_key:
                self._pipeline_use_track(name)
                self.base_track = load_track(name)
                self._track_key = name
                self._set_race_distance()
        out = dict(opts)
        if "start_offset" not in out and ep.start != "grid":
            out["start_offset"] = (
                "random"
                if ep.start == "random"
                else (k * ep.start_step % 1.0) * self.base_track.length
            )
        if "direction" not in out and ep.direction != "forward":
            out["direction"] = (
                "random" if ep.direction == "random" else ("reverse" if k % 2 else "forward")
            )
        return out

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, Obs], dict[str, dict[str, Any]]]:
        """Start a new race; see the class docstring for ``options``."""
        if seed is not None:
            self.np_random = np.random.default_rng(seed)
        opts = options or {}
        n = self.n_cars
        if self._unc is not None:
            opts = self._episode_options(opts)
            self._pert.start(self.np_random, given=opts.get("perturbation"))
            self._set_perturbation()
        spec: StartSpec = start_spec(opts, self.np_random, n)
        self._reversed = spec.reverse
        self.track = self._pipeline_view(spec.reverse)
        offset = start_offset(spec, self.np_random, self.track.length)
        self.grid_order = spec.order
        frame = self._pipeline_reset(spec.order, offset)
        self._frame = frame
        self.lap_times: list[list[float]] = [[] for _ in range(n)]
        self.dnf_reason: list[str | None] = [None] * n
        self.collision_count = np.zeros(n, dtype=np.int64)
        self.at_fault_count = np.zeros(n, dtype=np.int64)
        self.off_track_count = np.zeros(n, dtype=np.int64)
        self.agents = list(self.possible_agents)
        self._done_flags: dict[str, tuple[bool, bool]] = {}
        self._last: dict[str, tuple[Obs, dict[str, Any]]] = {}
        zero_terms = dict.fromkeys(RACING_TERMS, 0.0)
        cars = self._car_lists(frame)
        infos = {
            a: self._info(i, cars, [], False, False, zero_terms) for i, a in enumerate(self.cars)
        }
        observations: dict[str, Obs] = {a: frame.obs[i] for i, a in enumerate(self.cars)}
        if self._unc is not None:
            zero = np.zeros(n)
            self._add_uncertainty(observations, {}, infos, zero, zero)
        if self.park_finished:
            self._last = {a: (observations[a], infos[a]) for a in self.agents}
        return observations, infos

    # ---- step ----------------------------------------------------------------------------------

    def _controls(self, actions: dict[str, Any]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Steering commands and throttles (N,) for every car; parked cars get zeros."""
        n = self.n_cars
        active = self.active
        if self.action_mode == "discrete":
            idx = np.zeros(n, dtype=np.int64)
            for agent, act in actions.items():
                idx[self.agent_index[agent]] = int(np.asarray(act).reshape(()))
            assert self._frame is not None
            steer, throttle = self.discrete.to_controls(idx, self._frame.v_long)
            return np.where(active, steer, 0.0), np.where(active, throttle, 0.0)
        cmd: list[Any] = [(0.0, 0.0)] * n
        for agent, act in actions.items():
            if type(act) is np.ndarray and act.shape == (2,) and act.dtype.char in "fd":
                # A policy's usual action (float32 or float64): tolist() gives the float64
                # values the conversion below would, at a fraction of its cost.
                cmd[self.agent_index[agent]] = act.tolist()
                continue
            a = np.asarray(act, dtype=np.float64)
            if a.size != 2:
                raise SimError(f"action for {agent} must have shape (2,), got {a.shape}")
            cmd[self.agent_index[agent]] = tuple(a.reshape(-1).tolist())
        # NaN means "no input"; ±inf saturate. The env never lets a bad number into physics.
        # In Python floats per car: np.clip's values (min and max keep their first argument
        # unless the other compares beyond it), without numpy's per-call overhead.
        steers, throttles = [], []
        for (u, v), on in zip(cmd, active.tolist(), strict=True):
            racing = 1.0 if on else 0.0
            steers.append(min(max(0.0 if math.isnan(u) else u, -1.0), 1.0) * racing)
            throttles.append(min(max(0.0 if math.isnan(v) else v, -1.0), 1.0) * racing)
        return np.array(steers), np.array(throttles)

    def step(
        self, actions: dict[str, Any]
    ) -> tuple[
        dict[str, Obs],
        dict[str, float],
        dict[str, bool],
        dict[str, bool],
        dict[str, dict[str, Any]],
    ]:
        """Advance every car one control step; PettingZoo parallel semantics."""
        if not self.agents:
            raise SimError("step() called on a finished episode; call reset() first")
        racing = [a for a in self.agents if a not in self._done_flags]
        if self.park_finished:  # parked cars' actions are ignored
            actions = {a: v for a, v in actions.items() if a not in self._done_flags}
        if self._unc is not None:
            actions = self._advance_perturbation(actions)
        steer, throttle = self._controls(actions)
        frame = self._pipeline_step(steer, throttle)
        self._frame = frame
        out = frame.outcome
        assert out is not None
        # Events are rare: each bookkeeping line is skipped (one cheap test) when none happened.
        lap_done = out.lap_done[0]
        if count_true(lap_done):
            for i in np.flatnonzero(lap_done):
                self.lap_times[i].append(round(float(out.lap_time[0, i]), 10))
        new_contact, at_fault = out.new_contact[0], out.at_fault[0]
        if count_true(new_contact):
            self.collision_count += new_contact.any(axis=1)
            self.at_fault_count += (at_fault & new_contact).any(axis=1)
        off_track = out.off_track[0]
        if count_true(off_track):
            self.off_track_count += off_track & (self.off_time <= self.dt)
        dnf = out.dnf[0]
        if np.count_nonzero(dnf):
            for i in np.flatnonzero(dnf):
                self.dnf_reason[i] = DNF_REASONS[int(dnf[i])]
        terms = {k: v[0] for k, v in out.terms.items()}
        nominal = self._rewards(frame, terms, out)
        rewards = nominal if self._unc is None else self._perturbed(frame, terms, out, nominal)
        result_obs: dict[str, Obs] = {}
        result_rew: dict[str, float] = {}
        result_term: dict[str, bool] = {}
        result_trunc: dict[str, bool] = {}
        infos: dict[str, dict[str, Any]] = {}
        reward_list = rewards.tolist()
        term_list, trunc_list = out.terminated[0].tolist(), out.truncated[0].tolist()
        off_list, wall_list = off_track.tolist(), out.wall[0].tolist()
        term_lists = {name: v.tolist() for name, v in terms.items()}
        contact, closing = out.contact[0], out.closing[0]
        touching: list[bool] = (
            contact.any(axis=1).tolist() if count_true(contact) else [False] * len(contact)
        )
        cars = self._car_lists(frame)
        for agent in racing:
            if agent.startswith(NATURE_PREFIX):
                continue
            k = self.agent_index[agent]
            result_obs[agent] = frame.obs[k]
            result_rew[agent] = reward_list[k]
            result_term[agent] = term_list[k]
            result_trunc[agent] = trunc_list[k]
            events = [
                {
                    "with": self.possible_agents[j],
                    "at_fault": bool(at_fault[k, j]),
                    "closing_speed": float(closing[k, j]),
                    "new": bool(new_contact[k, j]),
                }
                for j in (np.flatnonzero(contact[k]) if touching[k] else ())
            ]
            infos[agent] = self._info(
                k,
                cars,
                events,
                off_list[k],
                wall_list[k],
                {name: values[k] for name, values in term_lists.items()},
            )
        if self._unc is not None:
            self._add_uncertainty(result_obs, result_rew, infos, nominal, rewards, racing)
            for nat in self.natures:
                if nat in racing:
                    k = self.agent_index[nat]
                    result_term[nat] = term_list[k]
                    result_trunc[nat] = trunc_list[k]
        done = out.terminated[0] | out.truncated[0]
        if count_true(done):
            for i in np.flatnonzero(done):
                self._pipeline_park(int(i))
        if not self.park_finished:
            self.agents = [a for a in self.agents if not done[self.agent_index[a]]]
            return result_obs, result_rew, result_term, result_trunc, infos
        return self._parked_step(
            racing, done, result_obs, result_rew, result_term, result_trunc, infos
        )

    def _parked_step(
        self,
        racing: list[str],
        done: NDArray[np.bool_],
        obs: dict[str, Obs],
        rew: dict[str, float],
        term: dict[str, bool],
        trunc: dict[str, bool],
        infos: dict[str, dict[str, Any]],
    ) -> tuple[
        dict[str, Obs],
        dict[str, float],
        dict[str, bool],
        dict[str, bool],
        dict[str, dict[str, Any]],
    ]:
        """``park_finished``: parked agents stay, with their last observation, reward 0.0 and
        their final flags; the episode ends (``agents`` empty) once every car is done."""
        for agent in racing:
            self._last[agent] = (obs[agent], infos[agent])
            if done[self.agent_index[agent]]:
                self._done_flags[agent] = (term[agent], trunc[agent])
        for agent in self.agents:
            if agent in racing:
                continue
            last_obs, last_info = self._last[agent]
            obs[agent] = last_obs
            rew[agent] = 0.0
            term[agent], trunc[agent] = self._done_flags[agent]
            infos[agent] = dict(last_info)
        if len(self._done_flags) == len(self.possible_agents):
            self.agents = []
        # Dict order follows ``possible_agents`` (vector wrappers read the values in order).
        order = [a for a in self.possible_agents if a in obs]
        return (
            {a: obs[a] for a in order},
            {a: rew[a] for a in order},
            {a: term[a] for a in order},
            {a: trunc[a] for a in order},
            {a: infos[a] for a in order},
        )

    def retire(self, agent: str, reason: str) -> None:
        """Take ``agent`` out of the race now (DNF with ``reason``), e.g. its policy failed."""
        if agent not in self.agents or agent in self._done_flags:
            raise SimError(f"{agent} is not racing")
        i = self.agent_index[agent]
        self.dnf_reason[i] = reason
        self._ep.active[0, i] = False
        self._pipeline_park(i)
        leaving = [a for a in self.agents if self.agent_index[a] == i]
        if self.park_finished:
            for a in leaving:
                self._done_flags[a] = (True, False)
                last_obs, last_info = self._last[a]
                if not a.startswith(NATURE_PREFIX):
                    self._last[a] = (last_obs, {**last_info, "dnf_reason": reason})
            if len(self._done_flags) == len(self.possible_agents):
                self.agents = []
        else:
            self.agents = [a for a in self.agents if a not in leaving]

    # ---- rewards -------------------------------------------------------------------------------

    def _reward_key(self) -> str:
        return self.reward_mode if isinstance(self.reward_mode, str) else "function"

    def _rewards(
        self, frame: Frame, terms: dict[str, NDArray[np.float64]], out: Outcome
    ) -> NDArray[np.float64]:
        """(N,) nominal rewards; a DeepRacer function adds its value to ``terms``."""
        if self.reward_mode == "racing":
            return np.asarray(out.reward[0], dtype=np.float64)
        if self.reward_mode == "progress":
            return np.asarray(terms["progress"], dtype=np.float64)
        fn = self.reward_mode
        assert callable(fn)
        key = (self._track_key, self._reversed)
        if key not in self._deepracer:
            self._deepracer[key] = DeepRacerParams(self.track, self.race_distance)
        builder = self._deepracer[key]
        live = out.terminated[0] | out.truncated[0] | frame.episode.active[0]
        result = np.zeros(self.n_cars)
        crashed = out.contact[0].any(axis=1) | out.wall[0]
        for i in np.flatnonzero(live):
            params = builder.build(
                int(i),
                poses=frame.poses,
                speed=frame.v_long,
                steering=frame.steering,
                s=frame.episode.s[0],
                d=frame.d,
                segment=frame.segment,
                heading_error=frame.heading_error,
                race_progress=self.race_progress,
                all_wheels_on=out.all_wheels_on[0],
                off_track=out.off_track[0],
                crashed=crashed,
                present=live,
                steps=self.steps,
            )
            result[i] = float(fn(params))
        terms["deepracer"] = result
        return result

    # ---- model uncertainty ---------------------------------------------------------------------

    def _perturbed(
        self,
        frame: Frame,
        terms: dict[str, NDArray[np.float64]],
        out: Outcome,
        nominal: NDArray[np.float64],
    ) -> NDArray[np.float64]:
        """(N,) this step's rewards under the perturbation (the cars' and, negated, their
        natures'); 0.0 for a car that was out of the race before the step."""
        active_before = out.terminated[0] | out.truncated[0] | frame.episode.active[0]
        return np.where(
            active_before,
            perturbed_reward(self._pert.values[0], terms, self._reward_key(), nominal),
            0.0,
        )

    def _set_perturbation(self) -> None:
        self.perturbation = Perturbation(self._pert.values[0].copy())
        self._pipeline_perturb(self._pert.values[0])

    def _advance_perturbation(self, actions: dict[str, Any]) -> dict[str, Any]:
        """Update this step's perturbation (sampler or nature); returns the cars' actions."""
        cfg = self._unc
        assert cfg is not None
        nature = None
        acting = np.zeros((1, self.n_cars), dtype=bool)
        if self.natures:
            nature = np.zeros((1, self.n_cars, len(cfg.free)))
            for nat in self.natures:
                if nat in actions and nat in self.agents and nat not in self._done_flags:
                    i = self.agent_index[nat]
                    act = np.asarray(actions[nat], dtype=np.float64).reshape(-1)
                    if act.shape != (len(cfg.free),):
                        raise SimError(f"action for {nat} must have shape ({len(cfg.free)},)")
                    nature[0, i] = act
                    acting[0, i] = True
        before = self._pert.values[0].copy()
        self._pert.advance(self.np_random, self.steps, nature, acting)
        if not np.array_equal(before, self._pert.values[0]):
            self._set_perturbation()
        if not self.natures:
            return actions
        return {a: act for a, act in actions.items() if not a.startswith(NATURE_PREFIX)}

    def global_state(self) -> NDArray[np.float32]:
        """The global state, as :meth:`state` (kept for env 0.2 callers)."""
        return self.state()

    def state(self) -> NDArray[np.float32]:
        """PettingZoo's global state (``state_space``), float32, always available.

        Per car (10 each): x, y (relative to the track's centre, in half-extents), cos and
        sin of yaw, vx, vy (/ max speed), yaw rate (/ π), s (/ lap length), race progress
        (/ race distance), racing (1/0); with a non-nominal ``uncertainty``, then every
        car's free perturbation parameters mapped to [-1, 1]
        (:func:`arena.uncertainty.normalised`). Parked cars read zeros.
        """
        if self._frame is None:
            raise SimError("call reset() before state()")
        f = self._frame
        feats = global_state(
            f.poses,
            f.velocity,
            f.episode.s[0],
            f.episode.race_progress[0],
            f.episode.active[0],
            self.track,
            self.race_distance,
            self.params.max_speed,
        )
        parts = [feats.ravel()]
        if self._unc is not None:
            parts.append(normalised(self._unc, self._pert.raw[0]).ravel())
        return np.concatenate(parts).astype(np.float32)

    def _add_uncertainty(
        self,
        obs: dict[str, Obs],
        rewards: dict[str, float],
        infos: dict[str, dict[str, Any]],
        nominal: NDArray[np.float64],
        perturbed: NDArray[np.float64],
        agents: list[str] | None = None,
    ) -> None:
        """Infos of the cars, and everything of the nature agents, for the live agents."""
        nom, pert = nominal.tolist(), perturbed.tolist()
        live = self.agents if agents is None else agents
        for agent in live:
            k = self.agent_index[agent]
            extra = {
                "reward_nominal": nom[k],
                "reward_perturbed": pert[k],
                "perturbation": self.perturbation.car(k),
            }
            if agent.startswith(NATURE_PREFIX):
                infos[agent] = {"target": self.cars[k], **extra}
            else:
                infos[agent].update(extra)
        if not self.natures:
            return
        state = self.state()
        onehot = np.eye(self.n_cars, dtype=np.float32)
        for nat in self.natures:
            if nat in live:
                k = self.agent_index[nat]
                obs[nat] = np.concatenate([state, onehot[k]])
                rewards[nat] = -pert[k]  # exactly zero-sum with its car's perturbed reward

    # ---- infos ---------------------------------------------------------------------------------

    @staticmethod
    def _car_lists(frame: Frame) -> tuple[list[Any], ...]:
        """Race 0's laps, s, race progress, rank and speed as Python lists (N,): one
        conversion per quantity and step, not one numpy scalar per car."""
        ep = frame.episode
        return (
            ep.laps[0].tolist(),
            ep.s[0].tolist(),
            ep.race_progress[0].tolist(),
            ep.positions[0].tolist(),
            frame.v_long.tolist(),
        )

    def _info(
        self,
        i: int,
        cars: tuple[list[Any], ...],
        collisions: list[dict[str, Any]],
        off_track: bool,
        wall: bool,
        terms: dict[str, float],
    ) -> dict[str, Any]:
        laps, s, progress, rank, speed = cars
        done_laps = max(int(laps[i]), 0)
        info: dict[str, Any] = {
            "lap": min(done_laps + 1, self.laps),
            "laps_completed": done_laps,
            "lap_times": list(self.lap_times[i]),
            "s": float(s[i]),
            "race_progress": float(progress[i]),
            "rank": int(rank[i]),
            "collisions": collisions,
            "off_track": off_track,
            "wall_contact": wall,
            "speed": float(speed[i]),
            "reward_terms": terms,
        }
        if self.dnf_reason[i] is not None:
            info["dnf_reason"] = self.dnf_reason[i]
        return info


__all__ = [
    "IMAGE_SHAPE",
    "NATURE_PREFIX",
    "PARAM_NAMES",
    "ActionMode",
    "Frame",
    "Obs",
    "ObsMode",
    "RaceEpisodeEnv",
]
