"""Slipstream's own policy checkpoint: a zip of ``meta.json`` + ``weights.safetensors``.

A stable-baselines3 ``.zip`` unpickles arbitrary code when loaded, and TorchScript is code
too, so neither is safe to open when it came from someone else. This format holds only data:

=======================  =================================================================
``meta.json``            UTF-8 JSON, strict (no NaN/Infinity), validated against
                         :data:`META_SCHEMA`: format and version, env version, obs/action
                         modes and spaces, algorithm, policy architecture, hyperparameters,
                         training info, package versions, name, creation time, and the
                         SHA-256 of ``weights.safetensors``
``weights.safetensors``  float32 tensors under stable-baselines3's names
                         (``mlp_extractor.policy_net.{0,2,…}.{weight,bias}``,
                         ``action_net.{weight,bias}``, optionally the value head), parsed by
                         ``safetensors`` — never unpickled
=======================  =================================================================

Reading (:func:`read_checkpoint`) checks, in order: the file size; that it is a zip; its
members (exactly those two; no absolute or ``..`` paths, duplicates, encryption, odd
compression, over-size members or zip-bomb compression ratios); ``meta.json`` (JSON, format,
version not newer than this reader, schema, spaces consistent with the modes); the weights'
SHA-256; that the weights are safetensors (a pickle is named and refused); and that the
tensor names, shapes and dtypes are exactly what the declared architecture needs, all finite.
Any failure raises :class:`CheckpointError` with a one-line message saying what is wrong.

:class:`TorchMLPPolicy` runs a checkpoint with plain torch (stable-baselines3 is not needed)
and reproduces ``model.predict(obs, deterministic=True)``: the Gaussian mean clipped to the
action bounds (or squashed by tanh and rescaled, for ``squash_output`` policies), or the
argmax of the categorical. :func:`export_sb3` writes one from a trained SB3 model.

torch, safetensors and stable-baselines3 (the ``train`` extra) are imported only inside the
functions that need them, so ``import agents`` stays light.

>>> from gymnasium import spaces
>>> space_to_json(spaces.Discrete(10))
{'type': 'Discrete', 'n': 10}
>>> space_from_json({"type": "Box", "shape": [2], "dtype": "float32", "low": [-1, -1],
...                  "high": [1, 1]})
Box(-1.0, 1.0, (2,), float32)
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import platform
import tempfile
import warnings
import zipfile
import zlib
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, is_dataclass, replace
from datetime import UTC, datetime
from enum import Enum
from importlib import metadata
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING, Any

import jsonschema
import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray

from agents.policy import PolicyError
from arena.version import ENV_VERSION, is_compatible

if TYPE_CHECKING:
    import torch

CHECKPOINT_FORMAT = "slipstream-policy"
CHECKPOINT_VERSION = 1
META_MEMBER = "meta.json"
WEIGHTS_MEMBER = "weights.safetensors"
MEMBERS = (META_MEMBER, WEIGHTS_MEMBER)
MAX_META_BYTES = 1 << 20  # 1 MiB: meta.json is a few kB
MAX_WEIGHTS_BYTES = 64 << 20  # 64 MiB: a [256, 256] MLP on a 95-float observation is 0.4 MB
MAX_FILE_BYTES = MAX_META_BYTES + MAX_WEIGHTS_BYTES + (64 << 10)  # + zip headers
MAX_MEMBERS = 16  # refuse before looking at names when the archive is plainly not ours
MAX_RATIO = 100.0  # uncompressed / compressed; float32 weights barely compress (~1.1)
RATIO_MIN_BYTES = 1 << 20  # only members larger than this are held to MAX_RATIO
MAX_SPACE_ELEMENTS = 1 << 16  # elements of an observation or action space
MAX_LAYERS = 16
MAX_WIDTH = 8192
ACTIVATIONS = {  # name in meta.json -> torch.nn class name (default arguments only)
    "tanh": "Tanh",
    "relu": "ReLU",
    "elu": "ELU",
    "leaky_relu": "LeakyReLU",
    "silu": "SiLU",
    "gelu": "GELU",
    "sigmoid": "Sigmoid",
}
OUTPUTS = ("gaussian_mean", "categorical_argmax")
TensorDict = dict[str, NDArray[np.float32]]


class CheckpointError(PolicyError):
    """A checkpoint is missing, corrupt, tampered with, unsafe, or of an unsupported kind."""


# ---- metadata -------------------------------------------------------------------------------


@dataclass
class PolicyArchitecture:
    """The network a checkpoint's tensors belong to (stable-baselines3 ``MlpPolicy`` shapes).

    Attributes:
        net_arch: hidden layer widths of the actor MLP, input side first (``[]``: linear).
        activation: activation after every hidden layer, a key of :data:`ACTIVATIONS`.
        output: ``"gaussian_mean"`` (Box actions: the deterministic action is the Gaussian
            mean) or ``"categorical_argmax"`` (Discrete actions: the most probable one).
        squash_output: Box only: tanh the mean, then rescale [-1, 1] to the action bounds.
        clip_actions: Box only: clip the action to the action bounds (SB3 ``predict``).
        value_net_arch: hidden widths of the value MLP when the value head is included.
        kind: network family; only ``"mlp"`` exists in format version 1.
    """

    net_arch: list[int]
    activation: str
    output: str
    squash_output: bool = False
    clip_actions: bool = True
    value_net_arch: list[int] | None = None
    kind: str = "mlp"


def _utc_now() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


def package_versions() -> dict[str, str]:
    """Versions of the packages that shape a checkpoint (those installed), plus Python."""
    out = {"python": platform.python_version()}
    for dist in ("slipstream", "numpy", "torch", "stable-baselines3", "safetensors", "gymnasium"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            continue
    return out


@dataclass
class CheckpointMeta:
    """Everything ``meta.json`` records; see the module docstring for the file layout.

    Attributes:
        name: display name of the policy (races and leaderboards show it).
        env_version: ``arena.ENV_VERSION`` the policy was trained on.
        obs_mode: the env's ``obs_mode`` (``"vector"`` for MLP policies).
        action_mode: ``"continuous"`` (Box actions) or ``"discrete"``.
        observation_space: JSON description (:func:`space_to_json`) of one agent's
            observation space, e.g. ``{"type": "Box", "shape": [95], "dtype": "float32",
            "low": [...], "high": [...]}``.
        action_space: the same for actions (``Box`` of shape (2,) or ``Discrete`` with ``n``).
        algorithm: training algorithm, e.g. ``"PPO"``.
        policy: the network architecture.
        hyperparameters: training hyperparameters (JSON values).
        training: training facts: ``steps``, ``wall_time_s``, ``tracks``, ``command``, ….
        env_config: the env keyword arguments used in training (JSON values); ``car`` is the
            car preset it drove (:mod:`arena.cars`; see :attr:`car`).
        packages: package versions at export (:func:`package_versions`).
        created: ISO 8601 UTC time of export.
        weights_sha256: hex SHA-256 of ``weights.safetensors`` (set by
            :func:`save_checkpoint`).
        format: always :data:`CHECKPOINT_FORMAT`.
        version: format version, :data:`CHECKPOINT_VERSION` when written by this code.
    """

    name: str
    env_version: str
    obs_mode: str
    action_mode: str
    observation_space: dict[str, Any]
    action_space: dict[str, Any]
    algorithm: str
    policy: PolicyArchitecture
    hyperparameters: dict[str, Any] = field(default_factory=dict)
    training: dict[str, Any] = field(default_factory=dict)
    env_config: dict[str, Any] = field(default_factory=dict)
    packages: dict[str, str] = field(default_factory=package_versions)
    created: str = field(default_factory=_utc_now)
    weights_sha256: str = "0" * 64
    format: str = CHECKPOINT_FORMAT
    version: int = CHECKPOINT_VERSION

    @property
    def observation_shape(self) -> tuple[int, ...]:
        """Shape of one observation, e.g. ``(95,)``."""
        return tuple(int(n) for n in self.observation_space["shape"])

    @property
    def n_outputs(self) -> int:
        """Width of the action head: action dimensions (Box) or number of actions."""
        if self.action_space["type"] == "Discrete":
            return int(self.action_space["n"])
        return int(math.prod(self.action_space["shape"]))

    @property
    def car(self) -> str | dict[str, Any]:
        """The car the policy was trained with: ``env_config["car"]``, a preset name of
        :mod:`arena.cars` or a custom car's parameters; ``"f1tenth"`` (the default car) when
        the checkpoint names none, as every one written before car presets existed."""
        from arena.cars import DEFAULT_CAR  # noqa: PLC0415 - the car module loads the simulator

        car = self.env_config.get("car", DEFAULT_CAR)
        return car if isinstance(car, str | dict) else str(car)

    @property
    def observes_perturbation(self) -> bool:
        """Trained on perturbation-aware observations (``env_config["observe_perturbation"]``,
        :attr:`arena.observations.ObservationLayout.context`): its races must observe so."""
        return self.env_config.get("observe_perturbation") is True

    def to_dict(self) -> dict[str, Any]:
        """The ``meta.json`` document (plain JSON values)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> CheckpointMeta:
        """Build from a ``meta.json`` document, validating it (:func:`validate_meta`).

        Raises:
            CheckpointError: the document is not a valid version-1 checkpoint description.
        """
        validate_meta(doc)
        fields = dict(doc)
        fields["policy"] = PolicyArchitecture(**fields["policy"])
        return cls(**fields)


