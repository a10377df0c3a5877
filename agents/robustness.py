"""Robustness of a racing policy under model uncertainty, and RARL-style nature training.

Protocol (Zhang et al. 2020; DeepRacer's robust evaluation; the anchors' §4.6). The policy
drives one car alone on a track, deterministic, from a standing start at each of ``starts``
(fractions of the lap; 0 is the grid) over ``laps`` laps' distance, and each race is scored
by its **effective speed**, m/s: the race distance divided by the time the car took to
cover it from its start, or the distance it covered divided by the env's time limit when it
did not (crashing out early or crawling both score low). A point's score is the mean over
the starts: one hard corner after the start then decides less of the worst case. Then:

* **nominal**: the unperturbed car;
* **grid**: every point of friction × motor gain × steering offset × latency (default
  {0.6, 0.8, 1.0, 1.2} × {0.8, 1.0, 1.2} × {−0.05, 0, 0.05} rad × {0, 1, 2} steps = 108
  races, the rest nominal): the **worst case**, the **worst-10 % mean** (CVaR₁₀) and
  **worst / nominal**;
* **random**: ``n_random`` draws of the whole default set (also mass, steering gain and
  action noise), :func:`arena.uncertainty.default_config` in ``sample`` mode: the mean;
* **degradation**: the grid shrunk about nominal by ``s`` (0 … 1): worst case and mean per
  ``s``, drawn as a PNG;
* **nature**: a fresh nature (PPO, ``nature_steps`` steps) trained against the frozen policy,
  acting every step inside the default set with a 10 %-per-step rate limit; the policy's
  score against it.

With ``backend="batch"`` every race of the grid, the degradation curve and the random draws
is one environment of a single :class:`arena.batch.sim.BatchSim` (:func:`run_batch_episodes`:
108 grid races in a few seconds on a laptop core), and the ``confirm`` worst grid points are
raced again on pybullet (the reference simulator of ranked races) and reported beside their
batch scores. The nature attack stays on pybullet.

:func:`rarl_callback` is the training side: every ``nature_every`` racer steps, a nature PPO
is trained for ``nature_steps`` against a frozen copy of the racer, and the racers then
race against a frozen copy of that nature (Pinto et al.'s RARL alternation).
"""

from __future__ import annotations

import itertools
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from agents.policy import Policy, PolicyError

if TYPE_CHECKING:
    from arena.env import RacingEnv

GRID: dict[str, tuple[float, ...]] = {
    "friction": (0.6, 0.8, 1.0, 1.2),
    "motor": (0.8, 1.0, 1.2),
    "steer_offset": (-0.05, 0.0, 0.05),
    "latency": (0, 1, 2),
}
NOMINAL = {"friction": 1.0, "motor": 1.0, "steer_offset": 0.0, "latency": 0}
AXES: dict[str, float] = {
    **NOMINAL,
    "mass": 1.0,
    "steer_gain": 1.0,
    "action_noise": 0.0,
    "lidar_noise": 0.0,
    "lidar_dropout": 0.0,
}
"""Every parameter a grid may vary (:mod:`arena.uncertainty`'s names), with its nominal value;
:data:`GRID` varies the first four, a grid of one's own any of them."""
SCALES = (0.0, 0.25, 0.5, 0.75, 1.0)
WORST_SHARE = 0.1  # the "worst-10 %" tail
ProgressFn = Callable[[str, int, int], None]


# ---- one race -------------------------------------------------------------------------------


@dataclass
class Episode:
    """One scored race."""

    score: float  # effective speed, m/s
    finished: bool  # covered the race distance
    distance: float  # m covered along the track from the start
    time: float  # s: time to cover the race distance, or the time limit
    dnf_reason: str | None
    perturbation: dict[str, float] = field(default_factory=dict)


def observation_kwargs(policy: Policy) -> dict[str, Any]:
    """The env arguments ``policy``'s observations need: ``observe_perturbation=True`` for a
    checkpoint trained on perturbation-aware observations, else none."""
    return {"observe_perturbation": True} if getattr(policy, "observes_perturbation", False) else {}


