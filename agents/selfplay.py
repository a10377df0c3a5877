"""Self-play vector env: one shared learning policy against frozen snapshots and baselines.

:class:`SelfPlayVecEnv` is a stable-baselines3 ``VecEnv`` over ``n_envs`` in-process
:class:`arena.RacingEnv` copies. In each copy the first ``n_learners`` cars (``car_0`` …)
are driven by the policy being trained, each one slot of the VecEnv batch
(``num_envs = n_envs × n_learners``: parameter sharing); the other cars are driven by
opponents drawn per episode from an :class:`OpponentPool` — frozen snapshots of the learner
and the pursuit / gap-follower baselines. SuperSuit's PettingZoo-to-VecEnv conversion cannot
do this: it hands every car to the learner.

Episode ends (PettingZoo agent removal). A car that terminates or is truncated leaves the
race. As soon as the *first* learner car of a copy is done, the whole copy is reset: that
car's slot reports ``done=True`` with its own ``terminal_observation`` (and
``TimeLimit.truncated`` when the env truncated it), and the copy's other learner slots end
too, marked ``TimeLimit.truncated=True`` so that PPO bootstraps their value instead of
treating the cut as a crash. No slot ever carries padding (zero observations of a car that
has left), so SB3 never trains on anything but real transitions. With ``n_learners=1`` (the
default) this is simply one learner car per copy.

Randomised per episode (DeepRacer's recipe): the track, the start point along the lap, the
direction of travel, the grid order and the opponents. The track is one of ``tracks`` or,
with probability ``procedural.share``, a freshly generated circuit
(:func:`tracks.generator.generate_track` with a random seed, length and difficulty) — the
domain randomisation that lets a policy drive tracks it has never seen. Everything is drawn
from one seeded generator per copy, so a run is reproducible given ``seed``.

Model uncertainty (``env_kwargs["uncertainty"]``): in ``sample`` mode nothing changes here
(the env draws the perturbations). In ``adversarial`` mode each race also has ``nature_car_i``
agents: with ``role="racer"`` they are driven by :attr:`SelfPlayVecEnv.nature` (a frozen
nature policy; None leaves the nominal point), with ``role="nature"`` the learner slots are
the natures ``nature_car_0 …`` of the first ``n_learners`` cars, those cars are driven by
:attr:`SelfPlayVecEnv.racer` (a frozen racer) and each slot's reward is exactly minus its
car's (shaped) reward — RARL's alternation, see :mod:`agents.robustness`.

Reward: the env's (``"racing"`` by default: metres of progress minus penalties) times
``reward_scale``, minus ``dnf_penalty`` on the step where a learner car retires (stuck,
off the track or flipped; not a time-out): without it, crashing only costs the progress the
car would have made within the discount horizon.

Infos: a finished slot gets ``episode`` (``r`` return, ``l`` length, ``t`` wall seconds,
SB3 Monitor's convention, so ``rollout/ep_rew_mean`` is logged), ``laps_completed``,
``dnf_reason`` (None when the car finished or was cut short), ``cut_short`` (its
team-mate's end ended the episode) and ``track``.
"""

from __future__ import annotations

import copy
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import torch
from gymnasium import spaces
from numpy.typing import NDArray
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.vec_env import VecEnv
from stable_baselines3.common.vec_env.base_vec_env import VecEnvIndices, VecEnvStepReturn

from agents.baselines import make_baseline
from agents.policy import Policy, PolicyError
from arena.env import RacingEnv
from tracks import Track, TrackError
from tracks.generator import generate_track

ObsArray = NDArray[np.float32]
OPPONENT_KINDS = ("snapshot", "pursuit", "gap")


class Driver(Protocol):
    """An opponent that drives several cars at once (one observation row per car)."""

    name: str

    def act_batch(self, obs: ObsArray) -> ObsArray:
        """Actions (k, 2) for observations (k, obs_size)."""
        ...


class PolicyDriver:
    """A stateless :class:`agents.policy.Policy` (a baseline, say) applied row by row."""

    def __init__(self, policy: Policy) -> None:
        self.policy = policy
        self.name = getattr(policy, "name", "policy")

    def act_batch(self, obs: ObsArray) -> ObsArray:
        """Actions (k, 2) for observations (k, obs_size)."""
        return np.stack([np.asarray(self.policy.act(row), dtype=np.float32) for row in obs])


