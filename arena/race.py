"""A whole race with policies: grid, laps, lap times, finishing order, results and a replay.

Finishing order: cars that complete the race distance, by total time (race time plus, in
ranked races, DeepRacer's penalties: +2 s per off-track excursion and +5 s per collision the
car was to blame for); then the cars that did not finish, by laps completed and distance.
A policy that raises leaves the race as ``dnf`` with reason ``error`` — or with the
exception's ``dnf_reason`` attribute when it has one (a sandboxed policy's ``"timeout"``,
``"invalid"``) —; one that returns an action outside the action space (wrong shape, not a
number, NaN/inf, out of range), with reason ``invalid``. The race goes on for the others.
A car still running when the race's step limit is reached is ``dnf`` with ``time_limit``.

Policies that offer ``start()`` are started before the env is built (a sandboxed policy
loads in its own process meanwhile); those that offer two-phase ``send(obs)`` /
``receive()`` are sent their observations all at once and then collected, so sandboxed cars
think in parallel, and they are ``close()``-d when the race ends.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from contextlib import suppress
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
from gymnasium import spaces

from arena.cars import car_name
from arena.colours import car_colour
from arena.env import RacingEnv
from arena.replay import ReplayLog
from arena.version import ENV_VERSION
from tracks import Track

OFF_TRACK_PENALTY = 2.0  # s per off-track excursion in ranked races (DeepRacer)
COLLISION_PENALTY = 5.0  # s per at-fault collision in ranked races (DeepRacer)
ProgressFn = Callable[[int, int], None]

_NUM_OR_NULL = {"type": ["number", "null"]}
RESULT_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "Slipstream race result",
    "type": "object",
    "required": ["track", "seed", "laps", "env_version", "ranked", "steps", "sim_time", "cars"],
    "properties": {
        "track": {"type": "string"},
        "seed": {"type": "integer"},
        "laps": {"type": "integer", "minimum": 1},
        "env_version": {"type": "string"},
        "ranked": {"type": "boolean"},
        "steps": {"type": "integer", "minimum": 0},
        "sim_time": {"type": "number", "minimum": 0},
        "cars": {
            "type": "array",
            "minItems": 1,
            "items": {
                "type": "object",
                "required": [
                    "agent",
                    "name",
                    "position",
                    "status",
                    "dnf_reason",
                    "laps_completed",
                    "lap_times",
                    "best_lap",
                    "total_time",
                    "collisions",
                    "at_fault_collisions",
                    "off_track",
                ],
                "properties": {
                    "agent": {"type": "string", "pattern": "^car_[0-9]+$"},
                    "name": {"type": "string"},
                    "position": {"type": "integer", "minimum": 1},
                    "status": {"enum": ["finished", "dnf"]},
                    "dnf_reason": {"type": ["string", "null"]},
                    "laps_completed": {"type": "integer", "minimum": 0},
                    "lap_times": {"type": "array", "items": {"type": "number", "minimum": 0}},
                    "best_lap": _NUM_OR_NULL,
                    "total_time": _NUM_OR_NULL,
                    "race_time": _NUM_OR_NULL,
                    "penalties": {"type": "number", "minimum": 0},
                    "collisions": {"type": "integer", "minimum": 0},
                    "at_fault_collisions": {"type": "integer", "minimum": 0},
                    "off_track": {"type": "integer", "minimum": 0},
                    "distance": {"type": "number"},
                },
            },
        },
    },
}


@runtime_checkable
class Policy(Protocol):
    """Something that drives one car: ``reset(seed)`` before a race, ``act(obs)`` each step."""

    name: str

    def reset(self, seed: int | None = None) -> None:
        """Prepare for a new race."""
        ...

    def act(self, obs: Any) -> Any:
        """The action for one observation."""
        ...


@dataclass
class CarResult:
    """One car's race (times in seconds of simulated time)."""

    agent: str
    name: str
    position: int
    status: str  # "finished" or "dnf"
    dnf_reason: str | None
    laps_completed: int
    lap_times: list[float]
    best_lap: float | None
    total_time: float | None
    race_time: float | None
    penalties: float
    collisions: int
    at_fault_collisions: int
    off_track: int
    distance: float