def run_episode(
    env: RacingEnv,
    policy: Policy,
    *,
    seed: int,
    perturbation: dict[str, float] | None = None,
    nature: Any = None,
    start: float = 0.0,
) -> Episode:
    """Race ``policy`` on car 0 of ``env`` (other cars parked) and score it.

    The race ends when the car has covered ``env.race_distance`` metres along the track
    from where it started (a mid-lap start does not have to reach the line first), or when
    the env ends it (a DNF or the time limit).

    Args:
        env: a one-car env, ``fixed`` mode for ``perturbation``, ``adversarial`` for
            ``nature`` (something with ``act_batch(obs (k, d)) -> (k, a)``).
        policy: drives car 0.
        seed: env and policy seed.
        perturbation: the fixed perturbation (names to values).
        nature: drives ``nature_car_0``.
        start: where the grid stands, as a fraction of the lap (0: the start line).
    """
    options: dict[str, Any] = {} if perturbation is None else {"perturbation": perturbation}
    if start:
        options["start_offset"] = start * env.base_track.length
    obs, infos = env.reset(seed=seed, options=options)
    policy.reset(seed)
    applied: dict[str, float] = infos["car_0"].get("perturbation", {})
    origin = float(env.race_progress[0])
    covered, finished = 0.0, False
    while env.agents:
        actions: dict[str, Any] = {"car_0": policy.act(obs["car_0"])}
        if nature is not None and "nature_car_0" in obs:
            actions["nature_car_0"] = nature.act_batch(np.asarray(obs["nature_car_0"])[None])[0]
        obs, _, _, _, infos = env.step(actions)
        applied = infos["car_0"].get("perturbation", applied)
        covered = float(env.race_progress[0]) - origin
        if covered >= env.race_distance or env.finished[0]:
            finished = True
            break
    t = env.steps * env.dt if finished else env.max_cycles * env.dt
    dist = min(covered, env.race_distance)
    return Episode(
        score=max(dist, 0.0) / t,
        finished=finished,
        distance=round(dist, 3),
        time=round(t, 3),
        dnf_reason=env.dnf_reason[0],
        perturbation=applied,
    )


def run_batch_episodes(
    policy: Policy,
    track: str,
    perturbations: Sequence[dict[str, float]],
    starts: Sequence[float],
    *,
    laps: int = 1,
    seed: int = 0,
    device: str = "numpy",
    values: np.ndarray | None = None,
) -> list[Episode]:
    """Race ``policy`` solo under many perturbations at once on the batched backend.

    Every pair ``(perturbations[k], starts[k])`` is one environment of one
    :class:`arena.batch.sim.BatchSim` (B = ``len(perturbations)``, one car each), all
    stepped together; each is scored as :func:`run_episode` scores a pybullet race (the
    race distance from the start, or the distance covered in the time limit). A start is
    rounded to the nearest of the simulator's 64 placements along the lap.

    Args:
        policy: drives every car (``act_batch(obs (B, d))`` if it has one, else ``act`` per row).
        track: anything :func:`tracks.load_track` takes.
        perturbations: (B,) names to values (the rest nominal), as ``reset(options=...)``.
        starts: (B,) start of each race, fractions of the lap.
        laps: laps per race.
        seed: seeds the policy and the simulator's noise.
        device: array device of the simulator.
        values: (B, 1, n_params) the perturbations as arrays instead (e.g. random draws);
            ``perturbations`` then only labels them.

    Returns:
        One :class:`Episode` per environment, in order.
    """
    from arena.batch.parallel import START_POSITIONS  # noqa: PLC0415 - heavy, imported on use
    from arena.batch.sim import BatchSim  # noqa: PLC0415 - heavy, imported on use
    from arena.core import DNF_REASONS  # noqa: PLC0415 - heavy, imported on use
    from arena.uncertainty import Perturbation  # noqa: PLC0415 - heavy, imported on use

    b = len(perturbations)
    if b == 0 or len(starts) != b:
        raise PolicyError("one start per perturbation, and at least one race")
    sim = BatchSim(
        track, b, 1, laps, device=device, auto_reset=False,
        start_positions=START_POSITIONS, seed=seed, **observation_kwargs(policy),
    )  # fmt: skip
    ops = sim.ops
    if values is None:
        values = np.stack([Perturbation.from_mapping(p, 1).values for p in perturbations])
    sim.set_perturbation(values)
    k = np.round(np.asarray(starts, dtype=np.float64) * sim.n_starts).astype(np.int64)
    obs = ops.to_numpy(
        sim.reset(seed=seed, start=k % sim.n_starts, slot_of_car=np.zeros((b, 1), np.int64))
    )
    policy.reset(seed)
    act_batch = getattr(policy, "act_batch", None)
    origin = ops.to_numpy(sim.state.race_progress)[:, 0].copy()
    distance = sim.race_distance
    covered = np.zeros(b)
    finished = np.zeros(b, dtype=bool)
    racing = np.ones(b, dtype=bool)
    end_step = np.full(b, sim.max_cycles)
    reason: list[str | None] = [None] * b
    for t in range(1, sim.max_cycles + 1):
        rows = obs[:, 0]
        if act_batch is not None:
            acts = np.asarray(act_batch(rows), dtype=np.float64)
        else:
            acts = np.stack([np.asarray(policy.act(r), dtype=np.float64) for r in rows])
        res = sim.step(acts.reshape(b, 1, 2))
        obs = ops.to_numpy(res.obs)
        progress = ops.to_numpy(sim.state.race_progress)[:, 0]
        covered = np.where(racing, progress - origin, covered)
        lapped = ops.to_numpy(res.laps_completed)[:, 0] >= laps
        done_now = racing & ((covered >= distance) | lapped)
        finished |= done_now
        end_step = np.where(done_now, t, end_step)
        ended = racing & ~done_now & ops.to_numpy(res.terminated | res.truncated)[:, 0]
        codes = ops.to_numpy(sim.outcome.dnf)[:, 0]  # the env core's DNF reason codes
        for i in np.flatnonzero(ended).tolist():
            reason[i] = DNF_REASONS[int(codes[i])]
        racing &= ~(done_now | ended)
        if not racing.any():
            break
    out = []
    for i in range(b):
        time_s = end_step[i] * sim.dt if finished[i] else sim.max_cycles * sim.dt
        dist = min(float(covered[i]), distance)
        out.append(
            Episode(
                score=max(dist, 0.0) / time_s,
                finished=bool(finished[i]),
                distance=round(dist, 3),
                time=round(float(time_s), 3),
                dnf_reason=None if finished[i] else reason[i],
                perturbation=dict(perturbations[i]),
            )
        )
    return out