# ---- spaces as JSON -------------------------------------------------------------------------


def _bound_to_json(x: float) -> float | str:
    if math.isinf(x):
        return "inf" if x > 0 else "-inf"
    return float(x)


def _bound_from_json(x: float | str) -> float:
    return float(x)  # "inf" / "-inf" parse to ±inf


def space_to_json(space: spaces.Space[Any]) -> dict[str, Any]:
    """JSON description of a Box or Discrete space (Box bounds flattened, ±inf as strings).

    Raises:
        CheckpointError: any other space (Dict, MultiDiscrete, …), or a Discrete with
            ``start != 0``.
    """
    if isinstance(space, spaces.Box):
        return {
            "type": "Box",
            "shape": [int(n) for n in space.shape],
            "dtype": str(space.dtype),
            "low": [_bound_to_json(float(v)) for v in space.low.reshape(-1)],
            "high": [_bound_to_json(float(v)) for v in space.high.reshape(-1)],
        }
    if isinstance(space, spaces.Discrete):
        if int(space.start) != 0:
            raise CheckpointError(f"Discrete spaces must start at 0, got start={space.start}")
        return {"type": "Discrete", "n": int(space.n)}
    raise CheckpointError(
        f"checkpoints support Box and Discrete spaces, not {type(space).__name__}"
    )


def space_from_json(doc: Mapping[str, Any]) -> spaces.Box | spaces.Discrete:
    """The gymnasium space a (validated) :func:`space_to_json` document describes."""
    if doc["type"] == "Discrete":
        return spaces.Discrete(int(doc["n"]))
    shape = tuple(int(n) for n in doc["shape"])
    dtype = np.dtype(doc["dtype"])
    low = np.array([_bound_from_json(v) for v in doc["low"]], dtype=dtype).reshape(shape)
    high = np.array([_bound_from_json(v) for v in doc["high"]], dtype=dtype).reshape(shape)
    return spaces.Box(low, high, shape, dtype=dtype)


# ---- meta.json schema -----------------------------------------------------------------------

