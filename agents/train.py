"""Train a racing policy: stable-baselines3 PPO, one policy shared by the learner cars.

CleanRL-style: every setting is a typed field of :class:`TrainArgs` whose docstring is its
``--help`` text; one seeding block; a run name built from tracks, seed and time; fixed metric
names; save, reload and evaluate straight after training.

What a run does:

1. builds a :class:`agents.selfplay.SelfPlayVecEnv` — ``n_envs`` race copies, ``n_learners``
   learner cars each, the rest driven by opponents drawn per episode from a pool of frozen
   snapshots of the learner and the pursuit / gap baselines; random track (of ``tracks``),
   start point, direction and grid order every episode;
2. trains ``PPO("MlpPolicy", ...)`` with TensorBoard logs under ``<out>/<run>/tb``, a
   progress bar, a snapshot into the opponent pool every ``snapshot_every`` steps and an
   evaluation every ``eval_every`` steps (:func:`evaluate`), each written to TensorBoard
   (``eval/*``) and as one JSON line to ``<out>/<run>/curve.jsonl``;
3. stops at ``total_timesteps``, after ``max_minutes`` of wall time, on Ctrl-C, or — with
   ``stop_at_first_clean_lap`` — at the first evaluation with a clean lap on every
   evaluation track;
4. exports ``<out>/<run>/policy.zip`` (our safe format: ``meta.json`` + safetensors, see
   :mod:`agents.checkpoint`), loads it back with :func:`agents.loading.load_policy` and races
   it against pursuit; writes ``<out>/<run>/summary.json``.

**Car.** Every car of every training and evaluation race is the ``car`` preset
(:mod:`arena.cars`), and every track — listed, evaluation or generated — is scaled by the
car's length over the F1TENTH car's (:func:`track_scale`: 0.52 for ``deepracer``), so the
1/18 car trains on roads its size; a track named ``NAME@<factor>`` keeps the scale it names.
The checkpoint records the car (``env_config["car"]``).

**Clean lap.** In the *solo* evaluation race (the policy alone on the track, grid start,
deterministic actions, ``eval_laps`` laps) the car completes every lap — status
``finished``, so no DNF (no crash out, no time-out, no stuck or off-track retirement) — and
has zero off-track excursions (never all four wheels off the road). A *completed* lap only
needs the first part.

Metric names: ``eval/solo_laps``, ``eval/solo_lap_time``, ``eval/duel_laps``,
``eval/duel_lap_time``, ``eval/pursuit_lap_time``, ``eval/completion_rate``,
``eval/clean_lap``, ``rollout/finish_rate`` (share of the last 100 training episodes whose
learner car completed ``train_laps``, not counting episodes cut short by a team-mate) and
``rollout/laps_per_episode``, besides SB3's ``rollout/*`` and ``train/*``.
"""

from __future__ import annotations

import argparse
import ast
import inspect
import itertools
import json
import math
import os
import platform
import random
import sys
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any, get_args, get_origin, get_type_hints

import numpy as np

from agents.curriculum import CURRICULUM_ARMS, CURRICULUM_START
from agents.policy import Policy, PolicyError
from agents.robustness import NATURE_ARMS

DEFAULT_EVAL_SEED = 12345  # evaluation races use fixed seeds, independent of training