@dataclass
class GridPoint:
    """One grid point: its perturbation, its score (mean over the starts) and the races."""

    perturbation: dict[str, float]
    score: float  # effective speed, m/s
    races: list[Episode]  # one per start

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict (the races without their copy of the perturbation)."""
        races = [{k: v for k, v in asdict(e).items() if k != "perturbation"} for e in self.races]
        return {"perturbation": self.perturbation, "score": self.score, "races": races}


# ---- the grid -------------------------------------------------------------------------------


def grid_points(
    scale: float = 1.0, grid: dict[str, tuple[float, ...]] | None = None
) -> list[dict[str, float]]:
    """The grid's points shrunk about nominal by ``scale`` (latency rounded), deduplicated.

    Raises:
        PolicyError: an axis that is not one of :data:`AXES`, one without values, or a value
            the simulator cannot take (:meth:`arena.uncertainty.Perturbation.from_mapping`:
            mass 0, dropout 1.5, half a step of latency, which would otherwise be rounded).
            The scaled points lie between nominal and these values, so they are valid too.
    """
    from arena.uncertainty import (  # noqa: PLC0415 - heavy, imported on use
        Perturbation,
        UncertaintyError,
    )

    grid = grid or GRID
    unknown = [name for name in grid if name not in AXES]
    if unknown or not all(grid.values()):
        raise PolicyError(
            f"a grid varies some of {', '.join(AXES)}, each over at least one value; "
            f"got {', '.join(f'{k}: {list(v)}' for k, v in grid.items())}"
        )
    for name, values in grid.items():
        try:
            Perturbation.from_mapping({name: list(values)}, len(values))
        except UncertaintyError as err:
            raise PolicyError(f"grid {name} {list(values)}: {err}") from None
    seen: dict[tuple[float, ...], dict[str, float]] = {}
    for combo in itertools.product(*grid.values()):
        point = {}
        for name, value in zip(grid, combo, strict=True):
            v = AXES[name] + scale * (value - AXES[name])
            point[name] = float(round(v)) if name == "latency" else round(v, 6)
        seen.setdefault(tuple(point.values()), point)
    return list(seen.values())


def tail_mean(scores: Sequence[float], share: float = WORST_SHARE) -> float:
    """Mean of the worst ``share`` of ``scores`` (at least one): CVaR of the lower tail."""
    ordered = sorted(scores)
    k = max(1, math.ceil(share * len(ordered)))
    return float(np.mean(ordered[:k]))


def summarise(scores: Sequence[float], nominal: float) -> dict[str, float]:
    """``mean``, ``worst``, ``worst10_mean`` and ``worst_over_nominal`` of some scores."""
    worst = float(min(scores))
    return {
        "mean": float(np.mean(scores)),
        "worst": worst,
        "worst10_mean": tail_mean(scores),
        "worst_over_nominal": worst / nominal if nominal > 0 else 0.0,
    }


# ---- the whole evaluation -------------------------------------------------------------------


@dataclass
class RobustnessReport:
    """Every figure of :func:`evaluate_robustness` (scores: effective speed, m/s)."""

    policy: str
    track: str
    laps: int
    seed: int
    starts: list[float]
    nominal: float
    grid: dict[str, float]
    random: dict[str, float] | None
    nature: dict[str, Any] | None
    degradation: list[dict[str, float]]
    grid_races: list[dict[str, Any]]
    backend: str = "pybullet"
    confirmed: list[dict[str, Any]] | None = None  # batch: worst points re-run on pybullet

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict."""
        return asdict(self)