@dataclass
class RaceResult:
    """The result of a race; ``to_json`` gives the document other parts read."""

    track: str
    seed: int
    laps: int
    env_version: str
    ranked: bool
    steps: int
    sim_time: float
    cars: list[CarResult] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict."""
        return asdict(self)

    def to_json(self, path: Path | None = None) -> str:
        """JSON text, also written to ``path`` when given."""
        text = json.dumps(self.to_dict(), indent=2)
        if path is not None:
            path.write_text(text + "\n", encoding="utf-8")
        return text

    def by_position(self) -> list[CarResult]:
        """Cars in finishing order."""
        return sorted(self.cars, key=lambda c: c.position)


ACTION_TOLERANCE = 1e-6  # slack on Box bounds for float rounding


def action_problem(action: Any, space: spaces.Space[Any] | None) -> str | None:
    """What is wrong with ``action`` for ``space`` (None: nothing).

    Checks that it is real numbers (not text, bool, complex or objects), finite, of the
    space's shape, and inside it: a ``Box``'s bounds (± ``ACTION_TOLERANCE``), a
    ``Discrete``'s integers ``start … start + n - 1``.
    """
    try:
        arr = np.asarray(action)
    except (TypeError, ValueError) as err:  # ragged nested lists and the like
        return f"not an array: {err}"
    if arr.dtype.kind not in "fiu":
        return f"not a number (dtype {arr.dtype})"
    if not bool(np.all(np.isfinite(arr))):
        return "NaN or infinite value"
    if space is None:
        return None
    if arr.shape != space.shape:
        return f"shape {arr.shape}, expected {space.shape}"
    if isinstance(space, spaces.Box):
        if np.any(arr < space.low - ACTION_TOLERANCE) or np.any(
            arr > space.high + ACTION_TOLERANCE
        ):
            return f"{arr.tolist()} outside [{space.low.tolist()}, {space.high.tolist()}]"
    elif isinstance(space, spaces.Discrete):
        value = float(arr)
        first, count = int(space.start), int(space.n)
        if value != round(value) or not first <= value < first + count:
            return f"{value:g} is not an action of Discrete({space.n})"
    return None


def _dnf_reason(err: BaseException) -> str:
    reason = getattr(err, "dnf_reason", None)
    return reason if isinstance(reason, str) and reason else "error"


def _two_phase(policy: Policy) -> bool:
    return callable(getattr(policy, "send", None)) and callable(getattr(policy, "receive", None))


def run_race(
    policies: Sequence[Policy],
    *,
    track: str | Path | Track = "oval",
    laps: int = 1,
    seed: int = 0,
    ranked: bool = False,
    grid_order: Sequence[int] | str | None = None,
    progress: ProgressFn | None = None,
    record: bool = True,
    env_kwargs: dict[str, Any] | None = None,
) -> tuple[RaceResult, ReplayLog | None]:
    """Race ``policies`` (car ``i`` is driven by ``policies[i]``) and return the result.

    Args:
        policies: one per car, 1–16.
        track: anything :func:`tracks.load_track` takes.
        laps: race distance in laps.
        seed: seeds the env (grid, noise) and each policy (``seed + i``).
        ranked: add DeepRacer time penalties.
        grid_order: car indices pole first, ``"random"`` (seeded), or None for 0, 1, 2…
        progress: called as ``progress(step, max_steps)`` after every step.
        record: also build a replay log.
        env_kwargs: extra :class:`RacingEnv` arguments.
    """
    start_errors: dict[int, Exception] = {}
    try:
        for i, pol in enumerate(policies):
            start = getattr(pol, "start", None)
            if callable(start):
                try:
                    start()
                except Exception as err:  # reported when the car would take the grid
                    start_errors[i] = err
        env = RacingEnv(track=track, n_cars=len(policies), laps=laps, **(env_kwargs or {}))
        try:
            return _race(
                env, policies, laps, seed, ranked, grid_order, progress, record, start_errors
            )
        finally:
            env.close()
    finally:
        for pol in policies:
            if _two_phase(pol):
                with suppress(Exception):
                    pol.close()  # type: ignore[attr-defined]


def _race(
    env: RacingEnv,
    policies: Sequence[Policy],
    laps: int,
    seed: int,
    ranked: bool,
    grid_order: Sequence[int] | str | None,
    progress: ProgressFn | None,
    record: bool,
    start_errors: dict[int, Exception],
) -> tuple[RaceResult, ReplayLog | None]:
    options: dict[str, Any] = {}
    if grid_order is not None:
        options["grid_order"] = grid_order if isinstance(grid_order, str) else list(grid_order)
    obs, _ = env.reset(seed=seed, options=options)
    agents = list(env.possible_agents)
    names = [getattr(p, "name", type(p).__name__) for p in policies]
    replay = None
    if record:
        replay = ReplayLog(
            track=env.track,
            dt=env.dt,
            cars=[
                {"agent": a, "name": names[i], "colour": list(car_colour(i))}
                for i, a in enumerate(agents)
            ],
            env_version=ENV_VERSION,
            car={
                "name": car_name(env.params),
                "length": env.params.length,
                "width": env.params.width,
                "height": env.params.height,
            },
        )
        _frame(env, replay, 0.0)
    for i, (agent, pol) in enumerate(zip(agents, policies, strict=True)):
        err = start_errors.get(i)
        if err is None:
            try:
                pol.reset(seed + i)
                continue
            except Exception as reset_err:  # a policy that cannot even start sits out
                err = reset_err
        _retire(env, replay, agent, _dnf_reason(err), detail=f"{type(err).__name__}: {err}")
    recorder = _EventRecorder(replay) if replay is not None else None
    while env.agents:
        actions = _actions(env, replay, policies, obs)
        if not env.agents:
            break
        obs, _, term, trunc, infos = env.step(actions)
        now = env.sim_state.time
        if replay is not None and recorder is not None:
            recorder.record(now, infos, term, trunc)
            _frame(env, replay, now)
        if progress is not None:
            progress(env.steps, env.max_cycles)
    return _result(env, names, laps, seed, ranked), replay


def _actions(
    env: RacingEnv, replay: ReplayLog | None, policies: Sequence[Policy], obs: dict[str, Any]
) -> dict[str, Any]:
    """One action per racing car; a car whose policy fails is retired instead.

    Two-phase policies get their observations first and are collected last, so they think
    while the in-process policies act.
    """
    results: dict[str, Any] = {}
    sent: list[str] = []
    for agent in list(env.agents):
        pol = policies[env.agent_index[agent]]
        try:
            if _two_phase(pol):
                pol.send(obs[agent])  # type: ignore[attr-defined]
                sent.append(agent)
            else:
                results[agent] = pol.act(obs[agent])
        except Exception as err:  # a policy's bug must not stop the race
            _retire(env, replay, agent, _dnf_reason(err), detail=f"{type(err).__name__}: {err}")
    for agent in sent:
        try:
            results[agent] = policies[env.agent_index[agent]].receive()  # type: ignore[attr-defined]
        except Exception as err:
            _retire(env, replay, agent, _dnf_reason(err), detail=f"{type(err).__name__}: {err}")
    actions: dict[str, Any] = {}
    for agent, act in results.items():
        problem = action_problem(act, env.action_space(agent))
        if problem is None:
            actions[agent] = act
        else:
            _retire(env, replay, agent, "invalid", detail=problem)
    return actions


def _retire(
    env: RacingEnv, replay: ReplayLog | None, agent: str, reason: str, detail: str = ""
) -> None:
    env.retire(agent, reason)
    if replay is not None:
        extra = {"detail": detail} if detail else {}
        replay.add_event(env.sim_state.time, "dnf", agent, reason=reason, **extra)


def _frame(env: RacingEnv, replay: ReplayLog, t: float) -> None:
    st = env.sim_state
    replay.add_frame(t, st.poses, st.steering, st.v_long, env.active)


@dataclass
class _EventRecorder:
    """Turns per-step infos into replay events (lap counts and off-track edges)."""

    replay: ReplayLog
    laps_seen: dict[str, int] = field(default_factory=dict)
    was_off: dict[str, bool] = field(default_factory=dict)

    def record(
        self,
        now: float,
        infos: dict[str, dict[str, Any]],
        term: dict[str, bool],
        trunc: dict[str, bool],
    ) -> None:
        replay = self.replay
        for agent, info in infos.items():
            laps = info["lap_times"]
            if len(laps) > self.laps_seen.get(agent, 0):
                replay.add_event(now, "lap", agent, lap=len(laps), lap_time=round(laps[-1], 4))
                self.laps_seen[agent] = len(laps)
            for hit in (h for h in info["collisions"] if h["new"]):  # once per contact
                replay.add_event(
                    now,
                    "collision",
                    agent,
                    other=hit["with"],
                    at_fault=hit["at_fault"],
                    closing_speed=round(hit["closing_speed"], 3),
                )
            if info["off_track"] and not self.was_off.get(agent, False):
                replay.add_event(now, "off_track", agent)
            self.was_off[agent] = info["off_track"]
            if term.get(agent) or trunc.get(agent):
                reason = info.get("dnf_reason")
                if reason is None:
                    replay.add_event(now, "finish", agent)
                else:
                    replay.add_event(now, "dnf", agent, reason=reason)


def _result(
    env: RacingEnv,
    names: list[str],
    laps: int,
    seed: int,
    ranked: bool,
) -> RaceResult:
    cars: list[CarResult] = []
    for i, agent in enumerate(env.possible_agents):
        finished = bool(env.finished[i])
        penalties = 0.0
        if ranked:
            penalties = OFF_TRACK_PENALTY * int(env.off_track_count[i]) + COLLISION_PENALTY * int(
                env.at_fault_count[i]
            )
        race_time = float(env.finish_time[i]) if finished else None
        lap_times = [round(t, 4) for t in env.lap_times[i]]
        cars.append(
            CarResult(
                agent=agent,
                name=names[i],
                position=0,
                status="finished" if finished else "dnf",
                dnf_reason=None if finished else (env.dnf_reason[i] or "time_limit"),
                laps_completed=int(env.laps_completed[i]),
                lap_times=lap_times,
                best_lap=min(lap_times) if lap_times else None,
                total_time=round(race_time + penalties, 4) if race_time is not None else None,
                race_time=round(race_time, 4) if race_time is not None else None,
                penalties=penalties,
                collisions=int(env.collision_count[i]),
                at_fault_collisions=int(env.at_fault_count[i]),
                off_track=int(env.off_track_count[i]),
                distance=round(float(env.race_progress[i]), 3),
            )
        )
    order = sorted(
        range(len(cars)),
        key=lambda i: (
            0 if cars[i].status == "finished" else 1,
            cars[i].total_time if cars[i].total_time is not None else math.inf,
            -cars[i].laps_completed,
            -cars[i].distance,
        ),
    )
    for pos, i in enumerate(order, start=1):
        cars[i].position = pos
    return RaceResult(
        track=env.base_track.name,
        seed=seed,
        laps=laps,
        env_version=ENV_VERSION,
        ranked=ranked,
        steps=env.steps,
        sim_time=round(env.sim_state.time, 4),
        cars=cars,
    )