@dataclass
class TrainArgs:
    """Settings of one training run (each field is a ``--flag`` of ``slipstream train``)."""

    tracks: list[str] = field(default_factory=lambda: ["oval"])
    """training tracks, one drawn per episode (built-in names, track files, random:<seed>)"""
    eval_tracks: list[str] = field(default_factory=list)
    """evaluation tracks (default: the training tracks)"""
    n_cars: int = 4
    """cars per training race: learners plus opponents"""
    n_learners: int = 2
    """learner cars per training race (each one slot of the PPO batch)"""
    n_envs: int = 8
    """race copies stepped in this process"""
    total_timesteps: int = 1_000_000
    """learner steps to train for (summed over all slots)"""
    seed: int = 1
    """seed of Python, NumPy, torch and the envs"""
    learning_rate: float = 3e-4
    """Adam learning rate"""
    anneal_lr: bool = True
    """decay the learning rate linearly towards 0 over total_timesteps (CleanRL's schedule)"""
    n_steps: int = 128
    """steps per slot per rollout (rollout size = n_steps × n_envs × n_learners)"""
    batch_size: int = 512
    """minibatch size"""
    n_epochs: int = 10
    """passes over each rollout"""
    gamma: float = 0.99
    """discount factor (0.99 ≈ a 5 s horizon at 20 Hz)"""
    gae_lambda: float = 0.95
    """GAE λ"""
    clip_range: float = 0.2
    """PPO clipping range"""
    ent_coef: float = 0.0
    """entropy bonus coefficient"""
    vf_coef: float = 0.5
    """value loss coefficient"""
    max_grad_norm: float = 0.5
    """gradient norm clip"""
    net_arch: list[int] = field(default_factory=lambda: [64, 64])
    """hidden layer sizes of the policy and of the value network (separate, tanh)"""
    log_std_init: float = -0.5
    """initial log standard deviation of the Gaussian actions"""
    reward_scale: float = 1.0
    """multiplies the env's racing reward (metres of progress per step minus penalties)"""
    dnf_penalty: float = 10.0
    """reward subtracted when a learner car retires (stuck, off the track, flipped)"""
    procedural: float = 0.0
    """share of training episodes on a freshly generated track (domain randomisation); with
    --backend batch a share of the race groups, whose generated tracks are redrawn in turn"""
    procedural_length: list[float] = field(default_factory=lambda: [60.0, 160.0])
    """lap length range of generated tracks, m (min max)"""
    procedural_difficulty: list[float] = field(default_factory=lambda: [0.2, 0.8])
    """difficulty range of generated tracks, 0-1 (min max): twistier and narrower towards 1"""
    procedural_hairpin: list[float] = field(default_factory=list)
    """hairpin radius range of generated tracks, m (min max): real-track-like tightness, bends
    tighter than the half-width with the inside narrowed (tracks.generator hairpin=; the
    F1TENTH race tracks have 0.4-1.1 m); empty: ordinary generated tracks"""
    procedural_width: list[float] = field(default_factory=list)
    """total road width range of generated tracks, m, before they are scaled to the car (min
    max; e.g. 1.3 1.8 with --car deepracer gives DeepRacer's 0.7-0.95 m roads); empty: the
    width the difficulty (or hairpin) gives"""
    train_laps: int = 1
    """laps per training episode"""
    wall_ends_episode: bool = False
    """--backend batch: a learner car that touches a wall retires at once (DNF, the DNF
    penalty). The batched simulator's soft walls let a car slide on; on pybullet a car that
    hits one at speed stops dead and often stays stuck, so a policy must learn to keep off"""
    off_track_limit: float = 3.0
    """s a learner car may spend off the road (all four wheels off) before it retires in
    training (both backends; races keep the env's 3 s). A short one (0.3-0.5 s) teaches a
    policy to keep on the road, where real tracks' walls stand right at the edge inside tight
    hairpins; 0: DeepRacer's rule (off the road ends the episode)"""
    runoff: float = 0.4
    """m of run-off between the road edge and the walls in training (both backends; races
    keep the env's 0.4 m). Compact real tracks (DeepRacer's) have walls right at the edge
    where two stretches of road run close: a small run-off teaches a policy to keep a car's
    width off the edge"""
    randomise: bool = True
    """random start point, direction and grid order every training episode"""
    backend: str = "bullet"
    """training simulator: bullet (pybullet races against snapshots and baselines) or batch
    (arena.batch: all races stepped as arrays, every car a learner; evaluation stays on bullet)"""
    batch_device: str = "numpy"
    """array device of --backend batch: numpy, torch:cpu or cuda"""
    snapshot_every: int = 50_000
    """add a frozen copy of the learner to the opponent pool every this many steps"""
    max_snapshots: int = 8
    """snapshots kept in the pool (oldest dropped)"""
    opponent_mix: str = "snapshot=0.5,pursuit=0.3,gap=0.2"
    """opponent kinds and their weights (snapshot, pursuit, gap)"""
    eval_every: int = 25_000
    """evaluate every this many steps (0: only at the end)"""
    eval_laps: int = 1
    """laps per evaluation race"""
    save_best: bool = True
    """also export the best evaluated policy (completion rate, then clean lap, then mean solo
    lap time) to <out>/<run>/best.zip"""
    out: Path = Path("runs")
    """output directory; the run writes to <out>/<run_name>/"""
    run_name: str | None = None
    """run name (default: <tracks>__s<seed>__<unix time>)"""
    tensorboard_dir: Path | None = None
    """TensorBoard log directory (default: <out>/<run_name>/tb)"""
    max_minutes: float | None = None
    """wall-clock budget: stop training after this many minutes"""
    stop_at_first_clean_lap: bool = False
    """stop at the first evaluation with a clean lap on every evaluation track"""
    progress_bar: bool = True
    """show a progress bar on stderr"""
    torch_threads: int = 1
    """torch CPU threads (small nets: 1 is fastest, and leaves cores to the envs)"""
    verbose: int = 0
    """SB3 verbosity (0: quiet, 1: print the training table)"""
    uncertainty: str = "nominal"
    """model uncertainty in training: nominal, sample (domain randomisation over the default
    robust set of arena.uncertainty), wide (the same over intervals 1.5 times as wide),
    cvar (wide, each PPO update on the worst half of its rollout's slots: agents.cvar),
    adversarial (RARL: nature agents pick each car's
    perturbation, every step within a rate limit; racer and nature trained in alternation;
    with --backend batch the natures of every car of every race act as one batch) or
    robust_mg (adversarial, and the nature also picks the car's reward inside a bounded set:
    Zhang et al.'s robust Markov game; agents.robustness.training_uncertainty)"""
    cvar_share: float = 0.5
    """cvar: the share of each rollout's slots (the lowest returns) every PPO update trains on
    (the experiment's best: 0.75 with --cvar-warmup 0; README "A CVaR objective")"""
    cvar_warmup: float = 0.2
    """cvar: the share of the budget first trained on every slot (EPOpt's warm-up)"""
    curriculum: float = 0.0
    """a curriculum on the bounds (--backend batch; sample, wide or cvar): the randomisation
    starts at 30 % of its width about the nominal car and widens linearly to the full
    set over this share of the budget (0: off; agents.curriculum)"""
    edge_share: float = 0.0
    """a corner-weighted sampler (sample, wide or cvar): each perturbation parameter of a draw
    takes one of its interval's ends with this probability instead of a uniform value, so
    several bad values at once (low grip with long latency) are drawn often (0: uniform;
    arena.uncertainty.UncertaintyConfig.edge_share)"""
    nature_every: int = 20_000
    """adversarial: train the nature for nature_steps after every this many racer steps"""
    nature_steps: int = 10_000
    """adversarial: nature steps per alternation phase"""
    natures: int = 1
    """adversarial and robust_mg on --backend batch: a population of this many natures, one
    trained per phase in turn, each race group facing one of them, drawn anew each phase
    (agents.robustness.rarl_callback)"""
    observe_perturbation: bool = False
    """perturbation-aware observations: each car also observes its own model-uncertainty
    values (9 floats, 0 for the nominal car; arena.uncertainty.CONTEXT_FEATURES), in
    training and wherever the checkpoint is raced or scored (recorded in its env_config)"""
    init_from: Path | None = None
    """start from the policy weights of this Slipstream checkpoint (fine-tuning; the value
    network starts fresh)"""
    car: str = "f1tenth"
    """car preset of every car (arena.cars): f1tenth (1/10) or deepracer (1/18). Every
    training, evaluation and generated track is scaled by the car's length over the f1tenth
    car's (0.52 for deepracer; a track named NAME@<factor> keeps that scale), and the
    checkpoint records the car"""


# ---- argparse from the dataclass ------------------------------------------------------------