def evaluate_robustness(
    policy: Policy,
    track: str,
    *,
    laps: int = 1,
    seed: int = 0,
    n_random: int = 20,
    nature_steps: int = 20_000,
    scales: Sequence[float] = SCALES,
    grid: dict[str, tuple[float, ...]] | None = None,
    starts: Sequence[float] = (0.0,),
    progress: ProgressFn | None = None,
    backend: str = "pybullet",
    confirm: int = 3,
    device: str = "numpy",
) -> RobustnessReport:
    """Score ``policy`` nominally, over the grid, on random draws and against a nature.

    Args:
        policy: the policy (deterministic policies give reproducible figures).
        track: anything :func:`tracks.load_track` takes.
        laps: laps per race.
        seed: seeds the races, the random draws and the nature.
        n_random: random draws of the default set (0: skip).
        nature_steps: PPO steps to train the nature (0: skip; always on pybullet).
        scales: bound scales for the degradation curve (0 and 1 are always included).
        grid: parameter values per axis, any of :data:`AXES` (default :data:`GRID`).
        starts: standing starts, as fractions of the lap (0: the grid); every grid point
            is raced from each and scored by the mean; random draw k starts from
            ``starts[k % len(starts)]``.
        progress: called as ``progress(stage, done, total)``.
        backend: ``pybullet`` (one race after the other) or ``batch`` (every race of the
            grid, the degradation curve and the random draws as one batch of
            :func:`run_batch_episodes`; then the ``confirm`` worst grid points are raced
            again on pybullet, reported under ``confirmed``).
        confirm: worst grid points re-run on pybullet with ``backend="batch"``.
        device: array device of the batch backend.
    """
    from arena.uncertainty import default_config  # noqa: PLC0415 - heavy, imported on use

    if not starts:
        raise PolicyError("robustness needs at least one start")
    if backend not in ("pybullet", "batch"):
        raise PolicyError(f"backend must be pybullet or batch, got {backend!r}")
    tell = progress or (lambda stage, done, total: None)
    curve_scales = sorted(set(scales) | {0.0, 1.0})  # s = 0 is the nominal race
    points_at = {s: grid_points(s, grid) for s in curve_scales}
    base = {name: AXES[name] for name in grid or GRID}  # the grid's nominal point
    unique = {tuple(p.values()): p for pts in points_at.values() for p in pts}
    unique.setdefault(tuple(base.values()), base)
    points = list(unique.values())
    if backend == "batch":
        cache = _batch_points(policy, track, points, starts, laps, seed, device, tell)
    else:
        cache = _pybullet_points(policy, track, points, starts, laps, seed, tell)
    nominal = cache[tuple(base.values())].score
    degradation = []
    for s, pts in points_at.items():
        degradation.append(
            {"scale": s, **summarise([cache[tuple(p.values())].score for p in pts], nominal)}
        )
    grid_eps = [cache[tuple(p.values())] for p in points_at[1.0]]
    random = None
    if n_random > 0:
        cfg = default_config("sample")
        draws = [starts[k % len(starts)] for k in range(n_random)]
        if backend == "batch":
            from arena.uncertainty import sample_values  # noqa: PLC0415 - heavy

            values = sample_values(cfg, np.random.default_rng(seed + 1), (n_random, 1))
            eps = run_batch_episodes(
                policy, track, [{}] * n_random, draws, laps=laps, seed=seed + 1,
                device=device, values=values,
            )  # fmt: skip
            scores = [e.score for e in eps]
            tell("random", n_random, n_random)
        else:
            from arena.env import RacingEnv  # noqa: PLC0415 - heavy, imported on use

            env = RacingEnv(
                track=track, n_cars=1, laps=laps, uncertainty=cfg, **observation_kwargs(policy)
            )
            try:
                scores = []
                for k in range(n_random):
                    scores.append(run_episode(env, policy, seed=seed + 1 + k, start=draws[k]).score)
                    tell("random", k + 1, n_random)
            finally:
                env.close()
        random = {"n": n_random, **summarise(scores, nominal)}
    confirmed = None
    if backend == "batch" and confirm > 0:
        worst = sorted(grid_eps, key=lambda g: g.score)[:confirm]
        again = _pybullet_points(
            policy, track, [g.perturbation for g in worst], starts, laps, seed, tell, "confirm"
        )
        confirmed = [
            {
                "perturbation": g.perturbation,
                "batch": g.score,
                "pybullet": again[tuple(g.perturbation.values())].score,
            }
            for g in worst
        ]
    nature = None
    if nature_steps > 0:
        nature = nature_attack(
            policy, track, laps=laps, seed=seed, steps=nature_steps, progress=tell
        )
        nature["worst_over_nominal"] = nature["score"] / nominal if nominal > 0 else 0.0
    name = getattr(policy, "name", type(policy).__name__)
    return RobustnessReport(
        policy=name,
        track=str(track),
        laps=laps,
        seed=seed,
        starts=[float(x) for x in starts],
        nominal=nominal,
        grid={"n": len(grid_eps), **summarise([e.score for e in grid_eps], nominal)},
        random=random,
        nature=nature,
        degradation=degradation,
        grid_races=[e.to_dict() for e in grid_eps],
        backend=backend,
        confirmed=confirmed,
    )