_BOUND = {"anyOf": [{"type": "number"}, {"enum": ["inf", "-inf"]}]}
_BOUNDS = {"type": "array", "items": _BOUND, "maxItems": MAX_SPACE_ELEMENTS}
_BOX = {
    "properties": {
        "type": {"const": "Box"},
        "shape": {
            "type": "array",
            "items": {"type": "integer", "minimum": 1, "maximum": MAX_SPACE_ELEMENTS},
            "minItems": 1,
            "maxItems": 4,
        },
        "dtype": {"enum": ["float32", "float64"]},
        "low": _BOUNDS,
        "high": _BOUNDS,
    },
    "required": ["type", "shape", "dtype", "low", "high"],
    "additionalProperties": False,
}
_DISCRETE = {
    "properties": {
        "type": {"const": "Discrete"},
        "n": {"type": "integer", "minimum": 1, "maximum": MAX_SPACE_ELEMENTS},
    },
    "required": ["type", "n"],
    "additionalProperties": False,
}
_SPACE = {
    "type": "object",
    "required": ["type"],
    "properties": {"type": {"enum": ["Box", "Discrete"]}},
    "allOf": [
        {"if": {"properties": {"type": {"const": "Box"}}}, "then": _BOX},
        {"if": {"properties": {"type": {"const": "Discrete"}}}, "then": _DISCRETE},
    ],
}
_LAYERS = {
    "type": "array",
    "items": {"type": "integer", "minimum": 1, "maximum": MAX_WIDTH},
    "maxItems": MAX_LAYERS,
}
_SHORT = {"type": "string", "minLength": 1, "maxLength": 200}
META_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "Slipstream policy checkpoint meta.json, format version 1",
    "type": "object",
    "properties": {
        "format": {"const": CHECKPOINT_FORMAT},
        "version": {"type": "integer", "minimum": 1},
        "name": _SHORT,
        "created": {"type": "string", "maxLength": 64},
        "env_version": {"type": "string", "minLength": 1, "maxLength": 32},
        "obs_mode": {"enum": ["vector", "dict", "image"]},
        "action_mode": {"enum": ["continuous", "discrete"]},
        "observation_space": _SPACE,
        "action_space": _SPACE,
        "algorithm": _SHORT,
        "policy": {
            "type": "object",
            "properties": {
                "kind": {"const": "mlp"},
                "net_arch": _LAYERS,
                "activation": {"enum": sorted(ACTIVATIONS)},
                "output": {"enum": list(OUTPUTS)},
                "squash_output": {"type": "boolean"},
                "clip_actions": {"type": "boolean"},
                "value_net_arch": {"anyOf": [{"type": "null"}, _LAYERS]},
            },
            "required": [
                "kind",
                "net_arch",
                "activation",
                "output",
                "squash_output",
                "clip_actions",
                "value_net_arch",
            ],
            "additionalProperties": False,
        },
        "hyperparameters": {"type": "object"},
        "training": {"type": "object"},
        "env_config": {"type": "object"},
        "packages": {"type": "object", "additionalProperties": {"type": "string"}},
        "weights_sha256": {"type": "string", "pattern": "^[0-9a-f]{64}$"},
    },
    "additionalProperties": False,
}
META_SCHEMA["required"] = sorted(META_SCHEMA["properties"])
_VALIDATOR = jsonschema.Draft202012Validator(META_SCHEMA)


def _short(text: str, limit: int = 160) -> str:
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 1] + "…"


def validate_meta(doc: Any) -> None:
    """Check a ``meta.json`` document: format, version, schema, and space/mode consistency.

    Raises:
        CheckpointError: saying the first thing that is wrong.
    """
    if not isinstance(doc, dict):
        raise CheckpointError(f"meta.json must be a JSON object, got {type(doc).__name__}")
    fmt = doc.get("format")
    if fmt != CHECKPOINT_FORMAT:
        raise CheckpointError(
            f"not a Slipstream policy checkpoint: meta.json format is {fmt!r}, "
            f"expected {CHECKPOINT_FORMAT!r}"
        )
    version = doc.get("version")
    if (
        isinstance(version, int)
        and not isinstance(version, bool)
        and (version > CHECKPOINT_VERSION)
    ):
        raise CheckpointError(
            f"checkpoint format version {version} is newer than this Slipstream reads "
            f"(up to {CHECKPOINT_VERSION}); upgrade slipstream"
        )
    error = jsonschema.exceptions.best_match(_VALIDATOR.iter_errors(doc))
    if error is not None:
        where = "/".join(str(p) for p in error.absolute_path) or "top level"
        message, instance = error.message, repr(error.instance)
        if len(instance) > 40:  # "[5, 5, …] is too long": keep the reason, not the value
            message = message.replace(instance, instance[:36] + " …")
        raise CheckpointError(f"meta.json is invalid at {where}: {_short(message)}")
    _check_consistency(doc)


def _check_consistency(doc: Mapping[str, Any]) -> None:
    """Cross-field rules the schema cannot say."""
    for key in ("observation_space", "action_space"):
        space = doc[key]
        if space["type"] == "Box":
            size = math.prod(space["shape"])
            if size > MAX_SPACE_ELEMENTS:
                raise CheckpointError(f"meta.json {key} has {size} elements, over the cap")
            if len(space["low"]) != size or len(space["high"]) != size:
                raise CheckpointError(
                    f"meta.json {key}: low/high need {size} values for shape "
                    f"{tuple(space['shape'])}, got {len(space['low'])}/{len(space['high'])}"
                )
            low = np.array([_bound_from_json(v) for v in space["low"]])
            high = np.array([_bound_from_json(v) for v in space["high"]])
            if np.any(low > high):
                raise CheckpointError(f"meta.json {key}: a low bound exceeds its high bound")
    if doc["observation_space"]["type"] != "Box":
        raise CheckpointError("meta.json observation_space must be a Box for an MLP policy")
    action, pol = doc["action_space"], doc["policy"]
    if doc["action_mode"] == "discrete":
        if action["type"] != "Discrete" or pol["output"] != "categorical_argmax":
            raise CheckpointError(
                "meta.json: action_mode 'discrete' needs a Discrete action_space and output "
                f"'categorical_argmax', got {action['type']} and {pol['output']!r}"
            )
    elif action["type"] != "Box" or pol["output"] != "gaussian_mean":
        raise CheckpointError(
            "meta.json: action_mode 'continuous' needs a Box action_space and output "
            f"'gaussian_mean', got {action['type']} and {pol['output']!r}"
        )
    elif len(action["shape"]) != 1:
        raise CheckpointError("meta.json: a Box action_space must be one-dimensional")
    elif pol["squash_output"] and not all(
        math.isfinite(_bound_from_json(v)) for v in action["low"] + action["high"]
    ):
        raise CheckpointError("meta.json: squash_output needs finite action bounds")


