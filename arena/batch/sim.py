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
from arena.env import CUT_JUMP, STUCK_DISTANCE, default_max_cycles
from arena.lidar import DEFAULT_FOV, DEFAULT_RANGE
from arena.observations import (
    LOOKAHEAD,
    ObservationLayout,
    ego_features,
    opponent_features,
    track_ahead_features,
    vector_observation,
    wrap_angle,
)
from arena.rewards import RACING_TERMS, RewardWeights, collision_blame, race_positions, racing_terms
from arena.sim import CarParams, SimError
from arena.walls import DEFAULT_RUNOFF
from tracks import Track, load_track
from tracks.geometry import DEFAULT_CHECKPOINTS


@dataclass
class RaceState:
    """Everything per environment and car that a step reads and writes; arrays (B, N).

    ``car`` holds the rigid bodies; ``history`` (B, W, N) the race progress of the last W
    steps (stuck detection); ``steps`` (B,) control steps since the environment's reset.
    """

    car: CarState
    s: Array
    d: Array
    heading: Array
    segment: Array
    next_gate: Array
    laps: Array
    race_progress: Array
    positions: Array
    active: Array
    finished: Array
    finish_time: Array
    off_time: Array
    line_time: Array
    last_lap: Array
    contact: Array  # (B, N, N)
    history: Array  # (B, W, N)
    steps: Array  # (B,)
    grid_start: Array  # (B,)


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
        seed: seeds the start draws.
    """

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
        self.track = load_track(track)
        self.n_envs, self.n_cars, self.laps = n_envs, n_cars, laps
        self.params = car_params or CarParams()
        self.contact_params = contact or ContactParams()
        self.weights = reward_weights or RewardWeights()
        self.control_hz, self.physics_hz = control_hz, physics_hz
        self.substeps = physics_hz // control_hz
        self.dt = 1.0 / control_hz
        self.physics_dt = 1.0 / physics_hz
        self.layout = ObservationLayout(lidar_rays, k_opponents)
        self.max_range = DEFAULT_RANGE
        self.off_track_limit, self.stuck_time = off_track_limit, stuck_time
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
        self.scales = self.nominal_scales(n_envs)
        self.rng = ops.rng(seed)
        self._build_start_table(start_positions)
        self.state = self._start_state(
            ops.zeros(n_envs, dtype=ops.int), self._identity_order(n_envs)
        )
        self.obs = self._start_obs(ops.zeros(n_envs, dtype=ops.int), self._identity_order(n_envs))

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
        grid_start = start == 0
        ahead = ops.searchsorted(self._gates, s)
        next_gate = ops.where(ahead >= self.n_gates, 0, ahead)
        offset = self._offsets[start]
        progress = self.dev.delta_s(s, 0.0) + ops.where(grid_start, 0.0, offset)[:, None]
        return RaceState(
            car=car,
            s=s,
            d=d,
            heading=heading,
            segment=seg,
            next_gate=next_gate,
            laps=ops.full((b, n), -1, dtype=ops.int),
            race_progress=progress,
            positions=race_positions(progress, ops),
            active=ops.full((b, n), True, dtype=ops.bool),
            finished=ops.full((b, n), False, dtype=ops.bool),
            finish_time=ops.full((b, n), 1e9),
            off_time=zeros,
            line_time=zeros,
            last_lap=zeros,
            contact=ops.full((b, n, n), False, dtype=ops.bool),
            history=progress[:, None, :] + ops.zeros((b, self.window, n)),
            steps=ops.zeros(b, dtype=ops.int),
            grid_start=grid_start,
        )

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
        drawn_start, drawn_slots = self.draw_starts(self.n_envs)
        start = drawn_start if start is None else self.ops.asarray(start, dtype=self.ops.int)
        slots = drawn_slots if slot_of_car is None else self.ops.asarray(slot_of_car)
        self.state = self._start_state(start, slots)
        self.obs = self._start_obs(start, slots)
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
        self.obs = self._observe(st, self.scales)
        return self.obs

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
    def _observe(self, st: RaceState, scales: Scales) -> Array:
        """Vector observations (B, N, D) float32 of a state."""
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
    def step(self, actions: Array) -> StepResult:
        """Advance every environment one control step.

        Args:
            actions: (B, N, 2) [steer, throttle] in [-1, 1] (NaN: no input; ±inf saturate).
        """
        ops, st = self.ops, self.state
        act = ops.asarray(actions)
        act = ops.clip(ops.where(ops.isnan(act), 0.0, act), -1.0, 1.0)  # NaN: no input
        act = act * st.active[..., None]
        old_car = st.car
        car, wall, touching = self._physics(old_car, act[..., 0], act[..., 1], st.active)
        steps = st.steps + 1
        now = ops.cast(steps, ops.float) * self.dt
        active = st.active
        dev = self.dev

        s, d, heading, seg = dev.project(car.x, car.y)
        ds = dev.delta_s(s, st.s)
        cut = ops.abs(ds) > CUT_JUMP
        progress = ops.where(active & ~cut, ds, 0.0)
        race_progress = st.race_progress + progress

        # Ordered gates, as tracks.LapCounter.
        gate = self._gates[st.next_gate]
        before = dev.delta_s(gate, st.s)
        crossed = (ds > 0) & (ds <= self.max_jump) & (before > 0) & (before <= ds)
        finish_line = crossed & (st.next_gate == 0)
        lap_done = finish_line & (st.laps >= 0) & active
        laps = ops.where(finish_line, st.laps + 1, st.laps)
        next_gate = ops.where(crossed, st.next_gate + 1, st.next_gate)
        next_gate = ops.where(next_gate >= self.n_gates, 0, next_gate)
        first_cross = (st.laps < 0) & (laps == 0) & active
        now_n = now[:, None]
        line_time = ops.where(first_cross & ~st.grid_start[:, None], now_n, st.line_time)
        lap_time = ops.where(lap_done, now_n - line_time, 0.0)
        line_time = ops.where(lap_done, now_n, line_time)
        laps_completed = ops.maximum(laps, 0)

        heading_error = wrap_angle(car.yaw - heading, ops)
        left, right = dev.widths_at(s)
        sin_h, cos_h = ops.sin(heading_error)[..., None], ops.cos(heading_error)[..., None]
        wheel_d = d[..., None] + self._wheel_x * sin_h + self._wheel_y * cos_h
        on = (wheel_d <= left[..., None]) & (wheel_d >= -right[..., None])
        off_track = ~ops.any(on, axis=-1) & active
        off_time = ops.where(off_track, st.off_time + self.dt, 0.0)

        pair = active[..., :, None] & active[..., None, :]
        contact = touching & pair
        old_poses = ops.stack([old_car.x, old_car.y, old_car.yaw], axis=-1)
        old_vel = ops.stack([old_car.vx, old_car.vy], axis=-1)
        at_fault, closing = collision_blame(old_poses, old_vel, contact, ops=ops)
        new_contact = contact & ~st.contact

        newly_finished = active & (laps_completed >= self.laps)
        finished = st.finished | newly_finished
        finish_time = ops.where(newly_finished, now_n, st.finish_time)
        rank_key = ops.where(finished, 1e12 - finish_time, race_progress)
        positions = race_positions(ops.where(active | finished, rank_key, -1e12), ops)
        gained = ops.where(active, st.positions - positions, 0)

        w = self.window
        slot = ops.cast(ops.mod(steps, w), ops.int)
        oldest = ops.mod(steps + 1, w)
        hist = st.history
        onehot = (ops.arange(w)[None, :] == slot[:, None])[..., None]
        hist = ops.where(onehot, race_progress[:, None, :], hist)
        moved = race_progress - ops.take_along(hist, oldest.reshape(-1, 1, 1), 1)[:, 0, :]
        warmed = (steps >= w)[:, None]
        still = active & ~newly_finished
        stuck = still & warmed & (moved < STUCK_DISTANCE)
        lost = still & (off_time > self.off_track_limit)
        terminated = newly_finished | stuck | lost
        truncated = active & ~terminated & (steps >= self.max_cycles)[:, None]

        terms = racing_terms(
            progress, off_track, wall & active, at_fault, closing, gained, self.dt,
            self.weights, ops,
        )  # fmt: skip
        reward = terms["progress"]
        for name in RACING_TERMS[1:]:
            reward = reward + terms[name]
        done = terminated | truncated
        new = RaceState(
            car=car, s=s, d=d, heading=heading, segment=seg, next_gate=next_gate, laps=laps,
            race_progress=race_progress, positions=positions, active=active & ~done,
            finished=finished, finish_time=finish_time, off_time=off_time, line_time=line_time,
            last_lap=ops.where(lap_done, lap_time, st.last_lap), contact=contact,
            history=hist, steps=steps, grid_start=st.grid_start,
        )  # fmt: skip
        # Observations see the cars that are still racing, as the pybullet env's do.
        obs = self._observe(replace(new, active=active), self.scales)
        env_done = ops.any(done, axis=1)
        final_obs = obs
        if self.auto_reset:
            start, slots = self.draw_starts(self.n_envs)
            new = _merge(env_done, self._fresh(start, slots), new, ops)
            obs = ops.where(env_done[:, None, None], self._start_obs(start, slots), obs)
        self.state = new
        self.obs = obs
        return StepResult(
            obs=obs, reward=reward, terminated=terminated, truncated=truncated, terms=terms,
            lap_done=lap_done, lap_time=lap_time, laps_completed=laps_completed,
            off_track=off_track, wall=wall & active, touching=ops.any(contact, axis=-1),
            contact=contact, new_contact=new_contact, at_fault=at_fault, closing=closing,
            env_done=env_done, final_obs=final_obs,
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