def _field_docs(cls: type) -> dict[str, str]:
    """The docstring under each field of a dataclass (CleanRL / tyro convention)."""
    try:
        tree = ast.parse(inspect.getsource(cls))
    except (OSError, TypeError):  # source not available (frozen app): no help texts
        return {}
    body = tree.body[0].body  # type: ignore[attr-defined]
    docs: dict[str, str] = {}
    for node, nxt in itertools.pairwise(body):
        if (
            isinstance(node, ast.AnnAssign)
            and isinstance(node.target, ast.Name)
            and isinstance(nxt, ast.Expr)
            and isinstance(nxt.value, ast.Constant)
            and isinstance(nxt.value.value, str)
        ):
            docs[node.target.id] = " ".join(nxt.value.value.split())
    return docs


def add_train_arguments(parser: argparse.ArgumentParser) -> None:
    """Add one ``--flag`` per :class:`TrainArgs` field, typed, with the field's docstring."""
    hints = get_type_hints(TrainArgs)
    docs = _field_docs(TrainArgs)
    defaults = TrainArgs()
    for f in fields(TrainArgs):
        flag = "--" + f.name.replace("_", "-")
        tp = hints[f.name]
        default = getattr(defaults, f.name)
        kwargs: dict[str, Any] = {"default": default, "dest": f.name}
        args = [a for a in get_args(tp) if a is not type(None)]
        base = args[0] if get_origin(tp) is not list and args else tp
        if tp is bool:
            kwargs["action"] = argparse.BooleanOptionalAction
        elif get_origin(tp) is list:
            item = get_args(tp)[0]
            kwargs.update(nargs="+", type=item, metavar=_METAVARS.get(item, "X"))
        else:
            kwargs.update(type=base, metavar=_METAVARS.get(base, "X"))
        help_text = f"{docs.get(f.name, '')} (default: {_show(default)})"
        kwargs["help"] = help_text.replace("%", "%%")  # argparse %-formats help texts
        parser.add_argument(flag, **kwargs)


_METAVARS: dict[Any, str] = {int: "N", float: "X", str: "TEXT", Path: "PATH"}


def _show(value: Any) -> str:
    if isinstance(value, list):
        return " ".join(map(str, value)) or "none"
    return str(value)


def args_from_namespace(ns: argparse.Namespace) -> TrainArgs:
    """The :class:`TrainArgs` in a parsed namespace."""
    return TrainArgs(**{f.name: getattr(ns, f.name) for f in fields(TrainArgs)})


def parse_args(argv: Sequence[str] | None = None) -> TrainArgs:
    """Parse a command line into :class:`TrainArgs`."""
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    add_train_arguments(parser)
    return args_from_namespace(parser.parse_args(argv))


def _check(args: TrainArgs) -> None:
    """Raise :class:`PolicyError` on settings that cannot work."""
    from agents.selfplay import parse_mix  # noqa: PLC0415 - heavy, imported on use
    from arena.cars import car_params  # noqa: PLC0415 - heavy, imported on use
    from tracks import load_track  # noqa: PLC0415 - heavy, imported on use

    car_params(args.car)  # raises CarError naming the presets
    for name in training_tracks(args, [*args.tracks, *args.eval_tracks]):
        load_track(name)  # raises TrackError with a clear message (a scale too small, too)
    positive = (
        "n_cars",
        "n_learners",
        "n_envs",
        "total_timesteps",
        "n_steps",
        "batch_size",
        "n_epochs",
        "eval_laps",
        "train_laps",
        "max_snapshots",
        "torch_threads",
    )
    for name in positive:
        if getattr(args, name) < 1:
            raise PolicyError(f"{name} must be at least 1, got {getattr(args, name)}")
    if args.n_learners > args.n_cars:
        raise PolicyError(f"n_learners ({args.n_learners}) exceeds n_cars ({args.n_cars})")
    optional = ("procedural_hairpin", "procedural_width")
    for name in ("procedural_length", "procedural_difficulty", *optional):
        pair = getattr(args, name)
        if (pair or name not in optional) and (len(pair) != 2 or pair[0] > pair[1]):
            raise PolicyError(f"{name} takes two numbers, min then max; got {pair}")
    if args.wall_ends_episode and args.backend != "batch":
        raise PolicyError("wall_ends_episode is for --backend batch (pybullet walls stop a car)")
    if not 0.0 <= args.off_track_limit < math.inf:
        raise PolicyError(f"off_track_limit must be 0 s or more, got {args.off_track_limit}")
    if not 0.0 <= args.runoff < math.inf:
        raise PolicyError(f"runoff must be 0 m or more, got {args.runoff}")
    if not 0.0 <= args.procedural <= 1.0:
        raise PolicyError(f"procedural is a share in [0, 1], got {args.procedural}")
    if not args.net_arch or min(args.net_arch) < 1:
        raise PolicyError("net_arch needs at least one positive layer size")
    if args.backend not in ("bullet", "batch"):
        raise PolicyError(f"backend must be bullet or batch, got {args.backend!r}")
    from agents.robustness import training_uncertainty  # noqa: PLC0415 - heavy, imported on use

    training_uncertainty(args.uncertainty)  # raises on an unknown arm
    if not 0.0 < args.cvar_share <= 1.0:
        raise PolicyError(f"cvar_share must be within (0, 1], not {args.cvar_share}")
    if not 0.0 <= args.cvar_warmup < 1.0:
        raise PolicyError(f"cvar_warmup must be within [0, 1), not {args.cvar_warmup}")
    if not 0.0 <= args.curriculum <= 1.0:
        raise PolicyError(f"curriculum is a share of the budget in [0, 1], got {args.curriculum}")
    if args.curriculum and (args.backend != "batch" or args.uncertainty not in CURRICULUM_ARMS):
        raise PolicyError(
            "curriculum widens domain randomisation on --backend batch: it needs "
            f"--uncertainty {', '.join(CURRICULUM_ARMS)}, not {args.backend}/{args.uncertainty}"
        )
    if not 0.0 <= args.edge_share <= 1.0:
        raise PolicyError(f"edge_share is a probability in [0, 1], got {args.edge_share}")
    if args.edge_share and args.uncertainty not in CURRICULUM_ARMS:
        raise PolicyError(
            "edge_share reshapes domain randomisation: it needs --uncertainty "
            f"{', '.join(CURRICULUM_ARMS)}, not {args.uncertainty}"
        )
    if args.natures < 1:
        raise PolicyError(f"natures must be at least 1, got {args.natures}")
    if args.natures > 1 and (args.backend != "batch" or args.uncertainty not in NATURE_ARMS):
        raise PolicyError(
            "a population of natures (--natures > 1) needs --backend batch and --uncertainty "
            f"adversarial or robust_mg, not {args.backend}/{args.uncertainty}"
        )
    if args.observe_perturbation and args.uncertainty == "nominal":
        raise PolicyError(
            "--observe-perturbation with --uncertainty nominal: every car is the nominal one, "
            "so the block would read zeros throughout; pick sample, wide, cvar, adversarial "
            "or robust_mg"
        )
    if args.init_from is not None and not Path(args.init_from).is_file():
        raise PolicyError(f"init_from: no such checkpoint {args.init_from}")
    parse_mix(args.opponent_mix)  # checked even when no car is an opponent: a typo is a typo