# ---- tensors --------------------------------------------------------------------------------


def expected_tensors(meta: CheckpointMeta) -> dict[str, tuple[int, ...]]:
    """Name → shape of every tensor the declared architecture needs (SB3 names).

    ``nn.Linear`` weights are (out_features, in_features); hidden layer ``i`` of the actor
    is ``mlp_extractor.policy_net.{2i}`` (SB3 interleaves activations in the Sequential).
    """
    n_in = math.prod(meta.observation_shape)
    shapes: dict[str, tuple[int, ...]] = {}

    def mlp(prefix: str, widths: list[int], head: str, n_out: int) -> None:
        last = n_in
        for i, width in enumerate(widths):
            shapes[f"{prefix}.{2 * i}.weight"] = (width, last)
            shapes[f"{prefix}.{2 * i}.bias"] = (width,)
            last = width
        shapes[f"{head}.weight"] = (n_out, last)
        shapes[f"{head}.bias"] = (n_out,)

    mlp("mlp_extractor.policy_net", meta.policy.net_arch, "action_net", meta.n_outputs)
    if meta.policy.value_net_arch is not None:
        mlp("mlp_extractor.value_net", meta.policy.value_net_arch, "value_net", 1)
    return shapes


def check_tensors(meta: CheckpointMeta, tensors: Mapping[str, NDArray[Any]]) -> None:
    """Check that ``tensors`` are exactly the float32, finite tensors ``meta`` declares.

    Raises:
        CheckpointError: a tensor is missing, unexpected, mis-shaped, not float32 or not finite.
    """
    want = expected_tensors(meta)
    missing = sorted(set(want) - set(tensors))
    if missing:
        raise CheckpointError(f"weights lack tensor(s) {', '.join(missing)}")
    extra = sorted(set(tensors) - set(want))
    if extra:
        raise CheckpointError(
            f"weights hold unexpected tensor(s) {', '.join(extra)} for the declared architecture"
        )
    for name, shape in want.items():
        arr = tensors[name]
        if tuple(arr.shape) != shape:
            raise CheckpointError(
                f"tensor {name} has shape {tuple(arr.shape)}, the declared architecture "
                f"needs {shape}"
            )
        if arr.dtype != np.float32:
            raise CheckpointError(f"tensor {name} is {arr.dtype}, expected float32")
        if not np.all(np.isfinite(arr)):
            raise CheckpointError(f"tensor {name} holds NaN or infinite values")


def _as_numpy(value: Any) -> NDArray[Any]:
    if hasattr(value, "detach"):  # a torch tensor: copy to host memory
        value = value.detach().cpu().numpy()
    return np.ascontiguousarray(value)


def _import_safetensors_numpy() -> Any:
    try:
        import safetensors.numpy  # noqa: PLC0415 - optional `train` extra, imported on use
    except ImportError as err:
        raise CheckpointError(
            "reading or writing checkpoints needs safetensors: pip install 'slipstream[train]'"
        ) from err
    return safetensors.numpy


# ---- writing --------------------------------------------------------------------------------


def save_checkpoint(state_dict: Mapping[str, Any], meta: CheckpointMeta, path: str | Path) -> Path:
    """Write a checkpoint zip (atomically: a temporary file, then a rename).

    Args:
        state_dict: tensor name → float32 array or torch tensor, exactly the tensors
            :func:`expected_tensors` lists for ``meta`` (other entries are an error).
        meta: the description; its ``weights_sha256`` is filled in here.
        path: destination file (parent directories are created).

    Returns:
        ``path`` as a :class:`Path`.

    Raises:
        CheckpointError: ``meta`` is invalid, or the tensors do not match it.
    """
    path = Path(path)
    tensors = {name: _as_numpy(value) for name, value in state_dict.items()}
    validate_meta(_json_roundtrip(meta.to_dict()))
    check_tensors(meta, tensors)
    weights = _import_safetensors_numpy().save(tensors)
    if len(weights) > MAX_WEIGHTS_BYTES:
        raise CheckpointError(
            f"weights are {len(weights)} bytes, over the {MAX_WEIGHTS_BYTES}-byte cap"
        )
    meta = replace(meta, weights_sha256=hashlib.sha256(weights).hexdigest())
    meta_bytes = (_dump_json(meta.to_dict()) + "\n").encode()
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh, zipfile.ZipFile(fh, "w") as zf:
            # Fixed timestamps: the same policy exported twice differs only in ``created``.
            meta_info = zipfile.ZipInfo(META_MEMBER, date_time=(1980, 1, 1, 0, 0, 0))
            zf.writestr(meta_info, meta_bytes, compress_type=zipfile.ZIP_DEFLATED)
            weights_info = zipfile.ZipInfo(WEIGHTS_MEMBER, date_time=(1980, 1, 1, 0, 0, 0))
            zf.writestr(weights_info, weights, compress_type=zipfile.ZIP_STORED)
        os.chmod(tmp, 0o644)  # mkstemp makes it owner-only; evaluation workers may be other users
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def _dump_json(value: Any, indent: str = "") -> str:
    """Strict JSON, objects indented, lists of numbers kept on one line (space bounds)."""
    inner = indent + "  "
    if isinstance(value, dict) and value:
        items = [f"{inner}{json.dumps(k)}: {_dump_json(v, inner)}" for k, v in value.items()]
        return "{\n" + ",\n".join(items) + "\n" + indent + "}"
    if isinstance(value, list) and any(isinstance(v, dict | list) for v in value):
        items = [inner + _dump_json(v, inner) for v in value]
        return "[\n" + ",\n".join(items) + "\n" + indent + "]"
    return json.dumps(value, allow_nan=False)


