"""The Slipstream racing environment on pybullet, a PettingZoo ``ParallelEnv``.

The episode rules live in :mod:`arena.core` and the PettingZoo side in
:mod:`arena.episode`; this module is the pybullet *pipeline*: it builds the world, moves the
cars, projects them onto the track, casts the lidar and renders.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from arena.batch.xp import get_ops
from arena.core import (
    CUT_JUMP,
    FLIP_UPRIGHT,
    STATE_FEATURES,
    STUCK_DISTANCE,
    EpisodeRules,
    EpisodeState,
    Sensed,
    default_max_cycles,
    episode_start,
    episode_step,
)
from arena.episode import (
    IMAGE_SHAPE,
    NATURE_PREFIX,
    ActionMode,
    Frame,
    Obs,
    ObsMode,
    RaceEpisodeEnv,
)
from arena.lidar import DEFAULT_FOV, DEFAULT_RANGE, Lidar
from arena.observations import (
    EGO_FEATURES,
    LOOKAHEAD,
    OPPONENT_FEATURES,
    ego_features,
    opponent_features,
    track_ahead_features,
    vector_observation,
    with_context,
    wrap_angle,
)
from arena.perception import jitter_image, jitter_lidar
from arena.render import TopDownRenderer
from arena.sim import SimState, Simulator
from arena.uncertainty import (
    MAX_LATENCY,
    PARAM_NAMES,
    Perturbation,
    nominal_values,
    perturbation_context,
)
from arena.walls import DEFAULT_RUNOFF, Walls
from tracks import Track, load_track

NUMPY = get_ops("numpy")
# Perturbation columns that jitter camera images, and jitter_image's argument names.
JITTER_NAMES = ("brightness", "contrast", "hue", "noise_std", "shift", "shadow")
JITTER = [
    PARAM_NAMES.index(n)
    for n in ("brightness", "contrast", "hue", "image_noise", "shift", "shadow")
]
JITTER_NOMINAL = nominal_values()[JITTER]  # levels at which an image is left untouched
LIDAR_NOISE, LIDAR_DROPOUT = PARAM_NAMES.index("lidar_noise"), PARAM_NAMES.index("lidar_dropout")
LATENCY_COL, NOISE_COL = PARAM_NAMES.index("latency"), PARAM_NAMES.index("action_noise")


class RacingEnv(RaceEpisodeEnv):
    """Several Ackermann cars racing on one track.

    ====================  ===========================================================
    Import                ``from arena import parallel_env`` (AEC: ``arena.env``)
    Agents                ``car_0 … car_{n-1}`` (1–16); + ``nature_car_i`` (adversarial)
    State                 ``state()``: ``Box((n · (10 + k),), float32)`` (``state_space``)
    Backends              ``"pybullet"`` (this class) or ``"batch"`` (same rules, B races)
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
    names, ``track_ahead`` (7, 2), ``opponents`` (k, 5)). With ``observe_perturbation=True``
    both end with the car's own model-uncertainty values (9 floats, ``perturbation``: 0 for
    the nominal car, fixed scales, :data:`arena.uncertainty.CONTEXT_FEATURES`) — a
    perturbation-aware observation, on either backend. ``"image"``: a 160×120
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
    steps (default: the time to cover the race at 2.5 m/s, plus 5 s; DNF reason
    ``"time_limit"``). Cars that are done leave ``agents`` and are lifted off the track; the
    episode ends when no agent is left. With ``park_finished=True`` a car that is done stays
    in ``agents`` until the episode ends: every later step reports its last observation,
    reward 0.0 and its final flags (``terminated=True`` for a finished or retired car), and
    its actions are ignored; once every car is done ``agents`` becomes ``[]``. This is what
    SuperSuit's ``pettingzoo_env_to_vec_env_v1`` needs; PettingZoo's ``parallel_api_test``
    forbids it by definition (an agent that reported ``terminated`` may not stay in
    ``agents``), so that test runs with the default.

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
    observes the global state (:meth:`state`: every car's pose, velocity and progress and
    the current perturbations) followed by a one-hot of its car; its reward is exactly
    minus its car's perturbed reward, and it leaves with its car. Cars' observations never
    contain the perturbation. The cars receive the *perturbed* reward.

    **State.** ``state()`` (PettingZoo's global state, always available, both backends):
    per car x, y (from the track's centre, in half-extents), cos and sin of yaw, vx, vy
    (/ max speed), yaw rate (/ π), s (/ lap length), race progress (/ race distance),
    racing (1/0) — parked cars read zeros —, then with a non-nominal ``uncertainty`` every
    car's free perturbation parameters in [-1, 1]. The simulator's own per-car arrays are
    ``sim_state`` (a :class:`arena.sim.SimState`).

    **Copies.** ``copy.deepcopy`` and pickling (cloudpickle, multiprocessing "spawn") give
    an env with its own pybullet client and the same state: the copy rebuilds the world
    and restores every body's pose, velocity and mass, so copies never share physics.

    **Infos** per car: ``lap`` (current lap, 1-based), ``laps_completed``, ``lap_times``
    (s), ``s`` (m along the lap), ``race_progress`` (m from the start line), ``rank``,
    ``collisions`` (list of ``{"with", "at_fault", "closing_speed", "new"}``; ``new`` marks
    the step a contact starts), ``off_track``,
    ``wall_contact``, ``reward_terms``, ``speed``, ``dnf_reason`` when a car stops early
    (``"off_track"``, ``"stuck"``, ``"flipped"``, ``"crashed"``, ``"time_limit"``, or the
    reason given to :meth:`retire`);
    with uncertainty also ``reward_nominal``, ``reward_perturbed`` and ``perturbation``
    (the car's parameters by name). Per nature agent: ``target`` and the same three.

    **Arguments.** ``track`` (built-in name, file path, ``random:<seed>`` or a ``Track``),
    ``n_cars`` (4), ``laps`` (1), ``control_hz`` (20), ``physics_hz`` (60), ``obs_mode``,
    ``action_mode``, ``lidar_rays`` (64), ``k_opponents`` (3), ``discrete_actions``
    ((5, 2)), ``reward``, ``reward_weights``, ``max_cycles``, ``render_mode``
    (None or ``"rgb_array"``: top-down image), ``off_track_limit`` (3 s), ``stuck_time``
    (4 s), ``runoff`` (0.4 m of run-off before the walls), ``car`` (a preset name of
    :mod:`arena.cars`: ``"f1tenth"`` (default) or ``"deepracer"``, or a ``CarParams``;
    ``car_params`` is the older spelling of the same), ``uncertainty`` (None: nominal),
    ``park_finished`` (False), ``preset`` (None or ``"deepracer"``: the DeepRacer car at
    15 Hz, a car's episode ends the step it leaves the road or hits anything — DNF
    ``"off_track"`` / ``"crashed"``), ``action_table`` (a DeepRacer ``model_metadata.json``
    path or :class:`arena.deepracer.ActionTable`: its discrete menu as the action space),
    ``observe_perturbation`` (False: see Observation Space).

    **Version History.**

    * 0.3: one episode core over both backends (:mod:`arena.core`, :mod:`arena.episode`):
      the same rules, names and numbers on ``"pybullet"`` and ``"batch"`` (the step-limit
      DNF is ``"time_limit"`` on both; a mid-lap start's ``race_progress`` counts from the
      start line on both); ``state()`` and ``state_space`` always (the SimState attribute is
      now ``sim_state``); ``park_finished``; ``car=`` presets; ``preset="deepracer"`` and
      ``action_table``; copies own their simulator; ``observe_perturbation`` (off by
      default, and the default observations are unchanged by it).
      Observations, actions and rewards mean what they meant in 0.2.

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
        runoff: float = DEFAULT_RUNOFF,
        **kwargs: Any,
    ) -> None:
        """Arguments: see the class docstring (the episode's are :class:`RaceEpisodeEnv`'s)."""
        super().__init__(track, n_cars, laps, **kwargs)
        self.runoff = runoff
        self._sim_args: dict[str, Any] = {
            "params": self.params,
            "physics_hz": self.physics_hz,
            "control_hz": self.control_hz,
            "runoff": runoff,
            "visuals": self.obs_mode == "image",
        }
        self.sim = Simulator(self.base_track, n_cars, **self._sim_args)
        self._worlds: dict[str, tuple[Track, Simulator]] = {}
        self._views: dict[tuple[str, bool], tuple[Track, Walls, Lidar, EpisodeRules]] = {}
        self._lookahead = np.asarray(LOOKAHEAD)
        self._renderer: TopDownRenderer | None = None
        self._values = Perturbation.nominal(n_cars).values
        self._context = perturbation_context(self._values)  # the observation's block (N, 9)
        self._fifo = np.zeros((MAX_LATENCY + 1, n_cars, 2))

    # ---- the pybullet pipeline -------------------------------------------------------------

    def _pipeline_view(self, reverse: bool) -> Track:
        """Track, walls, lidar and rules for one direction (built once)."""
        key = (self._track_key, reverse)
        if key not in self._views:
            track = self.base_track.reversed() if reverse else self.base_track
            walls = Walls.around(track, self.runoff)
            lidar = Lidar(walls, self.layout.n_rays, DEFAULT_FOV, DEFAULT_RANGE)
            rules = EpisodeRules.build(
                track,
                NUMPY,
                n_cars=self.n_cars,
                laps=self.laps,
                control_hz=self.control_hz,
                params=self.params,
                max_cycles=self.max_cycles,
                off_track_limit=self.off_track_limit,
                stuck_time=self.stuck_time,
                weights=self.weights,
                end_on_crash=self.end_on_crash,
            )
            self._views[key] = (track, walls, lidar, rules)
        track, self.walls, self.lidar, self._rules = self._views[key]
        return track

    def _pipeline_use_track(self, name: str) -> None:
        """Race on track ``name`` from now on (one simulator per track, built once)."""
        if not self._worlds:  # keep the constructor's world under its own key
            self._worlds[self._track_key] = (self.base_track, self.sim)
        if name not in self._worlds:
            track = load_track(name)
            self._worlds[name] = (track, Simulator(track, self.n_cars, **self._sim_args))
        self.sim = self._worlds[name][1]
        self._renderer = None

    def _pipeline_perturb(self, values: NDArray[np.float64]) -> None:
        old = self._values
        self._values = values.copy()
        self._context = perturbation_context(self._values)
        if not np.array_equal(old[:, :LATENCY_COL], values[:, :LATENCY_COL]):
            self.sim.set_scales(Perturbation(self._values).scales())

    def _pipeline_park(self, i: int) -> None:
        self.sim.park(i)

    def _pipeline_reset(self, order: NDArray[np.int64], offset: float) -> Frame:
        n = self.n_cars
        slots = self.track.start_grid(n, offset=offset)
        poses = np.empty_like(slots)
        poses[order] = slots
        state = self.sim.reset(poses)
        self._fifo[:] = 0.0
        proj = self.track.project(state.poses[:, :2])
        episode = episode_start(
            NUMPY, self._rules, proj.s[None], np.array([offset]), np.array([offset == 0.0])
        )
        return self._frame_of(state, proj, episode, None, episode.active[0])

    def _pipeline_step(self, steer: NDArray[np.float64], throttle: NDArray[np.float64]) -> Frame:
        episode = self._ep
        active = episode.active[0]
        if self._unc is not None:
            steer, throttle = self._actuate(steer, throttle, active)
        prev = self.sim_state
        state = self.sim.step(steer, throttle)
        proj = self.track.project(state.poses[:, :2])
        left, right = self.track.widths_at(proj.s)
        rules = self._rules
        if rules.max_cycles != self.max_cycles:  # a caller changed env.max_cycles
            rules = self._rules = EpisodeRules(**{**rules.__dict__, "max_cycles": self.max_cycles})
        sensed = Sensed(
            s=proj.s[None],
            d=proj.d[None],
            heading=proj.heading[None],
            yaw=state.poses[None, :, 2],
            left=left[None],
            right=right[None],
            wall=state.wall_contact[None],
            touching=state.car_contact[None],
            upright=state.upright[None],
            prev_poses=prev.poses[None],
            prev_velocity=prev.velocity[None, :, :2],
        )
        new, outcome = episode_step(NUMPY, rules, episode, sensed)
        # Observations see the cars that were racing during the step.
        return self._frame_of(state, proj, new, outcome, active, (left, right))

    def _frame_of(
        self,
        state: SimState,
        proj: Any,
        episode: EpisodeState,
        outcome: Any,
        active: NDArray[np.bool_],
        widths: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
    ) -> Frame:
        self.sim_state = state
        heading_error = wrap_angle(state.poses[:, 2] - proj.heading)
        if widths is None:
            widths = self.track.widths_at(proj.s)
        obs = self._observations(state, proj, heading_error, active, widths)
        return Frame(
            episode=episode,
            outcome=outcome,
            poses=state.poses,
            velocity=state.velocity,
            v_long=state.v_long,
            steering=state.steering,
            d=proj.d,
            segment=proj.segment,
            heading_error=heading_error,
            obs=obs,
            time=state.time,
        )

    def _actuate(
        self, steer: NDArray[np.float64], throttle: NDArray[np.float64], active: NDArray[np.bool_]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Commands (N,) through each car's latency FIFO, plus its action noise.

        The command applied at step t is the one given at ``t − k`` (k = the car's latency,
        whole steps); during the first k steps of an episode it is zero (no input).
        """
        n, fifo, t = self.n_cars, self._fifo, self.steps
        fifo[t % len(fifo)] = np.stack([steer, throttle], axis=1)
        lag = self._values[:, LATENCY_COL].astype(np.int64)
        cmd = fifo[(t - lag) % len(fifo), np.arange(n)]
        amp = self._values[:, NOISE_COL]
        cmd = cmd + self.np_random.uniform(-1.0, 1.0, (n, 2)) * amp[:, None]
        cmd = np.clip(cmd, -1.0, 1.0) * active[:, None]
        return cmd[:, 0], cmd[:, 1]

    def _jitter_images(self, images: list[NDArray[np.uint8]]) -> list[Obs]:
        """Each car's camera image with its perception perturbation (untouched if nominal)."""
        out: list[Obs] = []
        for i, img in enumerate(images):
            levels = self._values[i, JITTER]
            if np.array_equal(levels, JITTER_NOMINAL):
                out.append(img)
                continue
            named = dict(zip(JITTER_NAMES, levels.tolist(), strict=True))
            out.append(jitter_image(img, rng=self.np_random, **named))
        return out

    def _observations(
        self,
        state: SimState,
        proj: Any,
        heading_error: NDArray[np.float64],
        active: NDArray[np.bool_],
        widths: tuple[NDArray[np.float64], NDArray[np.float64]],
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
        ranges = self.lidar.scan(state.poses, proj.segment, corners) / self.lidar.max_range
        if self._unc is not None:
            noise, dropout = self._values[:, LIDAR_NOISE], self._values[:, LIDAR_DROPOUT]
            if noise.any() or dropout.any():
                ranges = jitter_lidar(ranges, noise, dropout, self.np_random).astype(np.float64)
        left, right = widths
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
            proj.d,
            left,
            right,
            along,
            p.max_speed,
            p.max_steer,
        )
        opp = opponent_features(
            state.poses,
            state.velocity,
            active,
            self.layout.k_opponents,
            self.lidar.max_range,
            p.max_speed,
        )
        frenet = np.zeros((self.n_cars * len(LOOKAHEAD), 2))  # [s, d = 0] of each point
        frenet[:, 0] = (proj.s[:, None] + self._lookahead).ravel()
        points = self.track.to_cartesian(frenet)
        ahead = track_ahead_features(
            state.poses, points.reshape(self.n_cars, -1, 2), self.lidar.max_range
        )
        flat = vector_observation(ranges, ego, ahead, opp, self.layout)
        if self.layout.context:
            flat = with_context(flat, self._context)
        if self.obs_mode == "vector":
            return list(flat)
        out: list[Obs] = []
        for row in flat:
            named = {"lidar": row[self.layout.lidar]}
            ego_row = row[self.layout.ego]
            for k, name in enumerate(EGO_FEATURES):
                named[name] = ego_row[k : k + 1]
            named["track_ahead"] = row[self.layout.track_ahead].reshape(len(LOOKAHEAD), 2)
            if self.layout.context:
                named["perturbation"] = row[self.layout.perturbation]
            named["opponents"] = row[self.layout.opponents].reshape(
                self.layout.k_opponents, len(OPPONENT_FEATURES)
            )
            out.append(named)
        return out

    # ---- rendering ------------------------------------------------------------------------

    def render(self) -> NDArray[np.uint8] | None:
        """A top-down RGB image (H, W, 3) of the track and the cars still racing."""
        if self.render_mode is None:
            return None
        if self._renderer is None:
            self._renderer = TopDownRenderer(
                self.base_track, Walls.around(self.base_track, self.runoff)
            )
        return self._renderer.render(self.sim.corners(self.sim_state.poses), self.active)

    def close(self) -> None:
        """Release the physics client(s)."""
        self.sim.close()
        for _, sim in self._worlds.values():
            sim.close()


__all__ = [
    "CUT_JUMP",
    "FLIP_UPRIGHT",
    "IMAGE_SHAPE",
    "NATURE_PREFIX",
    "STATE_FEATURES",
    "STUCK_DISTANCE",
    "ActionMode",
    "ObsMode",
    "RacingEnv",
    "default_max_cycles",
]