# ---- evaluation -------------------------------------------------------------------------------


def evaluate(
    policy: Policy,
    tracks: Sequence[str],
    *,
    laps: int = 1,
    seed: int = DEFAULT_EVAL_SEED,
    env_kwargs: dict[str, Any] | None = None,
    reverse: bool = False,
    both_grids: bool = False,
) -> dict[str, Any]:
    """Race ``policy`` alone and against pursuit on each track; lap completion and lap times.

    Per track (and direction): one solo race from the grid, and one race against pursuit
    with a seeded random grid order — or, with ``both_grids``, two: the policy on pole, then
    pursuit on pole. Policies are deterministic, so repeating a race changes nothing; the
    variety comes from directions and grid orders.

    Args:
        policy: the policy to evaluate.
        tracks: anything :func:`tracks.load_track` takes.
        laps: laps per race.
        seed: seeds the races.
        env_kwargs: the env arguments the policy was trained with (``car``: pursuit drives
            that car too).
        reverse: also race every track in the other direction (key ``"<track>:reverse"``).
        both_grids: two races against pursuit per track instead of one.

    Returns:
        ``completed_laps`` / ``possible_laps`` (all races), ``completion_rate``,
        ``best_lap`` (s, over all races; None without a lap), ``clean_lap`` (a clean solo
        lap on every track, see the module docstring), ``finished_lap`` (the same without
        the off-track condition) and ``tracks``: per track ``solo``, ``duels`` and the
        ``pursuit`` car of each duel.
    """
    from agents.baselines import make_baseline  # noqa: PLC0415 - heavy, imported on use
    from arena.cars import DEFAULT_CAR, car_params  # noqa: PLC0415 - heavy, imported on use
    from arena.observations import ObservationLayout  # noqa: PLC0415 - heavy, imported on use
    from arena.race import CarResult, run_race  # noqa: PLC0415 - heavy, imported on use
    from tracks import load_track  # noqa: PLC0415 - heavy, imported on use

    kw = dict(env_kwargs or {})
    layout = ObservationLayout(int(kw.get("lidar_rays", 64)), int(kw.get("k_opponents", 3)))
    pursuit = make_baseline("pursuit", layout, car_params(kw.get("car", DEFAULT_CAR)))

    def car(c: CarResult) -> dict[str, Any]:
        return {
            "status": c.status,
            "dnf_reason": c.dnf_reason,
            "laps": c.laps_completed,
            "lap_times": c.lap_times,
            "best_lap": c.best_lap,
            "off_track": c.off_track,
            "collisions": c.collisions,
        }

    grids: list[list[int] | str] = [[0, 1], [1, 0]] if both_grids else ["random"]
    per_track: dict[str, Any] = {}
    completed = possible = 0
    clean = finished = True
    best: list[float] = []
    for k, name in enumerate(tracks):
        base = load_track(name)
        for track, key in [(base, str(name))] + (
            [(base.reversed(), f"{name}:reverse")] if reverse else []
        ):
            solo = run_race(
                [policy], track=track, laps=laps, seed=seed + k, record=False, env_kwargs=kw
            )[0].cars[0]
            duels = [
                run_race(
                    [policy, pursuit],
                    track=track,
                    laps=laps,
                    seed=seed + k,
                    grid_order=g,
                    record=False,
                    env_kwargs=kw,
                )[0].cars
                for g in grids
            ]
            mine = [solo, *(d[0] for d in duels)]
            completed += sum(c.laps_completed for c in mine)
            possible += laps * len(mine)
            finished &= solo.status == "finished"
            clean &= solo.status == "finished" and solo.off_track == 0
            best += [c.best_lap for c in mine if c.best_lap is not None]
            per_track[key] = {
                "solo": car(solo),
                "duels": [car(d[0]) for d in duels],
                "pursuit": [car(d[1]) for d in duels],
            }
    return {
        "completed_laps": completed,
        "possible_laps": possible,
        "completion_rate": completed / possible if possible else 0.0,
        "best_lap": min(best) if best else None,
        "finished_lap": finished,
        "clean_lap": clean,
        "tracks": per_track,
    }


# ---- the training callback --------------------------------------------------------------------


