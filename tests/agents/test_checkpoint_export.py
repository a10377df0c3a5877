"""Exporting stable-baselines3 models and running them: what is detected, recorded, refused.

Companion to ``test_checkpoint.py``: these pin the exact architecture read from an SB3
policy, the exact metadata written (hyperparameters, car, steps, package versions), the exact
refusal of each model export cannot represent, and the details of :class:`TorchMLPPolicy`
(its name, dtypes, batches whose size is not the observation width).
"""

from __future__ import annotations

import dataclasses
import enum
import sys
import warnings
from decimal import Decimal
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from gymnasium import spaces

from agents import checkpoint as ckpt
from agents.checkpoint import CheckpointError, TorchMLPPolicy, export_sb3, read_checkpoint
from arena.cars import CAR_PRESETS
from arena.sim import CarParams
from tests.agents.models import (
    BOX_ACTIONS,
    DISCRETE_ACTIONS,
    SpacesOnlyEnv,
    fixed_observations,
    make_ppo,
    vector_space,
)

SUPPORTED = "ELU, GELU, LeakyReLU, ReLU, SiLU, Sigmoid, Tanh"  # torch class names, as passed


def _export(model: Any, tmp_path: Path, **kwargs: Any) -> ckpt.CheckpointMeta:
    """Export ``model`` (env_config ``{}`` unless given) and read back its metadata."""
    kwargs.setdefault("env_config", {})
    path = export_sb3(model, tmp_path / "p.zip", name="p", **kwargs)
    return read_checkpoint(path)[0]


def _refusal(model: Any, tmp_path: Path, **kwargs: Any) -> str:
    """The message of the CheckpointError exporting ``model`` raises (nothing is written)."""
    kwargs.setdefault("env_config", {})
    with pytest.raises(CheckpointError) as err:
        export_sb3(model, tmp_path / "x.zip", name="x", **kwargs)
    assert not (tmp_path / "x.zip").exists()
    return str(err.value)


def _small(**kwargs: Any) -> Any:
    """A PPO whose actor is [8, 8] (and critic [4]) with ``kwargs`` over that."""
    policy_kwargs = {"net_arch": {"pi": [8, 8], "vf": [4]}, **kwargs.pop("policy_kwargs", {})}
    return make_ppo(kwargs.pop("action_space", BOX_ACTIONS), policy_kwargs=policy_kwargs, **kwargs)


# ---- architecture detection -------------------------------------------------------------------


def test_architecture_is_read_from_the_policy(tmp_path: Path) -> None:
    """Widths, activation and the output rule come from the SB3 policy, for each action kind.

    Discrete and squashed policies are not clipped (SB3's predict clips only an unsquashed
    Gaussian), and squash_output is recorded only for a Gaussian.
    """
    meta = _export(_small(action_space=DISCRETE_ACTIONS), tmp_path)
    assert dataclasses.asdict(meta.policy) == {
        "net_arch": [8, 8],
        "activation": "tanh",
        "output": "categorical_argmax",
        "squash_output": False,
        "clip_actions": False,
        "value_net_arch": None,
        "kind": "mlp",
    }
    squashed = _small(
        use_sde=True,
        policy_kwargs={"squash_output": True, "activation_fn": torch.nn.ReLU},
    )
    meta = _export(squashed, tmp_path, include_value=True)
    assert dataclasses.asdict(meta.policy) == {
        "net_arch": [8, 8],
        "activation": "relu",
        "output": "gaussian_mean",
        "squash_output": True,
        "clip_actions": False,
        "value_net_arch": [4],
        "kind": "mlp",
    }
    assert meta.hyperparameters["policy_kwargs"] == {
        "net_arch": {"pi": [8, 8], "vf": [4]},
        "squash_output": True,
        "activation_fn": "ReLU",  # a class is recorded by its name
    }