def _pybullet_points(
    policy: Policy,
    track: str,
    points: Sequence[dict[str, float]],
    starts: Sequence[float],
    laps: int,
    seed: int,
    tell: ProgressFn,
    stage: str = "grid",
) -> dict[tuple[float, ...], GridPoint]:
    """Each point raced from each start on pybullet, one race after the other."""
    from arena.env import RacingEnv  # noqa: PLC0415 - heavy, imported on use
    from arena.uncertainty import UncertaintyConfig  # noqa: PLC0415 - heavy, imported on use

    env = RacingEnv(
        track=track, n_cars=1, laps=laps, uncertainty=UncertaintyConfig("fixed"),
        **observation_kwargs(policy),
    )  # fmt: skip
    out: dict[tuple[float, ...], GridPoint] = {}
    try:
        for k, point in enumerate(points):
            eps = [run_episode(env, policy, seed=seed, perturbation=point, start=x) for x in starts]
            out[tuple(point.values())] = GridPoint(
                point, float(np.mean([e.score for e in eps])), eps
            )
            tell(stage, k + 1, len(points))
    finally:
        env.close()
    return out


def _batch_points(
    policy: Policy,
    track: str,
    points: Sequence[dict[str, float]],
    starts: Sequence[float],
    laps: int,
    seed: int,
    device: str,
    tell: ProgressFn,
) -> dict[tuple[float, ...], GridPoint]:
    """Every point from every start as one batch (:func:`run_batch_episodes`)."""
    pairs = [(p, x) for p in points for x in starts]
    eps = run_batch_episodes(
        policy, track, [p for p, _ in pairs], [x for _, x in pairs], laps=laps, seed=seed,
        device=device,
    )  # fmt: skip
    tell("grid", len(points), len(points))
    m = len(starts)
    return {
        tuple(p.values()): GridPoint(
            p, float(np.mean([e.score for e in eps[k * m : (k + 1) * m]])), eps[k * m : (k + 1) * m]
        )
        for k, p in enumerate(points)
    }


# ---- nature ---------------------------------------------------------------------------------


def _nature_ppo(vec_env: Any, seed: int, tb_dir: Path | None = None) -> Any:
    """A small PPO for a nature (its actions: the perturbation, every step)."""
    from stable_baselines3 import PPO  # noqa: PLC0415 - heavy, imported on use

    return PPO(
        "MlpPolicy",
        vec_env,
        n_steps=128,
        batch_size=min(256, 128 * vec_env.num_envs),
        n_epochs=5,
        learning_rate=3e-4,
        gamma=0.99,
        ent_coef=0.0,
        policy_kwargs={"net_arch": {"pi": [64, 64], "vf": [64, 64]}, "log_std_init": -0.5},
        tensorboard_log=None if tb_dir is None else str(tb_dir),
        seed=seed,
        device="cpu",
        verbose=0,
    )