def _make_callback(
    args: TrainArgs,
    *,
    pool: Any,
    eval_tracks: list[str],
    env_kwargs: dict[str, Any],
    curve_path: Path,
    started: float,
    export: Callable[[Path], Path],
) -> Any:
    """The :class:`TrainingMonitor` callback (built here: SB3 is imported lazily)."""
    from stable_baselines3.common.callbacks import BaseCallback  # noqa: PLC0415 - heavy, imported on use
    from tqdm import tqdm  # noqa: PLC0415 - heavy, imported on use

    from agents.selfplay import SB3Driver  # noqa: PLC0415 - heavy, imported on use

    class TrainingMonitor(BaseCallback):
        """Progress bar, opponent snapshots, periodic evaluation, wall-clock budget."""

        def __init__(self) -> None:
            super().__init__()
            self.bar: Any = None
            self.next_snapshot = args.snapshot_every
            self.next_eval = args.eval_every if args.eval_every > 0 else math.inf
            self.episodes: deque[tuple[bool, int]] = deque(maxlen=100)
            self.first_lap: dict[str, float] | None = None
            self.first_clean_lap: dict[str, float] | None = None
            self.last_eval_at = -1
            self.stop_reason = "total_timesteps"
            self.best: dict[str, Any] | None = None
            self._best_key: tuple[float, ...] | None = None

        def _on_training_start(self) -> None:
            if args.progress_bar:
                self.bar = tqdm(
                    total=args.total_timesteps,
                    unit="step",
                    dynamic_ncols=True,
                    file=sys.stderr,
                    mininterval=1.0,
                )

        def _on_step(self) -> bool:
            n = self.training_env.num_envs
            if self.bar is not None:
                self.bar.update(n)
            for info, done in zip(self.locals["infos"], self.locals["dones"], strict=True):
                if done and "episode" in info and not info["cut_short"]:
                    finished = info["laps_completed"] >= args.train_laps
                    self.episodes.append((finished, info["laps_completed"]))
            t = self.num_timesteps
            if t >= self.next_snapshot:
                self.next_snapshot += args.snapshot_every
                pool.add_snapshot(self.model.policy, f"snapshot@{t}")
            keep_going = True
            if t >= self.next_eval:
                self.next_eval += args.eval_every
                row = self.evaluate()
                if args.stop_at_first_clean_lap and row["clean_lap"]:
                    self.stop_reason = "first_clean_lap"
                    keep_going = False
            if args.max_minutes is not None and time.perf_counter() - started > (
                60.0 * args.max_minutes
            ):
                self.stop_reason = "max_minutes"
                keep_going = False
            return keep_going

        def _on_rollout_end(self) -> None:
            if self.episodes:
                self.logger.record(
                    "rollout/finish_rate", float(np.mean([f for f, _ in self.episodes]))
                )
                self.logger.record(
                    "rollout/laps_per_episode", float(np.mean([n for _, n in self.episodes]))
                )

        def evaluate(self) -> dict[str, Any]:
            """One evaluation: TensorBoard scalars and a ``curve.jsonl`` line."""
            t, wall = self.num_timesteps, time.perf_counter() - started
            self.model.policy.set_training_mode(False)
            result = evaluate(
                SB3Driver(self.model.policy),
                eval_tracks,
                laps=args.eval_laps,
                env_kwargs=env_kwargs,
            )
            self.last_eval_at = t
            if result["finished_lap"] and self.first_lap is None:
                self.first_lap = {"timesteps": t, "wall_s": round(wall, 1)}
            if result["clean_lap"] and self.first_clean_lap is None:
                self.first_clean_lap = {"timesteps": t, "wall_s": round(wall, 1)}
            row = {"timesteps": t, "wall_s": round(wall, 2), **result}
            if args.save_best:
                self._keep_if_best(row, curve_path.parent / "best.zip")
            with curve_path.open("a", encoding="utf-8") as fh:
                fh.write(json.dumps(row) + "\n")
            self._log(result)
            if self.bar is not None:
                best = result["best_lap"]
                self.bar.set_postfix(
                    laps=f"{result['completed_laps']}/{result['possible_laps']}",
                    best="-" if best is None else f"{best:.2f}s",
                    clean=result["clean_lap"],
                )
            return row

        def _keep_if_best(self, row: dict[str, Any], path: Path) -> None:
            """Export the policy to ``path`` when this evaluation is the best so far."""
            solo = [p["solo"]["best_lap"] for p in row["tracks"].values()]
            lap = float(np.mean(solo)) if None not in solo else math.inf
            key = (row["completion_rate"], float(row["clean_lap"]), -lap)
            if self._best_key is None or key > self._best_key:
                self._best_key = key
                export(path)
                self.best = {
                    "path": str(path),
                    "timesteps": row["timesteps"],
                    "completion_rate": row["completion_rate"],
                    "clean_lap": row["clean_lap"],
                    "mean_solo_lap": None if math.isinf(lap) else round(lap, 3),
                }

        def _log(self, result: dict[str, Any]) -> None:
            log = self.logger.record
            log("eval/completion_rate", result["completion_rate"])
            log("eval/clean_lap", float(result["clean_lap"]))
            per = list(result["tracks"].values())
            groups = {
                "solo": [p["solo"] for p in per],
                "duel": [c for p in per for c in p["duels"]],
                "pursuit": [c for p in per for c in p["pursuit"]],
            }
            for key, cars in groups.items():
                times = [c["best_lap"] for c in cars if c["best_lap"] is not None]
                if key != "pursuit":
                    log(f"eval/{key}_laps", float(np.mean([c["laps"] for c in cars])))
                if times:
                    log(f"eval/{key}_lap_time", float(np.mean(times)))

        def _on_training_end(self) -> None:
            if self.bar is not None:
                self.bar.close()

    return TrainingMonitor()


# ---- main -------------------------------------------------------------------------------------


def machine_description() -> str:
    """CPU count, processor and OS of this machine, for the record."""
    import torch  # noqa: PLC0415 - heavy, imported on use

    cpu = platform.processor() or platform.machine()
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU"
    return f"{os.cpu_count()} CPU cores ({cpu}), {platform.system()} {platform.release()}, {gpu}"


def _batch_vec_env(
    args: TrainArgs,
    uncertainty: Any = None,
    *,
    seed: int | None = None,
    n_envs: int | None = None,
    procedural: bool = True,
) -> Any:
    """The training env of ``--backend batch``: every car of every race learns (self-play).

    One race group (a :class:`arena.batch.sim.BatchSim` of ``n_envs`` races) per training
    track, plus ``procedural_groups(args)`` groups on generated tracks (redrawn during
    training by :func:`procedural_callback`), each also reversed with ``--randomise``;
    ``uncertainty`` (an :class:`arena.uncertainty.UncertaintyConfig`) goes to every group.
    Every car is ``args.car`` and every track is scaled for it (:func:`training_tracks`).
    """
    from arena.batch.vec_env import BatchVecEnv  # noqa: PLC0415 - heavy, imported on use
    from arena.cars import car_params  # noqa: PLC0415 - heavy, imported on use

    seed = args.seed if seed is None else seed
    groups = procedural_groups(args) if procedural else 0
    rng = np.random.default_rng([seed, 7])
    draw = procedural_of(args).draw
    generated = [draw(rng) for _ in range(groups)]
    fixed = [] if args.procedural >= 1.0 and groups else training_tracks(args)
    return BatchVecEnv(
        [*fixed, *generated],
        n_envs=args.n_envs if n_envs is None else n_envs,
        n_cars=args.n_cars,
        laps=args.train_laps,
        device=args.batch_device,
        reverse=args.randomise,
        random_starts=args.randomise,
        reward_scale=args.reward_scale,
        dnf_penalty=args.dnf_penalty,
        seed=seed,
        sim_kwargs={
            "uncertainty": uncertainty,
            "end_on_wall": args.wall_ends_episode,
            "off_track_limit": args.off_track_limit,
            "runoff": args.runoff,
            "car_params": car_params(args.car),
            "observe_perturbation": args.observe_perturbation,
        },
    )