class SB3Driver:
    """Deterministic actions of an SB3 policy; also a :class:`agents.policy.Policy`.

    Wraps either the live policy being trained (for evaluation races) or a frozen copy of it
    (:meth:`frozen`, an opponent snapshot). Actions are the Gaussian mean clipped to [-1, 1].
    """

    def __init__(self, policy: BasePolicy, name: str = "learner") -> None:
        self.policy = policy
        self.name = name

    @classmethod
    def frozen(cls, policy: BasePolicy, name: str) -> SB3Driver:
        """A deep copy of ``policy`` in eval mode, on the CPU, with no gradients.

        Straight after ``learn()`` the last minibatch's action distribution still holds
        tensors of the autograd graph, which ``copy.deepcopy`` refuses; it is dropped first
        (the next forward pass rebuilds it).
        """
        dist = getattr(policy, "action_dist", None)
        if dist is not None and hasattr(dist, "distribution"):
            dist.distribution = None
        snap = copy.deepcopy(policy).to("cpu")
        snap.set_training_mode(False)
        for p in snap.parameters():
            p.requires_grad_(False)
        # The optimizer state is dead weight in a snapshot.
        snap.optimizer = None  # type: ignore[assignment]
        return cls(snap, name)

    def act_batch(self, obs: ObsArray) -> ObsArray:
        """Actions (k, 2) for observations (k, obs_size)."""
        with torch.no_grad():
            actions, _ = self.policy.predict(obs, deterministic=True)
        return np.clip(np.asarray(actions, dtype=np.float32), -1.0, 1.0)

    def reset(self, seed: int | None = None) -> None:
        """Stateless: nothing to reset."""

    def act(self, obs: ObsArray) -> ObsArray:
        """The action (2,) for one observation."""
        return self.act_batch(np.asarray(obs, dtype=np.float32)[None])[0]


def parse_mix(text: str) -> dict[str, float]:
    """Opponent weights from ``"snapshot=0.5,pursuit=0.3,gap=0.2"`` (normalised to sum 1).

    Raises:
        PolicyError: unknown kind, bad number, or all weights zero.
    """
    weights: dict[str, float] = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        kind, _, value = part.partition("=")
        kind = kind.strip()
        if kind not in OPPONENT_KINDS:
            raise PolicyError(f"unknown opponent kind {kind!r}; choose from {OPPONENT_KINDS}")
        try:
            w = float(value)
        except ValueError:
            raise PolicyError(f"bad opponent weight in {part!r}") from None
        if not w >= 0.0:
            raise PolicyError(f"opponent weight must be >= 0 in {part!r}")
        weights[kind] = w
    total = sum(weights.values())
    if total <= 0.0:
        raise PolicyError(f"opponent mix {text!r} has no positive weight")
    return {k: w / total for k, w in weights.items()}


@dataclass
class OpponentPool:
    """Opponents to sample from: baselines plus the most recent frozen snapshots.

    Attributes:
        mix: probability of each kind (``snapshot``, ``pursuit``, ``gap``). Until the first
            snapshot exists, the snapshot share goes to the baselines (or to pursuit when the
            mix names no baseline).
        max_snapshots: how many snapshots to keep (oldest dropped first); a snapshot is drawn
            uniformly among them.
    """

    mix: dict[str, float] = field(default_factory=lambda: {"snapshot": 0.5, "pursuit": 0.5})
    max_snapshots: int = 8
    snapshots: deque[SB3Driver] = field(init=False)
    _baselines: dict[str, PolicyDriver] = field(init=False, default_factory=dict)

    def __post_init__(self) -> None:
        self.snapshots = deque(maxlen=self.max_snapshots)

    def add_snapshot(self, policy: BasePolicy, name: str) -> None:
        """Freeze a copy of ``policy`` into the pool."""
        self.snapshots.append(SB3Driver.frozen(policy, name))

    def sample(self, rng: np.random.Generator, env: RacingEnv) -> Driver:
        """One opponent for one car of ``env``."""
        kinds = [k for k in self.mix if k != "snapshot" or self.snapshots]
        weights = np.array([self.mix[k] for k in kinds])
        if not kinds or weights.sum() <= 0.0:
            kinds, weights = ["pursuit"], np.ones(1)
        kind = kinds[int(rng.choice(len(kinds), p=weights / weights.sum()))]
        if kind == "snapshot":
            return self.snapshots[int(rng.integers(len(self.snapshots)))]
        if kind not in self._baselines:
            self._baselines[kind] = PolicyDriver(make_baseline(kind, env.layout, env.params))
        return self._baselines[kind]