def nature_attack(
    policy: Policy,
    track: str,
    *,
    laps: int = 1,
    seed: int = 0,
    steps: int = 20_000,
    episodes: int = 3,
    progress: ProgressFn | None = None,
) -> dict[str, Any]:
    """Train a fresh nature against the frozen ``policy``, then score the policy against it.

    The nature (default set, acting every step, rate-limited) learns with PPO on minus the
    car's reward for ``steps`` steps from random starts; then ``episodes`` races from the grid
    (seeds ``seed``, ``seed + 1`` …) with the nature deterministic.

    Returns:
        ``score`` (mean effective speed, m/s), ``scores``, ``steps`` and ``mean_perturbation``
        (the nature's average choice per parameter in its races).
    """
    from agents.selfplay import (  # noqa: PLC0415 - heavy, imported on use
        PolicyDriver,
        SB3Driver,
        SelfPlayVecEnv,
    )
    from arena.env import RacingEnv  # noqa: PLC0415 - heavy, imported on use
    from arena.uncertainty import default_config  # noqa: PLC0415 - heavy, imported on use

    cfg = default_config("adversarial")
    vec = SelfPlayVecEnv(
        [track],
        n_envs=4,
        n_cars=1,
        n_learners=1,
        laps=laps,
        seed=seed,
        env_kwargs={"uncertainty": cfg, **observation_kwargs(policy)},
        role="nature",
    )
    vec.racer = PolicyDriver(policy)
    try:
        model = _nature_ppo(vec, seed)
        callback = _ProgressCallback(progress, steps) if progress is not None else None
        model.learn(total_timesteps=steps, callback=callback)
        frozen = SB3Driver.frozen(model.policy, "nature")
    finally:
        vec.close()
    env = RacingEnv(track=track, n_cars=1, laps=laps, uncertainty=cfg, **observation_kwargs(policy))
    try:
        eps = [run_episode(env, policy, seed=seed + k, nature=frozen) for k in range(episodes)]
    finally:
        env.close()
    names = [k for k in eps[0].perturbation if k in cfg.free_names]
    return {
        "steps": steps,
        "score": float(np.mean([e.score for e in eps])),
        "scores": [e.score for e in eps],
        "final_perturbation": {k: float(np.mean([e.perturbation[k] for e in eps])) for k in names},
    }


def _ProgressCallback(progress: ProgressFn, total: int) -> Any:
    from stable_baselines3.common.callbacks import BaseCallback  # noqa: PLC0415 - heavy

    class Progress(BaseCallback):
        def _on_step(self) -> bool:
            progress("nature", min(self.num_timesteps, total), total)
            return True

    return Progress()


# ---- training side --------------------------------------------------------------------------

TRAINING_UNCERTAINTY = ("nominal", "sample", "wide", "cvar", "adversarial", "robust_mg")
"""What ``slipstream train --uncertainty`` takes (see :func:`training_uncertainty`)."""
NATURE_ARMS = ("adversarial", "robust_mg")
"""The arms of :data:`TRAINING_UNCERTAINTY` that train natures (:func:`rarl_callback`)."""


WIDE_FACTOR = 1.5  # how much wider than the scored set the ``wide`` arm's intervals are


def training_uncertainty(name: str) -> Any:
    """The :class:`arena.uncertainty.UncertaintyConfig` of a training arm (None: nominal).

    * ``sample``: domain randomisation over :data:`arena.uncertainty.DEFAULT_DYNAMICS`;
    * ``wide``: domain randomisation over :func:`wide_dynamics`, wider than the set a policy is
      scored on (over-randomisation: the evaluation grid's edges, where policies fail, are
      then inside the training range rather than at its rim);
    * ``cvar``: the same wide domain randomisation, with every PPO update on the worst half of
      its rollout's slots (a CVaR objective, EPOpt's recipe: :mod:`agents.cvar`; the
      selection is :func:`agents.cvar.cvar_buffer`, which ``slipstream train`` adds);
    * ``adversarial``: RARL, a nature per car choosing the dynamics inside that set every
      step (rate-limited);
    * ``robust_mg``: Zhang et al.'s robust Markov game: the same nature also chooses the
      car's *reward* inside :data:`ZHANG_REWARD` (additive noise δ and interval weights on
      the racing terms), so it plays the worst case of both the transitions and the reward,
      zero-sum (its reward is minus the car's perturbed reward).

    Raises:
        PolicyError: an unknown name.
    """
    from arena.uncertainty import default_config  # noqa: PLC0415 - heavy, imported on use

    if name not in TRAINING_UNCERTAINTY:
        raise PolicyError(f"uncertainty must be one of {', '.join(TRAINING_UNCERTAINTY)}: {name}")
    if name == "nominal":
        return None
    if name == "robust_mg":
        return default_config("adversarial", reward=zhang_reward())
    if name in ("wide", "cvar"):
        from arena.uncertainty import UncertaintyConfig  # noqa: PLC0415 - heavy, imported on use

        return UncertaintyConfig(mode="sample", dynamics=wide_dynamics())
    return default_config(name)