def test_policies_export_cannot_represent_are_refused_by_name(tmp_path: Path) -> None:
    """Each unsupported SB3 model gets its own whole message, naming what it is."""
    from stable_baselines3 import DQN

    dqn = DQN("MlpPolicy", SpacesOnlyEnv(DISCRETE_ACTIONS), buffer_size=16, device="cpu")
    assert _refusal(dqn, tmp_path) == (
        "export supports SB3 ActorCriticPolicy (PPO/A2C MlpPolicy), not DQNPolicy"
    )
    multi = make_ppo(spaces.MultiDiscrete([3, 3]))
    assert _refusal(multi, tmp_path) == (
        "unsupported action distribution MultiCategoricalDistribution"
    )
    softplus = _small(policy_kwargs={"activation_fn": torch.nn.Softplus})
    assert _refusal(softplus, tmp_path) == (
        f"unsupported activation Softplus; supported: {SUPPORTED}"
    )


class Tanh(torch.nn.Tanh):
    """A user's activation that only borrows the name of a supported one."""

    def forward(self, input: torch.Tensor) -> torch.Tensor:
        return 2.0 * torch.tanh(input)


def test_an_activation_borrowing_a_supported_name_is_refused(tmp_path: Path) -> None:
    """Only torch's own classes are supported: a ``Tanh`` from elsewhere would run as tanh."""
    model = _small(policy_kwargs={"activation_fn": Tanh})
    assert _refusal(model, tmp_path) == f"unsupported activation Tanh; supported: {SUPPORTED}"


def test_dict_observation_policy_is_refused_with_the_whole_message(tmp_path: Path) -> None:
    from stable_baselines3 import PPO

    obs = spaces.Dict({"a": spaces.Box(-1, 1, (3,), dtype=np.float32)})
    env = SpacesOnlyEnv(BOX_ACTIONS, obs)  # type: ignore[arg-type]
    model = PPO("MultiInputPolicy", env, n_steps=64, batch_size=32, device="cpu")
    assert _refusal(model, tmp_path) == (
        "export supports MlpPolicy (FlattenExtractor) only; CNN and Dict policies are not "
        "supported yet"
    )


class ScaledLinear(torch.nn.Linear):
    """A Linear whose forward differs: export would silently drop the scaling."""

    def forward(self, input: torch.Tensor) -> torch.Tensor:
        return 3.0 * super().forward(input)


def _edited(net: str, build: Any) -> Any:
    """A small PPO whose ``mlp_extractor.<net>`` was replaced by ``build(n_in)``."""
    model = _small()
    setattr(model.policy.mlp_extractor, net, build(vector_space().shape[0]))
    return model


EDITED_NETS = {
    # A user's hand-edited extractor, as SB3's docs on custom policies invite: each case is
    # a Sequential that the plain Linear/activation layout cannot reproduce.
    "trailing linear": lambda n: torch.nn.Sequential(
        torch.nn.Linear(n, 8), torch.nn.Tanh(), torch.nn.Linear(8, 8)
    ),
    "linear subclass": lambda n: torch.nn.Sequential(ScaledLinear(n, 8), torch.nn.Tanh()),
    "other activation": lambda n: torch.nn.Sequential(torch.nn.Linear(n, 8), torch.nn.ReLU()),
    "dropout": lambda n: torch.nn.Sequential(torch.nn.Linear(n, 8), torch.nn.Dropout()),
}


@pytest.mark.parametrize("case", sorted(EDITED_NETS))
def test_an_edited_actor_is_refused(case: str, tmp_path: Path) -> None:
    model = _edited("policy_net", EDITED_NETS[case])
    assert _refusal(model, tmp_path) == "policy_net is not a plain Linear/activation MLP"


def test_an_edited_critic_is_refused_only_when_it_is_exported(tmp_path: Path) -> None:
    model = _edited("value_net", EDITED_NETS["trailing linear"])
    message = _refusal(model, tmp_path, include_value=True)
    assert message == "value_net is not a plain Linear/activation MLP"
    assert _export(model, tmp_path).policy.value_net_arch is None  # the actor alone is fine


def test_activation_with_non_default_arguments_is_refused_naming_the_first(
    tmp_path: Path,
) -> None:
    """meta.json records an activation by name only, so its arguments must be the defaults."""
    model = _small(policy_kwargs={"activation_fn": torch.nn.LeakyReLU})
    net = model.policy.mlp_extractor.policy_net
    net[1].negative_slope, net[3].negative_slope = 0.2, 0.3
    assert _refusal(model, tmp_path) == (
        "policy_net uses LeakyReLU(negative_slope=0.2); only default arguments are supported"
    )


