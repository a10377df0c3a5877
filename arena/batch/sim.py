"""``BatchSim``: B race environments × N cars stepped together, numpy or torch.

One control step is the same for every car of every environment — no Python loop over cars
or environments and no branch on data (``where`` instead): the tyre model of
:mod:`arena.batch.dynamics` and the soft contacts of :mod:`arena.batch.contact` for each
physics substep, then the track projection, lap gates, the racing reward terms of
:mod:`arena.rewards`, the end-of-episode rules and the observation of
:mod:`arena.observations`, with the semantics of :class:`arena.env.RacingEnv`:

* observation: ``[lidar | ego 7 | track ahead 7×2 | opponents k×5]`` float32, clipped;
* reward: ``"racing"`` terms (progress, off-track, wall, collision blame, overtakes);
* a car *terminates* when it completes ``laps`` laps (ordered gates, as
  :class:`tracks.LapCounter`), stays off the road longer than ``off_track_limit`` or makes
  less than 0.5 m of progress in ``stuck_time``; it is *truncated* after ``max_cycles``.

With ``auto_reset`` (training), an environment in which any car is done starts again at
once, Brax style: its state is replaced (``where``) by a start state drawn from a table of
``start_positions`` grid placements along the lap (index 0: the grid behind the start line)
with a random grid order, and its observation by the one stored with that start state. The
observation of the step that ended the episode is returned as ``final_obs``. Without
``auto_reset`` (the PettingZoo env), done cars leave the race: they stop, and no other car
sees or touches them.

Model uncertainty (:mod:`arena.uncertainty`), per car and per environment, as arrays:
:meth:`BatchSim.set_perturbation` takes values (B, N, n_params) and the simulator applies
the dynamics multipliers and steering trim inside the tyre model, the actuation latency (a
FIFO of whole control steps per environment) and action noise before physics, and lidar
noise and dropout on the observation — all through ``where``, nothing per car in Python.
With ``uncertainty=`` (the training path) the simulator also draws or moves the values
itself (:class:`arena.uncertainty.PerturbationState`: per episode, per step, or by nature
agents whose observations :meth:`BatchSim.nature_obs` gives for all environments at once)
and returns the perturbed reward. Nominal simulators do none of this work.

One simulator holds one track (its maps are per track); several tracks are several
simulators (:class:`arena.batch.vec_env.BatchVecEnv` keeps one per track and direction).

Arrays live on ``device`` (:func:`arena.batch.xp.get_ops`): ``"numpy"`` (float64 by
default), ``"torch:cpu"`` or ``"cuda"`` (float32 by default).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from arena.batch.contact import ContactParams, PairMaps, car_contacts, corners, wall_contacts
from arena.batch.dynamics import CarState, Scales, integrate, steer_target, tyre_forces
from arena.batch.lidar import car_pairs, car_ranges, ray_angles, wall_ranges
from arena.batch.maps import TrackMaps
from arena.batch.track import DeviceTrack
from arena.batch.xp import Array, get_ops
from arena.core import (
    CUT_JUMP,
    STATE_FEATURES,
    EpisodeRules,
    EpisodeState,
    Sensed,
    default_max_cycles,
    episode_start,
    episode_step,
    global_state,
)
from arena.lidar import DEFAULT_FOV, DEFAULT_RANGE
from arena.observations import (
    CONTEXT_SIZE,
    LOOKAHEAD,
    ObservationLayout,
    ego_features,
    opponent_features,
    track_ahead_features,
    vector_observation,
    with_context,
    wrap_angle,
)
from arena.rewards import RewardWeights, race_positions
from arena.sim import CarParams, SimError
from arena.uncertainty import (
    INDEX,
    LATENCY,
    MAX_LATENCY,
    PARAM_NAMES,
    PerturbationState,
    UncertaintyConfig,
    UncertaintyError,
    normalised,
    perturbation_context,
    perturbed_reward,
)
from arena.walls import DEFAULT_RUNOFF
from tracks import Track, load_track
from tracks.geometry import DEFAULT_CHECKPOINTS


@dataclass
class RaceState(EpisodeState):
    """Everything per environment and car that a step reads and writes; arrays (B, N).

    The race rules' :class:`arena.core.EpisodeState` (progress, gates, laps, contacts, the
    stuck-detection ``history`` (B, W, N), ``steps`` (B,) …) plus the simulator's own:
    ``car`` (the rigid bodies) and the projection onto the centre line (``d``, ``heading``,
    ``segment``).
    """

    car: CarState
    d: Array
    heading: Array
    segment: Array


@dataclass
class StepResult:
    """What :meth:`BatchSim.step` returns; arrays on the device.

    Attributes:
        obs: (B, N, D) float32 observations (after any automatic reset).
        reward: (B, N) rewards.
        terminated, truncated: (B, N) bool, this step.
        terms: each racing reward term (B, N).
        lap_done: (B, N) bool, a lap was completed this step (its time in ``lap_time``).
        lap_time: (B, N) s, the time of the lap completed this step (else 0).
        laps_completed: (B, N) laps completed (before any reset).
        off_track, wall, touching: (B, N) bool.
        contact, new_contact, at_fault: (B, N, N) bool; closing (B, N, N) m/s.
        env_done: (B,) bool, the environment ended this step (and was reset with auto_reset).
        final_obs: (B, N, D) observations before the reset (equal to ``obs`` elsewhere).
        reward_nominal: (B, N) the unperturbed reward (``reward`` itself with no
            ``uncertainty``).
        final_nature_obs: (B, N, S) with ``uncertainty``: the nature observations before the
            reset (else None).
    """

    obs: Array
    reward: Array
    terminated: Array
    truncated: Array
    terms: dict[str, Array]
    lap_done: Array
    lap_time: Array
    laps_completed: Array
    off_track: Array
    wall: Array
    touching: Array
    contact: Array
    new_contact: Array
    at_fault: Array
    closing: Array
    env_done: Array
    final_obs: Array
    reward_nominal: Array | None = None
    final_nature_obs: Array | None = None


class BatchSim:
    """``n_envs`` races of ``n_cars`` cars on one track, stepped as arrays.

    Args:
        track: built-in name, file, ``random:<seed>`` or a :class:`Track`.
        n_envs: environments B.
        n_cars: cars per environment N (1–16).
        laps: race distance.
        device: ``"numpy"``, ``"torch:cpu"``, ``"cuda"`` … (:func:`arena.batch.xp.get_ops`).
        dtype: float type (default float64 on numpy, float32 on torch).
        control_hz, physics_hz: rates, Hz (physics a multiple of control).
        lidar_rays, k_opponents: observation layout, as the pybullet env.
        runoff: m of run-off before the walls.
        car_params: the car (as :class:`arena.sim.Simulator`).
        reward_weights: weights of the racing terms.
        max_cycles: steps before truncation (default as :class:`arena.env.RacingEnv`).
        off_track_limit, stuck_time: s, as the pybullet env.
        contact: soft-contact constants.
        auto_reset: restart finished environments inside :meth:`step`.
        start_positions: grid placements along the lap in the start table.
        random_starts: draw the placement and grid order of each reset at random (else the
            grid behind the start line, cars in order).
        seed: seeds the start draws and the perturbation draws.
        uncertainty: model uncertainty (:mod:`arena.uncertainty`), any mode: each
            environment's cars get their perturbation at every (automatic) reset and before
            every step from one :class:`arena.uncertainty.PerturbationState` (B, N); the
            simulator applies the dynamics, latency, action noise and lidar columns
            (:meth:`set_perturbation`) and returns the perturbed reward
            (:func:`arena.uncertainty.perturbed_reward`) with the nominal one beside it.
            In ``adversarial`` mode the natures' actions (B, N, k) come from ``step(...,
            nature=)`` or else from :attr:`nature` (a driver with ``act_batch``) applied to
            :meth:`nature_obs`; with neither, the nominal point (pulled into the box) stays.
        end_on_wall: a car that touches a wall retires at once (DNF ``"crashed"``): for
            training, so a policy learns that a wall costs the race, as on pybullet, where a
            car that hits one at speed stops dead (these soft walls let it slide on).
        observe_perturbation: append each car's perturbation block to its observation
            (:attr:`arena.observations.ObservationLayout.context`; zeros for a nominal car),
            as the pybullet env's option of the same name; a new episode's first
            observation reads the new episode's values.
    """

    # Model-uncertainty state, created on first use (set_perturbation / uncertainty=).
    _fifo: Array  # (B, MAX_LATENCY + 1, N, 2) commands of the last steps
    _lag: Array  # (B, N) int latency, control steps
    _noise_amp: Array  # (B, N) action-noise amplitude
    _lidar_noise: Array  # (B, N) std on normalised ranges
    _dropout: Array  # (B, N) probability a ray reads max range
    _context: Array  # (B, N, 9) perturbation blocks (observe_perturbation only)
    unc: PerturbationState
    final_nature_obs: Array

    def __init__(
        self,
        track: str | Path | Track = "oval",
        n_envs: int = 1,
        n_cars: int = 4,
        laps: int = 1,
        *,
        device: str = "numpy",
        dtype: str | None = None,
        control_hz: int = 20,
        physics_hz: int = 60,
        lidar_rays: int = 64,
        k_opponents: int = 3,
        runoff: float = DEFAULT_RUNOFF,
        car_params: CarParams | None = None,
        reward_weights: RewardWeights | None = None,
        max_cycles: int | None = None,
        off_track_limit: float = 3.0,
        stuck_time: float = 4.0,
        contact: ContactParams | None = None,
        auto_reset: bool = True,
        start_positions: int = 32,
        random_starts: bool = False,
        seed: int | None = None,
        uncertainty: UncertaintyConfig | None = None,
        end_on_wall: bool = False,
        observe_perturbation: bool = False,
    ) -> None:
        if not 1 <= n_cars <= 16:
            raise SimError(f"n_cars must be between 1 and 16, got {n_cars}")
        if n_envs < 1:
            raise SimError(f"n_envs must be at least 1, got {n_envs}")
        if control_hz <= 0 or physics_hz <= 0 or physics_hz % control_hz:
            raise SimError(
                f"physics_hz ({physics_hz}) must be a positive multiple of control_hz "
                f"({control_hz})"
            )
        if laps < 1:
            raise SimError(f"laps must be at least 1, got {laps}")
        self.ops = ops = get_ops(device, dtype)
        self.device = device
        self.track = load_track(track)
        self.n_envs, self.n_cars, self.laps = n_envs, n_cars, laps
        self.params = car_params or CarParams()
        self.contact_params = contact or ContactParams()
        self.weights = reward_weights or RewardWeights()
        self.control_hz, self.physics_hz = control_hz, physics_hz
        self.substeps = physics_hz // control_hz
        self.dt = 1.0 / control_hz
        self.physics_dt = 1.0 / physics_hz
        self.layout = ObservationLayout(lidar_rays, k_opponents, observe_perturbation)
        if observe_perturbation:
            self._context = ops.zeros((n_envs, n_cars, CONTEXT_SIZE))
        self.max_range = DEFAULT_RANGE
        self.off_track_limit, self.stuck_time = off_track_limit, stuck_time
        self.runoff = runoff
        self.auto_reset = auto_reset
        self.random_starts = random_starts
        self.race_distance = laps * self.track.length
        self.max_cycles = max_cycles or default_max_cycles(self.race_distance, control_hz)
        self.maps = TrackMaps.build(self.track, runoff, self.max_range)
        self.dev = DeviceTrack(self.maps, ops)
        p = self.params
        self._lx = ops.asarray(0.5 * p.length * np.array([1.0, -1.0, -1.0, 1.0]))
        self._ly = ops.asarray(0.5 * p.width * np.array([1.0, 1.0, -1.0, -1.0]))
        angles = ray_angles(lidar_rays, DEFAULT_FOV)
        bins = self.maps.ranges.shape[1]
        self._ray_bins = ops.asarray((angles + math.pi) * (bins / (2 * math.pi)))
        self._fan = (float(angles[0]), float(angles[1] - angles[0]) if lidar_rays > 1 else 1.0)
        self._ux, self._uy = ops.asarray(np.cos(angles)), ops.asarray(np.sin(angles))
        pi, pj = car_pairs(n_cars)
        self._pairs = (ops.asarray(pi), ops.asarray(pj))
        self._pair_maps = PairMaps(n_cars, ops)
        self._lookahead = ops.asarray(np.asarray(LOOKAHEAD))
        self._gates = ops.asarray(self.track.checkpoint_s(DEFAULT_CHECKPOINTS))
        n_gates = DEFAULT_CHECKPOINTS
        self.n_gates = n_gates
        self.max_jump = min(CUT_JUMP, 0.45 * self.track.length / n_gates)
        self._wheel_x = ops.asarray(np.array([0.5, 0.5, -0.5, -0.5]) * p.wheelbase)
        self._wheel_y = ops.asarray(np.array([0.5, -0.5, 0.5, -0.5]) * p.track_width)
        self.window = max(1, round(stuck_time * control_hz))
        self.rules = EpisodeRules.build(
            self.track, ops, n_cars=n_cars, laps=laps, control_hz=control_hz, params=p,
            max_cycles=self.max_cycles, off_track_limit=off_track_limit, stuck_time=stuck_time,
            weights=self.weights, end_on_wall=end_on_wall,
        )  # fmt: skip
        self.scales = self.nominal_scales(n_envs)
        self.perturbed = False  # set by set_perturbation: until then no uncertainty work
        self.rng = ops.rng(seed)
        if uncertainty is not None and not isinstance(uncertainty, UncertaintyConfig):
            raise UncertaintyError("uncertainty must be an arena.uncertainty.UncertaintyConfig")
        self.uncertainty = uncertainty if uncertainty and uncertainty.mode != "nominal" else None
        self.nature: Any = None  # adversarial: drives the natures when step() gets none
        if self.uncertainty is not None:
            self.unc = PerturbationState(self.uncertainty, (n_envs, n_cars))
            self._unc_rng = np.random.default_rng(seed)
            self.set_perturbation(self.unc.values)
        self._build_start_table(start_positions)
        self.state = self._start_state(
            ops.zeros(n_envs, dtype=ops.int), self._identity_order(n_envs)
        )
        self.obs = self._with_context(
            self._start_obs(ops.zeros(n_envs, dtype=ops.int), self._identity_order(n_envs))
        )

    # ---- construction helpers ---------------------------------------------------------------
    def nominal_scales(self, n_envs: int) -> Scales:
        """All cars of ``n_envs`` environments at their nominal parameters."""
        one = self.ops.full((n_envs, self.n_cars), 1.0)
        return Scales(one, one, one, one, self.ops.zeros((n_envs, self.n_cars)))

    def _identity_order(self, n_envs: int) -> Array:
        ops = self.ops
        return ops.arange(self.n_cars)[None, :] + ops.zeros((n_envs, self.n_cars), dtype=ops.int)

    def _build_start_table(self, k: int) -> None:
        """Grid placements at ``k`` offsets along the lap and their first observations."""
        ops, n, track = self.ops, self.n_cars, self.track
        offsets = np.arange(k) * (track.length / k)
        slots = np.stack([track.start_grid(n, offset=float(o)) for o in offsets])  # (K, N, 3)
        self.n_starts = k
        self._slots = ops.asarray(slots)
        self._offsets = ops.asarray(offsets)
        table = self._start_state(ops.arange(k), self._identity_order(k))
        self._start_table = table  # (K, N) per field: the car in each slot of each placement
        self._start_obs_table = self._observe(table, self.nominal_scales(k))  # (K, N, D)

    def _fresh(self, start: Array, slot_of_car: Array) -> RaceState:
        """:meth:`_start_state` read from the start table (gathers only), for auto-resets.

        ``history`` is not reset: it is read only once a whole window has been written.
        """
        t = self._start_table
        rows, cols = start[:, None], slot_of_car

        def pick(a: Array) -> Array:
            return a[rows, cols]

        car = CarState(*(pick(getattr(t.car, f.name)) for f in fields(CarState)))
        zeros = self.ops.zeros(slot_of_car.shape)
        progress = pick(t.race_progress)
        return RaceState(
            car=car, s=pick(t.s), d=pick(t.d), heading=pick(t.heading),
            segment=pick(t.segment), next_gate=pick(t.next_gate), laps=pick(t.laps),
            race_progress=progress, positions=race_positions(progress, self.ops),
            active=pick(t.active), finished=pick(t.finished), finish_time=pick(t.finish_time),
            off_time=zeros, line_time=zeros, last_lap=zeros,
            contact=self.ops.full((*slot_of_car.shape, self.n_cars), False, dtype=self.ops.bool),
            history=self.state.history, steps=self.ops.zeros(start.shape, dtype=self.ops.int),
            grid_start=start == 0,
        )  # fmt: skip

    def _start_state(self, start: Array, slot_of_car: Array) -> RaceState:
        """Fresh state of envs starting at table index ``start`` (B,) with car i in grid slot
        ``slot_of_car[b, i]``."""
        ops, n = self.ops, self.n_cars
        b = start.shape[0]
        poses = self._slots[start[:, None], slot_of_car]  # (B, N, 3)
        zeros = ops.zeros((b, n))
        car = CarState(
            x=poses[..., 0], y=poses[..., 1], yaw=poses[..., 2],
            vx=zeros, vy=zeros, r=zeros, steering=zeros,
        )  # fmt: skip
        s, d, heading, seg = self.dev.project(car.x, car.y)
        ep = episode_start(ops, self.rules, s, self._offsets[start], start == 0)
        return RaceState(car=car, d=d, heading=heading, segment=seg, **ep.__dict__)

    def _start_obs(self, start: Array, slot_of_car: Array) -> Array:
        return self._start_obs_table[start[:, None], slot_of_car]

    # ---- reset ------------------------------------------------------------------------------
    def draw_starts(self, n_envs: int) -> tuple[Array, Array]:
        """Start-table indices (B,) and grid slots (B, N) for ``n_envs`` resets."""
        ops = self.ops
        if not self.random_starts:
            return ops.zeros(n_envs, dtype=ops.int), self._identity_order(n_envs)
        start = ops.integers(self.rng, self.n_starts, (n_envs,))
        return start, ops.argsort(ops.uniform(self.rng, (n_envs, self.n_cars)), axis=1)

    def reset(
        self,
        seed: int | None = None,
        start: Array | None = None,
        slot_of_car: Array | None = None,
    ) -> Array:
        """Restart every environment; returns observations (B, N, D).

        Args:
            seed: reseeds the start draws.
            start: (B,) start-table indices (0: the grid behind the line); default drawn.
            slot_of_car: (B, N) grid slot of each car (0: pole); default drawn.
        """
        if seed is not None:
            self.rng = self.ops.rng(seed)
            if self.uncertainty is not None:
                self._unc_rng = np.random.default_rng(seed)
        if self.uncertainty is not None:
            self.unc.start(self._unc_rng)
            self.set_perturbation(self.unc.values)
        drawn_start, drawn_slots = self.draw_starts(self.n_envs)
        start = drawn_start if start is None else self.ops.asarray(start, dtype=self.ops.int)
        slots = drawn_slots if slot_of_car is None else self.ops.asarray(slot_of_car)
        self.state = self._start_state(start, slots)
        self.obs = self._start_obs(start, slots)
        if self.perturbed:
            self._fifo = self.ops.zeros(self._fifo.shape)
            self.obs = self._jitter_lidar(self.obs)
        self.obs = self._with_context(self.obs)
        return self.obs

    def set_poses(self, poses: Array, velocity: Array | None = None) -> Array:
        """Place cars at ``poses`` (B, N, 3) [x m, y m, yaw rad] (optionally with world
        velocities (B, N, 3) [vx, vy, yaw rate]) in a fresh race; returns observations."""
        ops = self.ops
        poses = ops.asarray(poses)
        vel = ops.zeros(poses.shape) if velocity is None else ops.asarray(velocity)
        st = self._start_state(ops.zeros(self.n_envs, dtype=ops.int), self._identity_order(1))
        st.car = CarState(
            poses[..., 0], poses[..., 1], poses[..., 2],
            vel[..., 0], vel[..., 1], vel[..., 2], ops.zeros(poses.shape[:-1]),
        )  # fmt: skip
        st.s, st.d, st.heading, st.segment = self.dev.project(st.car.x, st.car.y)
        ahead = ops.searchsorted(self._gates, st.s)
        st.next_gate = ops.where(ahead >= self.n_gates, 0, ahead)
        st.race_progress = self.dev.delta_s(st.s, 0.0)
        st.history = st.race_progress[:, None, :] + ops.zeros(
            (self.n_envs, self.window, self.n_cars)
        )
        st.positions = race_positions(st.race_progress, ops)
        self.state = st
        self.obs = self._with_context(self._observe(st, self.scales))
        return self.obs

    # ---- model uncertainty ------------------------------------------------------------------
    def set_perturbation(self, values: Any, envs: Any = None) -> None:
        """Give the cars of some environments new perturbation values.

        The simulator applies the dynamics (``friction``, ``mass``, ``motor``, ``steer_gain``
        multipliers and the ``steer_offset``), the actuation (``latency``: commands pass
        through a FIFO of whole control steps, zero during an episode's first ``latency``
        steps; ``action_noise``: uniform noise of that amplitude on each command, then
        clipped to [-1, 1]) and the lidar (``lidar_noise``: Gaussian std on the normalised
        ranges; ``lidar_dropout``: probability a ray reads max range) of
        :mod:`arena.uncertainty`, all per car as arrays. The reward columns are the caller's
        (:func:`arena.uncertainty.perturbed_reward`), the image columns have no camera here.
        Until the first call, none of this work is done.

        Args:
            values: (B, N, n_params) in :data:`arena.uncertainty.PARAM_NAMES` order (numpy or
                the device's arrays; latency whole steps in 0..MAX_LATENCY).
            envs: (B,) bool, the environments to update (None: all).

        Raises:
            SimError: values of the wrong shape.
        """
        ops, b, n = self.ops, self.n_envs, self.n_cars
        vals = ops.asarray(values)
        if tuple(vals.shape) != (b, n, len(PARAM_NAMES)):
            raise SimError(f"perturbation values must have shape {(b, n, len(PARAM_NAMES))}")
        if not self.perturbed:
            self.perturbed = True
            self._fifo = ops.zeros((b, MAX_LATENCY + 1, n, 2))
            zeros = ops.zeros((b, n))
            self._lag = ops.zeros((b, n), dtype=ops.int)
            self._noise_amp, self._lidar_noise, self._dropout = zeros, zeros, zeros
        mask = (
            ops.full((b,), True, dtype=ops.bool) if envs is None else ops.asarray(envs, ops.bool)
        )[:, None]

        def col(name: str, old: Array) -> Array:
            return ops.where(mask, vals[..., INDEX[name]], old)

        sc = self.scales
        self.scales = Scales(*(col(f.name, getattr(sc, f.name)) for f in fields(Scales)))
        lag = ops.cast(ops.where(mask, vals[..., LATENCY], ops.cast(self._lag, ops.float)), ops.int)
        self._lag = lag
        self._noise_amp = col("action_noise", self._noise_amp)
        self._lidar_noise = col("lidar_noise", self._lidar_noise)
        self._dropout = col("lidar_dropout", self._dropout)
        if self.layout.context:
            ctx = perturbation_context(vals, ops)
            self._context = ops.where(mask[..., None], ctx, self._context)

    def set_uncertainty(self, cfg: UncertaintyConfig) -> None:
        """Draw from ``cfg``'s bounds from now on (a curriculum on the bounds widens them as
        training goes). Values already drawn stay until their next draw (each episode's
        start, or the ``resample`` step); the mode and the free parameters (the width of
        :meth:`global_state` and of nature's action) cannot change.

        Raises:
            UncertaintyError: this simulator was built without uncertainty, or ``cfg`` has
                another mode or other free parameters.
        """
        old = self.uncertainty
        if old is None:
            raise UncertaintyError("set_uncertainty needs a simulator built with uncertainty=")
        if not isinstance(cfg, UncertaintyConfig) or cfg.mode != old.mode:
            raise UncertaintyError(f"set_uncertainty keeps the mode {old.mode!r}")
        if cfg.free_names != old.free_names:
            raise UncertaintyError(
                f"set_uncertainty keeps the free parameters {old.free_names}, not {cfg.free_names}"
            )
        self.uncertainty = self.unc.cfg = cfg

    def _advance_uncertainty(self, nature: Any) -> None:
        """Before a step: the sampler's or the natures' new values (one implementation:
        :meth:`arena.uncertainty.PerturbationState.advance`)."""
        ops, cfg = self.ops, self.unc.cfg
        acting = None
        if cfg.mode == "adversarial":
            if nature is None and self.nature is not None:
                obs = ops.to_numpy(self.nature_obs())
                acts = self.nature.act_batch(obs.reshape(-1, obs.shape[-1]))
                nature = np.asarray(acts, dtype=np.float64).reshape(self.n_envs, self.n_cars, -1)
            if nature is not None:
                nature = ops.to_numpy(ops.asarray(nature))
                acting = ops.to_numpy(self.state.active)
        steps = ops.to_numpy(self.state.steps)
        if self.unc.advance(self._unc_rng, steps, nature, acting):
            self.set_perturbation(self.unc.values)

    @property
    def state_size(self) -> int:
        """Length S of :meth:`global_state`: 10 per car, then k free parameters per car."""
        k = 0 if self.uncertainty is None else len(self.uncertainty.free)
        return self.n_cars * (STATE_FEATURES + k)

    def global_state(self, st: RaceState | None = None) -> Array:
        """(B, S) float32: the global state of every environment, as
        :meth:`arena.env.RacingEnv.global_state` (per car x, y relative to the track's centre
        in half-extents, cos and sin of yaw, vx, vy / max speed, yaw rate / π, s / lap,
        race progress / race distance, racing 1/0; parked cars read zeros; then every car's
        free perturbation parameters mapped to [-1, 1])."""
        ops, st = self.ops, st if st is not None else self.state
        car = st.car
        poses = ops.stack([car.x, car.y, car.yaw], axis=-1)
        velocity = ops.stack([car.vx, car.vy, car.r], axis=-1)
        feats = global_state(
            poses,
            velocity,
            st.s,
            st.race_progress,
            st.active,
            self.track,
            self.race_distance,
            self.params.max_speed,
            ops,
        ).reshape(self.n_envs, -1)
        if self.uncertainty is not None:
            xi = ops.asarray(normalised(self.uncertainty, self.unc.raw))
            feats = ops.concat([feats, xi.reshape(self.n_envs, -1)], axis=-1)
        return ops.cast(feats, ops.float32)

    def nature_obs(self) -> Array:
        """(B, N, S + N) float32: each nature's observation, the global state then a one-hot
        of its car (as the pybullet env's ``nature_car_i``)."""
        return self._nature_obs(self.state)

    def _nature_obs(self, st: RaceState) -> Array:
        ops, n = self.ops, self.n_cars
        state = self.global_state(st)[:, None, :] + ops.zeros(
            (self.n_envs, n, 1), dtype=ops.float32
        )
        onehot = ops.cast(ops.eye(n), ops.float32)[None] + ops.zeros(
            (self.n_envs, n, n), dtype=ops.float32
        )
        return ops.concat([state, onehot], axis=-1)

    def _actuate(self, act: Array, st: RaceState) -> Array:
        """Commands (B, N, 2) through each car's latency FIFO, plus its action noise: the
        command applied at step t is the one given at ``t − latency``."""
        ops, size = self.ops, MAX_LATENCY + 1
        slot = ops.mod(st.steps, size)  # (B,)
        write = (ops.arange(size)[None, :] == slot[:, None])[..., None, None]  # (B, L, 1, 1)
        self._fifo = ops.where(write, act[:, None], self._fifo)
        read = ops.mod(st.steps[:, None] - self._lag, size)  # (B, N)
        idx = read[:, None, :, None] + ops.zeros(
            (*read.shape[:1], 1, self.n_cars, 2), dtype=ops.int
        )
        cmd = ops.take_along(self._fifo, idx, 1)[:, 0]
        noise = 2.0 * ops.uniform(self.rng, cmd.shape) - 1.0
        cmd = ops.clip(cmd + noise * self._noise_amp[..., None], -1.0, 1.0)
        return cmd * st.active[..., None]

    def _jitter_lidar(self, obs: Array) -> Array:
        """Observations (B, N, D) with noisy lidar (as :func:`arena.perception.jitter_lidar`:
        Gaussian noise, dropped rays read 1, clipped to [0, 1])."""
        ops, rays = self.ops, self.layout.n_rays
        shape = (self.n_envs, self.n_cars, rays)
        u1 = 1.0 - ops.uniform(self.rng, shape)  # (0, 1]: Box-Muller
        u2 = ops.uniform(self.rng, shape)
        gauss = ops.sqrt(-2.0 * ops.lib.log(u1)) * ops.cos(2.0 * math.pi * u2)
        lidar = obs[..., :rays] + gauss * self._lidar_noise[..., None]
        dropped = ops.uniform(self.rng, shape) < self._dropout[..., None]
        lidar = ops.clip(ops.where(dropped, 1.0, lidar), 0.0, 1.0)
        return ops.concat([ops.cast(lidar, obs.dtype), obs[..., rays:]], axis=-1)

    # ---- physics ----------------------------------------------------------------------------
    def _physics(
        self, car: CarState, steer_cmd: Array, throttle: Array, active: Array
    ) -> tuple[CarState, Array, Array]:
        """``substeps`` physics steps; returns the new car state, wall (B, N) and car-car
        (B, N, N) contact flags seen during any substep."""
        ops, p, cp, sc, dt = (
            self.ops,
            self.params,
            self.contact_params,
            self.scales,
            self.physics_dt,
        )
        target = steer_target(steer_cmd, p, sc, ops)
        mass = p.mass * sc.mass
        inertia = mass * (p.length**2 + p.width**2) / 12.0
        max_delta = p.steer_rate * dt
        hl, hw = 0.5 * p.length, 0.5 * p.width
        wall_any = ops.full(active.shape, False, dtype=ops.bool)
        touch_any = ops.full((*active.shape, self.n_cars), False, dtype=ops.bool)
        for _ in range(self.substeps):  # a fixed count: static, not data-dependent
            steering = car.steering + ops.clip(target - car.steering, -max_delta, max_delta)
            car = replace(car, steering=ops.where(active, steering, 0.0))
            fx, fy, tq = tyre_forces(car, throttle, p, sc, dt, ops)
            cx, cy, cos, sin = corners(car, self._lx, self._ly, ops)
            if self.n_cars > 1:
                cfx, cfy, ctq, touching = car_contacts(
                    car, cos[..., 0], sin[..., 0], active, hl, hw, cp, self._pair_maps, ops
                )
                fx, fy, tq = fx + cfx, fy + cfy, tq + ctq
                touch_any = touch_any | touching
            clear, nx, ny = self.dev.clearance(cx, cy)
            wfx, wfy, wtq, wall = wall_contacts(car, cx, cy, clear, nx, ny, active, cp, ops)
            car = integrate(car, fx + wfx, fy + wfy, tq + wtq, mass, inertia, dt, active)
            wall_any = wall_any | wall
        return car, wall_any, touch_any

    # ---- observation ------------------------------------------------------------------------
    def _with_context(self, obs: Array) -> Array:
        """``obs`` (B, N, D) with the cars' perturbation block appended when
        ``observe_perturbation`` (:func:`arena.observations.with_context`), else as is."""
        return with_context(obs, self._context, self.ops) if self.layout.context else obs

    def _observe(self, st: RaceState, scales: Scales) -> Array:
        """Vector observations (B, N, D) float32 of a state, without the perturbation block."""
        ops, p, car = self.ops, self.params, st.car
        dev = self.dev
        walls = wall_ranges(
            car.x, car.y, car.yaw, self._ray_bins, self._ux, self._uy, dev.ranges, dev.lidar_rows,
            self.maps.lidar_grid.origin, self.maps.lidar_grid.cell,
            self.maps.lidar_grid.shape, self.max_range, ops,
        )  # fmt: skip
        if self.n_cars > 1:
            cos, sin = ops.cos(car.yaw), ops.sin(car.yaw)
            cars = car_ranges(
                car.x, car.y, cos, sin, self._pairs, self._ux, self._uy, self._fan, st.active,
                0.5 * p.length, 0.5 * p.width, self.max_range, ops,
            )  # fmt: skip
            walls = ops.minimum(walls, cars)
        lidar = walls / self.max_range
        heading_error = wrap_angle(car.yaw - st.heading, ops)
        left, right = dev.widths_at(st.s)
        along = car.vx * ops.cos(st.heading) + car.vy * ops.sin(st.heading)
        cy, sy = ops.cos(car.yaw), ops.sin(car.yaw)
        v_long = cy * car.vx + sy * car.vy
        v_lat = -sy * car.vx + cy * car.vy
        ego = ego_features(
            v_long, v_lat, car.steering, car.r, heading_error, st.d, left, right, along,
            p.max_speed, p.max_steer, ops,
        )  # fmt: skip
        px, py = dev.centre_at(st.s[..., None] + self._lookahead)
        poses = ops.stack([car.x, car.y, car.yaw], axis=-1)
        ahead = track_ahead_features(poses, ops.stack([px, py], axis=-1), self.max_range, ops)
        velocity = ops.stack([car.vx, car.vy], axis=-1)
        opp = opponent_features(
            poses, velocity, st.active, self.layout.k_opponents, self.max_range, p.max_speed, ops
        )
        return vector_observation(lidar, ego, ahead, opp, self.layout, ops)

    # ---- step -------------------------------------------------------------------------------
    def step(self, actions: Array, nature: Any = None) -> StepResult:
        """Advance every environment one control step.

        Args:
            actions: (B, N, 2) [steer, throttle] in [-1, 1] (NaN: no input; ±inf saturate).
            nature: (B, N, k) the natures' actions (``adversarial`` uncertainty only).
        """
        ops, st = self.ops, self.state
        if self.uncertainty is not None:
            self._advance_uncertainty(nature)
        act = ops.asarray(actions)
        act = ops.clip(ops.where(ops.isnan(act), 0.0, act), -1.0, 1.0)  # NaN: no input
        act = act * st.active[..., None]
        if self.perturbed:
            act = self._actuate(act, st)
        old_car = st.car
        car, wall, touching = self._physics(old_car, act[..., 0], act[..., 1], st.active)
        active = st.active
        dev = self.dev
        # The race rules are arena.core's, the same code the pybullet env runs.
        s, d, heading, seg = dev.project(car.x, car.y)
        left, right = dev.widths_at(s)
        sensed = Sensed(
            s=s, d=d, heading=heading, yaw=car.yaw, left=left, right=right, wall=wall,
            touching=touching, upright=None,
            prev_poses=ops.stack([old_car.x, old_car.y, old_car.yaw], axis=-1),
            prev_velocity=ops.stack([old_car.vx, old_car.vy], axis=-1),
        )  # fmt: skip
        episode = EpisodeState(**{f.name: getattr(st, f.name) for f in fields(EpisodeState)})
        ep, out = episode_step(ops, self.rules, episode, sensed)
        self.outcome = out
        terms, reward = out.terms, out.reward
        terminated, truncated = out.terminated, out.truncated
        lap_done, lap_time, laps_completed = out.lap_done, out.lap_time, ops.maximum(ep.laps, 0)
        off_track, contact, new_contact = out.off_track, out.contact, out.new_contact
        at_fault, closing = out.at_fault, out.closing
        done = terminated | truncated
        new = RaceState(car=car, d=d, heading=heading, segment=seg, **ep.__dict__)
        # Observations see the cars that are still racing, as the pybullet env's do.
        obs = self._observe(replace(new, active=active), self.scales)
        if self.perturbed:
            obs = self._jitter_lidar(obs)
        reward_nominal, final_nature = reward, None
        if self.uncertainty is not None:
            values = ops.asarray(self.unc.values)
            reward = ops.where(active, perturbed_reward(values, terms, "racing", reward), 0.0)
            final_nature = self._nature_obs(replace(new, active=active))
            self.final_nature_obs = final_nature
        env_done = ops.any(done, axis=1)
        obs = final_obs = self._with_context(obs)  # the ended episodes' own values
        if self.auto_reset:
            start, slots = self.draw_starts(self.n_envs)
            new = _merge(env_done, self._fresh(start, slots), new, ops)
            fresh_obs = self._start_obs(start, slots)
            if self.uncertainty is not None:  # the new episodes' perturbations
                ended = ops.to_numpy(env_done)
                if ended.any():
                    self.unc.start(self._unc_rng, envs=ended)
                    self.set_perturbation(self.unc.values, envs=env_done)
            if self.perturbed:
                # A new episode starts with an empty latency FIFO; its first observation
                # has the lidar noise of the env's levels now (without ``uncertainty=`` the
                # caller sets the new episode's values after this step, with
                # set_perturbation(..., envs=env_done)).
                self._fifo = ops.where(env_done[:, None, None, None], 0.0, self._fifo)
                fresh_obs = self._jitter_lidar(fresh_obs)
            obs = ops.where(env_done[:, None, None], self._with_context(fresh_obs), obs)
        self.state = new
        self.obs = obs
        return StepResult(
            obs=obs, reward=reward, terminated=terminated, truncated=truncated, terms=terms,
            lap_done=lap_done, lap_time=lap_time, laps_completed=laps_completed,
            off_track=off_track, wall=wall & active, touching=ops.any(contact, axis=-1),
            contact=contact, new_contact=new_contact, at_fault=at_fault, closing=closing,
            env_done=env_done, final_obs=final_obs, reward_nominal=reward_nominal,
            final_nature_obs=final_nature,
        )  # fmt: skip

    @property
    def time(self) -> Array:
        """(B,) simulated seconds since each environment's reset."""
        return self.ops.cast(self.state.steps, self.ops.float) * self.dt


def _merge(mask: Array, fresh: RaceState, cur: RaceState, ops: Any) -> RaceState:
    """``fresh`` where ``mask`` (B,) is True, else ``cur``, field by field."""

    def pick(a: Array, b: Array) -> Array:
        m = mask.reshape((-1,) + (1,) * (a.ndim - 1))
        return ops.where(m, a, b)

    car = CarState(
        *(pick(getattr(fresh.car, f.name), getattr(cur.car, f.name)) for f in fields(CarState))
    )
    out = {
        f.name: pick(getattr(fresh, f.name), getattr(cur, f.name))
        for f in fields(RaceState)
        if f.name not in ("car", "history")
    }
    out["history"] = cur.history
    return RaceState(car=car, **out)