@dataclass(frozen=True)
class Procedural:
    """How often, and which, generated tracks to train on.

    Attributes:
        share: probability that an episode runs on a new generated track (0: never).
        length: range of lap lengths, m.
        difficulty: range of :func:`tracks.generator.generate_track` difficulties (0–1:
            twistier and narrower towards 1).
        hairpin: range of the hairpin radius, m, of real-track-like generated tracks
            (``generate_track(hairpin=...)``: bends tighter than the road's half-width, the
            inside narrowed as the importers narrow real files); None: ordinary tracks.
        width: range of the total road width, m, before scaling (``generate_track(width=)``);
            None: the width difficulty (or hairpin) gives.
        scale: every generated track is scaled by this (:meth:`tracks.Track.scaled`; named
            ``random:…@<scale>``) after it is generated with the ranges above, which are
            therefore for the 1/10 car: 0.52 gives roads for the 1/18 DeepRacer car.
    """

    share: float = 0.0
    length: tuple[float, float] = (60.0, 160.0)
    difficulty: tuple[float, float] = (0.2, 0.8)
    hairpin: tuple[float, float] | None = None
    width: tuple[float, float] | None = None
    scale: float = 1.0

    def draw(self, rng: np.random.Generator, attempts: int = 20) -> Track:
        """A generated track with its seed, length, difficulty (and hairpin) drawn from ``rng``,
        scaled by :attr:`scale`.

        Raises:
            PolicyError: the generator gave up on ``attempts`` draws in a row (ranges too
                tight for any circuit).
        """
        for _ in range(attempts):  # a draw with no valid circuit is rare: try the next seed
            seed = int(rng.integers(2**31 - 1))
            length = float(rng.uniform(*self.length))
            difficulty = float(rng.uniform(*self.difficulty))
            hairpin = None if self.hairpin is None else float(rng.uniform(*self.hairpin))
            width = None if self.width is None else float(rng.uniform(*self.width))
            try:
                track = generate_track(seed, length, difficulty, hairpin, width)
                return track if self.scale == 1.0 else track.scaled(self.scale)
            except TrackError:
                continue
        raise PolicyError(
            f"no valid generated track in {attempts} draws; widen the procedural ranges"
        )


@dataclass
class _Copy:
    """One RacingEnv copy and its episode bookkeeping."""

    rng: np.random.Generator
    envs: dict[str, RacingEnv]  # one per listed track, built on first use
    env: RacingEnv | None = None
    generated: RacingEnv | None = None  # the env on the current generated track, if any
    track: str = ""
    obs: dict[str, Any] = field(default_factory=dict)
    opponents: dict[str, Driver] = field(default_factory=dict)
    returns: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    length: int = 0
    started: float = 0.0


