"""The Slipstream racing environment, a PettingZoo ``ParallelEnv``."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray
from pettingzoo import ParallelEnv

from arena.actions import DiscreteActions
from arena.deepracer import DeepRacerParams, RewardFunction
from arena.lidar import DEFAULT_FOV, DEFAULT_RANGE, Lidar
from arena.observations import (
    EGO_FEATURES,
    EGO_HIGH,
    EGO_LOW,
    LOOKAHEAD,
    OPP_HIGH,
    OPP_LOW,
    OPPONENT_FEATURES,
    TRACK_LIMIT,
    ObservationLayout,
    ego_features,
    opponent_features,
    track_ahead_features,
    vector_observation,
    wrap_angle,
)
from arena.perception import jitter_image, jitter_lidar
from arena.render import TopDownRenderer
from arena.rewards import (
    RACING_TERMS,
    RewardWeights,
    collision_blame,
    race_positions,
    racing_terms,
)
from arena.sim import CarParams, SimError, SimState, Simulator
from arena.uncertainty import (
    LATENCY,
    MAX_LATENCY,
    PARAM_NAMES,
    REWARD_NOISE,
    Perturbation,
    UncertaintyConfig,
    UncertaintyError,
    applied,
    nature_values,
    nominal_values,
    normalised,
    reward_noise,
    sample_values,
)
from arena.walls import DEFAULT_RUNOFF, Walls
from tracks import LapCounter, Track, load_track

ObsMode = Literal["vector", "dict", "image"]
ActionMode = Literal["continuous", "discrete"]
IMAGE_SHAPE = (120, 160, 1)  # rows, columns, channels: DeepRacer's 160×120 grayscale camera
STUCK_DISTANCE = 0.5  # m of progress a car must make within ``stuck_time`` seconds
FLIP_UPRIGHT = 0.3  # z of the car's up axis below which it counts as flipped
CUT_JUMP = 3.0  # m: a larger jump in progress in one control step is a cut, not driving
STATE_FEATURES = 10  # per car in the global state: x, y, cos, sin, vx, vy, yaw rate, s, race, on
NATURE_PREFIX = "nature_"
# Perturbation columns that jitter camera images, and jitter_image's argument names.
JITTER_NAMES = ("brightness", "contrast", "hue", "noise_std", "shift", "shadow")
JITTER = [
    PARAM_NAMES.index(n)
    for n in ("brightness", "contrast", "hue", "image_noise", "shift", "shadow")
]
JITTER_NOMINAL = nominal_values()[JITTER]  # levels at which an image is left untouched
Obs = NDArray[np.float32] | NDArray[np.uint8] | dict[str, NDArray[np.float32]]


def default_max_cycles(race_distance: float, control_hz: int) -> int:
    """The default step limit: the time to cover ``race_distance`` m at 2.5 m/s, plus 5 s."""
    return math.ceil((5.0 + race_distance / 2.5) * control_hz)


class RacingEnv(ParallelEnv):
    """Several Ackermann cars racing on one track.

    ====================  ===========================================================
    Import                ``from arena import parallel_env`` (AEC: ``arena.env``)
    Agents                ``car_0 … car_{n-1}`` (1–16); + ``nature_car_i`` (adversarial)
    Action space          ``Box(-1, 1, (2,))`` [steer, throttle] or ``Discrete(5×2)``
    Observation space     ``Box((n_rays + 21 + 5k,), float32)``, ``Dict``, or image
    Version               ``ENV_VERSION`` (see Version History)
    ====================  ===========================================================

    **Action Space.** ``"continuous"``: ``[steer, throttle]`` in [-1, 1]²; steer is the
    fraction of full lock (0.42 rad, + turns left); positive throttle drives, negative
    brakes while rolling forward and then reverses. ``"discrete"``: a DeepRacer-style menu
    of ``n_steer × n_speed`` (steering, target speed) pairs, see :mod:`arena.actions`.

    **Observation Space.** ``"vector"`` (default): a flat float32 Box — lidar ranges
    (``lidar_rays`` over 270°, 10 m, normalised to [0, 1], cast against walls and the other
    cars), 7 ego features (speed, lateral speed, steering, yaw rate, heading error, lateral
    offset relative to the half-width, progress rate), the centre line at 1–10 m ahead as
    7 ``[dx, dy]`` points in the car's frame, and the ``k_opponents`` nearest cars as
    ``[present, dx, dy, dvx, dvy]`` in the car's frame; layout in
    :mod:`arena.observations`. ``"dict"``: the same, named (``lidar``, the ego feature
    names, ``track_ahead`` (7, 2), ``opponents`` (k, 5)). ``"image"``: a 160×120
    grayscale ego camera (uint8, (120, 160, 1)), rendered headless with pybullet's
    TinyRenderer — slower.

    **Rewards.** ``"racing"`` (default) = progress (metres along the centre line; negative
    backwards) − off-track (1/s) − wall contact (2/s) − collision (0.5 × closing speed in
    m/s, only for the car to blame: the one that drives into another from behind) +
    overtaking (1 per place gained, −1 per place lost). Worked number: at 5 m/s and 20 Hz a
    car gains 0.25 m per step, reward 0.25; rear-ending a car while closing at 2 m/s costs
    1.0 that step, the car hit pays nothing. ``"progress"``: progress only. Or any DeepRacer
    ``reward_function(params) -> float`` (params as in :mod:`arena.deepracer`). Every term
    is reported per car in ``infos[agent]["reward_terms"]``.

    **Starting State.** A staggered two-wide grid behind the start line, cars at rest.
    ``reset(seed, options)`` options: ``grid_order`` (list of car indices, pole first, or
    ``"random"``), ``start_offset`` (metres along the lap to move the grid, or ``"random"``)
    and ``direction`` (``"forward"``, ``"reverse"`` or ``"random"``; reverse drives the
    track the other way round).

    **Episode End.** A car *terminates* when it completes ``laps`` laps (validated by
    ordered checkpoints; a grid start counts lap 1 from the start signal, a mid-lap start
    counts from its first crossing of the line), when all four wheels stay off the road for
    more than ``off_track_limit`` seconds, when it flips, or when it makes less than 0.5 m of
    progress in ``stuck_time`` seconds. Everyone left is *truncated* after ``max_cycles``
    steps (default: the time to cover the race at 2.5 m/s, plus 5 s). Cars that are done
    leave ``agents`` and are lifted off the track; the episode ends when no agent is left.

    **Model Uncertainty.** ``uncertainty=`` takes an
    :class:`arena.uncertainty.UncertaintyConfig`: boxes ``[lo, hi]`` per car over the
    dynamics (friction, mass, motor and steering gains, steering offset, actuation latency in
    whole control steps — a per-car FIFO —, action noise), the perception (lidar noise and
    dropout; image brightness, contrast, hue, noise, shift, shadow), the reward (bounded
    noise of level λ, interval weights on the racing terms), and the episode (start offset,
    direction, track drawn from a set). Modes: ``"nominal"`` (the default: nothing changes,
    nothing is paid); ``"sample"`` (uniform draws per episode, per step or every k steps,
    independent per car, from the env's seeded generator); ``"fixed"`` (exactly the
    perturbation in ``reset(options={"perturbation": {name: value or [per car]}})``, else
    the config's); ``"adversarial"``: one more agent per car, ``nature_car_i``, whose
    ``Box(-1, 1, (k,))`` action chooses car i's perturbation inside the box (k = the
    parameters with ``lo < hi``, affine map, see :func:`arena.uncertainty.nature_values`),
    at the first step of the episode (then held) or every step with a rate limit. Nature
    observes the global state (:meth:`global_state`: every car's pose, velocity and progress and
    the current perturbations) followed by a one-hot of its car; its reward is exactly
    minus its car's perturbed reward, and it leaves with its car. Cars' observations never
    contain the perturbation. The cars receive the *perturbed* reward.

    **Infos** per car: ``lap`` (current lap, 1-based), ``laps_completed``, ``lap_times``
    (s), ``s`` (m along the lap), ``race_progress`` (m from the start line), ``rank``,
    ``collisions`` (list of ``{"with", "at_fault", "closing_speed", "new"}``; ``new`` marks
    the step a contact starts), ``off_track``,
    ``wall_contact``, ``reward_terms``, ``speed``, ``dnf_reason`` when a car stops early;
    with uncertainty also ``reward_nominal``, ``reward_perturbed`` and ``perturbation``
    (the car's parameters by name). Per nature agent: ``target`` and the same three.

    **Arguments.** ``track`` (built-in name, file path, ``random:<seed>`` or a ``Track``),
    ``n_cars`` (4), ``laps`` (1), ``control_hz`` (20), ``physics_hz`` (60), ``obs_mode``,
    ``action_mode``, ``lidar_rays`` (64), ``k_opponents`` (3), ``discrete_actions``
    ((5, 2)), ``reward``, ``reward_weights``, ``max_cycles``, ``render_mode``
    (None or ``"rgb_array"``: top-down image), ``off_track_limit`` (3 s), ``stuck_time``
    (4 s), ``runoff`` (0.4 m of run-off before the walls), ``car_params``,
    ``uncertainty`` (None: nominal).

    **Version History.**

    * 0.2: ``uncertainty`` (model-uncertainty sets, ``nature_car_i`` agents),
      ``global_state()``; infos ``reward_nominal``, ``reward_perturbed``, ``perturbation``;
      a mid-lap start's ``race_progress`` no longer counts the ``start_offset`` twice.
    * 0.1: first release.

    >>> env = RacingEnv(track="oval", n_cars=2)
    >>> obs, infos = env.reset(seed=0)
    >>> obs["car_0"].shape
    (100,)
    >>> env.close()
    """

    metadata = {  # noqa: RUF012 - PettingZoo reads this class attribute
        "name": "slipstream_racing_v0",
        "render_modes": ["rgb_array"],
        "is_parallelizable": True,
        "render_fps": 20,
    }

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
        runoff: float = DEFAULT_RUNOFF,
        car_params: CarParams | None = None,
        uncertainty: UncertaintyConfig | None = None,
    ) -> None:
        if obs_mode not in ("vector", "dict", "image"):
            raise SimError(f"obs_mode must be 'vector', 'dict' or 'image', got {obs_mode!r}")
        if action_mode not in ("continuous", "discrete"):
            raise SimError(f"action_mode must be 'continuous' or 'discrete', got {action_mode!r}")
        if render_mode not in (None, "rgb_array"):
            raise SimError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        if not (isinstance(reward, str) and reward in ("racing", "progress")) and not callable(
            reward
        ):
            raise SimError("reward must be 'racing', 'progress' or a reward_function(params)")
        if laps < 1:
            raise SimError(f"laps must be at least 1, got {laps}")
        if uncertainty is not None and not isinstance(uncertainty, UncertaintyConfig):
            raise UncertaintyError("uncertainty must be an arena.uncertainty.UncertaintyConfig")
        # Python ``if`` on this static config only: nominal costs nothing per step.
        self.uncertainty = uncertainty
        self._unc = (
            uncertainty if uncertainty is not None and uncertainty.mode != "nominal" else None
        )
        self.base_track = load_track(track)
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
        self.runoff = runoff
        self._sim_args: dict[str, Any] = {
            "params": car_params,
            "physics_hz": physics_hz,
            "control_hz": control_hz,
            "runoff": runoff,
            "visuals": obs_mode == "image",
        }
        self.sim = Simulator(self.base_track, n_cars, **self._sim_args)
        self._worlds: dict[str, tuple[Track, Simulator]] = {}
        self._track_key = track if isinstance(track, str) else self.base_track.name
        self.params = self.sim.params
        self.control_hz = control_hz
        self.dt = 1.0 / control_hz
        self.layout = ObservationLayout(lidar_rays, k_opponents)
        self._lookahead = np.asarray(LOOKAHEAD)
        self.discrete = DiscreteActions(*discrete_actions, top_speed=self.params.top_speed)
        self.race_distance = laps * self.base_track.length
        self.max_cycles = max_cycles or default_max_cycles(self.race_distance, control_hz)
        self.cars = [f"car_{i}" for i in range(n_cars)]
        adversarial = self._unc is not None and self._unc.mode == "adversarial"
        self.natures = [NATURE_PREFIX + a for a in self.cars] if adversarial else []
        self.possible_agents = self.cars + self.natures
        # A nature agent shares its car's index: it acts on, and leaves with, that car.
        self.agent_index = {a: i for i, a in enumerate(self.cars)}
        self.agent_index.update({a: i for i, a in enumerate(self.natures)})
        self.agents: list[str] = []
        self._views: dict[tuple[str, bool], tuple[Track, Walls, Lidar, DeepRacerParams | None]]
        self._views = {}
        self._observation_spaces = {a: self._make_obs_space() for a in self.cars}
        self._action_spaces = {a: self._make_action_space() for a in self.cars}
        if self._unc is not None:
            n_free = len(self._unc.free)
            self.state_space = spaces.Box(
                -np.inf, np.inf, (n_cars * (STATE_FEATURES + n_free),), dtype=np.float32
            )
            for a in self.natures:
                self._observation_spaces[a] = spaces.Box(
                    -np.inf, np.inf, (self.state_space.shape[0] + n_cars,), dtype=np.float32
                )
                self._action_spaces[a] = spaces.Box(-1.0, 1.0, (n_free,), dtype=np.float32)
            self.perturbation = Perturbation.nominal(n_cars)
            self._raw = self.perturbation.values.copy()  # nature's continuous choice
            self._episodes = 0
            self._fifo = np.zeros((MAX_LATENCY + 1, n_cars, 2))
        self.np_random = np.random.default_rng()
        self._renderer: TopDownRenderer | None = None
        self._reversed = False
        self.track = self.base_track

    # ---- spaces ---------------------------------------------------------------------------

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

    # ---- reset ----------------------------------------------------------------------------

    def _view(self, reverse: bool) -> tuple[Track, Walls, Lidar, DeepRacerParams | None]:
        """Track, walls, lidar and DeepRacer params for one direction (built once)."""
        key = (self._track_key, reverse)
        if key not in self._views:
            track = self.base_track.reversed() if reverse else self.base_track
            walls = Walls.around(track, self.runoff)
            lidar = Lidar(walls, self.layout.n_rays, DEFAULT_FOV, DEFAULT_RANGE)
            dr = DeepRacerParams(track, self.race_distance) if callable(self.reward_mode) else None
            self._views[key] = (track, walls, lidar, dr)
        return self._views[key]

    def _use_track(self, name: str) -> None:
        """Race on track ``name`` from now on (one simulator per track, built once)."""
        if name == self._track_key:
            return
        if not self._worlds:  # keep the constructor's world under its own key
            self._worlds[self._track_key] = (self.base_track, self.sim)
        if name not in self._worlds:
            track = load_track(name)
            self._worlds[name] = (track, Simulator(track, self.n_cars, **self._sim_args))
        self.base_track, self.sim = self._worlds[name]
        self._track_key = name
        self.race_distance = self.laps * self.base_track.length
        self.max_cycles = self._fixed_max_cycles or default_max_cycles(
            self.race_distance, self.control_hz
        )
        self._renderer = None

    def _episode_options(self, opts: dict[str, Any]) -> dict[str, Any]:
        """``opts`` with the config's episode randomisation filled in (explicit ones win)."""
        assert self._unc is not None
        ep = self._unc.episode
        k = self._episodes
        self._episodes += 1
        if ep.tracks:
            self._use_track(ep.tracks[int(self.np_random.integers(len(ep.tracks)))])
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

    def _reset_perturbation(self, opts: dict[str, Any]) -> None:
        """This episode's starting perturbation, applied to the simulator before reset."""
        cfg = self._unc
        assert cfg is not None
        n = self.n_cars
        given = opts.get("perturbation")
        if given is not None and cfg.mode != "fixed":
            raise UncertaintyError("reset option 'perturbation' needs uncertainty mode 'fixed'")
        if cfg.mode == "sample":
            values = sample_values(cfg, self.np_random, n)
        elif cfg.mode == "fixed":
            given = given if given is not None else cfg.perturbation
            if isinstance(given, Perturbation):
                values = Perturbation.from_mapping(
                    {name: given.values[:, k].tolist() for k, name in enumerate(PARAM_NAMES)}, n
                ).values
            else:
                values = Perturbation.from_mapping(given or {}, n).values
        else:  # adversarial: nominal, pulled into the box, until nature's first action
            values = np.tile(np.clip(nominal_values(), cfg.lows, cfg.highs), (n, 1))
        self._raw = values
        self.perturbation = Perturbation(applied(values))
        self.sim.set_scales(self.perturbation.scales())
        self._fifo[:] = 0.0

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, Obs], dict[str, dict[str, Any]]]:
        """Start a new race; see the class docstring for ``options``."""
        if seed is not None:
            self.np_random = np.random.default_rng(seed)
        opts = options or {}
        if self._unc is not None:
            opts = self._episode_options(opts)
            self._reset_perturbation(opts)
        n = self.n_cars
        direction = opts.get("direction", "forward")
        if direction == "random":
            direction = "reverse" if self.np_random.random() < 0.5 else "forward"
        if direction not in ("forward", "reverse"):
            raise SimError(f"direction must be forward, reverse or random, got {direction!r}")
        self._reversed = direction == "reverse"
        self.track, self.walls, self.lidar, self._deepracer = self._view(self._reversed)
        order = opts.get("grid_order")
        if order == "random":
            order = self.np_random.permutation(n)
        order = np.arange(n) if order is None else np.asarray(order, dtype=np.int64)
        if sorted(order.tolist()) != list(range(n)):
            raise SimError(f"grid_order must be a permutation of 0..{n - 1}")
        offset = opts.get("start_offset", 0.0)
        if offset == "random":
            offset = float(self.np_random.uniform(0.0, self.track.length))
        self._grid_start = float(offset) == 0.0
        slots = self.track.start_grid(n, offset=float(offset))
        poses = np.empty_like(slots)
        poses[order] = slots
        self.grid_order = order
        state = self.sim.reset(poses)

        proj = self.track.project(state.poses[:, :2])
        self._s = proj.s
        self._counter = LapCounter(self.track, proj.s, max_jump=CUT_JUMP)
        # Signed metres from the start line (the grid's offset is already in proj.s).
        self.race_progress = self.track.delta_s(proj.s, 0.0)
        self.active = np.ones(n, dtype=bool)
        self.finished = np.zeros(n, dtype=bool)
        self.finish_time = np.full(n, np.inf)
        self.line_time = np.zeros(n)
        self.lap_times: list[list[float]] = [[] for _ in range(n)]
        self.off_time = np.zeros(n)
        self.dnf_reason: list[str | None] = [None] * n
        self.collision_count = np.zeros(n, dtype=np.int64)
        self.at_fault_count = np.zeros(n, dtype=np.int64)
        self._contact = np.zeros((n, n), dtype=bool)
        self.off_track_count = np.zeros(n, dtype=np.int64)
        window = max(1, round(self.stuck_time * self.control_hz))
        self._progress_history = np.tile(self.race_progress, (window, 1))
        self.steps = 0
        self.agents = list(self.possible_agents)
        self.positions = race_positions(self.race_progress)
        self.state = state
        self._widths: tuple[NDArray[np.float64], NDArray[np.float64]] = self.track.widths_at(proj.s)
        obs = self._observations(state, proj.segment, proj.d, self._heading_error(state, proj))
        zero_terms = dict.fromkeys(RACING_TERMS, 0.0)
        infos = {a: self._info(i, [], False, False, zero_terms) for i, a in enumerate(self.cars)}
        observations = {a: obs[i] for i, a in enumerate(self.cars)}
        if self._unc is not None:
            zero = np.zeros(n)
            self._add_uncertainty(observations, {}, infos, zero, zero)
        return observations, infos

    # ---- step -----------------------------------------------------------------------------

    def _controls(self, actions: dict[str, Any]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Steering commands and throttles (n,) for every car; parked cars get zeros."""
        n = self.n_cars
        if self.action_mode == "discrete":
            idx = np.zeros(n, dtype=np.int64)
            for agent, act in actions.items():
                i = self.agent_index[agent]
                idx[i] = int(np.asarray(act).reshape(()))
            steer, throttle = self.discrete.to_controls(idx, self.state.v_long)
            return np.where(self.active, steer, 0.0), np.where(self.active, throttle, 0.0)
        cmd = np.zeros((n, 2))
        for agent, act in actions.items():
            a = np.asarray(act, dtype=np.float64).reshape(-1)
            if a.shape != (2,):
                raise SimError(f"action for {agent} must have shape (2,), got {a.shape}")
            cmd[self.agent_index[agent]] = a
        # NaN means "no input"; ±inf saturate. The env never lets a bad number into physics.
        cmd = np.clip(np.where(np.isnan(cmd), 0.0, cmd), -1.0, 1.0) * self.active[:, None]
        return cmd[:, 0], cmd[:, 1]

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
        if self._unc is not None:
            actions = self._perturb(actions)
            steer, throttle = self._actuate(*self._controls(actions))
        else:
            steer, throttle = self._controls(actions)
        state = self.sim.step(steer, throttle)
        self.steps += 1
        now = state.time
        track = self.track
        active = self.active

        proj = track.project(state.poses[:, :2])
        ds = track.delta_s(proj.s, self._s)
        cut = np.abs(ds) > CUT_JUMP
        progress = np.where(active & ~cut, ds, 0.0)
        self.race_progress = self.race_progress + progress
        self._s = proj.s

        laps_before = self._counter.laps.copy()
        lap_done = self._counter.update(proj.s) & active
        first_cross = (laps_before < 0) & (self._counter.laps == 0) & active
        if not self._grid_start:
            self.line_time = np.where(first_cross, now, self.line_time)
        for i in np.flatnonzero(lap_done):
            self.lap_times[i].append(now - float(self.line_time[i]))
            self.line_time[i] = now

        heading_error = self._heading_error(state, proj)
        self._widths = track.widths_at(proj.s)  # (left, right) m, for off-track and the obs
        off_track = self._off_track(proj.d, heading_error) & active
        self.off_time = np.where(off_track, self.off_time + self.dt, 0.0)
        self.off_track_count += (off_track & (self.off_time <= self.dt)).astype(np.int64)

        contact = state.car_contact & active[:, None] & active[None, :]
        if contact.any():
            # Blame from the state before the step: by its end the impact has already evened
            # out the two cars' speeds, so their closing speed would read about zero.
            at_fault, closing = collision_blame(self.state.poses, self.state.velocity, contact)
        else:  # the common case, and the same result without the work
            at_fault, closing = np.zeros_like(contact), np.zeros(contact.shape)
        # A collision counts once, when the contact starts: a long push is one incident.
        new_contact = contact & ~self._contact
        self._contact = contact
        self.collision_count += new_contact.any(axis=1)
        self.at_fault_count += (at_fault & new_contact).any(axis=1)

        newly_finished = active & (self._counter.laps_completed >= self.laps)
        self.finished |= newly_finished
        self.finish_time = np.where(newly_finished, now, self.finish_time)
        rank_key = np.where(self.finished, 1e12 - self.finish_time, self.race_progress)
        positions = race_positions(np.where(active | self.finished, rank_key, -1e12))
        gained = np.where(active, self.positions - positions, 0)
        self.positions = positions

        # Ring buffer of the last ``window`` race progresses; row ``steps % window`` is now.
        window = len(self._progress_history)
        self._progress_history[self.steps % window] = self.race_progress
        moved = self.race_progress - self._progress_history[(self.steps + 1) % window]
        warmed_up = self.steps >= window
        stuck = active & ~newly_finished & warmed_up & (moved < STUCK_DISTANCE)
        flipped = active & ~newly_finished & (state.upright < FLIP_UPRIGHT)
        lost = active & ~newly_finished & (self.off_time > self.off_track_limit)
        for i in np.flatnonzero(stuck | flipped | lost):
            self.dnf_reason[i] = "flipped" if flipped[i] else ("off_track" if lost[i] else "stuck")
        terminated = newly_finished | stuck | flipped | lost
        truncated = active & ~terminated & (self.steps >= self.max_cycles)
        for i in np.flatnonzero(truncated):
            self.dnf_reason[i] = "time_limit"

        terms = racing_terms(
            progress,
            off_track,
            state.wall_contact & active,
            at_fault,
            closing,
            gained,
            self.dt,
            self.weights,
        )
        obs = self._observations(state, proj.segment, proj.d, heading_error)
        rewards = self._rewards(terms, state, proj, heading_error, off_track, contact)
        nominal = rewards
        if self._unc is not None:
            rewards = self._perturbed_rewards(terms, rewards)

        result_obs: dict[str, Obs] = {}
        result_rew: dict[str, float] = {}
        result_term: dict[str, bool] = {}
        result_trunc: dict[str, bool] = {}
        infos: dict[str, dict[str, Any]] = {}
        self.state = state  # before the infos, which report this step's speed
        # Python scalars once for all cars: per-element numpy indexing is slow.
        reward_list, term_list, trunc_list = (
            rewards.tolist(),
            terminated.tolist(),
            truncated.tolist(),
        )
        off_list, wall_list = off_track.tolist(), state.wall_contact.tolist()
        term_lists = {name: v.tolist() for name, v in terms.items()}
        touching: list[bool] = np.any(contact, axis=1).tolist()
        for agent in self.agents:
            if agent.startswith(NATURE_PREFIX):
                continue
            k = self.agent_index[agent]
            result_obs[agent] = obs[k]
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
                events,
                off_list[k],
                wall_list[k],
                {name: values[k] for name, values in term_lists.items()},
            )
        if self._unc is not None:
            self._add_uncertainty(result_obs, result_rew, infos, nominal, rewards)
            for nat in self.natures:
                if nat in self.agents:
                    k = self.agent_index[nat]
                    result_term[nat] = term_list[k]
                    result_trunc[nat] = trunc_list[k]
        done = terminated | truncated
        for i in np.flatnonzero(done):
            self.active[i] = False
            self.sim.park(int(i))
        self.agents = [a for a in self.agents if not done[self.agent_index[a]]]
        return result_obs, result_rew, result_term, result_trunc, infos

    @property
    def laps_completed(self) -> NDArray[np.int64]:
        """(n_cars,) laps each car has completed in this episode."""
        return self._counter.laps_completed

    def retire(self, agent: str, reason: str) -> None:
        """Take ``agent`` out of the race now (DNF with ``reason``), e.g. its policy failed."""
        if agent not in self.agents:
            raise SimError(f"{agent} is not racing")
        i = self.agent_index[agent]
        self.dnf_reason[i] = reason
        self.active[i] = False
        self.sim.park(i)
        self.agents = [a for a in self.agents if self.agent_index[a] != i]

    # ---- model uncertainty ----------------------------------------------------------------

    def _perturb(self, actions: dict[str, Any]) -> dict[str, Any]:
        """Update this step's perturbation (sampler or nature); returns the cars' actions."""
        cfg = self._unc
        assert cfg is not None
        n, rng, t = self.n_cars, self.np_random, self.steps
        changed = False
        if cfg.mode == "sample":
            if t > 0 and (
                cfg.resample == "step" or (cfg.resample == "every_k" and t % cfg.every_k == 0)
            ):
                self._raw = sample_values(cfg, rng, n)
                changed = True
            else:  # the reward noise is noise: a new draw every step
                self._raw[:, REWARD_NOISE] = reward_noise(cfg, rng, n)
        elif cfg.mode == "adversarial" and (t == 0 or cfg.nature_acts == "step"):
            rate = cfg.nature_rate if t > 0 else None  # the episode-start choice is free
            for nat in self.natures:
                if nat in actions and nat in self.agents:
                    i = self.agent_index[nat]
                    act = np.asarray(actions[nat], dtype=np.float64).reshape(-1)
                    if act.shape != (len(cfg.free),):
                        raise SimError(f"action for {nat} must have shape ({len(cfg.free)},)")
                    self._raw[i : i + 1] = nature_values(cfg, act, self._raw[i : i + 1], rate)
                    changed = True
        if changed or cfg.mode == "sample":
            old_scales = self.perturbation.values[:, :LATENCY]
            self.perturbation = Perturbation(applied(self._raw))
            if not np.array_equal(old_scales, self.perturbation.values[:, :LATENCY]):
                self.sim.set_scales(self.perturbation.scales())
        if not self.natures:
            return actions
        return {a: act for a, act in actions.items() if not a.startswith(NATURE_PREFIX)}

    def _actuate(
        self, steer: NDArray[np.float64], throttle: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Commands (n,) through each car's latency FIFO, plus its action noise.

        The command applied at step t is the one given at ``t − k`` (k = the car's latency,
        whole steps); during the first k steps of an episode it is zero (no input).
        """
        n = self.n_cars
        fifo = self._fifo
        fifo[self.steps % len(fifo)] = np.stack([steer, throttle], axis=1)
        lag = self.perturbation.column("latency").astype(np.int64)
        cmd = fifo[(self.steps - lag) % len(fifo), np.arange(n)]
        amp = self.perturbation.column("action_noise")
        cmd = cmd + self.np_random.uniform(-1.0, 1.0, (n, 2)) * amp[:, None]
        cmd = np.clip(cmd, -1.0, 1.0) * self.active[:, None]
        return cmd[:, 0], cmd[:, 1]

    def _perturbed_rewards(
        self, terms: dict[str, NDArray[np.float64]], nominal: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """(n,) rewards under the reward perturbation: weighted terms plus the noise δ."""
        pert = self.perturbation
        weights = pert.weights()
        if self.reward_mode == "racing":
            base = np.sum(weights * np.stack([terms[k] for k in RACING_TERMS], axis=1), axis=1)
        elif self.reward_mode == "progress":
            base = weights[:, 0] * terms["progress"]
        else:  # a DeepRacer reward function: additive noise only
            base = nominal
        return np.where(self.active, base + pert.column("reward_noise"), 0.0)

    def global_state(self) -> NDArray[np.float32]:
        """The global state (``state_space``; needs ``uncertainty``), float32.

        Per car (10 each): x, y (relative to the track's centre, in half-extents), cos and
        sin of yaw, vx, vy (/ max speed), yaw rate (/ π), s (/ lap length), race progress
        (/ race distance), racing (1/0); then every car's free perturbation parameters
        mapped to [-1, 1] (:func:`arena.uncertainty.normalised`). Parked cars read zeros.
        """
        if self._unc is None:
            raise SimError("global_state() needs an uncertainty config (it holds the perturbation)")
        st = self.state
        xmin, ymin, xmax, ymax = self.track.bounds
        centre = np.array([0.5 * (xmin + xmax), 0.5 * (ymin + ymax)])
        half = max(0.5 * (xmax - xmin), 0.5 * (ymax - ymin), 1.0)
        vmax = self.params.max_speed
        feats = np.column_stack(
            [
                (st.poses[:, :2] - centre) / half,
                np.cos(st.poses[:, 2]),
                np.sin(st.poses[:, 2]),
                st.velocity[:, :2] / vmax,
                st.velocity[:, 2] / np.pi,
                self._s / self.track.length,
                self.race_progress / self.race_distance,
                np.ones(self.n_cars),
            ]
        )
        feats = np.where(self.active[:, None], feats, 0.0)
        xi = normalised(self._unc, self._raw)
        return np.concatenate([feats.ravel(), xi.ravel()]).astype(np.float32)

    def _add_uncertainty(
        self,
        obs: dict[str, Obs],
        rewards: dict[str, float],
        infos: dict[str, dict[str, Any]],
        nominal: NDArray[np.float64],
        perturbed: NDArray[np.float64],
    ) -> None:
        """Infos of the cars, and everything of the nature agents, for the live agents."""
        nom, pert = nominal.tolist(), perturbed.tolist()
        for agent in self.agents:
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
        state = self.global_state()
        onehot = np.eye(self.n_cars, dtype=np.float32)
        for nat in self.natures:
            if nat in self.agents:
                k = self.agent_index[nat]
                obs[nat] = np.concatenate([state, onehot[k]])
                rewards[nat] = -pert[k]  # exactly zero-sum with its car's perturbed reward

    def _jitter_images(self, images: list[NDArray[np.uint8]]) -> list[Obs]:
        """Each car's camera image with its perception perturbation (untouched if nominal)."""
        out: list[Obs] = []
        for i, img in enumerate(images):
            levels = self.perturbation.values[i, JITTER]
            if np.array_equal(levels, JITTER_NOMINAL):
                out.append(img)
                continue
            named = dict(zip(JITTER_NAMES, levels.tolist(), strict=True))
            out.append(jitter_image(img, rng=self.np_random, **named))
        return out

    # ---- pieces ---------------------------------------------------------------------------

    def _heading_error(self, state: SimState, proj: Any) -> NDArray[np.float64]:
        return wrap_angle(state.poses[:, 2] - proj.heading)

    def _off_track(
        self, d: NDArray[np.float64], heading_error: NDArray[np.float64]
    ) -> NDArray[np.bool_]:
        """True where all four wheels are off the road (DeepRacer's off-track rule).

        The road's half-widths at the cars are ``self._widths``, set once per step.
        """
        p = self.params
        wx = np.array([0.5, 0.5, -0.5, -0.5]) * p.wheelbase
        wy = np.array([0.5, -0.5, 0.5, -0.5]) * p.track_width
        sin, cos = np.sin(heading_error)[:, None], np.cos(heading_error)[:, None]
        wheel_d = d[:, None] + wx * sin + wy * cos  # lateral offset of each wheel, m
        left, right = self._widths
        on = (wheel_d <= left[:, None]) & (wheel_d >= -right[:, None])
        self._all_wheels_on: NDArray[np.bool_] = np.all(on, axis=1)
        return np.logical_not(np.any(on, axis=1))

    def _observations(
        self,
        state: SimState,
        segment: NDArray[np.int64],
        d: NDArray[np.float64],
        heading_error: NDArray[np.float64],
    ) -> list[Obs]:
        if self.obs_mode == "image":
            images = [
                self.sim.camera(i, IMAGE_SHAPE[1], IMAGE_SHAPE[0]) for i in range(self.n_cars)
            ]
            if self._unc is not None:
                return self._jitter_images(images)
            return list[Obs](images)
        p = self.params
        corners = self.sim.corners(state.poses)
        ranges = self.lidar.scan(state.poses, segment, corners) / self.lidar.max_range
        if self._unc is not None:
            noise = self.perturbation.column("lidar_noise")
            dropout = self.perturbation.column("lidar_dropout")
            if noise.any() or dropout.any():
                ranges = jitter_lidar(ranges, noise, dropout, self.np_random).astype(np.float64)
        left, right = self._widths
        # Progress rate: speed along the centre line, from the velocity and heading error.
        speed = np.hypot(state.velocity[:, 0], state.velocity[:, 1])
        course = np.arctan2(state.velocity[:, 1], state.velocity[:, 0])
        along = speed * np.cos(course - (state.poses[:, 2] - heading_error))
        ego = ego_features(
            state.v_long,
            state.v_lat,
            state.steering,
            state.velocity[:, 2],
            heading_error,
            d,
            left,
            right,
            along,
            p.max_speed,
            p.max_steer,
        )
        opp = opponent_features(
            state.poses,
            state.velocity,
            self.active,
            self.layout.k_opponents,
            self.lidar.max_range,
            p.max_speed,
        )
        ahead_s = (self._s[:, None] + self._lookahead).ravel()
        points = self.track.to_cartesian(np.stack([ahead_s, np.zeros_like(ahead_s)], axis=1))
        ahead = track_ahead_features(
            state.poses, points.reshape(self.n_cars, -1, 2), self.lidar.max_range
        )
        flat = vector_observation(ranges, ego, ahead, opp, self.layout)
        if self.obs_mode == "vector":
            return list(flat)
        out: list[Obs] = []
        for row in flat:
            named = {"lidar": row[self.layout.lidar]}
            ego_row = row[self.layout.ego]
            for k, name in enumerate(EGO_FEATURES):
                named[name] = ego_row[k : k + 1]
            named["track_ahead"] = row[self.layout.track_ahead].reshape(len(LOOKAHEAD), 2)
            named["opponents"] = row[self.layout.opponents].reshape(
                self.layout.k_opponents, len(OPPONENT_FEATURES)
            )
            out.append(named)
        return out

    def _rewards(
        self,
        terms: dict[str, NDArray[np.float64]],
        state: SimState,
        proj: Any,
        heading_error: NDArray[np.float64],
        off_track: NDArray[np.bool_],
        contact: NDArray[np.bool_],
    ) -> NDArray[np.float64]:
        if self.reward_mode == "racing":
            return np.sum(list(terms.values()), axis=0)
        if self.reward_mode == "progress":
            return terms["progress"]
        fn: Callable[[dict[str, Any]], float] = self.reward_mode  # type: ignore[assignment]
        assert self._deepracer is not None
        out = np.zeros(self.n_cars)
        for i in np.flatnonzero(self.active):
            params = self._deepracer.build(
                int(i),
                poses=state.poses,
                speed=state.v_long,
                steering=state.steering,
                s=proj.s,
                d=proj.d,
                segment=proj.segment,
                heading_error=heading_error,
                race_progress=self.race_progress,
                all_wheels_on=self._all_wheels_on,
                off_track=off_track,
                crashed=contact.any(axis=1) | state.wall_contact,
                present=self.active,
                steps=self.steps,
            )
            out[i] = float(fn(params))
        terms["deepracer"] = out
        return out

    def _info(
        self,
        i: int,
        collisions: list[dict[str, Any]],
        off_track: bool,
        wall: bool,
        terms: dict[str, float],
    ) -> dict[str, Any]:
        done_laps = int(self._counter.laps_completed[i])
        info: dict[str, Any] = {
            "lap": min(done_laps + 1, self.laps),
            "laps_completed": done_laps,
            "lap_times": list(self.lap_times[i]),
            "s": float(self._s[i]),
            "race_progress": float(self.race_progress[i]),
            "rank": int(self.positions[i]),
            "collisions": collisions,
            "off_track": off_track,
            "wall_contact": wall,
            "speed": float(self.state.v_long[i]),
            "reward_terms": terms,
        }
        if self.dnf_reason[i] is not None:
            info["dnf_reason"] = self.dnf_reason[i]
        return info

    # ---- rendering ------------------------------------------------------------------------

    def render(self) -> NDArray[np.uint8] | None:
        """A top-down RGB image (H, W, 3) of the track and the cars still racing."""
        if self.render_mode is None:
            return None
        if self._renderer is None:
            self._renderer = TopDownRenderer(
                self.base_track, Walls.around(self.base_track, self.runoff)
            )
        return self._renderer.render(self.sim.corners(self.state.poses), self.active)

    def close(self) -> None:
        """Release the physics client."""
        self.sim.close()
