"""Model-uncertainty sets for robust racing: bounds, samplers, perturbations, nature's map.

Zhang et al. (NeurIPS 2020) give each agent an uncertainty set over its reward and its
transitions, and let a *nature* player pick the worst case inside it; DeepRacer's sim-to-real
recipe randomises the same kinds of things (start, direction, action noise, image jitter).
Here every set is a **box**: each parameter ``p`` has an interval ``[lo, hi]``, per car.

=================  ==========================================================================
group              parameters (nominal value)
=================  ==========================================================================
dynamics           ``friction`` (1), ``mass`` (1), ``motor`` (1), ``steer_gain`` (1)
                   multipliers; ``steer_offset`` (0 rad, added to the steering target);
                   ``latency`` (0 whole control steps); ``action_noise`` (0: amplitude of
                   uniform noise added to each command in [-1, 1] units)
perception         ``lidar_noise`` (0: std of Gaussian noise on ranges normalised to [0, 1]),
                   ``lidar_dropout`` (0: probability that a ray returns nothing);
                   image: ``brightness`` (0, fraction of 255 added), ``contrast`` (1),
                   ``hue`` (0 turns; colour images only), ``image_noise`` (0, std in grey
                   levels), ``shift`` (0 px, horizontal), ``shadow`` (0: darkness of a band)
reward             ``reward_noise`` (0: additive δ in ``[-c·λ, c·λ]``), ``w_progress``,
                   ``w_off_track``, ``w_wall``, ``w_collision``, ``w_overtake`` (1: interval
                   weights on the racing reward terms)
=================  ==========================================================================

A :class:`Perturbation` holds one value of every parameter for every car, as an array
``(n_cars, n_params)`` in :data:`PARAM_NAMES` order. Modes (:class:`UncertaintyConfig`):

* ``nominal``: nothing is perturbed (the env does no extra work at all);
* ``sample``: uniform draws inside the box, independently per car, per episode, per step or
  every k steps, from the env's seeded generator; the reward noise is redrawn every step
  from Zhang's truncated Gaussian ``N_trunc(0, λ)`` cut at ``±c·λ``;
* ``fixed``: an exact perturbation (:meth:`Perturbation.from_mapping`), e.g. a grid point;
* ``adversarial``: nature agents choose it: a Box action ``x`` in ``[-1, 1]^k`` over the
  ``k`` parameters whose interval is not a single point maps to
  ``lo + (x + 1) / 2 · (hi − lo)`` (clipped; latency rounded), see :func:`nature_values`.

>>> cfg = UncertaintyConfig(mode="sample", dynamics=DynamicsBounds(friction=(0.6, 1.2)))
>>> cfg.free_names
('friction',)
>>> float(nature_values(cfg, np.array([-1.0]), np.tile(cfg.nominal, (1, 1)))[0, 0])
0.6
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from functools import cached_property
from typing import Any, Literal, cast

import numpy as np
from numpy.typing import NDArray

from arena.batch.xp import NUMPY, NumpyOps
from arena.sim import CarScales
from tracks.errors import SlipstreamError

FloatArray = NDArray[np.float64]
Interval = tuple[float, float]
Mode = Literal["nominal", "sample", "fixed", "adversarial"]
Resample = Literal["episode", "step", "every_k"]
MODES = ("nominal", "sample", "fixed", "adversarial")
MAX_LATENCY = 10  # control steps: the FIFO's length bound (0.5 s at 20 Hz)

DYNAMICS = ("friction", "mass", "motor", "steer_gain", "steer_offset", "latency", "action_noise")
PERCEPTION = (
    "lidar_noise",
    "lidar_dropout",
    "brightness",
    "contrast",
    "hue",
    "image_noise",
    "shift",
    "shadow",
)
REWARD_WEIGHTS = ("w_progress", "w_off_track", "w_wall", "w_collision", "w_overtake")
REWARD = ("reward_noise", *REWARD_WEIGHTS)
PARAM_NAMES = (*DYNAMICS, *PERCEPTION, *REWARD)
INDEX = {name: k for k, name in enumerate(PARAM_NAMES)}
LATENCY = INDEX["latency"]
REWARD_NOISE = INDEX["reward_noise"]
# What a perturbation-aware observation holds (arena.observations.ObservationLayout.context):
# these parameters as (value - nominal) / scale, the scales the half-widths of the widest
# training set (agents.robustness.wide_dynamics), so the same value reads the same whatever
# set an env draws from.
CONTEXT_FEATURES = (*DYNAMICS, "lidar_noise", "lidar_dropout")
CONTEXT_SCALES = (0.6, 0.3, 0.3, 0.225, 0.075, 3.0, 0.15, 0.05, 0.1)
_CONTEXT_COLUMNS = [INDEX[name] for name in CONTEXT_FEATURES]
_POSITIVE = ("friction", "mass", "motor", "steer_gain", "contrast")
_FRACTIONS = ("lidar_dropout", "shadow")


class UncertaintyError(SlipstreamError):
    """An uncertainty configuration or perturbation that cannot be used."""


@dataclass(frozen=True)
class DynamicsBounds:
    """Per-car transition uncertainty: intervals ``(lo, hi)`` around the nominal car."""

    friction: Interval = (1.0, 1.0)  # × tyre-road μ
    mass: Interval = (1.0, 1.0)  # × chassis mass and yaw inertia (motor, brakes unchanged)
    motor: Interval = (1.0, 1.0)  # × drive force
    steer_gain: Interval = (1.0, 1.0)  # × steering command
    steer_offset: Interval = (0.0, 0.0)  # rad added to the steering target (trim)
    latency: Interval = (0, 0)  # whole control steps between a command and its effect
    action_noise: Interval = (0.0, 0.0)  # amplitude of uniform noise on each command


@dataclass(frozen=True)
class PerceptionBounds:
    """Observation uncertainty: lidar noise and dropout, image jitter (DeepRacer's set)."""

    lidar_noise: Interval = (0.0, 0.0)  # std, on ranges normalised to [0, 1]
    lidar_dropout: Interval = (0.0, 0.0)  # probability a ray reads max range
    brightness: Interval = (0.0, 0.0)  # fraction of 255 added to every pixel
    contrast: Interval = (1.0, 1.0)  # × distance from mid-grey
    hue: Interval = (0.0, 0.0)  # turns of hue rotation (colour images; grey ones ignore it)
    image_noise: Interval = (0.0, 0.0)  # std of Gaussian pixel noise, grey levels
    shift: Interval = (0.0, 0.0)  # px of horizontal shift
    shadow: Interval = (0.0, 0.0)  # darkness (0-1) of a vertical shadow band


@dataclass(frozen=True)
class RewardBounds:
    """Reward uncertainty: bounded additive noise and interval weights on the terms.

    ``noise`` is Zhang's level λ: sampled noise is ``N(0, λ)`` truncated to ``±noise_clip·λ``,
    and nature may choose any δ in that interval. The weights multiply the racing reward
    terms of :mod:`arena.rewards` (with ``reward="progress"`` only ``progress`` applies; a
    DeepRacer reward function gets the additive noise only).
    """

    noise: float = 0.0  # λ, reward units per step
    noise_clip: float = 2.0  # truncation, in multiples of λ
    progress: Interval = (1.0, 1.0)
    off_track: Interval = (1.0, 1.0)
    wall: Interval = (1.0, 1.0)
    collision: Interval = (1.0, 1.0)
    overtake: Interval = (1.0, 1.0)


@dataclass(frozen=True)
class EpisodeRandomisation:
    """Per-episode randomisation of where and on what the race starts.

    Explicit ``reset`` options (``start_offset``, ``direction``) take precedence.
    """

    start: Literal["grid", "random", "round_robin"] = "grid"
    start_step: float = 0.05  # fraction of a lap the round-robin start moves per episode
    direction: Literal["forward", "random", "alternate"] = "forward"
    tracks: tuple[str, ...] = ()  # draw each episode's track from these (empty: the env's)


@dataclass(frozen=True)
class UncertaintyConfig:
    """Everything the env's ``uncertainty=`` argument takes (see the module docstring).

    Attributes:
        mode: ``nominal``, ``sample``, ``fixed`` or ``adversarial``.
        resample: in ``sample`` mode, draw once per ``episode``, every ``step`` or
            ``every_k`` steps.
        every_k: the k of ``every_k``.
        dynamics: transition bounds.
        perception: observation bounds.
        reward: reward bounds.
        episode: start / direction / track randomisation (any mode but nominal).
        nature_acts: ``reset``: nature's first action of an episode sets the perturbation,
            held to the end (episode-level worst case); ``step``: every step.
        nature_rate: with ``nature_acts="step"``, the largest change per step as a
            fraction of each interval (None: no limit).
        perturbation: in ``fixed`` mode, the perturbation used when ``reset`` gets none
            (names to a value or one value per car; the rest nominal).
        edge_share: in ``sample`` mode, the probability that a parameter of a draw takes
            one of its interval's two ends (each as likely) instead of a uniform value
            inside: a corner-weighted sampler (0: plain uniform draws, the same stream as
            before; the reward noise stays Gaussian). Uniform draws put little mass where
            several parameters are bad at once (friction 0.5 or less, latency 3 and a
            steering offset past 0.06 rad together: 0.6 % of wide draws; 7 % at 0.5).
    """

    mode: Mode = "nominal"
    resample: Resample = "episode"
    every_k: int = 10
    dynamics: DynamicsBounds = field(default_factory=DynamicsBounds)
    perception: PerceptionBounds = field(default_factory=PerceptionBounds)
    reward: RewardBounds = field(default_factory=RewardBounds)
    episode: EpisodeRandomisation = field(default_factory=EpisodeRandomisation)
    nature_acts: Literal["reset", "step"] = "reset"
    nature_rate: float | None = None
    perturbation: Mapping[str, float | Sequence[float]] | None = None
    edge_share: float = 0.0

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise UncertaintyError(f"uncertainty mode must be one of {MODES}, got {self.mode!r}")
        if self.resample not in ("episode", "step", "every_k"):
            raise UncertaintyError(f"resample must be episode, step or every_k: {self.resample!r}")
        if self.every_k < 1:
            raise UncertaintyError(f"every_k must be at least 1, got {self.every_k}")
        if self.nature_acts not in ("reset", "step"):
            raise UncertaintyError(f"nature_acts must be reset or step: {self.nature_acts!r}")
        if self.nature_rate is not None and not 0.0 < self.nature_rate <= 1.0:
            raise UncertaintyError(f"nature_rate must be in (0, 1], got {self.nature_rate}")
        if not 0.0 <= self.edge_share <= 1.0:
            raise UncertaintyError(f"edge_share must be in [0, 1], got {self.edge_share}")
        if self.edge_share and self.mode != "sample":
            raise UncertaintyError(f"edge_share needs mode 'sample', not {self.mode!r}")
        if self.reward.noise < 0.0 or self.reward.noise_clip <= 0.0:
            raise UncertaintyError("reward noise must be >= 0 and noise_clip > 0")
        ep = self.episode
        if ep.start not in ("grid", "random", "round_robin"):
            raise UncertaintyError(
                f"episode start must be grid, random or round_robin: {ep.start!r}"
            )
        if ep.direction not in ("forward", "random", "alternate"):
            raise UncertaintyError(
                f"direction must be forward, random or alternate: {ep.direction!r}"
            )
        lo, hi = self.lows, self.highs
        for k, name in enumerate(PARAM_NAMES):
            if not (np.isfinite(lo[k]) and np.isfinite(hi[k]) and lo[k] <= hi[k]):
                raise UncertaintyError(f"{name} bounds must be finite with lo <= hi")
        _check_values(lo[None], "bounds")
        _check_values(hi[None], "bounds")
        if self.mode == "adversarial" and not self.free_names:
            raise UncertaintyError("adversarial mode needs at least one interval with lo < hi")
        if self.perturbation is not None:  # names and values checked early
            sizes = [np.size(v) for v in self.perturbation.values() if np.ndim(v) == 1]
            Perturbation.from_mapping(self.perturbation, max(sizes, default=1))

    # ---- the box ------------------------------------------------------------------------

    # Cached (the config is frozen; the env reads these every step) and read-only.
    @cached_property
    def lows(self) -> FloatArray:
        """(n_params,) lower bounds in :data:`PARAM_NAMES` order."""
        return _read_only(np.array([b[0] for b in self._intervals()], dtype=np.float64))

    @cached_property
    def highs(self) -> FloatArray:
        """(n_params,) upper bounds in :data:`PARAM_NAMES` order."""
        return _read_only(np.array([b[1] for b in self._intervals()], dtype=np.float64))

    @property
    def nominal(self) -> FloatArray:
        """(n_params,) the unperturbed values."""
        return nominal_values()

    @cached_property
    def free(self) -> NDArray[np.int64]:
        """Indices of the parameters with ``lo < hi`` (what nature chooses)."""
        return _read_only(np.flatnonzero(self.lows < self.highs))

    @property
    def free_names(self) -> tuple[str, ...]:
        """Names of the parameters with ``lo < hi``, in nature's action order."""
        return tuple(PARAM_NAMES[k] for k in self.free)

    def _intervals(self) -> list[Interval]:
        d, p, r = self.dynamics, self.perception, self.reward
        eps = r.noise * r.noise_clip
        return [
            *(getattr(d, name) for name in DYNAMICS),
            *(getattr(p, name) for name in PERCEPTION),
            (-eps, eps),
            *(getattr(r, name[2:]) for name in REWARD_WEIGHTS),
        ]

    def scaled(self, s: float) -> UncertaintyConfig:
        """The same config with every interval shrunk (``s < 1``) or grown about nominal.

        ``lo' = nom + s·(lo − nom)``, ``hi' = nom + s·(hi − nom)`` (latency rounded);
        ``s = 0`` is the nominal point, ``s = 1`` this config. Used by degradation curves.
        """
        if s < 0.0:
            raise UncertaintyError(f"scale must be >= 0, got {s}")
        nom = nominal_values()

        def shrink(group: Any, names: Sequence[str], prefix: str = "") -> Any:
            changes: dict[str, Interval] = {}
            for name in names:
                attr = name[len(prefix) :]
                lo, hi = getattr(group, attr)
                n = nom[INDEX[name]]
                new = (n + s * (lo - n), n + s * (hi - n))
                if name == "latency":
                    new = (round(new[0]), round(new[1]))
                changes[attr] = new
            return replace(group, **changes)

        return replace(
            self,
            dynamics=shrink(self.dynamics, DYNAMICS),
            perception=shrink(self.perception, PERCEPTION),
            reward=replace(
                shrink(self.reward, REWARD_WEIGHTS, prefix="w_"), noise=s * self.reward.noise
            ),
        )

    def to_dict(self) -> dict[str, Any]:
        """A JSON-able description (for run records and checkpoints' metadata)."""
        out: dict[str, Any] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if hasattr(value, "__dataclass_fields__"):
                value = {g.name: getattr(value, g.name) for g in fields(value)}
            elif isinstance(value, Mapping):
                value = dict(value)
            out[f.name] = value
        return out


def _read_only(arr: NDArray[Any]) -> NDArray[Any]:
    """``arr``, made unwritable (safe to cache and share)."""
    arr.flags.writeable = False
    return arr


def nominal_values() -> FloatArray:
    """(n_params,) nominal value of every parameter, :data:`PARAM_NAMES` order."""
    nom = np.zeros(len(PARAM_NAMES))
    for name in ("friction", "mass", "motor", "steer_gain", "contrast", *REWARD_WEIGHTS):
        nom[INDEX[name]] = 1.0
    return nom


_CONTEXT_NOMINAL = tuple(float(x) for x in nominal_values()[_CONTEXT_COLUMNS])


def _check_values(values: FloatArray, what: str) -> None:
    """Raise on values (n, n_params) the simulator cannot take."""
    for name in _POSITIVE:
        if np.any(values[:, INDEX[name]] <= 0.0):
            raise UncertaintyError(f"{name} in the {what} must be positive")
    lat = values[:, LATENCY]
    if np.any(lat < 0) or np.any(lat > MAX_LATENCY) or np.any(lat != np.round(lat)):
        raise UncertaintyError(f"latency in the {what} must be whole steps in 0..{MAX_LATENCY}")
    for name in _FRACTIONS:
        col = values[:, INDEX[name]]
        if np.any(col < 0.0) or np.any(col > 1.0):
            raise UncertaintyError(f"{name} in the {what} must be in [0, 1]")
    for name in ("action_noise", "lidar_noise", "image_noise", "shift"):
        if np.any(values[:, INDEX[name]] < 0.0):
            raise UncertaintyError(f"{name} in the {what} must be >= 0")


@dataclass
class Perturbation:
    """One value of every parameter for every car.

    Attributes:
        values: (n_cars, n_params) in :data:`PARAM_NAMES` order.
    """

    values: FloatArray

    @classmethod
    def nominal(cls, n_cars: int) -> Perturbation:
        """Every car unperturbed."""
        return cls(np.tile(nominal_values(), (n_cars, 1)))

    @classmethod
    def from_mapping(
        cls, mapping: Mapping[str, float | Sequence[float]], n_cars: int
    ) -> Perturbation:
        """From ``{name: value}`` (all cars) or ``{name: [one per car]}``; the rest nominal.

        Raises:
            UncertaintyError: an unknown name, a list of the wrong length, or a value the
                simulator cannot take (non-positive scale, fractional latency, …).
        """
        if not isinstance(mapping, Mapping):
            raise UncertaintyError("a perturbation is a mapping of parameter names to values")
        out = cls.nominal(n_cars)
        for name, value in mapping.items():
            if name not in INDEX:
                raise UncertaintyError(f"unknown perturbation parameter {name!r}")
            try:  # a reset option from a user: "fast" or {} must not escape as a numpy error
                arr = np.asarray(value, dtype=np.float64)
            except (TypeError, ValueError):
                raise UncertaintyError(f"{name} must be a finite number or one per car") from None
            if arr.ndim == 1 and arr.shape != (n_cars,):
                raise UncertaintyError(
                    f"{name} needs one value per car ({n_cars}), got {arr.shape}"
                )
            if arr.ndim > 1 or not np.all(np.isfinite(arr)):
                raise UncertaintyError(f"{name} must be a finite number or one per car")
            out.values[:, INDEX[name]] = arr
        _check_values(out.values, "perturbation")
        return out

    def column(self, name: str) -> FloatArray:
        """(n_cars,) values of one parameter."""
        return self.values[:, INDEX[name]]

    def car(self, i: int) -> dict[str, float]:
        """Car ``i``'s parameters by name (latency as an int)."""
        row = self.values[i].tolist()
        out = dict(zip(PARAM_NAMES, row, strict=True))
        out["latency"] = int(out["latency"])
        return out

    def scales(self) -> CarScales:
        """The simulator's per-car multipliers for these values."""
        v = self.values
        return CarScales(
            friction=v[:, INDEX["friction"]].copy(),
            mass=v[:, INDEX["mass"]].copy(),
            motor=v[:, INDEX["motor"]].copy(),
            steer_gain=v[:, INDEX["steer_gain"]].copy(),
            steer_offset=v[:, INDEX["steer_offset"]].copy(),
        )

    def weights(self) -> FloatArray:
        """(n_cars, 5) reward-term weights, in :data:`arena.rewards.RACING_TERMS` order."""
        return self.values[:, [INDEX[name] for name in REWARD_WEIGHTS]]


def _shape(shape: int | tuple[int, ...]) -> tuple[int, ...]:
    return (shape,) if isinstance(shape, int) else tuple(shape)


def sample_values(
    cfg: UncertaintyConfig, rng: np.random.Generator, shape: int | tuple[int, ...]
) -> FloatArray:
    """Uniform draws ``(*shape, n_params)`` inside the box, independent per car and parameter.

    ``shape`` is ``n_cars`` (one race) or ``(n_envs, n_cars)`` (a batch of races). Latency
    is uniform over the whole steps ``lo..hi``; the reward noise column is drawn from the
    truncated Gaussian (:func:`reward_noise`). With ``cfg.edge_share`` > 0 each other value
    is then, with that probability, replaced by its interval's low or high end (a coin
    each); with 0 the generator's stream is exactly the uniform sampler's.
    """
    shape = _shape(shape)
    lo, hi = cfg.lows, cfg.highs
    values = lo + rng.random((*shape, len(PARAM_NAMES))) * (hi - lo)
    values[..., LATENCY] = rng.integers(int(lo[LATENCY]), int(hi[LATENCY]) + 1, size=shape)
    if cfg.edge_share:
        at_end = rng.random(values.shape) < cfg.edge_share
        values = np.where(at_end, np.where(rng.random(values.shape) < 0.5, hi, lo), values)
    values[..., REWARD_NOISE] = reward_noise(cfg, rng, shape)  # drawn last: never an end
    return values


def reward_noise(
    cfg: UncertaintyConfig, rng: np.random.Generator, shape: int | tuple[int, ...]
) -> FloatArray:
    """``shape`` draws of ``N(0, λ)`` truncated to ``±clip·λ`` (by rejection; zeros if λ=0)."""
    shape = _shape(shape)
    lam = cfg.reward.noise
    if lam == 0.0:
        return np.zeros(shape)
    bound = cfg.reward.noise_clip * lam
    out = rng.normal(0.0, lam, shape)
    bad = np.abs(out) > bound
    while bad.any():
        out[bad] = rng.normal(0.0, lam, int(bad.sum()))
        bad = np.abs(out) > bound
    return out


def nature_values(
    cfg: UncertaintyConfig,
    action: FloatArray,
    current: FloatArray,
    rate: float | None = None,
) -> FloatArray:
    """Map nature actions onto the box.

    Args:
        cfg: the config (its free parameters are nature's action dimensions).
        action: (..., k) in [-1, 1] (clipped; NaN counts as 0, the midpoint), e.g. (k,),
            (n_cars, k) or (n_envs, n_cars, k).
        current: (..., n_params) the values now (kept for the fixed parameters, and the
            start of a rate-limited move).
        rate: the largest change per call, as a fraction of each interval (None: none).

    Returns:
        (..., n_params): ``lo + (x + 1) / 2 · (hi − lo)`` on the free parameters, moved at
        most ``rate · (hi − lo)`` from ``current``. Latency stays continuous here, so that a
        rate-limited move can accumulate; :func:`applied` rounds it.
    """
    free = cfg.free
    lo, hi = cfg.lows[free], cfg.highs[free]
    x = np.clip(np.nan_to_num(np.asarray(action, dtype=np.float64), nan=0.0), -1.0, 1.0)
    target = lo + 0.5 * (x + 1.0) * (hi - lo)
    out = np.array(current, dtype=np.float64, copy=True)
    if rate is not None:
        # The target clipped into reach (not now + clipped difference): a target within one
        # step, the box's edges included, is then reached exactly, not to within a rounding.
        step = rate * (hi - lo)
        now = out[..., free]
        target = np.clip(target, now - step, now + step)
    out[..., free] = np.clip(target, lo, hi)
    return out


def applied(values: FloatArray) -> FloatArray:
    """A copy of ``values`` (..., n_params) with latency rounded to whole control steps."""
    out = np.array(values, dtype=np.float64, copy=True)
    out[..., LATENCY] = np.round(out[..., LATENCY])
    return out


def perturbation_context(values: Any, ops: NumpyOps = NUMPY) -> Any:
    """The observation's perturbation block (..., n, 9), unclipped, of values
    (..., n, n_params) in :data:`PARAM_NAMES` order (numpy or ``ops``'s arrays):
    ``(values[..., CONTEXT_FEATURES] − nominal) /`` :data:`CONTEXT_SCALES`, 0 for the
    nominal car."""
    picked = values[..., _CONTEXT_COLUMNS]
    return (picked - ops.floats(_CONTEXT_NOMINAL)) / ops.floats(CONTEXT_SCALES)


def normalised(cfg: UncertaintyConfig, values: FloatArray) -> FloatArray:
    """(..., k) the free parameters mapped back to [-1, 1] (the inverse of nature's map)."""
    free = cfg.free
    lo, hi = cfg.lows[free], cfg.highs[free]
    return np.clip(2.0 * (values[..., free] - lo) / (hi - lo) - 1.0, -1.0, 1.0)


def perturbed_reward(
    values: FloatArray,
    terms: Mapping[str, FloatArray],
    reward_mode: str,
    nominal: FloatArray,
) -> FloatArray:
    """Rewards under the reward perturbation: interval weights on the terms plus the noise δ.

    One implementation for both backends (the env core calls it for one race or B races).

    Args:
        values: (..., n_params) the perturbation, e.g. (n_cars, P) or (n_envs, n_cars, P).
        terms: each :data:`arena.rewards.RACING_TERMS` term (...) of this step.
        reward_mode: ``"racing"`` (all five weights), ``"progress"`` (its weight only) or
            anything else (a DeepRacer reward function: the additive noise only).
        nominal: (...) the unperturbed reward (used as the base for a reward function).

    Returns:
        (...) the perturbed rewards (the caller zeroes cars that are out of the race); numpy
        or torch arrays alike (no conversion).
    """
    if reward_mode == "racing":
        base: Any = 0.0
        for name in REWARD_WEIGHTS:
            base = base + values[..., INDEX[name]] * terms[name[2:]]
    elif reward_mode == "progress":
        base = values[..., INDEX["w_progress"]] * terms["progress"]
    else:
        base = nominal
    return base + values[..., REWARD_NOISE]


class PerturbationState:
    """The perturbation of every car of ``shape`` races through their episodes (any mode).

    The one implementation of *when* values change, for one race (``shape=(1, n_cars)``) or
    a batch of races (``(n_envs, n_cars)``): drawn or given at each episode's start
    (:meth:`start`, for all races or those in a mask), then before every step
    (:meth:`advance`) re-drawn (``sample``: every step or every k steps, and the reward
    noise every step) or moved by nature's actions (``adversarial``: at the first step, or
    every step at most ``nature_rate`` of each interval).

    Attributes:
        raw: (B, N, n_params) the continuous values (nature's latency is continuous so a
            rate-limited move can accumulate).
        values: (B, N, n_params) what acts (:func:`applied`: latency whole steps).
    """

    def __init__(self, cfg: UncertaintyConfig, shape: tuple[int, int]) -> None:
        self.cfg = cfg
        self.shape = shape
        base = np.clip(nominal_values(), cfg.lows, cfg.highs)
        self.raw: FloatArray = np.broadcast_to(base, (*shape, len(PARAM_NAMES))).copy()
        self.values: FloatArray = applied(self.raw)

    def start(
        self,
        rng: np.random.Generator,
        envs: NDArray[np.bool_] | None = None,
        given: Mapping[str, float | Sequence[float]] | Perturbation | None = None,
    ) -> None:
        """New episodes for the races in ``envs`` (B,) (None: all).

        ``sample``: fresh draws; ``fixed``: ``given`` (else the config's ``perturbation``;
        names to one value or one per car; the rest nominal); ``nominal`` and
        ``adversarial``: nominal pulled into the box (nature moves it at the first step).

        Raises:
            UncertaintyError: ``given`` outside ``fixed`` mode, or a bad perturbation.
        """
        cfg, (b, n) = self.cfg, self.shape
        mask = np.ones(b, dtype=bool) if envs is None else np.asarray(envs, dtype=bool)
        if given is not None and cfg.mode != "fixed":
            raise UncertaintyError("reset option 'perturbation' needs uncertainty mode 'fixed'")
        k = int(mask.sum())
        if k == 0:
            return
        if cfg.mode == "sample":
            fresh = sample_values(cfg, rng, (k, n))
        elif cfg.mode == "fixed":
            given = given if given is not None else cfg.perturbation
            if isinstance(given, Perturbation):
                given = {name: given.values[:, j].tolist() for j, name in enumerate(PARAM_NAMES)}
            fresh = np.broadcast_to(
                Perturbation.from_mapping(given or {}, n).values, (k, n, len(PARAM_NAMES))
            )
        else:
            fresh = np.broadcast_to(
                np.clip(nominal_values(), cfg.lows, cfg.highs), (k, n, len(PARAM_NAMES))
            )
        self.raw[mask] = fresh
        self.values[mask] = applied(self.raw[mask])

    def advance(
        self,
        rng: np.random.Generator,
        steps: NDArray[np.int64] | int,
        nature: FloatArray | None = None,
        acting: NDArray[np.bool_] | None = None,
    ) -> bool:
        """Update the values before a control step.

        Args:
            rng: the env's generator.
            steps: (B,) or one int: control steps already taken in each race's episode.
            nature: (B, N, k) nature actions (``adversarial``; None: no nature acted).
            acting: (B, N) bool: the cars whose nature acted (default all).

        Returns:
            Whether any dynamics/perception value (not only the reward noise) changed, so
            the caller knows whether to hand the simulator new values.
        """
        cfg = self.cfg
        t = np.broadcast_to(np.asarray(steps, dtype=np.int64), self.shape[:1])
        if cfg.mode == "sample":
            if cfg.resample == "step":
                redraw = t > 0
            elif cfg.resample == "every_k":
                redraw = (t > 0) & (t % cfg.every_k == 0)
            else:
                redraw = np.zeros_like(t, dtype=bool)
            # The reward noise is noise: a new draw every step (drawn for all, so the
            # stream does not depend on which races redraw).
            noise = reward_noise(cfg, rng, self.shape)
            if redraw.any():
                self.raw[redraw] = sample_values(cfg, rng, (int(redraw.sum()), self.shape[1]))
            self.raw[~redraw, :, REWARD_NOISE] = noise[~redraw]
            self.values = applied(self.raw)
            return bool(redraw.any())
        if cfg.mode != "adversarial" or nature is None:
            return False
        first = t == 0
        moving = first | (cfg.nature_acts == "step")
        who = moving[:, None] & (True if acting is None else np.asarray(acting, dtype=bool))
        if not who.any():
            return False
        act = np.asarray(nature, dtype=np.float64)
        if act.shape != (*self.shape, len(cfg.free)):
            raise UncertaintyError(
                f"nature actions must have shape {(*self.shape, len(cfg.free))}, got {act.shape}"
            )
        free_move = nature_values(cfg, act, self.raw)
        limited = (
            free_move
            if cfg.nature_rate is None
            else nature_values(cfg, act, self.raw, cfg.nature_rate)
        )
        new = np.where(first[:, None, None], free_move, limited)  # the episode-start choice is free
        self.raw = np.where(who[..., None], new, self.raw)
        self.values = applied(self.raw)
        return True


# The default robust set (the reference's suggested ranges; DeepRacer's ≤10 % action noise):
# what ``slipstream train --uncertainty`` randomises over and ``slipstream robustness`` probes.
DEFAULT_DYNAMICS = DynamicsBounds(
    friction=(0.6, 1.2),
    mass=(0.8, 1.2),
    motor=(0.8, 1.2),
    steer_gain=(0.85, 1.15),
    steer_offset=(-0.05, 0.05),
    latency=(0, 2),
    action_noise=(0.0, 0.1),
)


def default_config(mode: str, **changes: Any) -> UncertaintyConfig:
    """:data:`DEFAULT_DYNAMICS` in ``mode``; adversarial natures act every step, moving at
    most 10 % of each interval per step (override with ``changes``)."""
    if mode == "adversarial":
        changes = {"nature_acts": "step", "nature_rate": 0.1, **changes}
    return UncertaintyConfig(mode=cast(Mode, mode), dynamics=DEFAULT_DYNAMICS, **changes)