def _json_roundtrip(doc: dict[str, Any]) -> Any:
    """``doc`` as it will read back from ``meta.json`` (tuples become lists, etc.)."""
    try:
        return json.loads(json.dumps(doc, allow_nan=False))
    except (TypeError, ValueError) as err:
        raise CheckpointError(f"checkpoint metadata is not plain JSON: {err}") from err


# ---- reading --------------------------------------------------------------------------------


def _unsafe_member_name(name: str) -> bool:
    """Absolute, drive-letter, backslash, ``..`` or directory names: not a plain file name."""
    if not name or name.startswith("/") or "\\" in name or ":" in name or name.endswith("/"):
        return True
    return any(part in ("..", ".", "") for part in PurePosixPath(name).parts) or "//" in name


def _check_members(zf: zipfile.ZipFile, label: str) -> dict[str, zipfile.ZipInfo]:
    infos = zf.infolist()
    if len(infos) > MAX_MEMBERS:
        raise CheckpointError(f"{label}: zip has {len(infos)} members; a checkpoint has 2")
    for info in infos:
        if _unsafe_member_name(info.filename):
            raise CheckpointError(
                f"{label}: member {info.filename!r} has an unsafe path (absolute, '..' or a "
                "directory); refusing the archive"
            )
    names = [info.filename for info in infos]
    dups = sorted({n for n in names if names.count(n) > 1})
    if dups:
        raise CheckpointError(f"{label}: duplicate member(s) {', '.join(dups)}")
    extra = sorted(set(names) - set(MEMBERS))
    if extra:
        raise CheckpointError(
            f"{label}: unexpected member(s) {', '.join(extra)}; a checkpoint holds only "
            f"{META_MEMBER} and {WEIGHTS_MEMBER}"
        )
    missing = [n for n in MEMBERS if n not in names]
    if missing:
        raise CheckpointError(f"{label}: missing {', '.join(missing)}")
    caps = {META_MEMBER: MAX_META_BYTES, WEIGHTS_MEMBER: MAX_WEIGHTS_BYTES}
    by_name = {info.filename: info for info in infos}
    for name, info in by_name.items():
        if info.flag_bits & 0x1:
            raise CheckpointError(f"{label}: member {name} is encrypted")
        if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
            raise CheckpointError(
                f"{label}: member {name} uses compression method {info.compress_type}; "
                "only stored or deflated members are read"
            )
        if info.file_size > caps[name]:
            raise CheckpointError(
                f"{label}: member {name} is {info.file_size} bytes uncompressed, over the "
                f"{caps[name]}-byte cap"
            )
        ratio = info.file_size / max(info.compress_size, 1)
        if info.file_size > RATIO_MIN_BYTES and ratio > MAX_RATIO:
            raise CheckpointError(
                f"{label}: member {name} compresses {ratio:.0f}:1 (a zip bomb?); refusing"
            )
    return by_name


def _read_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, cap: int, label: str) -> bytes:
    """The member's bytes, reading at most ``cap + 1`` whatever its header claims."""
    try:
        with zf.open(info) as fh:
            data = fh.read(cap + 1)
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError) as err:
        raise CheckpointError(
            f"{label}: member {info.filename} is corrupt: {_short(str(err))}"
        ) from err
    if len(data) > cap:
        raise CheckpointError(f"{label}: member {info.filename} exceeds the {cap}-byte cap")
    return data


def _reject_constant(name: str) -> Any:
    raise ValueError(f"{name} is not valid JSON")


def _parse_meta(raw: bytes, label: str) -> CheckpointMeta:
    try:
        doc = json.loads(raw.decode("utf-8"), parse_constant=_reject_constant)
    except (UnicodeDecodeError, ValueError, RecursionError) as err:
        raise CheckpointError(f"{label}: meta.json is not valid JSON: {_short(str(err))}") from err
    try:
        return CheckpointMeta.from_dict(doc)
    except CheckpointError as err:
        raise CheckpointError(f"{label}: {err}") from None
    except RecursionError as err:  # JSON nested just below the parser's limit
        raise CheckpointError(f"{label}: meta.json is nested too deeply") from err


def looks_like_pickle(head: bytes) -> bool:
    """Whether bytes start like a pickle (protocol 2 to 5), from their first two bytes."""
    return head[:1] == b"\x80" and head[1:2] in (b"\x02", b"\x03", b"\x04", b"\x05")


def _parse_weights(raw: bytes, meta: CheckpointMeta, label: str) -> TensorDict:
    digest = hashlib.sha256(raw).hexdigest()
    if digest != meta.weights_sha256:
        raise CheckpointError(
            f"{label}: weights checksum mismatch: meta.json records sha256 "
            f"{meta.weights_sha256[:16]}…, weights.safetensors hashes to {digest[:16]}… "
            "(modified or corrupted)"
        )
    # Name what a wrong file is before the parser fails on it; nothing here unpickles.
    if looks_like_pickle(raw):
        raise CheckpointError(
            f"{label}: weights.safetensors holds a pickle, not safetensors; pickles can run "
            "code and are never loaded"
        )
    if raw[:4] == b"PK\x03\x04":
        raise CheckpointError(
            f"{label}: weights.safetensors is a zip (torch.save?), not safetensors; refusing"
        )
    try:
        loaded = _import_safetensors_numpy().load(raw)
    except CheckpointError:
        raise
    except Exception as err:  # the Rust parser raises SafetensorError and friends
        raise CheckpointError(
            f"{label}: weights.safetensors is not a valid safetensors file: {_short(str(err))}"
        ) from err
    try:
        check_tensors(meta, loaded)
    except CheckpointError as err:
        raise CheckpointError(f"{label}: {err}") from None
    return {name: np.ascontiguousarray(arr, dtype=np.float32) for name, arr in loaded.items()}