# ---- what is recorded -------------------------------------------------------------------------


def test_hyperparameters_record_schedules_at_their_start(tmp_path: Path) -> None:
    """SB3 schedules (progress_remaining 1 → 0) are recorded at progress 1, the start.

    The linear schedule is the recipe of SB3's docs ("Learning Rate Schedule" example).
    """

    def linear_schedule(progress_remaining: float) -> float:
        return 1e-3 * progress_remaining

    model = _small(learning_rate=linear_schedule, clip_range=0.25)
    hyper = _export(model, tmp_path).hyperparameters
    assert hyper["learning_rate"] == 1e-3
    assert hyper["clip_range"] == 0.25  # PPO wraps it in a schedule object
    assert hyper["n_steps"] == 64 and hyper["batch_size"] == 32 and hyper["seed"] == 0
    assert hyper["policy_kwargs"] == {"net_arch": {"pi": [8, 8], "vf": [4]}}
    assert "policy_kwargs" not in _export(make_ppo(), tmp_path).hyperparameters  # none given


def test_a2c_exports_with_the_hyperparameters_it_has(tmp_path: Path) -> None:
    """A2C (no epochs, batches or clipping) exports; what it lacks is recorded as null."""
    from stable_baselines3 import A2C

    model = A2C("MlpPolicy", SpacesOnlyEnv(BOX_ACTIONS), seed=0, device="cpu")
    path = export_sb3(model, tmp_path / "a2c.zip", name="a2c", env_config={})
    meta, tensors = read_checkpoint(path)
    assert meta.algorithm == "A2C"
    hyper = meta.hyperparameters
    assert (hyper["learning_rate"], hyper["n_steps"]) == (7e-4, 5)
    assert hyper["n_epochs"] is None and hyper["clip_range"] is None
    # A2C's own policy_kwargs (its RMSprop optimizer), classes by name.
    assert hyper["policy_kwargs"] == {
        "optimizer_class": "RMSprop",
        "optimizer_kwargs": {"alpha": 0.99, "eps": 1e-05, "weight_decay": 0},
    }
    policy = TorchMLPPolicy(meta, tensors)
    obs = fixed_observations(model.observation_space, n=10)
    np.testing.assert_array_equal(policy.act_batch(obs), model.predict(obs, deterministic=True)[0])


class PolicyOnly:
    """A policy loaded without its algorithm (SB3 docs: ``MlpPolicy.load("policy")``)."""

    def __init__(self, model: Any) -> None:
        self.policy = model.policy
        self.observation_space = model.observation_space
        self.action_space = model.action_space


def test_training_steps_come_from_the_model(tmp_path: Path) -> None:
    model = _small()
    model.num_timesteps = 4096
    assert _export(model, tmp_path).training == {"steps": 4096}
    meta = _export(model, tmp_path, training={"steps": 5, "tracks": ["oval"]})
    assert meta.training == {"steps": 5, "tracks": ["oval"]}  # the caller's facts win
    bare = _export(PolicyOnly(model), tmp_path)
    assert bare.training == {"steps": 0}
    assert bare.algorithm == "PolicyOnly"
    assert set(bare.hyperparameters) == set(ckpt._SB3_HYPERPARAMETERS)
    assert all(v is None for v in bare.hyperparameters.values())


@pytest.mark.parametrize(
    ("car", "recorded"),
    [
        ("deepracer", "deepracer"),
        (" F1TENTH ", "f1tenth"),  # a preset name as the CLI accepts it, normalised
        (CAR_PRESETS["deepracer"], "deepracer"),  # preset parameters are named
        (
            dataclasses.replace(CAR_PRESETS["f1tenth"], mass=4.0),
            dataclasses.asdict(dataclasses.replace(CAR_PRESETS["f1tenth"], mass=4.0)),
        ),
    ],
)
def test_the_car_is_recorded_by_preset_name_or_parameters(
    car: str | CarParams, recorded: Any, tmp_path: Path
) -> None:
    meta = _export(_small(), tmp_path, env_config={"car": car, "track": "oval"})
    assert meta.env_config == {"car": recorded, "track": "oval"}
    assert meta.car == recorded