def _selfplay_vec_env(
    args: TrainArgs, env_kwargs: dict[str, Any], *, seed: int, n_envs: int, **extra: Any
) -> Any:
    """The pybullet training env of ``args`` (:class:`agents.selfplay.SelfPlayVecEnv` on the
    training tracks); ``extra`` goes to it as is (``pool``, ``procedural``, ``role``)."""
    from agents.selfplay import SelfPlayVecEnv  # noqa: PLC0415 - heavy, imported on use

    return SelfPlayVecEnv(
        training_tracks(args),
        n_envs=n_envs,
        n_cars=args.n_cars,
        n_learners=args.n_learners,
        laps=args.train_laps,
        randomise=args.randomise,
        reward_scale=args.reward_scale,
        dnf_penalty=args.dnf_penalty,
        seed=seed,
        env_kwargs=env_kwargs,
        **extra,
    )


REDRAW_SAMPLES = 8192  # agent-steps of rollouts per redrawn generated track (batch backend)


def procedural_groups(args: TrainArgs) -> int:
    """Race groups on generated tracks for ``--backend batch --procedural P``.

    The batched backend holds one track per group of races (its maps are per track), so the
    share P is a share of groups: ``G / (G + len(tracks)) ≈ P`` (at least one when P > 0;
    with P = 1 every group is generated, as many as there are training tracks).
    """
    p, n = args.procedural, len(args.tracks)
    if p <= 0.0:
        return 0
    if p >= 1.0:
        return n
    return max(1, round(p / (1.0 - p) * n))


def procedural_of(args: TrainArgs) -> Any:
    """The :class:`agents.selfplay.Procedural` of ``--procedural*`` (share and ranges)."""
    from agents.selfplay import Procedural  # noqa: PLC0415 - heavy, imported on use

    return Procedural(
        share=args.procedural,
        length=(args.procedural_length[0], args.procedural_length[1]),
        difficulty=(args.procedural_difficulty[0], args.procedural_difficulty[1]),
        hairpin=(
            (args.procedural_hairpin[0], args.procedural_hairpin[1])
            if args.procedural_hairpin
            else None
        ),
        width=(
            (args.procedural_width[0], args.procedural_width[1]) if args.procedural_width else None
        ),
        scale=track_scale(args.car),
    )


def track_scale(car: str) -> float:
    """How much smaller (or larger) roads are for ``car``: its length over the F1TENTH car's
    (the built-in tracks and the generator's ranges are drawn for the 1/10 car).

    >>> track_scale("f1tenth"), track_scale("deepracer")
    (1.0, 0.52)
    """
    from arena.cars import car_params  # noqa: PLC0415 - heavy, imported on use
    from arena.sim import CarParams  # noqa: PLC0415 - heavy, imported on use

    return car_params(car).length / CarParams().length


def training_tracks(args: TrainArgs, names: Sequence[str] | None = None) -> list[str]:
    """``names`` (default: ``args.tracks``) as the names of the tracks scaled for ``args.car``
    (:func:`track_scale`): ``NAME@<factor>``; a name that already ends in ``@<factor>``, and
    every name when the factor is 1, stays as it is.

    >>> training_tracks(TrainArgs(car="deepracer"), ["oval", "random:7", "carrera.json@1"])
    ['oval@0.52', 'random:7@0.52', 'carrera.json@1']
    """
    from tracks.geometry import short_float  # noqa: PLC0415 - heavy, imported on use
    from tracks.library import split_scale  # noqa: PLC0415 - heavy, imported on use

    factor = track_scale(args.car)
    names = list(args.tracks if names is None else names)
    if factor == 1.0:
        return names
    return [
        n if split_scale(str(n))[1] is not None else f"{n}@{short_float(factor)}" for n in names
    ]