def wide_dynamics(factor: float = WIDE_FACTOR) -> Any:
    """:data:`arena.uncertainty.DEFAULT_DYNAMICS` with every interval ``factor`` times as wide
    about its nominal value (:meth:`arena.uncertainty.UncertaintyConfig.scaled`; friction
    0.6–1.2 → 0.4–1.3 at 1.5, latency 0–2 → 0–3 whole steps) in plain floats rounded to 6
    decimals, an :class:`arena.uncertainty.DynamicsBounds`."""
    import dataclasses  # noqa: PLC0415 - only here

    from arena.uncertainty import default_config  # noqa: PLC0415 - heavy, imported on use

    def plain(v: float) -> float:  # whole latency steps stay ints
        return v if isinstance(v, int) else round(float(v), 6)

    grown = default_config("sample").scaled(factor).dynamics
    changes: dict[str, tuple[float, float]] = {}
    for f in dataclasses.fields(grown):
        lo, hi = getattr(grown, f.name)
        changes[f.name] = (plain(lo), plain(hi))
    return dataclasses.replace(grown, **changes)


def zhang_reward() -> Any:
    """The reward uncertainty set of the ``robust_mg`` arm (an ``arena.uncertainty.RewardBounds``).

    Noise level λ = 0.02 per step (δ in ±0.04, about 10 % of a 6 m/s car's 0.3 m of progress
    per step); progress weighted 0.8–1 and the off-track, wall and blamed-collision
    penalties 1–2 times; overtakes 0.5–1. Nature's worst case is a car paid less for speed and
    punished more for mistakes, as Zhang et al.'s bounded reward perturbation.
    """
    from arena.uncertainty import RewardBounds  # noqa: PLC0415 - heavy, imported on use

    return RewardBounds(
        noise=0.02,
        progress=(0.8, 1.0),
        off_track=(1.0, 2.0),
        wall=(1.0, 2.0),
        collision=(1.0, 2.0),
        overtake=(0.5, 1.0),
    )


def load_weights(model: Any, path: Path) -> None:
    """Copy a Slipstream checkpoint's policy weights into an SB3 PPO ``model`` (fine-tuning).

    Raises:
        PolicyError: the checkpoint's network does not fit the model's.
    """
    import torch  # noqa: PLC0415 - heavy, imported on use

    from agents.checkpoint import read_checkpoint  # noqa: PLC0415 - heavy, imported on use

    _, tensors = read_checkpoint(path)
    own = model.policy.state_dict()
    for name, value in tensors.items():
        if name not in own or tuple(own[name].shape) != tuple(value.shape):
            want = tuple(own[name].shape) if name in own else "no such tensor"
            raise PolicyError(
                f"{path}: tensor {name} {tuple(value.shape)} does not fit the model being "
                f"trained ({want}: other observations, e.g. --observe-perturbation, or layers?)"
            )
    model.policy.load_state_dict({k: torch.as_tensor(v) for k, v in tensors.items()}, strict=False)