def read_checkpoint(source: str | Path | bytes) -> tuple[CheckpointMeta, TensorDict]:
    """Open and fully validate a checkpoint (see the module docstring for what is checked).

    Safe on untrusted input: nothing is unpickled or executed, and memory use is bounded by
    :data:`MAX_FILE_BYTES` plus the member caps.

    Args:
        source: path to the zip, or its bytes (an upload).

    Returns:
        ``(meta, tensors)``: the metadata and name → float32 array (SB3 names and shapes).

    Raises:
        CheckpointError: one line saying what is wrong.
    """
    if isinstance(source, bytes):
        label, size, handle = "checkpoint", len(source), io.BytesIO(source)
    else:
        path = Path(source)
        label = str(path)
        if not path.exists():
            raise CheckpointError(f"{label}: no such file")
        if not path.is_file():
            raise CheckpointError(f"{label}: not a file")
        size = path.stat().st_size
        handle = None
    if size > MAX_FILE_BYTES:
        raise CheckpointError(f"{label}: {size} bytes, over the {MAX_FILE_BYTES}-byte cap")
    try:
        zf = zipfile.ZipFile(handle if handle is not None else path)
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError) as err:
        raise CheckpointError(
            f"{label}: not a valid zip archive (corrupt or truncated): {_short(str(err))}"
        ) from err
    with zf:
        infos = _check_members(zf, label)
        meta = _parse_meta(_read_member(zf, infos[META_MEMBER], MAX_META_BYTES, label), label)
        raw = _read_member(zf, infos[WEIGHTS_MEMBER], MAX_WEIGHTS_BYTES, label)
    return meta, _parse_weights(raw, meta, label)


# ---- export from stable-baselines3 ----------------------------------------------------------


def _jsonable(value: Any) -> Any:
    """``value`` as plain JSON; what has no JSON form is kept as its ``repr``."""
    if value is None or isinstance(value, bool | int | str):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else repr(value)
    if isinstance(value, np.generic):
        return _jsonable(value.item())
    if isinstance(value, Path | Enum):
        return str(value.value if isinstance(value, Enum) else value)
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple | set | frozenset):
        return [_jsonable(v) for v in value]
    if isinstance(value, type):
        return value.__name__
    if is_dataclass(value) and not isinstance(value, type):
        return _jsonable(asdict(value))
    return _short(repr(value), 200)


_SB3_HYPERPARAMETERS = (
    "learning_rate",
    "n_steps",
    "batch_size",
    "n_epochs",
    "gamma",
    "gae_lambda",
    "clip_range",
    "clip_range_vf",
    "normalize_advantage",
    "ent_coef",
    "vf_coef",
    "max_grad_norm",
    "use_sde",
    "sde_sample_freq",
    "target_kl",
    "seed",
    "n_envs",
)


def _sb3_hyperparameters(model: Any) -> dict[str, Any]:
    """The common PPO/A2C hyperparameters of an SB3 model (schedules as their start value)."""
    out: dict[str, Any] = {}
    for key in _SB3_HYPERPARAMETERS:
        value = getattr(model, key, None)
        if callable(value):  # SB3 schedules: progress_remaining (1 → 0) -> value
            value = value(1.0)
        out[key] = _jsonable(value)
    policy_kwargs = getattr(model, "policy_kwargs", None)
    if policy_kwargs:
        out["policy_kwargs"] = _jsonable(policy_kwargs)
    return out


def _mlp_widths(sequential: Any, activation: type, label: str) -> list[int]:
    """Hidden widths of an SB3 ``Sequential(Linear, act, Linear, act, …)``."""
    import torch  # noqa: PLC0415 - optional `train` extra, imported on use

    modules = list(sequential)
    widths: list[int] = []
    for i in range(0, len(modules), 2):
        linear, act = modules[i], modules[i + 1] if i + 1 < len(modules) else None
        if type(linear) is not torch.nn.Linear or act is None or type(act) is not activation:
            raise CheckpointError(f"{label} is not a plain Linear/activation MLP")
        if repr(act) != repr(activation()):
            raise CheckpointError(f"{label} uses {act!r}; only default arguments are supported")
        widths.append(int(linear.out_features))
    return widths


def _architecture(policy: Any, include_value: bool) -> PolicyArchitecture:
    """The :class:`PolicyArchitecture` of an SB3 ``ActorCriticPolicy`` (refusing others)."""
    from stable_baselines3.common import distributions as dist  # noqa: PLC0415 - optional extra
    from stable_baselines3.common.policies import ActorCriticPolicy  # noqa: PLC0415
    from stable_baselines3.common.torch_layers import FlattenExtractor  # noqa: PLC0415

    if not isinstance(policy, ActorCriticPolicy):
        raise CheckpointError(
            "export supports SB3 ActorCriticPolicy (PPO/A2C MlpPolicy), not "
            f"{type(policy).__name__}"
        )
    extractors = [policy.features_extractor, policy.pi_features_extractor]
    if not all(isinstance(e, FlattenExtractor) for e in extractors):
        raise CheckpointError(
            "export supports MlpPolicy (FlattenExtractor) only; CNN and Dict policies are not "
            "supported yet"
        )
    cls = policy.activation_fn
    names = {v: k for k, v in ACTIVATIONS.items()}
    if cls.__module__ != "torch.nn.modules.activation" or cls.__name__ not in names:
        raise CheckpointError(
            f"unsupported activation {cls.__name__}; supported: {', '.join(sorted(names))}"
        )
    action_dist = policy.action_dist
    if isinstance(action_dist, dist.CategoricalDistribution):
        output = "categorical_argmax"
    elif isinstance(
        action_dist, dist.DiagGaussianDistribution | dist.StateDependentNoiseDistribution
    ):
        output = "gaussian_mean"
    else:
        raise CheckpointError(f"unsupported action distribution {type(action_dist).__name__}")
    squash = bool(policy.squash_output) and output == "gaussian_mean"
    net = policy.mlp_extractor
    return PolicyArchitecture(
        net_arch=_mlp_widths(net.policy_net, cls, "policy_net"),
        activation=names[cls.__name__],
        output=output,
        squash_output=squash,
        clip_actions=output == "gaussian_mean" and not squash,
        value_net_arch=_mlp_widths(net.value_net, cls, "value_net") if include_value else None,
    )