def procedural_callback(args: TrainArgs, vec_env: Any) -> Any:
    """Redraws the generated tracks of ``--backend batch --procedural P`` during training.

    At the end of a rollout one generated group (round robin) gets a fresh track: its
    simulators (and their reversed twins) are rebuilt on it and restarted, and PPO's next
    rollout starts those slots as new episodes. Building a track's maps takes 1-3 s of a core
    (100-250 m; twice with ``--randomise``, for the reversed twin; ``bench/map_build.py``), so
    this happens once per :data:`REDRAW_SAMPLES` agent-steps of rollouts (every rollout when
    rollouts are at least that big); episodes of one group share its track.
    """
    from stable_baselines3.common.callbacks import BaseCallback  # noqa: PLC0415 - heavy

    from arena.batch.sim import BatchSim  # noqa: PLC0415 - heavy, imported on use

    groups = procedural_groups(args)
    n_views = len(vec_env.sims)
    n_base = n_views // 2 if args.randomise else n_views
    first = n_base - groups  # generated groups come after the fixed tracks
    rng = np.random.default_rng([args.seed, 11])
    procedural = procedural_of(args)

    class Redraw(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.rollouts = 0
            self.drawn: list[str] = []

        def _on_step(self) -> bool:
            return True

        def _on_rollout_end(self) -> None:
            self.rollouts += 1
            n_steps = int(getattr(self.model, "n_steps", 1))  # PPO's rollout length per slot
            every = max(1, math.ceil(REDRAW_SAMPLES / (n_steps * vec_env.num_envs)))
            if self.rollouts % every:
                return
            g = first + len(self.drawn) % groups
            track = procedural.draw(rng)
            self.drawn.append(track.name)
            views = [(g, track)] + ([(g + n_base, track.reversed())] if args.randomise else [])
            for k, view in views:
                old = vec_env.sims[k]
                new = BatchSim(
                    view, old.n_envs, old.n_cars, old.laps, device=old.device,
                    random_starts=old.random_starts, seed=int(rng.integers(0, 2**31 - 1)),
                    uncertainty=old.uncertainty, end_on_wall=old.rules.end_on_wall,
                    car_params=old.params, off_track_limit=old.off_track_limit,
                    stuck_time=old.stuck_time, runoff=old.runoff,
                    observe_perturbation=old.layout.context,
                )  # fmt: skip
                new.nature = old.nature
                vec_env.sims[k] = new
                lo, hi = int(vec_env._bounds[k]), int(vec_env._bounds[k + 1])
                obs = new.ops.to_numpy(new.reset()).reshape(hi - lo, -1)
                # The slots start new episodes: PPO's next rollout begins from these.
                self.model._last_obs[lo:hi] = obs  # type: ignore[index]
                self.model._last_episode_starts[lo:hi] = True  # type: ignore[index]
                vec_env._returns[lo:hi] = 0.0
                vec_env._lengths[lo:hi] = 0

    return Redraw()


def training_env_kwargs(args: TrainArgs, env_kwargs: dict[str, Any]) -> dict[str, Any]:
    """The pybullet training envs' arguments: ``env_kwargs`` (the evaluation races' own) plus
    the training-only rules: ``--off-track-limit``, ``--runoff`` and the model uncertainty
    (evaluation and the checkpoint stay nominal)."""
    out = dict(env_kwargs, off_track_limit=args.off_track_limit, runoff=args.runoff)
    if args.uncertainty != "nominal":
        from agents.robustness import training_uncertainty  # noqa: PLC0415 - heavy

        cfg = training_uncertainty(args.uncertainty)
        out["uncertainty"] = replace(cfg, edge_share=args.edge_share)
    return out


def run_name_for(args: TrainArgs) -> str:
    """``<tracks>__s<seed>__<unix time>`` unless ``args.run_name`` is set."""
    if args.run_name:
        return args.run_name
    tracks = "+".join(Path(t).stem for t in args.tracks)
    return f"{tracks}__s{args.seed}__{int(time.time())}"


def main(args: TrainArgs) -> dict[str, Any]:
    """Train, export, reload and race; returns the run summary (also in ``summary.json``).

    Raises:
        PolicyError: settings that cannot work (see :func:`_check`).
        tracks.TrackError: an unknown track.
    """
    _check(args)
    started = time.perf_counter()
    import torch  # noqa: PLC0415 - heavy, imported on use
    from stable_baselines3 import PPO  # noqa: PLC0415 - heavy, imported on use

    from agents.checkpoint import export_sb3  # noqa: PLC0415 - heavy, imported on use
    from agents.loading import load_policy  # noqa: PLC0415 - heavy, imported on use
    from agents.selfplay import (  # noqa: PLC0415 - heavy, imported on use
        OpponentPool,
        parse_mix,
    )
    from arena.cars import car_name, car_params  # noqa: PLC0415 - heavy, imported on use

    run = run_name_for(args)
    run_dir = Path(args.out) / run
    run_dir.mkdir(parents=True, exist_ok=True)
    tb_dir = Path(args.tensorboard_dir) if args.tensorboard_dir else run_dir / "tb"
    curve_path = run_dir / "curve.jsonl"
    curve_path.write_text("", encoding="utf-8")
    eval_tracks = training_tracks(args, args.eval_tracks or args.tracks)
    # The env defaults (vector obs, continuous actions) with the run's car, by preset name.
    env_kwargs: dict[str, Any] = {"car": car_name(car_params(args.car))}
    if args.observe_perturbation:
        env_kwargs["observe_perturbation"] = True
    train_env_kwargs = training_env_kwargs(args, env_kwargs)

    # Seeding: one block.
    random.seed(args.seed)
    np.random.seed(args.seed)  # noqa: NPY002 - seeds the global RNG third-party code may use
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.torch_threads)

    mix = parse_mix(args.opponent_mix) if args.n_learners < args.n_cars else {}
    pool = OpponentPool(mix=mix, max_snapshots=args.max_snapshots)
    vec_env: Any
    full: Any = train_env_kwargs.get("uncertainty")  # the training set (None: nominal)
    if args.backend == "batch":
        # With a curriculum the first episodes already draw from the narrowest bounds.
        vec_env = _batch_vec_env(args, full.scaled(CURRICULUM_START) if args.curriculum else full)
    else:
        vec_env = _selfplay_vec_env(
            args,
            train_env_kwargs,
            seed=args.seed,
            n_envs=args.n_envs,
            pool=pool,
            procedural=procedural_of(args),
        )
    vec_env.seed(args.seed)
    lr = args.learning_rate
    # CleanRL's annealing: the update after rollout i of N uses lr·(1 − (i−1)/N). SB3 hands the
    # schedule the progress left *after* the rollout, 1 − i/N, which is 0 on the last update:
    # adding one rollout's share back keeps that update (a one-rollout run's only one) learning.
    share = args.n_steps * vec_env.num_envs / args.total_timesteps
    hyper: dict[str, Any] = {
        "learning_rate": (lambda left: min(1.0, left + share) * lr) if args.anneal_lr else lr,
        "n_steps": args.n_steps,
        "batch_size": args.batch_size,
        "n_epochs": args.n_epochs,
        "gamma": args.gamma,
        "gae_lambda": args.gae_lambda,
        "clip_range": args.clip_range,
        "ent_coef": args.ent_coef,
        "vf_coef": args.vf_coef,
        "max_grad_norm": args.max_grad_norm,
    }
    cvar_kwargs: dict[str, Any] = {}
    if args.uncertainty == "cvar":  # updates on the worst share of each rollout
        from agents.cvar import cvar_buffer  # noqa: PLC0415 - only this arm

        cvar_kwargs = cvar_buffer(
            args.total_timesteps,
            args.n_steps,
            vec_env.num_envs,
            share=args.cvar_share,
            warmup=args.cvar_warmup,
        )
    model = PPO(
        "MlpPolicy",
        vec_env,
        **hyper,
        policy_kwargs={
            "net_arch": {"pi": list(args.net_arch), "vf": list(args.net_arch)},
            "log_std_init": args.log_std_init,
        },
        tensorboard_log=str(tb_dir),
        seed=args.seed,
        device="cpu",
        verbose=args.verbose,
        **cvar_kwargs,
    )
    recorded = {
        **hyper,
        "learning_rate": lr,
        "anneal_lr": args.anneal_lr,
        "net_arch": list(args.net_arch),
        "log_std_init": args.log_std_init,
        "reward_scale": args.reward_scale,
        "dnf_penalty": args.dnf_penalty,
        "procedural": args.procedural,
        "procedural_length": args.procedural_length,
        "procedural_difficulty": args.procedural_difficulty,
        "procedural_hairpin": args.procedural_hairpin,
        "procedural_width": args.procedural_width,
        "wall_ends_episode": args.wall_ends_episode,
        "off_track_limit": args.off_track_limit,
        "runoff": args.runoff,
        "n_envs": args.n_envs,
        "n_cars": args.n_cars,
        "n_learners": args.n_learners,
        "opponent_mix": args.opponent_mix,
        "uncertainty": args.uncertainty,
        **(
            {"cvar_share": args.cvar_share, "cvar_warmup": args.cvar_warmup}
            if args.uncertainty == "cvar"
            else {}
        ),
        **({"curriculum": args.curriculum} if args.curriculum else {}),
        **({"edge_share": args.edge_share} if args.edge_share else {}),
        **({"natures": args.natures} if args.natures > 1 else {}),
        **({"observe_perturbation": True} if args.observe_perturbation else {}),
        "backend": args.backend,
        "car": env_kwargs["car"],
        "track_scale": track_scale(args.car),
    }
    if args.init_from is not None:
        from agents.robustness import load_weights  # noqa: PLC0415 - heavy, imported on use

        load_weights(model, Path(args.init_from))
        recorded["init_from"] = str(args.init_from)

    def export(path: Path, training: dict[str, Any] | None = None) -> Path:
        training = training or {"tracks": list(args.tracks), "seed": args.seed}
        return export_sb3(
            model,
            path,
            name=run,
            env_config=env_kwargs,
            hyperparameters=recorded,
            training=training,
        )

    monitor = _make_callback(
        args,
        pool=pool,
        eval_tracks=eval_tracks,
        env_kwargs=env_kwargs,
        curve_path=curve_path,
        started=started,
        export=export,
    )
    callback: Any = monitor
    redraw = None
    if args.backend == "batch" and procedural_groups(args):
        from stable_baselines3.common.callbacks import CallbackList  # noqa: PLC0415 - heavy

        redraw = procedural_callback(args, vec_env)
        callback = CallbackList([monitor, redraw])
    if args.curriculum:
        from stable_baselines3.common.callbacks import CallbackList  # noqa: PLC0415 - heavy

        from agents.curriculum import curriculum_callback  # noqa: PLC0415 - only this option

        widen = curriculum_callback(full, vec_env, args.total_timesteps, args.curriculum)
        callback = CallbackList([callback, widen])
    if args.uncertainty in NATURE_ARMS:  # a nature to train
        from agents.robustness import rarl_callback  # noqa: PLC0415 - heavy, imported on use

        callback = rarl_callback(args, vec_env, train_env_kwargs, run_dir, callback)
    try:
        try:
            model.learn(total_timesteps=args.total_timesteps, callback=callback, tb_log_name="ppo")
        except KeyboardInterrupt:  # Ctrl-C ends training early; the policy is still saved
            monitor.stop_reason = "interrupted"
            if monitor.bar is not None:
                monitor.bar.close()
        train_s = time.perf_counter() - started
        if monitor.last_eval_at != model.num_timesteps:
            monitor.evaluate()  # the final point of the learning curve
    finally:
        vec_env.close()

    training = {
        "steps": int(model.num_timesteps),
        "wall_time_s": round(train_s, 1),
        "machine": machine_description(),
        "stop_reason": monitor.stop_reason,
        "first_lap": monitor.first_lap,
        "first_clean_lap": monitor.first_clean_lap,
        "best": monitor.best,
        "tracks": list(args.tracks),
        "seed": args.seed,
        "command": "slipstream train " + " ".join(_to_argv(args)),
    }
    if args.backend == "batch" and procedural_groups(args):
        training["generated_tracks"] = [
            sim.track.name for sim in vec_env.sims if sim.track.name.startswith("random:")
        ]
        training["generated_tracks_drawn"] = len(redraw.drawn) if redraw is not None else 0
    path = export(run_dir / "policy.zip", training)
    # CleanRL: reload what was saved and race it straight away.
    reloaded = load_policy(str(path), observe_perturbation=args.observe_perturbation)
    final = evaluate(reloaded, eval_tracks[:1], laps=args.eval_laps, env_kwargs=env_kwargs)
    summary = {
        "run": run,
        "run_dir": str(run_dir),
        "policy": str(path),
        "policy_bytes": path.stat().st_size,
        "tensorboard": str(tb_dir),
        "curve": str(curve_path),
        "training": training,
        "reloaded_eval": final,
        "args": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(args).items()},
    }
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    return summary


def _to_argv(args: TrainArgs) -> list[str]:
    """The flags that reproduce ``args`` (only those that differ from the defaults)."""
    out: list[str] = []
    defaults = TrainArgs()
    for f in fields(TrainArgs):
        value, default = getattr(args, f.name), getattr(defaults, f.name)
        if value == default or f.name in ("progress_bar", "verbose"):
            continue
        flag = "--" + f.name.replace("_", "-")
        if isinstance(value, bool):
            out.append(flag if value else "--no-" + flag[2:])
        elif isinstance(value, list):
            out += [flag, *map(str, value)]
        else:
            out += [flag, str(value)]
    return out


if __name__ == "__main__":
    print(json.dumps(main(parse_args()), indent=2))