@pytest.mark.parametrize(
    ("car", "message"),
    [
        ("beetle", "env_config: unknown car 'beetle'; choose one of: f1tenth, deepracer"),
        (3, "env_config: car must be a preset name or CarParams, got int"),
    ],
)
def test_an_unknown_car_is_refused(car: Any, message: str, tmp_path: Path) -> None:
    assert _refusal(_small(), tmp_path, env_config={"car": car}) == message


def test_obs_mode_is_recorded_from_env_config(tmp_path: Path) -> None:
    assert _export(_small(), tmp_path).obs_mode == "vector"
    assert _export(_small(), tmp_path, env_config={"obs_mode": "dict"}).obs_mode == "dict"


def test_non_float_observations_are_refused(tmp_path: Path) -> None:
    """Discrete or integer observations are not the vector observations checkpoints hold."""
    message = "export supports float Box (vector) observations only"
    for obs_space in (spaces.Discrete(5), spaces.Box(0, 9, (4,), dtype=np.int64)):
        assert _refusal(make_ppo(obs_space=obs_space), tmp_path) == message  # type: ignore[arg-type]


def test_float64_observations_and_actions_export_and_act_identically(tmp_path: Path) -> None:
    """A float64 env (numpy's default dtype) is exported as such; actions stay float32."""
    obs_space = spaces.Box(-2.0, 2.0, (6,), dtype=np.float64)
    action_space = spaces.Box(-1.0, 1.0, (2,), dtype=np.float64)
    model = make_ppo(action_space, obs_space)
    meta, tensors = read_checkpoint(
        export_sb3(model, tmp_path / "f64.zip", name="f64", env_config={})
    )
    assert meta.observation_space["dtype"] == meta.action_space["dtype"] == "float64"
    policy = TorchMLPPolicy(meta, tensors)
    obs = fixed_observations(obs_space, n=30).astype(np.float64)
    want, _ = model.predict(obs, deterministic=True)
    got = policy.act_batch(obs)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, want.astype(np.float32))
    one = policy.act(obs[0])
    assert isinstance(one, np.ndarray) and one.dtype == np.float32
    np.testing.assert_array_equal(one, got[0])


class Surface(enum.Enum):
    ASPHALT = "asphalt"


@dataclasses.dataclass
class Schedule:
    start: float
    end: float


class LongRepr:
    def __init__(self, n: int) -> None:
        self.n = n

    def __repr__(self) -> str:
        return "L" * self.n


def test_values_without_a_json_form_are_recorded_readably(tmp_path: Path) -> None:
    """numpy scalars, enums, dataclasses, classes, infinities and other objects in env_config
    or hyperparameters become plain JSON; an object's repr is kept up to 200 characters."""
    config = {
        "np": np.float32(0.5),
        "int": np.int64(3),
        "inf": float("inf"),
        "surface": Surface.ASPHALT,
        "path": Path("tracks/oval.json"),
        "schedule": Schedule(1.0, 0.5),
        "cls": torch.nn.ReLU,
        "tuple": (1, 2),
        "decimal": Decimal("0.1"),
        "repr200": LongRepr(200),
        "repr201": LongRepr(201),
    }
    meta = _export(_small(), tmp_path, env_config=config, hyperparameters={"ent": float("-inf")})
    assert meta.env_config == {
        "np": 0.5,
        "int": 3,
        "inf": "inf",
        "surface": "asphalt",
        "path": "tracks/oval.json",
        "schedule": {"start": 1.0, "end": 0.5},
        "cls": "ReLU",
        "tuple": [1, 2],
        "decimal": "Decimal('0.1')",
        "repr200": "L" * 200,
        "repr201": "L" * 199 + "…",
    }
    assert meta.hyperparameters["ent"] == "-inf"


