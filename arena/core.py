"""The episode rules, written once over arrays with a leading batch axis (Brax's PipelineEnv).

Both simulators — pybullet (:class:`arena.sim.Simulator`, one race, ``B = 1``) and the
batched one (:class:`arena.batch.sim.BatchSim`, ``B`` races) — only move the cars and sense
them (projection onto the centre line, contacts, lidar). Everything that makes a race a race
is here, as pure functions of ``(B, N)`` arrays through the :mod:`arena.batch.xp` namespace
(numpy or torch), with ``where`` instead of per-car branches:

* :func:`episode_start` / :func:`episode_step`: progress along the lap, lap gates (exactly
  :class:`tracks.LapCounter`'s), lap times (a grid start counts lap 1 from the start signal,
  a mid-lap start from its first crossing of the line), off-track (all four wheels off the
  road), car–car contact and blame, positions and overtakes, the racing reward terms, and
  termination (finished, stuck, flipped, off the road too long) and truncation
  (``max_cycles``), with the DNF reason as a code into :data:`DNF_REASONS`;
* :func:`start_spec`: the ``reset(options=...)`` grammar (``grid_order``, ``start_offset``,
  ``direction``), one parser for both PettingZoo envs;
* :func:`global_state`: PettingZoo's ``state()`` features.

One numpy race (the pybullet env) takes a shortcut on the usual, quiet step — nobody crosses
the line, nears a road edge, touches another car or is done —: the same arithmetic in Python
floats per car (``_quiet_step``, held bit for bit to the array path by
``tests/arena/test_step_shortcuts.py``), which declines every other step.

:class:`arena.episode.RaceEpisodeEnv` (the PettingZoo side: agents, spaces, infos, model
uncertainty, ``park_finished``) drives either simulator through these functions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from arena.batch.xp import NUMPY, Array, NumpyOps, count_true
from arena.rewards import RACING_TERMS, RewardWeights, collision_blame, race_positions, racing_terms
from arena.sim import CarParams, SimError
from tracks import Track
from tracks.geometry import DEFAULT_CHECKPOINTS

STUCK_DISTANCE = 0.5  # m of progress a car must make within ``stuck_time`` seconds
FLIP_UPRIGHT = 0.3  # z of the car's up axis below which it counts as flipped
CUT_JUMP = 3.0  # m: a larger jump in progress in one control step is a cut, not driving
STATE_FEATURES = 10  # per car in the global state: x, y, cos, sin, vx, vy, yaw rate, s, race, on
WHEEL_MARGIN = 1e-9  # m added to the wheels' reach: far above the rounding of wheel offsets
# DNF reasons by code (0: none). "time_limit" is the step limit on both backends.
DNF_REASONS: tuple[str | None, ...] = (
    None,
    "off_track",
    "stuck",
    "flipped",
    "time_limit",
    "crashed",
)
OFF_TRACK, STUCK, FLIPPED, TIME_LIMIT, CRASHED = 1, 2, 3, 4, 5


def default_max_cycles(race_distance: float, control_hz: int) -> int:
    """The default step limit: the time to cover ``race_distance`` m at 2.5 m/s, plus 5 s."""
    return math.ceil((5.0 + race_distance / 2.5) * control_hz)


@dataclass(frozen=True)
class EpisodeRules:
    """The static rules of one track's races (built once per track and direction).

    Attributes:
        n_cars, laps: cars per race, race distance in laps.
        control_hz: control steps per second; ``dt = 1 / control_hz`` s.
        max_cycles: steps before everyone left is truncated.
        off_track_limit: s off the road before a car retires.
        window: control steps of the stuck test (``stuck_time · control_hz``).
        length: lap length, m.
        gate_s: (G,) m, the ordered lap gates (gate 0 is the start line).
        max_jump: m, the largest one-step move that may cross a gate.
        wheel_x, wheel_y: (4,) m, wheel offsets in the car frame (off-track test).
        weights: racing reward weights.
        end_on_crash: a car's episode ends when it touches a wall or another car
            (DeepRacer's ``is_crashed``; DNF ``"crashed"``).
        end_on_wall: a car's episode ends when it touches a wall (DNF ``"crashed"``); for
            training on the batched simulator, whose soft walls let a car slide on where a
            pybullet car that hits one at speed stops dead.
        wheel_reach: m, at least any wheel's distance from the car's centre (plus a margin
            far above rounding); inf turns off the off-track test's shortcut.
    """

    n_cars: int
    laps: int
    control_hz: int
    max_cycles: int
    off_track_limit: float
    window: int
    length: float
    gate_s: Array
    max_jump: float
    wheel_x: Array
    wheel_y: Array
    weights: RewardWeights
    end_on_crash: bool = False
    end_on_wall: bool = False
    wheel_reach: float = math.inf

    @property
    def dt(self) -> float:
        """Control step, s."""
        return 1.0 / self.control_hz

    @property
    def race_distance(self) -> float:
        """m from the start line to the finish."""
        return self.laps * self.length

    @classmethod
    def build(
        cls,
        track: Track,
        ops: NumpyOps,
        *,
        n_cars: int,
        laps: int,
        control_hz: int,
        params: CarParams,
        max_cycles: int | None = None,
        off_track_limit: float = 3.0,
        stuck_time: float = 4.0,
        weights: RewardWeights | None = None,
        end_on_crash: bool = False,
        end_on_wall: bool = False,
    ) -> EpisodeRules:
        """The rules for ``track`` with arrays on ``ops``' device."""
        length = track.length
        n_gates = DEFAULT_CHECKPOINTS
        # tracks.LapCounter's rule: a move may cross at most one gate.
        max_jump = CUT_JUMP if 0.5 * length / n_gates > CUT_JUMP else 0.45 * length / n_gates
        wheel_x = np.array([0.5, 0.5, -0.5, -0.5]) * params.wheelbase
        wheel_y = np.array([0.5, -0.5, 0.5, -0.5]) * params.track_width
        return cls(
            n_cars=n_cars,
            laps=laps,
            control_hz=control_hz,
            max_cycles=max_cycles or default_max_cycles(laps * length, control_hz),
            off_track_limit=off_track_limit,
            window=max(1, round(stuck_time * control_hz)),
            length=length,
            gate_s=ops.asarray(track.checkpoint_s(n_gates)),
            max_jump=max_jump,
            wheel_x=ops.asarray(wheel_x),
            wheel_y=ops.asarray(wheel_y),
            weights=weights or RewardWeights(),
            end_on_crash=end_on_crash,
            end_on_wall=end_on_wall,
            wheel_reach=float(np.max(np.hypot(wheel_x, wheel_y))) + WHEEL_MARGIN,
        )

    def delta_s(self, ops: NumpyOps, s_to: Array, s_from: Array) -> Array:
        """Signed shortest progress from ``s_from`` to ``s_to``, m in ``[-L/2, L/2)``."""
        half = 0.5 * self.length
        return ops.mod(s_to - s_from + half, self.length) - half


@dataclass
class EpisodeState:
    """Per race and car, everything the rules carry from step to step; arrays (B, N).

    ``contact`` is (B, N, N); ``history`` (B, W, N) the race progress of the last W steps
    (row ``steps % W`` is the newest); ``steps`` and ``grid_start`` are (B,).
    ``laps`` is -1 until a car first crosses the start line; ``race_progress`` is metres
    from the start line (negative behind it).
    """

    s: Array
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
    contact: Array
    history: Array
    steps: Array
    grid_start: Array


@dataclass
class Sensed:
    """What the simulator reports after one control step (arrays (B, N) unless noted).

    Attributes:
        s, d, heading: projection onto the centre line: m along, m left, rad.
        yaw: rad; ``left``, ``right``: road half-widths at the cars, m.
        wall: touched a wall during the step; touching: (B, N, N) touched each other.
        upright: z of the up axis (None: the simulator cannot flip a car).
        prev_poses: (B, N, 3) [x, y, yaw] and prev_velocity (B, N, 2) [vx, vy] world m/s
            before the step (collision blame is judged from before the impact).
    """

    s: Array
    d: Array
    heading: Array
    yaw: Array
    left: Array
    right: Array
    wall: Array
    touching: Array
    upright: Array | None
    prev_poses: Array
    prev_velocity: Array


@dataclass
class Outcome:
    """What the rules decided about one step (arrays (B, N) unless noted).

    ``terms`` holds each :data:`arena.rewards.RACING_TERMS` term and ``reward`` their sum;
    ``dnf`` is a code into :data:`DNF_REASONS` (0 where none was decided this step);
    ``contact``, ``new_contact``, ``at_fault`` and ``closing`` (m/s) are (B, N, N).
    """

    progress: Array
    lap_done: Array
    lap_time: Array
    off_track: Array
    all_wheels_on: Array
    wall: Array
    contact: Array
    new_contact: Array
    at_fault: Array
    closing: Array
    terms: dict[str, Array]
    reward: Array
    terminated: Array
    truncated: Array
    dnf: Array
    now: Array  # (B,) s since the race's start


def _plain_numpy(ops: NumpyOps) -> bool:
    return ops is NUMPY or (ops.name == "numpy" and ops.float == np.dtype(np.float64))


def episode_start(
    ops: NumpyOps,
    rules: EpisodeRules,
    s: Array,
    offset: Array,
    grid_start: Array,
) -> EpisodeState:
    """The state of fresh races: cars at rest at progress ``s`` (B, N) m.

    Args:
        offset: (B,) m, where the grid was moved along the lap (0: behind the start line).
        grid_start: (B,) bool: a grid start (lap 1 counts from the start signal); else a
            mid-lap start (lap 1 counts from the first crossing of the line).
    """
    b, n = s.shape
    # First gate strictly ahead of each car (tracks.LapCounter's searchsorted side="right").
    ahead = ops.searchsorted(rules.gate_s, ops.mod(s, rules.length))
    next_gate = ops.where(ahead >= rules.gate_s.shape[0], 0, ahead)
    # Signed metres from the start line; a mid-lap start's offset is already in ``s``.
    progress = rules.delta_s(ops, s, 0.0 * s)
    zeros = ops.zeros((b, n))
    return EpisodeState(
        s=s,
        next_gate=next_gate,
        laps=ops.full((b, n), -1, dtype=ops.int),
        race_progress=progress,
        positions=race_positions(progress, ops),
        active=ops.full((b, n), True, dtype=ops.bool),
        finished=ops.full((b, n), False, dtype=ops.bool),
        finish_time=zeros,
        off_time=zeros,
        line_time=zeros,
        last_lap=zeros,
        contact=ops.full((b, n, n), False, dtype=ops.bool),
        history=progress[:, None, :] + ops.zeros((b, rules.window, n)),
        steps=ops.zeros(b, dtype=ops.int),
        grid_start=grid_start,
    )


def episode_step(
    ops: NumpyOps, rules: EpisodeRules, st: EpisodeState, sensed: Sensed
) -> tuple[EpisodeState, Outcome]:
    """Apply the race rules to one control step; returns the new state and the outcome.

    Cars that are done (terminated or truncated) this step leave the race in the returned
    state (``active`` False); the outcome's arrays describe the step itself.
    """
    if _plain_numpy(ops) and isinstance(st.s, np.ndarray) and st.s.shape[0] == 1:
        quiet = _quiet_step(rules, st, sensed)
        if quiet is not None:
            return quiet
    return _rules_step(ops, rules, st, sensed)


def _quiet_step(
    rules: EpisodeRules, st: EpisodeState, sensed: Sensed
) -> tuple[EpisodeState, Outcome] | None:
    """:func:`_rules_step` of one numpy race on a quiet step, in Python floats per car.

    Quiet: every car racing, and none crosses the start line, has a wheel near a road edge,
    touches another car, finishes, stalls, flips, crashes or runs out of steps — the usual
    step (a car crossing another gate only moves on to the next). Then most of the rules'
    outcome is known (no lap, no contact, nobody done) and
    the rest is a few operations per car, the same IEEE operations in the same order as
    the array path's (Python's float ``%`` is ``np.mod``'s remainder, a stable sort the
    stable argsort), so the very same bits (a test holds the two paths equal) without its
    ~80 numpy calls on (1, N) arrays. None, when the step is not quiet or a value is NaN:
    then the array path decides.
    """
    active, touching, wall = st.active, sensed.touching, sensed.wall
    if not active.dtype == touching.dtype == wall.dtype == np.bool_:
        return None
    n = active.shape[1]
    if count_true(active) != n or count_true(touching):
        return None
    steps = st.steps + 1
    step = int(steps[0])
    w = rules.window
    if step >= rules.max_cycles or rules.off_track_limit < 0.0:  # truncated; off too long
        return None
    if (rules.end_on_crash or rules.end_on_wall) and count_true(wall):
        return None
    length = rules.length
    half = 0.5 * length
    laps_done = rules.laps
    s_now, s_prev = sensed.s[0].tolist(), st.s[0].tolist()
    gates = rules.gate_s[st.next_gate[0]].tolist()
    old_progress = st.race_progress[0].tolist()
    n_gates, max_jump = rules.gate_s.shape[0], rules.max_jump
    next_gates = st.next_gate[0].tolist()
    passed = False
    progress: list[float] = []
    race_progress: list[float] = []
    for i, (s_to, s_from, gate, before_progress, laps) in enumerate(
        zip(s_now, s_prev, gates, old_progress, st.laps[0].tolist(), strict=True)
    ):
        ds = (s_to - s_from + half) % length - half  # EpisodeRules.delta_s
        ahead = (gate - s_from + half) % length - half
        if ahead > 0 and ahead <= ds <= max_jump:  # crosses its next gate
            if next_gates[i] == 0:  # the line: laps and lap times are the array path's
                return None
            next_gates[i] = next_gates[i] + 1 if next_gates[i] + 1 < n_gates else 0
            passed = True
        if max(laps, 0) >= laps_done:  # a finisher (never one still racing)
            return None
        moved = 0.0 if abs(ds) > CUT_JUMP else ds
        progress.append(moved)
        race_progress.append(before_progress + moved)
    reach = rules.wheel_reach
    for d, left, right in zip(
        sensed.d[0].tolist(), sensed.left[0].tolist(), sensed.right[0].tolist(), strict=True
    ):
        wheels = abs(d) + reach
        if not (wheels <= left and wheels <= right):  # near an edge, or NaN
            return None
    if sensed.upright is not None and any(up < FLIP_UPRIGHT for up in sensed.upright[0].tolist()):
        return None
    if any(map(math.isnan, race_progress)):
        return None
    # Positions: the stable argsort of −progress (no NaN), inverted, 1-based.
    behind = [-x for x in race_progress]
    rank = [0] * n
    for place, i in enumerate(sorted(range(n), key=behind.__getitem__)):
        rank[i] = place + 1
    progress_row = np.array([race_progress])
    history = st.history.copy()
    history[0, step % w] = progress_row[0]
    if step >= w:
        oldest = history[0, (step + 1) % w].tolist()
        for now_at, then in zip(race_progress, oldest, strict=True):
            if now_at - then < STUCK_DISTANCE:  # stuck
                return None
    # racing_terms' products per car (nothing off track, to blame or done: zeros there),
    # then their sum in RACING_TERMS order; one table of rows (1, N).
    wt = rules.weights
    off_term, wall_scale = -wt.off_track * rules.dt * 0.0, -wt.wall * rules.dt
    blame_term = -wt.collision * 0.0
    progress_terms, wall_terms, overtake_terms, reward = [], [], [], []
    for moved, on, before_rank, now_rank in zip(
        progress, wall[0].tolist(), st.positions[0].tolist(), rank, strict=True
    ):
        progress_term = wt.progress * moved
        wall_term = wall_scale * (1.0 if on else 0.0)
        overtake_term = wt.overtake * float(before_rank - now_rank)
        progress_terms.append(progress_term)
        wall_terms.append(wall_term)
        overtake_terms.append(overtake_term)
        reward.append((((progress_term + off_term) + wall_term) + blame_term) + overtake_term)
    off_terms, blame_terms = [off_term] * n, [blame_term] * n
    table = np.array(
        [progress_terms, off_terms, wall_terms, blame_terms, overtake_terms, reward, progress]
    )
    rows = [table[k : k + 1] for k in range(len(table))]
    terms = dict(zip(RACING_TERMS, rows, strict=False))
    none = np.zeros((1, n), dtype=bool)  # no lap, off-track car, termination or truncation
    contact = np.zeros((1, n, n), dtype=bool)
    new = EpisodeState(
        s=sensed.s,
        next_gate=np.array([next_gates], dtype=np.int64) if passed else st.next_gate,
        laps=st.laps,
        race_progress=progress_row,
        positions=np.array([rank], dtype=np.int64),
        active=active.copy(),
        finished=st.finished,
        finish_time=st.finish_time,
        off_time=np.zeros((1, n)),
        line_time=st.line_time,
        last_lap=st.last_lap,
        contact=contact,
        history=history,
        steps=steps,
        grid_start=st.grid_start,
    )
    out = Outcome(
        progress=rows[6],
        lap_done=none,
        lap_time=np.zeros((1, n)),
        off_track=none,
        all_wheels_on=~none,
        wall=wall.copy(),
        contact=contact,
        new_contact=contact.copy(),
        at_fault=contact,
        closing=np.zeros((1, n, n)),
        terms=terms,
        reward=rows[5],
        terminated=none,
        truncated=none,
        dnf=np.zeros((1, n), dtype=np.int64),
        now=steps.astype(np.float64) / rules.control_hz,
    )
    return new, out


def _rules_step(
    ops: NumpyOps, rules: EpisodeRules, st: EpisodeState, sensed: Sensed
) -> tuple[EpisodeState, Outcome]:
    """:func:`episode_step` over arrays (any backend, any number of races)."""
    # numpy float64 takes np.where as it is (ops.where only keeps float32 arrays float32).
    where = np.where if _plain_numpy(ops) else ops.where
    active = st.active
    # The usual step on one race: every car racing, so a mask by ``active`` is the array
    # itself (the same values below in fewer operations).
    everyone = isinstance(active, np.ndarray) and count_true(active) == active.size
    steps = st.steps + 1
    now = ops.cast(steps, ops.float) / rules.control_hz  # exact: k / 20, not k · 0.05
    now_n = now[:, None]

    ds = rules.delta_s(ops, sensed.s, st.s)
    cut = ops.abs(ds) > CUT_JUMP
    progress = where(~cut if everyone else active & ~cut, ds, 0.0)
    race_progress = st.race_progress + progress

    # Ordered gates, exactly tracks.LapCounter (only racing cars count).
    gate = rules.gate_s[st.next_gate]
    before = rules.delta_s(ops, gate, st.s)
    reached = (before > 0) & (before <= ds)  # the next gate lies within this step's move
    if isinstance(reached, np.ndarray) and not count_true(reached):
        # The common case on one race (a car passes a gate every second or so): nothing
        # crossed, the same values as below without the work.
        lap_done = reached
        lap_time = ops.zeros(reached.shape)
        laps, next_gate, line_time, last_lap = st.laps, st.next_gate, st.line_time, st.last_lap
    else:
        crossed = (ds > 0) & (ds <= rules.max_jump) & reached & active
        finish_line = crossed & (st.next_gate == 0)
        started = st.laps >= 0  # laps is -1 until the first crossing of the line, then counts
        lap_done = finish_line & started
        first_cross = finish_line & ~started
        laps = where(finish_line, st.laps + 1, st.laps)
        next_gate = where(crossed, st.next_gate + 1, st.next_gate)
        next_gate = where(next_gate >= rules.gate_s.shape[0], 0, next_gate)
        line_time = where(first_cross & ~st.grid_start[:, None], now_n, st.line_time)
        lap_time = where(lap_done, now_n - line_time, 0.0)
        line_time = where(lap_done, now_n, line_time)
        last_lap = where(lap_done, lap_time, st.last_lap)
    laps_completed = ops.maximum(laps, 0)

    # DeepRacer's off-track rule: all four wheels off the road.
    reach = ops.abs(sensed.d) + rules.wheel_reach  # m: no wheel is farther off the centre
    clear = (reach <= sensed.left) & (reach <= sensed.right)
    if isinstance(clear, np.ndarray) and count_true(clear) == clear.size:
        # The common case on one race: every car's wheels are all on the road, whatever its
        # heading; the same values as below, without the work.
        off_track = np.zeros(clear.shape, dtype=bool)
        all_wheels_on = ~off_track
        off_time = ops.zeros(clear.shape)
    else:
        heading_error = sensed.yaw - sensed.heading
        sin_h, cos_h = ops.sin(heading_error)[..., None], ops.cos(heading_error)[..., None]
        wheel_d = sensed.d[..., None] + rules.wheel_x * sin_h + rules.wheel_y * cos_h
        on = (wheel_d <= sensed.left[..., None]) & (wheel_d >= -sensed.right[..., None])
        off_track = ~ops.any(on, axis=-1) & active
        all_wheels_on = ops.all(on, axis=-1)
        off_time = where(off_track, st.off_time + rules.dt, 0.0)

    if everyone:
        contact = sensed.touching.astype(bool)  # a copy, as the masked one below
    else:
        contact = sensed.touching & active[..., :, None] & active[..., None, :]
    if isinstance(contact, np.ndarray) and not count_true(contact):
        # The common case on one race, and the same result without the work.
        at_fault, closing = contact, ops.zeros(contact.shape)
    else:
        at_fault, closing = collision_blame(
            sensed.prev_poses, sensed.prev_velocity, contact, ops=ops
        )
    # A collision counts once, when the contact starts: a long push is one incident.
    new_contact = contact & ~st.contact

    reached_laps = laps_completed >= rules.laps
    newly_finished = reached_laps if everyone else active & reached_laps
    nobody_finished = isinstance(newly_finished, np.ndarray) and not count_true(newly_finished)
    if nobody_finished:  # the usual step: the same values as below, without the work
        finished, finish_time, still = st.finished, st.finish_time, active
    else:
        finished = st.finished | newly_finished
        finish_time = where(newly_finished, now_n, st.finish_time)
        still = active & ~newly_finished
    if everyone and not count_true(finished):
        # Everyone still racing, nobody finished: the key below is the race progress.
        positions = race_positions(race_progress, ops)
    else:
        # Finished cars first (earliest first), then by race progress, then the parked cars;
        # ``top`` exceeds any progress and stays exact in float32 (not 1e12 − t).
        top = 4.0 * rules.race_distance + 1000.0
        rank_key = where(finished, top - finish_time, race_progress)
        positions = race_positions(where(active | finished, rank_key, -top), ops)
    gained = st.positions - positions if everyone else where(active, st.positions - positions, 0)

    w = rules.window
    slot = ops.mod(steps, w)
    oldest = ops.mod(steps + 1, w)
    if isinstance(st.history, np.ndarray):  # plain indexing: same values, less work
        rows = ops.arange(len(slot))
        history = st.history.copy()
        history[rows, slot] = race_progress
        moved = race_progress - history[rows, oldest]
    else:
        onehot = (ops.arange(w)[None, :] == slot[:, None])[..., None]
        history = where(onehot, race_progress[:, None, :], st.history)
        moved = race_progress - ops.take_along(history, oldest.reshape(-1, 1, 1), 1)[:, 0, :]
    stuck = (steps >= w)[:, None] & (moved < STUCK_DISTANCE)
    lost = off_time > rules.off_track_limit
    flipped = sensed.upright < FLIP_UPRIGHT if sensed.upright is not None else still & False
    if not (everyone and nobody_finished):  # else ``still`` is everyone
        stuck, lost, flipped = still & stuck, still & lost, still & flipped
    terminated = stuck | lost | flipped
    if not nobody_finished:
        terminated = newly_finished | terminated
    crashed = None
    if rules.end_on_crash or rules.end_on_wall:  # static configuration
        hit = sensed.wall | ops.any(contact, axis=-1) if rules.end_on_crash else sensed.wall
        crashed = still & hit
        terminated = terminated | crashed
    truncated = ~terminated & (steps >= rules.max_cycles)[:, None]
    if not everyone:
        truncated = active & truncated
    done = terminated | truncated
    if isinstance(done, np.ndarray) and not count_true(done):
        dnf = np.zeros(done.shape, dtype=np.int64)  # the common case on one race
    else:
        reason = where(stuck, STUCK, 0)
        if crashed is not None:
            reason = where(crashed, CRASHED, reason)
        reason = where(lost, OFF_TRACK, reason)
        dnf = where(flipped, FLIPPED, reason) + where(truncated, TIME_LIMIT, 0)

    wall = sensed.wall.astype(bool) if everyone else sensed.wall & active  # a copy either way
    terms = racing_terms(
        progress, off_track, wall, at_fault, closing, gained, rules.dt, rules.weights, ops
    )
    reward = terms[RACING_TERMS[0]]
    for name in RACING_TERMS[1:]:
        reward = reward + terms[name]
    new = EpisodeState(
        s=sensed.s,
        next_gate=next_gate,
        laps=laps,
        race_progress=race_progress,
        positions=positions,
        active=active & ~done,
        finished=finished,
        finish_time=finish_time,
        off_time=off_time,
        line_time=line_time,
        last_lap=last_lap,
        contact=contact,
        history=history,
        steps=steps,
        grid_start=st.grid_start,
    )
    out = Outcome(
        progress=progress,
        lap_done=lap_done,
        lap_time=lap_time,
        off_track=off_track,
        all_wheels_on=all_wheels_on,
        wall=wall,
        contact=contact,
        new_contact=new_contact,
        at_fault=at_fault,
        closing=closing,
        terms=terms,
        reward=reward,
        terminated=terminated,
        truncated=truncated,
        dnf=dnf,
        now=now,
    )
    return new, out


@dataclass(frozen=True)
class StartSpec:
    """A parsed ``reset(options=...)``: direction, grid order and start offset.

    Attributes:
        reverse: drive the track the other way round.
        order: (N,) car indices, pole first.
        offset: m along the lap the grid is moved (0: behind the start line), or None for a
            random offset (drawn by :func:`start_offset` once the track is known).
    """

    reverse: bool
    order: NDArray[np.int64]
    offset: float | None


def start_spec(options: dict[str, Any], rng: np.random.Generator, n_cars: int) -> StartSpec:
    """Parse ``reset`` options ``direction``, ``grid_order`` and ``start_offset``.

    ``"random"`` draws from ``rng`` in that order (direction, grid order, then the offset in
    :func:`start_offset`), so a seed fixes all three.

    Raises:
        SimError: a value outside the grammar.

    >>> spec = start_spec({"grid_order": [1, 0], "start_offset": 12}, np.random.default_rng(0), 2)
    >>> spec.reverse, spec.order.tolist(), spec.offset
    (False, [1, 0], 12.0)
    """
    direction = options.get("direction", "forward")
    if direction == "random":
        direction = "reverse" if rng.random() < 0.5 else "forward"
    if direction not in ("forward", "reverse"):
        raise SimError(f"direction must be forward, reverse or random, got {direction!r}")
    order = options.get("grid_order")
    if isinstance(order, str) and order == "random":
        order = rng.permutation(n_cars)
    try:
        order = np.arange(n_cars) if order is None else np.asarray(order, dtype=np.int64)
    except (TypeError, ValueError) as exc:
        raise SimError(f"grid_order must be a permutation of 0..{n_cars - 1}") from exc
    if order.ndim != 1 or sorted(order.tolist()) != list(range(n_cars)):
        raise SimError(f"grid_order must be a permutation of 0..{n_cars - 1}")
    offset = options.get("start_offset", 0.0)
    if isinstance(offset, str):
        if offset != "random":
            raise SimError(f"start_offset must be metres or 'random', got {offset!r}")
        return StartSpec(direction == "reverse", order, None)
    try:
        value = float(offset)
    except (TypeError, ValueError) as exc:
        raise SimError(f"start_offset must be metres or 'random', got {offset!r}") from exc
    if not math.isfinite(value):
        raise SimError(f"start_offset must be finite, got {offset!r}")
    return StartSpec(direction == "reverse", order, value)


def start_offset(spec: StartSpec, rng: np.random.Generator, length: float) -> float:
    """The spec's offset, m, drawing a random one in ``[0, length)`` if asked."""
    return float(rng.uniform(0.0, length)) if spec.offset is None else spec.offset


def global_state(
    poses: Array,
    velocity: Array,
    s: Array,
    race_progress: Array,
    active: Array,
    track: Track,
    race_distance: float,
    max_speed: float,
    ops: NumpyOps = NUMPY,
) -> Array:
    """(..., N, STATE_FEATURES) per-car global-state features; parked cars read zeros.

    Per car: x, y (relative to the track's centre, in half-extents), cos and sin of yaw,
    vx, vy (/ max speed), yaw rate (/ π), s (/ lap length), race progress (/ race
    distance), racing (1/0). Any leading batch axes (one race: (N, ...); the batched
    simulator: (B, N, ...)), any :mod:`arena.batch.xp` namespace.

    Args:
        poses: (..., N, 3) [x m, y m, yaw rad]; velocity: (..., N, 3) [vx, vy m/s world,
            yaw rate rad/s].
        s, race_progress: (..., N) m; active: (..., N) still racing.
        ops: array namespace.
    """
    xmin, ymin, xmax, ymax = track.bounds
    half = max(0.5 * (xmax - xmin), 0.5 * (ymax - ymin), 1.0)
    feats = ops.stack(
        [
            (poses[..., 0] - 0.5 * (xmin + xmax)) / half,
            (poses[..., 1] - 0.5 * (ymin + ymax)) / half,
            ops.cos(poses[..., 2]),
            ops.sin(poses[..., 2]),
            velocity[..., 0] / max_speed,
            velocity[..., 1] / max_speed,
            velocity[..., 2] / math.pi,
            s / track.length,
            race_progress / race_distance,
            ops.full(tuple(s.shape), 1.0),
        ],
        axis=-1,
    )
    return ops.where(active[..., None], feats, 0.0)