def _nature_env(args: Any, racer_env: Any, env_kwargs: dict[str, Any], k: int) -> Any:
    """The races nature ``k`` of ``slipstream train`` learns in: the natures of every car of
    half as many races as the racers', on the fixed training tracks, seeded apart."""
    from agents.train import _batch_vec_env, _selfplay_vec_env  # noqa: PLC0415 - heavy

    n_envs, seed = max(1, args.n_envs // 2), args.seed + 10_000 + k
    if args.backend == "batch":
        from agents.batch_rarl import BatchNatureVecEnv  # noqa: PLC0415 - heavy

        return BatchNatureVecEnv(
            _batch_vec_env(
                args, env_kwargs["uncertainty"], seed=seed, n_envs=n_envs, procedural=False
            )
        )
    env = _selfplay_vec_env(args, env_kwargs, seed=seed, n_envs=n_envs, role="nature")
    env.pool = racer_env.pool  # the same opponents
    return env


def rarl_callback(
    args: Any, racer_env: Any, env_kwargs: dict[str, Any], run_dir: Path, monitor: Any
) -> Any:
    """``monitor`` plus RARL's alternation for ``slipstream train --uncertainty adversarial``.

    Every ``args.nature_every`` racer steps: a nature PPO (its own race copies, the learner
    cars driven by a frozen copy of the racer) trains for ``args.nature_steps``; then the
    racers' natures are driven by a frozen copy of it. The nature is saved next to the run
    as ``nature_sb3.zip`` (stable-baselines3's format: your own file, trusted).

    With ``args.natures`` K > 1 (``--backend batch``), a *population* of natures (Vinitsky
    et al., "Robust Reinforcement Learning using Adversarial Populations", 2020): K nature
    PPOs, each with its own race copies and seed; each phase trains one of them in turn
    (the same nature steps in all, so each gets about 1/K of them), then every race group of
    the racers' env gets one of the natures trained so far, drawn anew each phase (seeded),
    so the racers meet several adversaries at once rather than the latest one's habits.
    Saved as ``nature_sb3.zip`` (the first) and ``nature_sb3_<k>.zip``.
    """
    from stable_baselines3.common.callbacks import BaseCallback, CallbackList  # noqa: PLC0415

    from agents.selfplay import SB3Driver  # noqa: PLC0415 - heavy

    k_natures = int(getattr(args, "natures", 1))
    nature_envs = [_nature_env(args, racer_env, env_kwargs, k) for k in range(k_natures)]
    tb_dir = run_dir / "tb_nature"
    natures = [_nature_ppo(env, args.seed + k, tb_dir) for k, env in enumerate(nature_envs)]
    rng = np.random.default_rng([args.seed, 13])

    class Alternate(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.next = args.nature_every
            self.phases = 0
            self.drivers: dict[int, Any] = {}  # frozen copies of the natures trained so far

        def _on_step(self) -> bool:
            if self.num_timesteps >= self.next:
                self.next += args.nature_every
                k = self.phases % k_natures
                self.phases += 1
                nature_envs[k].racer = SB3Driver.frozen(self.model.policy, "racer")
                natures[k].learn(args.nature_steps, reset_num_timesteps=False, tb_log_name="nature")
                name = "nature" if k_natures == 1 else f"nature_{k}"
                self.drivers[k] = SB3Driver.frozen(natures[k].policy, name)  # only k changed
                drivers = list(self.drivers.values())  # in the order first trained
                if args.backend != "batch":
                    racer_env.nature = drivers[-1]
                elif k_natures == 1:  # every simulator's natures, one batch each
                    racer_env.set_attr("nature", drivers[-1])
                else:  # each race group meets one of the population, drawn anew
                    for sim in racer_env.sims:
                        sim.nature = drivers[int(rng.integers(len(drivers)))]
            return True

        def _on_training_end(self) -> None:
            for k, nature in enumerate(natures):
                nature.save(run_dir / ("nature_sb3.zip" if k == 0 else f"nature_sb3_{k}.zip"))
            for env in nature_envs:
                env.close()

    return CallbackList([monitor, Alternate()])


# ---- output ---------------------------------------------------------------------------------


def save_plot(report: RobustnessReport, path: Path) -> Path:
    """The degradation curve (worst case and mean against the bound scale) as a PNG."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: PLC0415 - heavy
    from matplotlib.figure import Figure  # noqa: PLC0415 - heavy

    fig = Figure(figsize=(6.0, 4.0), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    s = [row["scale"] for row in report.degradation]
    ax.plot(s, [row["mean"] for row in report.degradation], "o-", label="grid mean")
    ax.plot(s, [row["worst10_mean"] for row in report.degradation], "s-", label="worst-10 % mean")
    ax.plot(s, [row["worst"] for row in report.degradation], "v-", label="worst case")
    ax.axhline(report.nominal, color="grey", ls="--", lw=1, label="nominal")
    if report.nature is not None:
        ax.axhline(
            report.nature["score"], color="crimson", ls=":", lw=1, label="vs. trained nature"
        )
    ax.set_xlabel("bound scale s (0: nominal, 1: full grid)")
    ax.set_ylabel("effective speed, m/s")
    ax.set_ylim(bottom=0.0)
    ax.set_title(f"{report.policy} on {report.track}: robustness")
    ax.legend(fontsize=8, loc="lower left")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path


def save_report(report: RobustnessReport, path: Path) -> Path:
    """The report as JSON."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report.to_dict(), indent=2) + "\n", encoding="utf-8")
    return path