class SelfPlayVecEnv(VecEnv):
    """``n_envs`` racing envs, ``n_learners`` learner cars each, as one SB3 ``VecEnv``.

    Args:
        tracks: track names (or paths) to draw from, uniformly per episode.
        n_envs: number of in-process env copies.
        n_cars: cars per race (learners + opponents), 1–16.
        n_learners: learner cars per race (1 ≤ n_learners ≤ n_cars).
        pool: where opponents come from; None when ``n_cars == n_learners``.
        laps: laps per episode.
        randomise: random start point, direction and grid order each episode; False starts
            every episode from the grid, forward, learners on pole.
        reward_scale: multiplies every reward (``episode.r`` sums the rewards PPO sees).
        dnf_penalty: subtracted (after scaling) when a learner car retires early.
        procedural: share and ranges of generated training tracks.
        seed: seeds the per-copy generators (also settable with :meth:`seed`).
        env_kwargs: more :class:`arena.RacingEnv` arguments (``lidar_rays``, ``reward``…).
    """

    def __init__(
        self,
        tracks: Sequence[str],
        *,
        n_envs: int = 4,
        n_cars: int = 2,
        n_learners: int = 1,
        pool: OpponentPool | None = None,
        laps: int = 1,
        randomise: bool = True,
        reward_scale: float = 1.0,
        dnf_penalty: float = 0.0,
        procedural: Procedural | None = None,
        seed: int | None = None,
        env_kwargs: dict[str, Any] | None = None,
        role: str = "racer",
    ) -> None:
        if role not in ("racer", "nature"):
            raise PolicyError(f"role must be racer or nature, got {role!r}")
        if not tracks:
            raise PolicyError("at least one training track is needed")
        if not 1 <= n_learners <= n_cars:
            raise PolicyError(f"n_learners must be in 1..n_cars ({n_cars}), got {n_learners}")
        if n_envs < 1:
            raise PolicyError(f"n_envs must be at least 1, got {n_envs}")
        self.tracks = list(tracks)
        self.n_copies = n_envs
        self.n_cars = n_cars
        self.n_learners = n_learners
        self.pool = pool if pool is not None else OpponentPool()
        self.laps = laps
        self.randomise = randomise
        self.reward_scale = reward_scale
        self.dnf_penalty = dnf_penalty
        self.procedural = procedural or Procedural()
        self.env_kwargs = dict(env_kwargs or {})
        self.role = role
        self.cars = [f"car_{j}" for j in range(n_learners)]
        self.learners = [("nature_" if role == "nature" else "") + a for a in self.cars]
        self.nature: Driver | None = None  # drives the nature agents of the racer role
        self.racer: Driver | None = None  # drives the learners' cars in the nature role
        self._copies = [
            _Copy(rng=np.random.default_rng(None if seed is None else seed + k), envs={})
            for k in range(n_envs)
        ]
        first = self._env_for(self._copies[0], self.tracks[0])
        if self.learners[0] not in first.possible_agents:
            raise PolicyError("role='nature' needs an adversarial uncertainty config")
        obs_space = first.observation_space(self.learners[0])
        act_space = first.action_space(self.learners[0])
        if not isinstance(obs_space, spaces.Box) or not isinstance(act_space, spaces.Box):
            raise PolicyError("self-play needs obs_mode='vector' and action_mode='continuous'")
        self.render_mode = None
        self._obs_shape: tuple[int, ...] = obs_space.shape
        super().__init__(n_envs * n_learners, obs_space, act_space)
        self._actions: NDArray[np.float32] = np.zeros(
            (self.num_envs, *act_space.shape), dtype=np.float32
        )

    # ---- env copies -----------------------------------------------------------------------

    def _env_for(self, copy_: _Copy, track: str) -> RacingEnv:
        if track not in copy_.envs:  # RacingEnv loads the track (TrackError) before building
            copy_.envs[track] = RacingEnv(
                track=track, n_cars=self.n_cars, laps=self.laps, **self.env_kwargs
            )
        return copy_.envs[track]

    def _generated_env(self, rng: np.random.Generator) -> RacingEnv:
        """An env on a new generated track (redrawn if the generator gives up)."""
        track = self.procedural.draw(rng)
        return RacingEnv(track=track, n_cars=self.n_cars, laps=self.laps, **self.env_kwargs)

    def _reset_copy(self, k: int, seed: int | None = None) -> None:
        """Start a new episode in copy ``k``: draw track, start, direction, opponents."""
        c = self._copies[k]
        if seed is not None:
            c.rng = np.random.default_rng(seed)
        if c.generated is not None:
            c.generated.close()
            c.generated = None
        if c.rng.random() < self.procedural.share:
            env = c.env = c.generated = self._generated_env(c.rng)
            c.track = env.base_track.name
        else:
            c.track = self.tracks[int(c.rng.integers(len(self.tracks)))]
            env = c.env = self._env_for(c, c.track)
        options: dict[str, Any] = {}
        if self.randomise:
            options = {"start_offset": "random", "direction": "random", "grid_order": "random"}
        c.obs, _ = env.reset(seed=int(c.rng.integers(2**31)), options=options)
        c.opponents = {
            a: self.pool.sample(c.rng, env)
            for a in env.possible_agents[self.n_learners : self.n_cars]
        }
        if self.role == "nature" and self.racer is not None:
            c.opponents.update(dict.fromkeys(self.cars, self.racer))
        if self.nature is not None:
            natures = env.possible_agents[self.n_cars :]
            c.opponents.update({a: self.nature for a in natures if a not in self.learners})
        c.returns = np.zeros(self.n_learners)
        c.length = 0
        c.started = time.perf_counter()

    # ---- VecEnv API -----------------------------------------------------------------------

    def reset(self) -> NDArray[np.float32]:
        """Reset every copy; returns observations (num_envs, obs_size)."""
        for k in range(self.n_copies):
            self._reset_copy(k, self._seeds[k * self.n_learners])
        self._reset_seeds()
        self._reset_options()
        return np.stack(
            [self._copies[k].obs[a] for k in range(self.n_copies) for a in self.learners]
        )

    def step_async(self, actions: NDArray[np.float32]) -> None:
        """Store the learners' actions (num_envs, 2) for :meth:`step_wait`."""
        self._actions = np.asarray(actions, dtype=np.float32).reshape(self.num_envs, -1)

    def _opponent_actions(self) -> list[dict[str, ObsArray]]:
        """Every racing opponent car's action, one batched call per driver."""
        groups: dict[int, tuple[Driver, list[tuple[int, str]]]] = {}
        for k, c in enumerate(self._copies):
            assert c.env is not None
            for agent in c.env.agents:
                drv = c.opponents.get(agent)
                if drv is not None:
                    groups.setdefault(id(drv), (drv, []))[1].append((k, agent))
        out: list[dict[str, ObsArray]] = [{} for _ in self._copies]
        for drv, cars in groups.values():
            acts = drv.act_batch(np.stack([self._copies[k].obs[a] for k, a in cars]))
            for (k, agent), act in zip(cars, acts, strict=True):
                out[k][agent] = act
        return out

    def step_wait(self) -> VecEnvStepReturn:
        """Step every copy; reset the copies whose first learner car is done."""
        n_l = self.n_learners
        obs_out = np.empty((self.num_envs, *self._obs_shape), dtype=np.float32)
        rewards = np.zeros(self.num_envs, dtype=np.float32)
        dones = np.zeros(self.num_envs, dtype=bool)
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        opp_actions = self._opponent_actions()
        sign = -1.0 if self.role == "nature" else 1.0
        for k, c in enumerate(self._copies):
            env = c.env
            assert env is not None
            actions = opp_actions[k]
            for j, agent in enumerate(self.learners):
                actions[agent] = self._actions[k * n_l + j]
            step = env.step(actions)
            obs: dict[str, Any] = step[0]
            rew, term, trunc, env_infos = step[1:]
            c.length += 1
            ended = False
            for j, agent in enumerate(self.learners):
                car = self.cars[j]
                r = rew.get(car, 0.0) * self.reward_scale
                if term.get(car, False) and env_infos[car].get("dnf_reason") is not None:
                    r -= self.dnf_penalty
                r *= sign  # a nature's reward is exactly minus its car's
                c.returns[j] += r
                rewards[k * n_l + j] = r
                ended |= term.get(agent, False) or trunc.get(agent, False)
            c.obs = obs
            if not ended:
                for j, agent in enumerate(self.learners):
                    obs_out[k * n_l + j] = obs[agent]
                continue
            elapsed = time.perf_counter() - c.started
            for j, agent in enumerate(self.learners):
                slot = k * n_l + j
                info = env_infos[self.cars[j]]
                # Cut short by a team-mate's end: bootstrap like a time limit.
                cut = not (term[agent] or trunc[agent])
                dones[slot] = True
                infos[slot] = {
                    "terminal_observation": obs[agent],
                    "TimeLimit.truncated": bool(trunc[agent]) or cut,
                    "episode": {"r": float(c.returns[j]), "l": c.length, "t": round(elapsed, 3)},
                    "laps_completed": int(info["laps_completed"]),
                    "dnf_reason": info.get("dnf_reason"),
                    "cut_short": cut,
                    "track": c.track,
                }
            self._reset_copy(k)
            for j, agent in enumerate(self.learners):
                obs_out[k * n_l + j] = c.obs[agent]
        return obs_out, rewards, dones, infos

    def close(self) -> None:
        """Close every env copy (their pybullet clients)."""
        for c in self._copies:
            for env in c.envs.values():
                env.close()
            c.envs.clear()
            if c.generated is not None:
                c.generated.close()
                c.generated = None

    def _copy_indices(self, indices: VecEnvIndices) -> list[int]:
        if indices is None:
            slots: Sequence[int] = range(self.num_envs)
        elif isinstance(indices, int):
            slots = [indices]
        else:
            slots = list(indices)
        return [s // self.n_learners for s in slots]

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        """Attribute of the env copy behind each slot (its current track's env)."""
        if attr_name == "render_mode":
            return [None for _ in self._copy_indices(indices)]
        return [getattr(self._current(k), attr_name) for k in self._copy_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        """Set an attribute on the env copy behind each slot."""
        for k in self._copy_indices(indices):
            setattr(self._current(k), attr_name, value)

    def env_method(
        self,
        method_name: str,
        *method_args: Any,
        indices: VecEnvIndices = None,
        **method_kwargs: Any,
    ) -> list[Any]:
        """Call a method of the env copy behind each slot."""
        return [
            getattr(self._current(k), method_name)(*method_args, **method_kwargs)
            for k in self._copy_indices(indices)
        ]

    def env_is_wrapped(self, wrapper_class: type[Any], indices: VecEnvIndices = None) -> list[bool]:
        """No copy is a Gymnasium wrapper."""
        return [False for _ in self._copy_indices(indices)]

    def _current(self, k: int) -> RacingEnv:
        c = self._copies[k]
        return c.env if c.env is not None else self._env_for(c, self.tracks[0])