def test_package_versions_name_each_installed_package(monkeypatch: pytest.MonkeyPatch) -> None:
    """Versions of everything installed are recorded, even when one package is missing."""
    versions = ckpt.package_versions()
    for dist in ("slipstream", "numpy", "torch", "stable-baselines3", "safetensors", "gymnasium"):
        assert versions[dist] == metadata.version(dist)
    real = metadata.version

    def without_torch(dist: str) -> str:
        if dist == "torch":
            raise metadata.PackageNotFoundError(dist)
        return real(dist)

    monkeypatch.setattr(metadata, "version", without_torch)
    versions = ckpt.package_versions()
    assert "torch" not in versions
    assert {"stable-baselines3", "safetensors", "gymnasium"} <= set(versions)


# ---- running a checkpoint -------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_checkpoint(tmp_path_factory: pytest.TempPathFactory) -> tuple[Any, Path]:
    model = _small()
    path = tmp_path_factory.mktemp("small") / "small.zip"
    return model, export_sb3(model, path, name="small", env_config={"track": "oval"})


def test_policy_name_defaults_to_the_checkpoints(small_checkpoint: tuple[Any, Path]) -> None:
    _, path = small_checkpoint
    assert TorchMLPPolicy.from_file(path).name == "small"
    assert TorchMLPPolicy.from_file(path, name="renamed").name == "renamed"
    assert TorchMLPPolicy(*read_checkpoint(path), name="other").name == "other"


def test_a_batch_whose_size_is_not_the_observation_width(
    small_checkpoint: tuple[Any, Path],
) -> None:
    """Batches of any size act as SB3 does (7 rows of 100 floats, not 100 of 100)."""
    model, path = small_checkpoint
    policy = TorchMLPPolicy.from_file(path)
    obs = fixed_observations(model.observation_space, n=7)
    want, _ = model.predict(obs, deterministic=True)
    np.testing.assert_array_equal(policy.act_batch(obs), want)
    # Observations as float64 arrays or lists act exactly as float32 ones.
    np.testing.assert_array_equal(policy.act(obs[3].astype(np.float64)), want[3])
    np.testing.assert_array_equal(policy.act(obs[3].tolist()), want[3])
    n = policy.observation_shape[0]
    with pytest.raises(CheckpointError) as err:
        policy.act_batch(np.zeros((4, n + 1), dtype=np.float32))
    assert str(err.value) == (
        f"policy 'small' expects a batch (B, *obs_shape) of ({n},), got (4, {n + 1}) "
        "(obs_mode 'vector', env_config {'track': 'oval'})"
    )


def test_discrete_batches_are_int64(tmp_path: Path) -> None:
    model = _small(action_space=DISCRETE_ACTIONS)
    policy = TorchMLPPolicy.from_file(
        export_sb3(model, tmp_path / "d.zip", name="d", env_config={})
    )
    obs = fixed_observations(model.observation_space, n=9)
    got = policy.act_batch(obs)
    assert got.dtype == np.int64 and got.shape == (9,)
    np.testing.assert_array_equal(got, model.predict(obs, deterministic=True)[0])


def test_current_checkpoints_load_without_warning(small_checkpoint: tuple[Any, Path]) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        TorchMLPPolicy.from_file(small_checkpoint[1])


def test_old_env_version_warning_points_at_the_caller(
    small_checkpoint: tuple[Any, Path], tmp_path: Path
) -> None:
    """The warning is attributed to the line that loaded the checkpoint, not to our module."""
    meta, tensors = read_checkpoint(small_checkpoint[1])
    old = ckpt.save_checkpoint(
        tensors, dataclasses.replace(meta, env_version="0.0-old"), tmp_path / "old.zip"
    )
    with pytest.warns(UserWarning, match="env version 0.0-old") as record:
        TorchMLPPolicy.from_file(old)
    # Under mutmut the call goes through its trampoline, one frame between us and the module.
    assert [Path(w.filename).name for w in record] in (
        [Path(__file__).name],
        ["trampoline.py"],
    )


def test_missing_torch_is_named_with_the_extra(
    small_checkpoint: tuple[Any, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    meta, tensors = read_checkpoint(small_checkpoint[1])
    monkeypatch.setitem(sys.modules, "torch", None)  # what `import torch` sees uninstalled
    with pytest.raises(CheckpointError) as err:
        TorchMLPPolicy(meta, tensors)
    assert str(err.value) == "running a checkpoint needs torch: pip install 'slipstream[train]'"