def export_sb3(
    model: Any,
    path: str | Path,
    *,
    name: str,
    env_config: dict[str, Any],
    hyperparameters: dict[str, Any] | None = None,
    training: dict[str, Any] | None = None,
    include_value: bool = False,
) -> Path:
    """Export a stable-baselines3 PPO/A2C ``MlpPolicy`` model to a Slipstream checkpoint.

    Only the actor tensors (and the value head when ``include_value``) are written; the
    checkpoint then reproduces ``model.predict(obs, deterministic=True)``. Observation
    normalisation done outside the policy (``VecNormalize``) is not part of the model and is
    not exported.

    Args:
        model: a trained ``stable_baselines3`` PPO or A2C with a Box observation space.
        path: destination zip.
        name: the policy's display name.
        env_config: the env keyword arguments it was trained with (``obs_mode`` defaults to
            ``"vector"``; ``action_mode`` to the one the action space implies; ``car``, a
            preset name or :class:`arena.sim.CarParams`, is recorded as the preset's name, a
            custom car as its parameters).
        hyperparameters: recorded as given, over the model's own (learning rate, n_steps, …).
        training: facts about the run (``steps``, ``wall_time_s``, ``tracks``, ``command``);
            ``steps`` defaults to ``model.num_timesteps``.
        include_value: also store the value network (``value_net``, (1,) output).

    Returns:
        ``path`` as a :class:`Path`.

    Raises:
        CheckpointError: the model is not an MLP actor-critic, its spaces disagree with
            ``env_config``, or its ``car`` is neither a preset name nor a CarParams.
    """
    policy = model.policy
    arch = _architecture(policy, include_value)
    obs_space = space_to_json(model.observation_space)
    if obs_space["type"] != "Box" or obs_space["dtype"] not in ("float32", "float64"):
        raise CheckpointError("export supports float Box (vector) observations only")
    action_space = space_to_json(model.action_space)
    implied = "discrete" if action_space["type"] == "Discrete" else "continuous"
    config = _jsonable(dict(env_config))
    if "car" in env_config:
        from arena.cars import CarError, car_name, car_params  # noqa: PLC0415 - loads the simulator

        try:
            params = car_params(env_config["car"])
        except CarError as err:
            raise CheckpointError(f"env_config: {err}") from None
        config["car"] = car_name(params) or _jsonable(params)
    action_mode = config.get("action_mode", implied)
    if action_mode != implied:
        raise CheckpointError(
            f"env_config says action_mode {action_mode!r}, but the model's action space is "
            f"{action_space['type']}"
        )
    info: dict[str, Any] = {"steps": int(getattr(model, "num_timesteps", 0))}
    info.update(_jsonable(training or {}))
    hyper = _sb3_hyperparameters(model)
    hyper.update(_jsonable(hyperparameters or {}))
    meta = CheckpointMeta(
        name=name,
        env_version=ENV_VERSION,
        obs_mode=config.get("obs_mode", "vector"),
        action_mode=action_mode,
        observation_space=obs_space,
        action_space=action_space,
        algorithm=type(model).__name__,
        policy=arch,
        hyperparameters=hyper,
        training=info,
        env_config=config,
    )
    prefixes: tuple[str, ...] = ("mlp_extractor.policy_net.", "action_net.")
    if include_value:
        prefixes += ("mlp_extractor.value_net.", "value_net.")
    state = {k: v for k, v in policy.state_dict().items() if k.startswith(prefixes)}
    return save_checkpoint(state, meta, path)


# ---- running a checkpoint -------------------------------------------------------------------


def _build_mlp(
    n_in: int, widths: list[int], n_out: int, activation: str
) -> tuple[torch.nn.Sequential, torch.nn.Linear]:
    """SB3's layout: ``Sequential(Linear, act, Linear, act, …)`` body and a Linear head."""
    import torch  # noqa: PLC0415 - optional `train` extra, imported on use

    act = getattr(torch.nn, ACTIVATIONS[activation])
    layers: list[torch.nn.Module] = []
    last = n_in
    for width in widths:
        layers += [torch.nn.Linear(last, width), act()]
        last = width
    return torch.nn.Sequential(*layers), torch.nn.Linear(last, n_out)


class TorchMLPPolicy:
    """A checkpoint as a :class:`agents.Policy`, rebuilt in plain torch (no SB3 needed).

    ``act(obs)`` takes one observation of exactly ``meta.observation_shape`` and returns
    what ``model.predict(obs, deterministic=True)`` would: a float32 action array of the
    action space's shape (Box), or an ``int`` (Discrete). It is deterministic and stateless.

    Args:
        meta: the checkpoint's metadata.
        tensors: its tensors (validated against ``meta`` again here).
        name: display name; defaults to ``meta.name``.

    Raises:
        CheckpointError: the tensors do not match the metadata, or torch is not installed.
    """

    def __init__(
        self, meta: CheckpointMeta, tensors: Mapping[str, NDArray[Any]], *, name: str | None = None
    ) -> None:
        try:
            import torch  # noqa: PLC0415 - optional `train` extra, imported on use
        except ImportError as err:
            raise CheckpointError(
                "running a checkpoint needs torch: pip install 'slipstream[train]'"
            ) from err
        check_tensors(meta, tensors)
        self.meta = meta
        self.name = name or meta.name
        self.observation_shape = meta.observation_shape
        pol = meta.policy
        n_in = math.prod(self.observation_shape)
        body, head = _build_mlp(n_in, pol.net_arch, meta.n_outputs, pol.activation)
        modules: dict[str, torch.nn.Module] = {"policy_net": body}
        root: dict[str, torch.nn.Module] = {"action_net": head}
        if pol.value_net_arch is not None:
            vbody, vhead = _build_mlp(n_in, pol.value_net_arch, 1, pol.activation)
            modules["value_net"] = vbody
            root["value_net"] = vhead
        self.net = torch.nn.ModuleDict({"mlp_extractor": torch.nn.ModuleDict(modules), **root})
        state = {k: torch.from_numpy(np.array(v, dtype=np.float32)) for k, v in tensors.items()}
        self.net.load_state_dict(state, strict=True)
        self.net.eval()
        space = space_from_json(meta.action_space)
        self._box = isinstance(space, spaces.Box)
        # Box bounds in the space's dtype, so clipping rounds exactly as SB3's predict does.
        self._action_shape: tuple[int, ...] = tuple(space.shape or ())
        self._low = space.low if isinstance(space, spaces.Box) else np.zeros(())
        self._high = space.high if isinstance(space, spaces.Box) else np.zeros(())

    @classmethod
    def from_file(cls, path: str | Path | bytes, *, name: str | None = None) -> TorchMLPPolicy:
        """Read, validate and build a checkpoint (:func:`read_checkpoint`).

        Warns (``UserWarning``) when the checkpoint was trained on an env version whose
        observations may differ (not in :data:`arena.version.COMPATIBLE_ENV_VERSIONS`).
        """
        meta, tensors = read_checkpoint(path)
        if not is_compatible(meta.env_version):
            warnings.warn(
                f"checkpoint {meta.name!r} was trained on env version {meta.env_version}, "
                f"this is {ENV_VERSION}: observations may mean something else",
                UserWarning,
                stacklevel=2,
            )
        return cls(meta, tensors, name=name)

    def reset(self, seed: int | None = None) -> None:
        """Deterministic and stateless: nothing to reset."""

    def _features(self, obs: Any, batched: bool) -> torch.Tensor:
        import torch  # noqa: PLC0415 - optional `train` extra, imported on use

        arr = np.asarray(obs, dtype=np.float32)
        want = (arr.shape[0], *self.observation_shape) if batched and arr.ndim else None
        if arr.shape != (want or self.observation_shape):
            what = "a batch (B, *obs_shape) of" if batched else "observation shape"
            raise CheckpointError(
                f"policy {self.name!r} expects {what} {self.observation_shape}, got "
                f"{arr.shape} (obs_mode {self.meta.obs_mode!r}, env_config "
                f"{self.meta.env_config})"
            )
        rows = arr.shape[0] if batched else 1
        return torch.from_numpy(np.ascontiguousarray(arr.reshape(rows, -1)))

    def _actions(self, features: torch.Tensor) -> NDArray[Any]:
        import torch  # noqa: PLC0415 - optional `train` extra, imported on use

        with torch.no_grad():
            latent = self.net["mlp_extractor"]["policy_net"](features)  # type: ignore[index]
            out = self.net["action_net"](latent)
            if not self._box:
                # As SB3: argmax of the categorical's probabilities (same ties as predict).
                probs = torch.distributions.Categorical(logits=out).probs
                return torch.argmax(probs, dim=1).numpy()
            if self.meta.policy.squash_output:
                out = torch.tanh(out)
        actions = out.numpy().reshape((-1, *self._action_shape))
        if self.meta.policy.squash_output:
            return self._low + (0.5 * (actions + 1.0) * (self._high - self._low))
        if self.meta.policy.clip_actions:
            return np.clip(actions, self._low, self._high)
        return actions

    @property
    def observes_perturbation(self) -> bool:
        """Trained on perturbation-aware observations (``meta.observes_perturbation``)."""
        return self.meta.observes_perturbation

    def act(self, obs: NDArray[np.floating[Any]]) -> NDArray[np.float32] | int:
        """The deterministic action for one observation.

        Args:
            obs: one observation, shape ``meta.observation_shape`` (e.g. (95,)).

        Returns:
            float32 array of the action shape (e.g. (2,) [steer, throttle]), or an int.

        Raises:
            CheckpointError: the observation has the wrong shape.
        """
        actions = self._actions(self._features(obs, batched=False))
        if not self._box:
            return int(actions[0])
        return actions[0].astype(np.float32, copy=False)

    def act_batch(self, obs: NDArray[np.floating[Any]]) -> NDArray[Any]:
        """Actions for a batch: (B, *obs_shape) → (B, action_dim) float32 or (B,) int64."""
        actions = self._actions(self._features(obs, batched=True))
        return actions if not self._box else actions.astype(np.float32, copy=False)

    def value(self, obs: NDArray[np.floating[Any]]) -> float:
        """The value estimate of one observation (only if the value head was exported).

        Raises:
            CheckpointError: the checkpoint has no value head, or the shape is wrong.
        """
        import torch  # noqa: PLC0415 - optional `train` extra, imported on use

        if self.meta.policy.value_net_arch is None:
            raise CheckpointError(f"checkpoint {self.meta.name!r} has no value head")
        features = self._features(obs, batched=False)
        with torch.no_grad():
            latent = self.net["mlp_extractor"]["value_net"](features)  # type: ignore[index]
            return float(self.net["value_net"](latent)[0, 0])
